"""Whole-body support planning in the loop: Chen et al. 2019, Sects. 2.2 and 3.1, as a controller of the MJX
hexapod on a terrain it knows as a DEM.

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

`hexjax.experiments.papers.chen2019` walks it and the Luneckas 2020 fixed gait over randomised wave patches.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hexjax.control.base import Controller
from hexjax.control.gait import check_open_ranges
from hexjax.plan.motion import TRIPODS
from hexjax.plan.support import (clamped_spline, foothold_candidates, foothold_plane, max_along, overlap_center,
                                 plane_pitch_roll, side_distances, torso_pitch_roll)
from hexjax.world.dem import DEM, dem_lookup
from hexjax.world.robot import N_LEGS, RobotSpec, body_to_leg, leg_ik, neutral_feet_body, quat_yaw, wrap_angle

SWING_GROUP = np.zeros((2, N_LEGS), bool)
SWING_GROUP[0, TRIPODS[0]] = True
SWING_GROUP[1, TRIPODS[1]] = True


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
class SupportPlanController(Controller):
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

    params_prefix = "support"

    def params_defaults(self) -> SupportParams:
        """A 5 cm stride per 0.5 s phase at the robot's hip height, on a flat placeholder DEM (give the
        terrain's: `default_params(dem=...)`)."""
        dem = DEM(heights=jnp.zeros((4, 4)), origin=jnp.array([-1.0, -1.0]), cell=jnp.asarray(0.5))
        f = lambda v: jnp.asarray(v, jnp.float32)
        return SupportParams(stride=f(0.05), phase_time=f(0.5), height=f(self.robot.hip_height),
                             clearance=f(0.03), torso_margin=f(0.02), delta_s=f(0.04), w_dist=f(0.5), w_height=f(0.5),
                             dem=dem)

    def validate_params(self, p: SupportParams) -> None:
        check_open_ranges("support", p, {"stride": (0.0, 0.2), "phase_time": (0.05, 10.0), "height": (0.02, 1.0),
                                         "clearance": (0.0, 0.3), "torso_margin": (-1.0, 0.3), "delta_s": (0.0, 0.3)})
        h = np.asarray(p.dem.heights)
        if h.ndim < 2 or min(h.shape[-2:]) < 3 or not np.all(np.isfinite(h)):
            raise ValueError(f"support.dem.heights shape={h.shape!r}: need a finite grid of at least 3 x 3 cells")
        if not np.all(np.asarray(p.dem.cell) > 0):
            raise ValueError(f"support.dem.cell={np.asarray(p.dem.cell).tolist()!r}: must be > 0")

    def for_distance(self, distance: float, params=None):
        """The torso advances about one stride a phase (a tripod's swing), so the walk gets that many phases
        plus two (the first plan and a settling phase); the planner walks on, so no stop is set."""
        p = self.default_params() if params is None else params
        stride, phase = float(np.mean(p.stride)), float(np.mean(p.phase_time))
        return self, (math.ceil(distance / stride) + 2) * phase

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


