"""Whole-body support planning in the loop on the rugged wave patch: Chen et al. 2019 (seed 002), Sects. 2.2
and 3.1, run on the MJX hexapod, against a fixed gait.

`SupportPlanController` walks an alternating tripod (duty 0.5) over a terrain it knows in advance as a 2.5D
grid (DEM; Chen Sect. 1 assumes the map is given). At each support-swing transition it plans the next phase:

* Footholds of the swing tripod, chosen from the DEM grid: the nominal foothold (half a phase ahead of the
  leg's neutral position along the path) and the cells within `search` cells of it are scored by the
  height spread of their 3 x 3 neighbourhood (a flat spot, not a column edge), the distance from the
  nominal and the height (low spots, like Chen's hand-picked 10-80 mm footholds below 178 mm peaks); cells
  the leg could not reach, or reach `clearance` above, from the nominal torso pose at the phase end are
  ruled out; the best cell's centre is the foothold.
* Torso target at the end of the phase (Sect. 2.2): horizontally towards the incenter of the overlap of
  the current and the next support triangles (Fig. 1's O_2, `support.overlap_center`, exact): the point
  nearest the nominal path, on the way to O_2, whose margin to both triangles is at least
  min(delta_s, 0.8 r(O_2)). Going all the way to O_2 swayed the torso +-6.7 cm sideways every 0.5 s on
  flat ground (for mirrored tripod triangles O_2 sits off the path), and tipped it; height h above
  the plane fitted to the six footholds (Sect. 2.2.1; raised where needed so the torso's underside clears
  the DEM under it by `torso_margin`, which Chen's hand-picked footholds made unnecessary); pitch and roll
  by Eq. 3, the mean of the fitted plane's and the measured ones; yaw back to the path heading.
* Torso trajectory over the phase: the cubic with zero end velocities between the two poses (Eqs. 4-5 with
  two knots). Stance feet hold their world positions; their joints follow by inverse kinematics.
* Swing legs: joint-space clamped cubic splines (Eqs. 4-5) through four knots at phase fractions 0, 1/3,
  2/3, 1: lift-off, above lift-off, above the foothold and the foothold, the middle two at `clearance`
  above the highest DEM cell along the chord. Chen solves the swing as an optimal control problem (Sect.
  2.3; `hexjax.plan.swing.optimise_swing` is the batched offline version); in the loop, under `vmap`, a
  per-swing optimisation would run at every control step, so the loop uses that optimisation's starting
  path, which meets the same clearance and end constraints.

The commanded world frame is re-anchored at every transition to the measured horizontal position and yaw
(a rigid shift of the torso and every foot target, so the joint commands stay continuous); height, pitch
and roll stay as commanded, the measured pitch and roll entering through Eq. 3.

`run_chen2019` rolls out the planned controller and the seed-000 fixed gait (same robot, stride, period)
over a batch of randomised patches and counts capsizes; `plot_chen2019` draws Fig. 6-like torso traces.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Dict, Optional

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from tqdm.auto import tqdm

from hexjax.control.gait import GaitController, GaitParams
from hexjax.mjcf import PhysicsConfig
from hexjax.plan.motion import TRIPODS
from hexjax.plan.support import (clamped_spline, foothold_plane, overlap_center, plane_pitch_roll, side_distances,
                                 torso_pitch_roll)
from hexjax.robot import (N_LEGS, RobotSpec, body_to_leg, get_robot, leg_ik, neutral_feet_body, quat_yaw,
                          wrap_angle)
from hexjax.sim.rollout import RolloutConfig, rollout
from hexjax.terrain import Terrain, get_terrain, sample

SWING_GROUP = np.zeros((2, N_LEGS), bool)
SWING_GROUP[0, TRIPODS[0]] = True
SWING_GROUP[1, TRIPODS[1]] = True


# The DEM ------------------------------------------------------------------------------------------------
@struct.dataclass
class DEM:
    """A 2.5D grid: heights (NX, NY) m of cells `cell` m wide, cell (0, 0) spanning origin .. origin + cell."""

    heights: jax.Array
    origin: jax.Array
    cell: jax.Array


def rasterise(terrain: Terrain, origin, shape, cell: float) -> jax.Array:
    """Top height (NX, NY) of one terrain at each cell centre of a grid (the highest box covering it, else
    the ground)."""
    nx, ny = shape
    xs = origin[0] + (jnp.arange(nx) + 0.5) * cell
    ys = origin[1] + (jnp.arange(ny) + 0.5) * cell
    top = terrain.box_pos[:, 2] + terrain.box_half[:, 2]

    def column(x):
        inx = jnp.abs(x - terrain.box_pos[:, 0]) <= terrain.box_half[:, 0]
        iny = jnp.abs(ys[:, None] - terrain.box_pos[None, :, 1]) <= terrain.box_half[None, :, 1]
        h = jnp.where(inx[None] & iny & terrain.box_valid[None], top[None], -jnp.inf)
        return jnp.maximum(jnp.max(h, -1), terrain.ground_z)

    return jax.lax.map(column, xs)


def dem_lookup(dem: DEM, xy):
    """Height (...) at points xy (..., 2) (nearest cell; points off the grid read its edge)."""
    ij = jnp.floor((xy - dem.origin) / dem.cell).astype(jnp.int32)
    i = jnp.clip(ij[..., 0], 0, dem.heights.shape[0] - 1)
    j = jnp.clip(ij[..., 1], 0, dem.heights.shape[1] - 1)
    return dem.heights[i, j]


def _snap(dem: DEM, xy):
    return dem.origin + (jnp.floor((xy - dem.origin) / dem.cell) + 0.5) * dem.cell


_N3 = np.array([(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)], np.float32)


def foothold_candidates(dem: DEM, nominal, search: int, w_dist: float, w_height: float):
    """The DEM cell centres within `search` cells of `nominal` (2,) and their costs: spread of the 3 x 3
    neighbourhood + w_dist |offset| + w_height height. Returns (xy (C, 2), ground height (C,), cost (C,))."""
    r = np.arange(-search, search + 1, dtype=np.float32)
    offs = np.stack(np.meshgrid(r, r, indexing="ij"), -1).reshape(-1, 2)
    cand = _snap(dem, nominal) + jnp.asarray(offs) * dem.cell  # (C, 2)
    nb = dem_lookup(dem, cand[:, None, :] + jnp.asarray(_N3) * dem.cell)  # (C, 9)
    h = nb[:, 4]
    cost = (jnp.max(nb, -1) - jnp.min(nb, -1)) + w_dist * jnp.linalg.norm(cand - nominal, axis=-1) + w_height * h
    return cand, h, cost


def max_along(dem: DEM, a, b, n: int = 10):
    """Highest DEM cell within one cell of the chord a -> b (2,)."""
    pts = a + (b - a) * jnp.linspace(0.0, 1.0, n)[:, None]
    return jnp.max(dem_lookup(dem, pts[:, None, :] + jnp.asarray(_N3) * dem.cell))


# Poses ----------------------------------------------------------------------------------------------------
def rotation(yaw, pitch, roll):
    """Torso rotation for yaw, pitch (nose up > 0) and roll (left side up > 0), the convention of
    `support.plane_pitch_roll`: R = Rz(yaw) Ry(-pitch) Rx(roll)."""
    cy, sy, cp, sp, cr, sr = jnp.cos(yaw), jnp.sin(yaw), jnp.cos(pitch), jnp.sin(pitch), jnp.cos(roll), jnp.sin(roll)
    rz = jnp.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = jnp.array([[cp, 0.0, -sp], [0.0, 1.0, 0.0], [sp, 0.0, cp]])  # Ry(-pitch)
    rx = jnp.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def _smooth(u):
    """The cubic with zero end slopes from 0 to 1 (Eqs. 4-5 with two knots)."""
    return u * u * (3.0 - 2.0 * u)


# The controller --------------------------------------------------------------------------------------------
@struct.dataclass
class SupportParams:
    """Traced numbers: stride () m torso advance per phase along +x; phase_time () s (one tripod's swing);
    height () m torso centre above the foothold plane (Chen's h); clearance () m swing foot above the DEM;
    torso_margin () m torso underside above the DEM; delta_s () m wanted stability margin at a transition;
    w_dist, w_height () foothold cost weights; dem: the
    terrain map (per env)."""

    stride: jax.Array
    phase_time: jax.Array
    height: jax.Array
    clearance: jax.Array
    torso_margin: jax.Array
    delta_s: jax.Array
    w_dist: jax.Array
    w_height: jax.Array
    dem: DEM


@struct.dataclass
class SupportState:
    """k control steps; phase index (-1 before the first); feet (6, 3) world foot targets of the stance legs
    (and lift-off points of the swing legs); land (6, 3) footholds of the swing legs; torso_from / torso_to
    (6,) x, y, z, yaw, pitch, roll at the phase's start and end; path (2,) nominal torso position at the
    phase start; margin () stability margin (overlap incenter radius, m) of the coming transition; min_margin
    () smallest so far; unreachable () control steps with a leg target out of reach."""

    k: jax.Array
    phase: jax.Array
    feet: jax.Array
    land: jax.Array
    apex: jax.Array
    torso_from: jax.Array
    torso_to: jax.Array
    path: jax.Array
    margin: jax.Array
    min_margin: jax.Array
    unreachable: jax.Array


@dataclasses.dataclass(frozen=True)
class SupportPlanController:
    """Chen 2019 whole-body support planning on a known DEM (module docstring). Static: robot, control
    period, foothold search half-width in cells."""

    robot: RobotSpec
    dt: float = 0.02
    search: int = 3

    def __post_init__(self):
        if not (0 < self.dt <= 0.1):
            raise ValueError(f"controller.dt={self.dt!r}: must be in (0, 0.1] s")
        if not (isinstance(self.search, int) and self.search >= 0):
            raise ValueError(f"controller.search={self.search!r}: must be an integer >= 0")

    def default_params(self, dem: Optional[DEM] = None) -> SupportParams:
        dem = dem if dem is not None else DEM(heights=jnp.zeros((4, 4)), origin=jnp.array([-1.0, -1.0]),
                                              cell=jnp.asarray(0.5))
        f = lambda v: jnp.asarray(v, jnp.float32)
        return SupportParams(stride=f(0.05), phase_time=f(0.5), height=f(self.robot.hip_height),
                             clearance=f(0.03), torso_margin=f(0.02), delta_s=f(0.04), w_dist=f(0.5), w_height=f(0.5),
                             dem=dem)

    def validate_params(self, p: SupportParams) -> None:
        for name, lo, hi in (("stride", 0.0, 0.2), ("phase_time", 0.05, 10.0), ("height", 0.02, 1.0),
                             ("clearance", 0.0, 0.3), ("torso_margin", -1.0, 0.3), ("delta_s", 0.0, 0.3)):
            v = np.asarray(getattr(p, name))
            if not np.all(np.isfinite(v)) or np.any(v <= lo) or np.any(v > hi):
                raise ValueError(f"support.{name}={v.tolist()!r}: must be in ({lo}, {hi}]")
        h = np.asarray(p.dem.heights)
        if h.ndim < 2 or min(h.shape[-2:]) < 3 or not np.all(np.isfinite(h)):
            raise ValueError(f"support.dem.heights shape={h.shape!r}: need a finite grid of at least 3 x 3 cells")
        if not np.all(np.asarray(p.dem.cell) > 0):
            raise ValueError(f"support.dem.cell={np.asarray(p.dem.cell).tolist()!r}: must be > 0")

    def init(self, params: SupportParams, key) -> SupportState:
        del key
        z6, z3 = jnp.zeros(6), jnp.zeros((N_LEGS, 3))
        zero = 0.0 * params.stride
        return SupportState(k=jnp.int32(0), phase=jnp.int32(-1), feet=z3, land=z3, apex=jnp.zeros(N_LEGS),
                            torso_from=z6, torso_to=z6, path=jnp.zeros(2), margin=zero, min_margin=zero + jnp.inf,
                            unreachable=jnp.int32(0))

    def _start(self, params: SupportParams, obs):
        """Commanded pose and feet before the first phase: the neutral stance at the measured x, y, yaw (the
        joint targets the robot settled with)."""
        yaw = quat_yaw(obs.torso_quat)
        pose = jnp.stack([obs.torso_pos[0], obs.torso_pos[1], params.height + 0.0 * yaw, yaw, 0.0 * yaw, 0.0 * yaw])
        feet = self._to_world(pose, jnp.asarray(neutral_feet_body(self.robot), jnp.float32))
        return pose, feet

    @staticmethod
    def _to_world(pose, p_body):
        return p_body @ rotation(pose[3], pose[4], pose[5]).T + pose[:3]

    @staticmethod
    def _to_body(pose, p_world):
        return (p_world - pose[:3]) @ rotation(pose[3], pose[4], pose[5])

    def _plan_phase(self, params: SupportParams, st: SupportState, obs, j):
        """The transition into phase j (module docstring): re-anchor, footholds, torso target."""
        first = st.phase < 0
        pose0, feet0 = self._start(params, obs)
        prev_swing = jnp.asarray(SWING_GROUP)[(j + 1) % 2]  # the group that swung in phase j - 1
        feet = jnp.where(first, feet0, jnp.where(prev_swing[:, None] & (j > 0), st.land, st.feet))
        pose = jnp.where(first, pose0, st.torso_to)
        path = jnp.where(first, pose0[:2], st.path)
        # re-anchor: the rigid horizontal shift and turn taking the commanded (x, y, yaw) to the measured
        yaw_m = quat_yaw(obs.torso_quat)
        dyaw = wrap_angle(yaw_m - pose[3])
        c, s = jnp.cos(dyaw), jnp.sin(dyaw)
        rot = jnp.array([[c, -s], [s, c]])
        move = lambda xy: (xy - pose[:2]) @ rot.T + obs.torso_pos[:2]
        feet = jnp.concatenate([move(feet[:, :2]), feet[:, 2:]], -1)
        path = jnp.stack([move(path)[0], path[1]])  # slips along the path delay it; sideways ones are undone
        pose = pose.at[:2].set(obs.torso_pos[:2]).at[3].set(yaw_m)

        swing = jnp.asarray(SWING_GROUP)[j % 2]
        stance_idx = jnp.where(j % 2 == 0, jnp.asarray(TRIPODS[1]), jnp.asarray(TRIPODS[0]))
        swing_idx = jnp.where(j % 2 == 0, jnp.asarray(TRIPODS[0]), jnp.asarray(TRIPODS[1]))
        # nominal footholds: half a phase into the leg's next stance, i.e. the path 1.5 strides ahead
        ahead = path + jnp.array([1.5, 0.0]) * params.stride
        neutral = jnp.asarray(neutral_feet_body(self.robot)[:, :2], jnp.float32)
        nominal = ahead + neutral  # path heading +x
        cand, ground, cost = jax.vmap(lambda q: foothold_candidates(params.dem, q, self.search, params.w_dist,
                                                                     params.w_height))(nominal)  # (6, C, ...)
        # a cell the leg cannot reach from the nominal torso pose at the phase end, or cannot lift off from
        # to `clearance` above it, is ruled out (unless every one is)
        end_pose = pose.at[:2].set(path + jnp.array([1.0, 0.0]) * params.stride).at[3:].set(0.0)
        feet_c = jnp.concatenate([cand, (ground + self.robot.foot_radius)[..., None]], -1)  # (6, C, 3)
        lifted = feet_c.at[..., 2].add(params.clearance)
        reach = lambda f: leg_ik(self.robot, self._leg_frame(end_pose, f))[1]  # f (6, 3): one cell per leg
        ok = jax.vmap(reach, in_axes=1, out_axes=1)(feet_c) & jax.vmap(reach, in_axes=1, out_axes=1)(lifted)
        best = jnp.argmin(cost + jnp.where(ok, 0.0, 10.0), axis=-1)
        new = jnp.take_along_axis(feet_c, best[:, None, None], 1)[:, 0]
        land = jnp.where(swing[:, None], new, feet)
        apex = jax.vmap(lambda a, b: max_along(params.dem, a, b))(feet[:, :2], land[:, :2])
        apex = jnp.maximum(apex, jnp.maximum(feet[:, 2], land[:, 2]) - self.robot.foot_radius)
        # torso target (Sect. 2.2): overlap incenter, height above the foothold plane, Eq. 3 pitch / roll
        tri_now, tri_next = feet[stance_idx, :2], land[swing_idx, :2]
        ones = jnp.ones(3, bool)
        o2, r2 = overlap_center(tri_now, ones, tri_next, ones)
        # from the nominal path point towards O_2, the first point with margin >= min(delta_s, 0.8 r(O_2))
        nominal_xy = path + jnp.array([1.0, 0.0]) * params.stride
        cand = nominal_xy + (o2 - nominal_xy) * jnp.linspace(0.0, 1.0, 17)[:, None]
        marg = jax.vmap(lambda q: jnp.minimum(jnp.min(side_distances(q, tri_now, ones)[0]),
                                              jnp.min(side_distances(q, tri_next, ones)[0])))(cand)
        need = jnp.minimum(params.delta_s, 0.8 * r2)
        # O_2 (the last candidate) qualifies whenever the triangles overlap; when they do not, no point does
        # and argmax picks the first, the nominal point
        pick = jnp.argmax(marg >= need - 1e-6)
        centre, margin = cand[pick], marg[pick]
        # Sect. 2.2.1: the torso centre `height` above the plane of the footholds (the ground under the feet)
        plane = foothold_plane(land.at[:, 2].add(-self.robot.foot_radius), jnp.ones(N_LEGS, bool))
        z = plane[0] * centre[0] + plane[1] * centre[1] + plane[2] + params.height
        hx, hy = 0.5 * self.robot.body_length, 0.5 * self.robot.body_width
        corners = jnp.array([[hx, hy], [hx, -hy], [-hx, hy], [-hx, -hy], [0.0, 0.0], [hx, 0.0], [-hx, 0.0]])
        under = jnp.max(dem_lookup(params.dem, centre + corners))
        z = jnp.maximum(z, under + 0.5 * self.robot.body_thickness + params.torso_margin)
        p_sp, r_sp = plane_pitch_roll(plane[:2], 0.0)
        p_m, r_m = torso_pitch_roll(obs.torso_quat)
        target = jnp.stack([centre[0], centre[1], z, 0.0, 0.5 * (p_sp + p_m), 0.5 * (r_sp + r_m)])  # Eq. 3
        return st.replace(phase=j, feet=feet, land=land, apex=apex, torso_from=pose, torso_to=target,
                          path=path + jnp.array([1.0, 0.0]) * params.stride, margin=margin,
                          min_margin=jnp.minimum(st.min_margin, jnp.where(first, jnp.inf, margin)))

    def _leg_frame(self, pose, p_world):
        """World points (6, 3), one per leg, in each leg's frame for torso pose (6,)."""
        return body_to_leg(self.robot, self._to_body(pose, p_world))

    def _joints(self, pose, p_world):
        """(joint angles (6, 3), reachable (6,)) for world foot targets (6, 3) at torso pose (6,)."""
        return leg_ik(self.robot, self._leg_frame(pose, p_world))

    def step(self, params: SupportParams, state: SupportState, obs):
        t = state.k * self.dt
        j = jnp.floor(t / params.phase_time + 1e-6).astype(jnp.int32)
        planned = self._plan_phase(params, state, obs, j)
        st = jax.tree_util.tree_map(lambda a, b: jnp.where(j != state.phase, a, b), planned, state)
        u = jnp.clip(t / params.phase_time - j, 0.0, 1.0)

        def pose_at(v):
            d = st.torso_to - st.torso_from
            d = d.at[3].set(wrap_angle(d[3]))
            return st.torso_from + d * _smooth(v)

        pose = pose_at(u)
        q_stance, ok_stance = self._joints(pose, st.feet)
        # swing: joint-space clamped spline through lift-off, two apex points and the foothold (Eqs. 4-5)
        knots_u = jnp.array([0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0])
        top = (st.apex + params.clearance + self.robot.foot_radius)[:, None]
        pts = jnp.stack([st.feet, jnp.concatenate([st.feet[:, :2], top], -1),
                         jnp.concatenate([st.land[:, :2], top], -1), st.land])  # (4, 6, 3)
        qk, okk = jax.vmap(self._joints)(jax.vmap(pose_at)(knots_u), pts)  # (4, 6, 3)
        q_swing = clamped_spline(knots_u, qk)(u[None])[0]
        swing = jnp.asarray(SWING_GROUP)[j % 2]
        q = jnp.where(swing[:, None], q_swing, q_stance)
        bad = jnp.any(jnp.where(swing, jnp.all(okk, 0), ok_stance) == 0)
        st = st.replace(k=state.k + 1, unreachable=st.unreachable + bad.astype(jnp.int32))
        return st, q.reshape(-1)

    def trace(self, state: SupportState, obs):
        """Per control step (RolloutConfig.record): measured pitch, roll; commanded target pitch, roll, z."""
        p, r = torso_pitch_roll(obs.torso_quat)
        return jnp.stack([p, r, state.torso_to[4], state.torso_to[5], state.torso_to[2]])


@dataclasses.dataclass(frozen=True)
class TracedGait(GaitController):
    """The seed-000 open-loop gait, recording measured pitch and roll (for Fig. 6-like traces)."""

    def trace(self, state, obs):
        p, r = torso_pitch_roll(obs.torso_quat)
        return jnp.stack([p, r])


# The experiment -------------------------------------------------------------------------------------------
def patch_spec(width: float = 0.8, taper: float = 0.1):
    """The `waves` preset (Chen Sect. 3.1: 800 mm long, peaks 150-178 mm) at `width` m across, its heights
    fading to the floor over `taper` m inside its edges. The paper's "400 x 800 mm" does not say which side
    lies along the path; its physical patch is 850 wide x 800 long, and a 0.4 m wide patch would leave the
    chen2019 robot's feet (0.56 m apart) on flat ground either side, so the patch is 0.8 m square by default.
    Without the taper the patch starts with a cliff of up to 178 mm that the fixed gait cannot step onto
    (it stalls in front of it); with it both controllers walk onto the waves."""
    return get_terrain("waves", width=width, taper=taper)


def dem_for(spec, terrain: Terrain, margin: float = 0.5) -> DEM:
    """Per-env DEMs (leading axis B) of a batch of `spec` terrains on the terrain's own grid, extended by
    `margin` m of ground on every side."""
    cell = spec.cell
    pad = int(round(margin / cell))
    nx, ny = spec._grid_shape()
    origin = np.array([spec.start_x - pad * cell, -0.5 * spec.width - pad * cell], np.float32)
    shape = (nx + 2 * pad, ny + 2 * pad)
    h = jax.jit(jax.vmap(lambda t: rasterise(t, jnp.asarray(origin), shape, cell)))(terrain)
    b = h.shape[0]
    return DEM(heights=h, origin=jnp.broadcast_to(jnp.asarray(origin), (b, 2)), cell=jnp.full((b,), cell, jnp.float32))


CHEN_PHYSICS = PhysicsConfig(slots_per_leg=4, iterations=4)
"""Physics of the rugged patch: 4 terrain slots per leg (a 12 mm foot on 20 mm columns touches up to 4) and
4 Newton iterations. With the default 2, the 4 kg chen2019 robot's stance feet sometimes sank 3 cm into the
columns and popped out (1 of 8 planned walks capsized that way); with 4 none did (8 of 8 crossed, max tilt
14 deg)."""


def _summarise(parts, far: float) -> Dict:
    cat = lambda f: np.concatenate([np.asarray(f(p)) for p in parts])
    fell, nan = cat(lambda s: s.fell), cat(lambda s: s.nan)
    end_x = cat(lambda s: s.end_pose[:, 0])
    tilt = np.degrees(cat(lambda s: s.max_tilt))
    crossed = (end_x > far) & ~fell & ~nan
    return {"capsized": int(fell.sum()), "capsize_rate": float(fell.mean()), "nan": int(nan.sum()),
            "crossed": int(crossed.sum()), "cross_rate": float(crossed.mean()),
            "stalled": int((~crossed & ~fell & ~nan).sum()),
            "max_tilt_deg": {"median": float(np.median(tilt)), "p95": float(np.percentile(tilt, 95)),
                             "max": float(np.max(tilt))},
            "tilted_over_30deg": int((tilt > 30).sum()), "end_x_median": float(np.median(end_x))}


def run_chen2019(n: int = 16, seed: int = 0, robot: str = "chen2019", duration: float = 16.0, stride: float = 0.05,
                 phase_time: float = 0.5, fixed_step_heights=(0.08, 0.13), chunk: int = 0, mesh=None) -> Dict:
    """Planned (SupportPlanController) vs fixed (the seed-000 tripod at the same stride and period and the
    robot's standard posture, at each swing height of `fixed_step_heights`) over n randomised wave patches
    (`patch_spec`), physics `CHEN_PHYSICS`. Per controller: capsizes (the rollout's fall test: torso tilt
    > 60 deg or centre < 3 cm above the ground), crossings (torso past the patch's far edge, upright),
    stalls (neither), tilt statistics; for the planned one also the smallest stability margin at a
    transition and control steps with a leg target out of reach. `_records` keeps traces for plots."""
    if not (isinstance(n, int) and n >= 1):
        raise ValueError(f"batch n={n!r}: must be an integer >= 1")
    if not (isinstance(duration, (int, float)) and duration > 0):
        raise ValueError(f"duration={duration!r}: must be > 0 s")
    rb = get_robot(robot)
    spec = patch_spec()
    k_t, k_r = jax.random.split(jax.random.PRNGKey(seed))
    terrain = sample(spec, k_t, n)
    cfg = RolloutConfig(record=True)
    planned = SupportPlanController(rb)
    pp = planned.default_params().replace(stride=jnp.float32(stride), phase_time=jnp.float32(phase_time))
    tile = lambda x: jnp.broadcast_to(x, (n,) + jnp.shape(x))
    pp = jax.tree_util.tree_map(tile, pp.replace(dem=None)).replace(dem=dem_for(spec, terrain))
    variants = [("planned", planned, pp, True)]
    for h in fixed_step_heights:
        # the seed-000 tripod moves the torso l per swing slot: the same advance per phase as `stride`
        fp = GaitParams(step_length=jnp.float32(stride), step_height=jnp.float32(h),
                        swing_time=jnp.float32(phase_time), direction=jnp.float32(0.0),
                        body_height_offset=jnp.float32(0.0))
        variants.append((f"fixed_h{round(100 * h)}cm", TracedGait(rb, "tripod", dt=0.02), fp, False))
    chunk = chunk or n
    far = spec.start_x + spec.length
    res = {"config": {"robot": robot, "patches": n, "seed": seed, "duration_s": duration, "stride": stride,
                      "phase_time": phase_time, "speed": stride / phase_time,
                      "fixed_step_heights": list(fixed_step_heights),
                      "patch": {"length": spec.length, "width": spec.width, "start_x": spec.start_x,
                                "taper": spec.taper, "peak_range": list(spec.height_range), "cell": spec.cell},
                      "torso_height": float(pp.height[0]), "physics_iterations": CHEN_PHYSICS.iterations,
                      "slots_per_leg": CHEN_PHYSICS.slots_per_leg, "device": str(jax.devices()[0].platform)},
           "_records": {}, "_terrain": terrain}
    for name, ctrl, params, batched in variants:
        parts = []
        t0 = time.perf_counter()
        comp = 0.0
        for i in tqdm(range(0, n, chunk), desc=f"chen2019 {name}", unit="chunk", disable=n <= chunk):
            sl = lambda x: x[i:i + chunk]
            prm = jax.tree_util.tree_map(sl, params) if batched else params
            s = rollout(rb, jax.tree_util.tree_map(sl, terrain), ctrl, prm, duration, jax.random.fold_in(k_r, i),
                        physics=CHEN_PHYSICS, config=cfg, params_batched=batched, mesh=mesh)
            comp += rollout.last_compile_s
            parts.append(jax.device_get(s))
        row = _summarise(parts, far)
        row["wall_s"], row["compile_s"] = time.perf_counter() - t0, comp
        cat = lambda f: np.concatenate([np.asarray(f(p)) for p in parts])
        if name == "planned":
            row["min_stability_margin_m"] = {"median": float(np.median(cat(lambda s: s.final_state.min_margin))),
                                             "min": float(np.min(cat(lambda s: s.final_state.min_margin)))}
            row["steps_with_a_leg_out_of_reach"] = int(cat(lambda s: s.final_state.unreachable).sum())
        res[name] = row
        res["_records"][name] = {"trace": cat(lambda s: s.trace), "ctrl": cat(lambda s: s.ctrl_trace),
                                 "fell": cat(lambda s: s.fell)}
    return res


def plot_chen2019(res: Dict, png: str, env: int = 0) -> None:
    """Fig. 6-like: torso pitch, roll and height over time for one patch, planned (measured and Eq. 3
    target) and the last fixed variant; plus the patch's height map with both torso paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from hexjax.terrain import heightmap
    fixed = [k for k in res["_records"] if k.startswith("fixed")]
    fname = fixed[-1]
    rp, rf = res["_records"]["planned"], res["_records"][fname]
    dt = 0.02
    t = np.arange(rp["trace"].shape[1]) * dt
    fig, ax = plt.subplots(2, 2, figsize=(10, 6))
    ax[0, 0].plot(t, np.degrees(rp["ctrl"][env, :, 0]), label="planned, measured")
    ax[0, 0].plot(t, np.degrees(rp["ctrl"][env, :, 2]), "--", lw=0.8, label="planned, Eq. 3 target")
    ax[0, 0].plot(t, np.degrees(rf["ctrl"][env, :, 0]), label=fname)
    ax[0, 0].set_ylabel("pitch (deg)")
    ax[0, 0].legend(fontsize=7)
    ax[0, 1].plot(t, np.degrees(rp["ctrl"][env, :, 1]), label="planned, measured")
    ax[0, 1].plot(t, np.degrees(rp["ctrl"][env, :, 3]), "--", lw=0.8, label="planned, Eq. 3 target")
    ax[0, 1].plot(t, np.degrees(rf["ctrl"][env, :, 1]), label=fname)
    ax[0, 1].set_ylabel("roll (deg)")
    ax[1, 0].plot(t, rp["trace"][env, :, 2], label="planned")
    ax[1, 0].plot(t, rf["trace"][env, :, 2], label=fname)
    ax[1, 0].set_ylabel("torso height (m)")
    for a in (ax[0, 0], ax[0, 1], ax[1, 0]):
        a.set_xlabel("time (s)")
    terr = jax.tree_util.tree_map(lambda x: x[env], res["_terrain"])
    c = res["config"]["patch"]
    xr, yr = (-0.2, c["start_x"] + c["length"] + 0.4), (-0.5, 0.5)
    hm = heightmap(terr, xr, yr, 0.01)
    im = ax[1, 1].imshow(hm.T, origin="lower", extent=(*xr, *yr), cmap="terrain")
    ax[1, 1].plot(rp["trace"][env, :, 0], rp["trace"][env, :, 1], "k-", label="planned")
    ax[1, 1].plot(rf["trace"][env, :, 0], rf["trace"][env, :, 1], "r-", label=fname)
    ax[1, 1].legend(fontsize=7)
    fig.colorbar(im, ax=ax[1, 1], label="height (m)")
    ok = lambda name: "capsized" if res["_records"][name]["fell"][env] else "upright"
    counts = ", ".join(f"{k} {res[k]['capsized']}" for k in ["planned"] + fixed)
    fig.suptitle(f"chen2019 patch {env}: planned {ok('planned')}, {fname} {ok(fname)}; capsized of "
                 f"{res['config']['patches']}: {counts}", fontsize=10)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
