"""The avoidance planner in the loop: an MJX hexapod walks among obstacles to a target (Zhao 2018, seed 004,
Sect. 3.2, run on the simulated seed-000 robot instead of Octopus-III).

`AvoidGaitController` wraps the seed-000 gait (`hexjax.control.gait`, Luneckas 2020 Eqs. 2-4). Every n_T
gait cycles, at a cycle boundary, it reads the torso position from the simulator, scores the candidate
directions with Eqs. 1-6 (`hexjax.plan.avoid.scores`, predicting n_T gait cycles ahead) and sets the gait's
walking direction eps (Luneckas Eq. 2) to the chosen world heading minus the measured yaw. The obstacle
circles, the target and every planner number are traced params, so `rollout(..., params_batched=True)`
walks thousands of different fields in one call.

Readings and choices (also in docs/planning.md):
  * One planner time-step is one gait cycle; the planner's `step` is the gait's advance per cycle
    (l T / (T - 1)), so its predictions are where the gait would put the robot.
  * A new direction (and stroke scale) is blended in linearly over one gait cycle, from the plan time (a
    cycle boundary). The foot offsets are cos/sin(eps) times the stroke, so an abrupt eps would make every
    foot jump; blended, the feet stay continuous and the stance feet, which share one stroke phase per
    tripod, all move together.
  * Walking capacity |w_i| scales the stroke: the chosen candidate's w is the stroke scale. The seed-000
    gait moves the same stroke in any direction (measured: 0.90-0.97 m in 4 s at 0, 45, 90, -90 and
    135 deg), so `small_robot_params` sets |w| = 1 over a forward half-fan of 36 directions.
  * Where every candidate would overlap an obstacle the robot marks time (stroke 0, legs still stepping)
    until the next plan, as the kinematic planner holds its place. Within `goal_tol` of the target it stops
    for good: the stroke shrinks to 0 over one cycle.
  * Physical obstacles are boxes (the terrain is boxes, see docs/terrain.md) inscribed in the planner's
    circles (Eq. 1 envelopes each obstacle by a circle): square columns and elongated boxes, 0.25 m tall,
    taller than the robot, so touching one means a collision, not a step over it.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Dict, Optional

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from tqdm.auto import tqdm

from hexjax.control.gait import GaitController, GaitParams, GaitState, PatternClock
from hexjax.plan import avoid
from hexjax.plan.avoid import AvoidConfig, AvoidParams
from hexjax.plan.fields import Fields, dist_to_polyline, random_fields
from hexjax.robot import RobotSpec, get_robot, hip_positions, neutral_feet_body, quat_yaw, wrap_angle
from hexjax.sim.rollout import RolloutConfig, rollout
from hexjax.terrain import Terrain

OBSTACLE_HEIGHT = 0.25  # m: taller than the seed-000 robot (torso top ~0.12 m)


@struct.dataclass
class AvoidGaitParams:
    """Traced params of one env (batch them all for per-env fields). gait: the seed-000 gait's numbers
    (its `direction` is overwritten by the planner); avoid: the planner's; target (2,) m world frame;
    centres (Q, 2) m, radii (Q,) m, valid (Q,) bool: the obstacle circles (Eq. 1)."""

    gait: GaitParams
    avoid: AvoidParams
    target: jax.Array
    centres: jax.Array
    radii: jax.Array
    valid: jax.Array


@struct.dataclass
class AvoidGaitState:
    """k control steps since the gait started (gait time t = k dt, exact: a float sum of dt drifts past
    plan times); the heading (world, rad) and stroke scale blend from *_from to *_to over one gait
    cycle starting at t_switch; next_plan: gait time of the next plan; done: stopped at the target;
    plans / held: plan cycles run / spent marking time (every candidate overlapped); chosen: index of the
    last chosen candidate (n = the target direction, -1 none)."""

    k: jax.Array
    heading_from: jax.Array
    heading_to: jax.Array
    scale_from: jax.Array
    scale_to: jax.Array
    t_switch: jax.Array
    next_plan: jax.Array
    done: jax.Array
    plans: jax.Array
    held: jax.Array
    chosen: jax.Array


def footprint_radius(robot: RobotSpec, step_length: float) -> float:
    """Radius (m) of one circle about the torso centre enveloping the robot while it walks (Zhao Eq. 1):
    the farthest neutral foot, plus half a stroke, plus the foot radius."""
    r = float(np.max(np.linalg.norm(neutral_feet_body(robot)[:, :2], axis=-1)))
    return r + 0.5 * step_length + robot.foot_radius


@dataclasses.dataclass(frozen=True)
class AvoidGaitController(PatternClock):
    """The seed-000 gait steered by the Zhao 2018 planner (module docstring). Static: the robot, the gait
    pattern, the control period, the swing height, and the planner's `AvoidConfig` (n_T: gait cycles per
    plan cycle and predicted ahead; max_cycles is unused here: the rollout's duration bounds the walk)."""

    robot: RobotSpec
    gait: str = "tripod"
    dt: float = 0.02
    step_height: float = 0.03
    avoid: AvoidConfig = AvoidConfig(n_T=2)

    def __post_init__(self):
        self._check_gait_and_dt()
        self.avoid.validate()

    @property
    def base(self) -> GaitController:
        return GaitController(self.robot, self.gait, self.dt, self.step_height)

    def default_params(self) -> AvoidGaitParams:
        """The fast gait of `fast_gait`, `small_robot_params`, a target 2 m ahead and no obstacles."""
        g = fast_gait(self)
        return AvoidGaitParams(gait=g, avoid=small_robot_params(self.robot, float(g.step_length),
                                                                 advance=self.advance(g)),
                               target=jnp.array([2.0, 0.0]), centres=jnp.zeros((1, 2)),
                               radii=jnp.full((1,), 0.1), valid=jnp.zeros((1,), bool))

    def advance(self, g: GaitParams) -> float:
        """Body advance per gait cycle of gait params g, m (Luneckas: l per swing slot x T / (T - 1))."""
        period = self.pattern.period
        return float(np.mean(g.step_length)) * period / (period - 1)

    def validate_params(self, params: AvoidGaitParams) -> None:
        """Host-side checks before tracing: the gait's ranges, the planner's params, finite obstacle
        circles and a target outside every obstacle (`avoid.check_inputs`)."""
        self.base.validate_params(params.gait)
        t = np.asarray(params.target)
        start = np.zeros_like(t)  # the start is not a param; only the target is checked against obstacles
        avoid.check_inputs(start, t, params.centres, params.radii, params.valid, params.avoid, self.avoid)

    def init(self, params: AvoidGaitParams, key) -> AvoidGaitState:
        del key
        z, h = jnp.asarray(0.0), jnp.asarray(0.0) + 0.0 * params.target[0]
        return AvoidGaitState(k=jnp.int32(0), heading_from=h, heading_to=h, scale_from=z + 1.0, scale_to=z + 1.0,
                              t_switch=z, next_plan=z, done=jnp.asarray(False), plans=jnp.int32(0),
                              held=jnp.int32(0), chosen=jnp.int32(-1))

    def step(self, params: AvoidGaitParams, state: AvoidGaitState, obs):
        cycle = params.gait.swing_time * self.pattern.period
        pos, yaw = obs.torso_pos[:2], quat_yaw(obs.torso_quat)
        t = state.k * self.dt
        u = jnp.clip((t - state.t_switch) / cycle, 0.0, 1.0)
        heading = state.heading_from + wrap_angle(state.heading_to - state.heading_from) * u
        scale = state.scale_from + (state.scale_to - state.scale_from) * u

        p = params.avoid
        arrived = jnp.linalg.norm(params.target - pos) <= p.goal_tol
        stop_now = arrived & ~state.done
        plan_now = (t >= state.next_plan - 0.5 * self.dt) & ~state.done & ~arrived
        # Eqs. 1-6 at the measured position (computed every step: under vmap a cond would run both sides)
        f, dirs, w, overlap = avoid.scores(pos, params.target, p, self.avoid, params.centres, params.radii,
                                           params.valid)
        f = jnp.where(overlap, jnp.inf, f)
        k = jnp.argmin(f)
        hold = jnp.all(overlap)
        switch = plan_now | stop_now
        new_heading = jnp.where(plan_now & ~hold, jnp.arctan2(dirs[k, 1], dirs[k, 0]), heading)
        new_scale = jnp.where(plan_now & ~hold, w[k], 0.0)
        st = AvoidGaitState(
            k=state.k + 1,
            heading_from=jnp.where(switch, heading, state.heading_from),
            heading_to=jnp.where(switch, new_heading, state.heading_to),
            scale_from=jnp.where(switch, scale, state.scale_from),
            scale_to=jnp.where(switch, new_scale, state.scale_to),
            t_switch=jnp.where(switch, t, state.t_switch),
            next_plan=jnp.where(plan_now, state.next_plan + self.avoid.n_T * cycle, state.next_plan),
            done=state.done | arrived,
            plans=state.plans + plan_now.astype(jnp.int32),
            held=state.held + (plan_now & hold).astype(jnp.int32),
            chosen=jnp.where(plan_now, jnp.where(hold, -1, k), state.chosen).astype(jnp.int32))
        g = params.gait.replace(step_length=params.gait.step_length * scale, direction=heading - yaw)
        return st, self.base.step(g, GaitState(t=t), obs)[1]

    def trace(self, state: AvoidGaitState, obs):
        """Recorded per control step (RolloutConfig.record): the blended world heading's target, the
        stroke scale target, done."""
        del obs
        return jnp.stack([state.heading_to, state.scale_to, state.done.astype(jnp.float32)])


def fast_gait(ctrl: PatternClock) -> GaitParams:
    """The seed-000 tripod at l = 6 cm, swing 0.25 s: 0.12 m per gait cycle, 0.24 m/s (measured on flat
    ground: 0.90 m in 4 s, heading within 4 deg of eps in every direction). The paper's 0.036 m/s would make
    a 2 m field a minute of simulated time."""
    return GaitParams(step_length=jnp.asarray(0.06), step_height=jnp.asarray(ctrl.step_height),
                      swing_time=jnp.asarray(0.25), direction=jnp.asarray(0.0),
                      body_height_offset=jnp.asarray(0.0))


def small_robot_params(robot: RobotSpec, step_length: float, advance: float, d_min: float = 0.03,
                       d_max: float = 0.12, n_dirs: int = 36) -> AvoidParams:
    """Planner params for a seed-000-sized robot facing +x: 36 directions over the forward half-plane
    (-90..85 deg, the paper's fan turned to +x), |w| = 1 (the gait walks every direction alike), one circle
    of `footprint_radius`, d_min / d_max scaled from the paper's 0.05 / 0.2 m for a 1.3 m robot to ~0.5 m
    (0.03 / 0.12 m), one time-step = one gait cycle (`advance` m), goal tolerance 0.1 m."""
    a = avoid.fan(n_dirs, 180.0, -90.0)
    return AvoidParams(angles=jnp.asarray(a, jnp.float32), capacity=jnp.ones(n_dirs, jnp.float32),
                       robot_offsets=jnp.zeros((1, 2)),
                       robot_radii=jnp.array([footprint_radius(robot, step_length)], jnp.float32),
                       d_min=jnp.float32(d_min), d_max=jnp.float32(d_max), step=jnp.float32(advance),
                       goal_tol=jnp.float32(0.1))


# Fields, terrain and the check for touching -------------------------------------------------------------
def small_fields(key, n: int, robot_radius: float, d_max: float, n_obstacles: int = 40, length: float = 2.0,
                 width: float = 1.6) -> Fields:
    """`random_fields` scaled to the seed-000 robot and turned to face +x: start (0, 0), target (2, U(-0.3,
    0.3)); `n_obstacles` circles of radius 0.05-0.12 m drawn in a 1.6 m wide corridor, of which those within
    robot radius + d_max + 2 cm of a lane swaying up to 0.6 m are dropped (~10.6 stay; the straight line is
    blocked in ~35 % of fields), so a collision-free path exists by construction."""
    f = random_fields(key, n, n_obstacles=n_obstacles, length=length, width=width, radius_range=(0.05, 0.12),
                      lane_points=3, lane_sway=0.6, lane_half_width=robot_radius + d_max + 0.02,
                      target_sway=0.3)
    turn = lambda xy: jnp.stack([xy[..., 1], -xy[..., 0]], -1)  # (x, y) -> (y, -x): +y ahead becomes +x
    return Fields(start=turn(f.start), target=turn(f.target), centres=turn(f.centres), radii=f.radii,
                  valid=f.valid, lane=turn(f.lane))


def straight_line_blocked(fields: Fields, robot_radius: float) -> np.ndarray:
    """(N,) bool: a robot circle walking the straight line from start to target would overlap an obstacle."""
    line = jnp.stack([fields.start, fields.target], 1)
    d = dist_to_polyline(fields.centres, line)
    return np.asarray(jnp.any((d < fields.radii + robot_radius) & fields.valid, -1))


def obstacle_boxes(key, fields: Fields, height: float = OBSTACLE_HEIGHT) -> Terrain:
    """Each obstacle circle as a box inscribed in it: footprint half extents r (cos a, sin a) with the aspect
    angle a drawn from U(25, 65) deg (45: a square column; elsewhere an elongated box)."""
    a = jax.random.uniform(key, fields.radii.shape, minval=math.radians(25), maxval=math.radians(65))
    hx, hy = fields.radii * jnp.cos(a), fields.radii * jnp.sin(a)
    pos = jnp.concatenate([fields.centres, jnp.full(fields.radii.shape + (1,), 0.5 * height)], -1)
    half = jnp.stack([hx, hy, jnp.full_like(hx, 0.5 * height)], -1)
    return Terrain(box_pos=pos, box_half=half, box_valid=fields.valid,
                   ground_z=jnp.zeros(fields.radii.shape[:-1]))


def _body_points(robot: RobotSpec, n_seg: int = 6):
    """Points of the robot's horizontal outline in the torso frame: the torso's perimeter (radius 0) and
    each leg's hip-to-foot chord (radius foot_radius, added by the caller). Returns (torso (P, 2),
    fractions (n_seg,) along hip -> foot)."""
    hx, hy = 0.5 * robot.body_length, 0.5 * robot.body_width
    s = np.linspace(-1, 1, 9)
    per = np.concatenate([np.stack([hx * s, np.full(9, hy)], 1), np.stack([hx * s, np.full(9, -hy)], 1),
                          np.stack([np.full(9, hx), hy * s], 1), np.stack([np.full(9, -hx), hy * s], 1)])
    return per, np.linspace(0.0, 1.0, n_seg)


def touches(robot: RobotSpec, trace, foot_trace, terrain: Terrain, chunk: int = 256) -> np.ndarray:
    """(B,) bool: at some control step a part of the robot was inside an obstacle box's footprint: a point
    of the torso outline, or a point of a leg's hip-to-foot chord within foot_radius of it (legs splay out,
    so the knee lies over that chord), or the box's centre inside the torso. trace (B, T, 4): x, y, z,
    yaw; foot_trace (B, T, 6, 3); world frame. Obstacles are taller than the robot, so height is ignored."""
    per, frac = _body_points(robot)
    hips = hip_positions(robot)[:, :2]
    out = []

    @jax.jit
    def one(tr, ft, bp, bh, bv):
        c, s = jnp.cos(tr[..., 3]), jnp.sin(tr[..., 3])
        rot = lambda p: jnp.stack([c[..., None] * p[:, 0] - s[..., None] * p[:, 1],
                                   s[..., None] * p[:, 0] + c[..., None] * p[:, 1]], -1)
        torso = rot(jnp.asarray(per)) + tr[..., None, :2]  # (T, P, 2)
        hip = rot(jnp.asarray(hips)) + tr[..., None, :2]  # (T, 6, 2)
        legs = hip[:, :, None] + (ft[..., :2] - hip)[:, :, None] * jnp.asarray(frac)[:, None]  # (T, 6, S, 2)
        pts = jnp.concatenate([torso, legs.reshape(legs.shape[0], -1, 2)], 1)  # (T, N, 2)
        rad = jnp.concatenate([jnp.zeros(torso.shape[1]), jnp.full(legs.shape[1] * legs.shape[2], robot.foot_radius)])
        d = jnp.abs(pts[:, :, None, :] - bp[None, None, :, :2]) - bh[None, None, :, :2]  # (T, N, Q, 2)
        dist = jnp.linalg.norm(jnp.maximum(d, 0.0), axis=-1) - rad[None, :, None]
        hit = jnp.any((dist <= 0.0) & bv[None, None, :])
        # a box centre inside the torso rectangle (a small box could fit between its outline points)
        rel = bp[None, :, :2] - tr[:, None, :2]  # (T, Q, 2)
        lx = c[:, None] * rel[..., 0] + s[:, None] * rel[..., 1]
        ly = -s[:, None] * rel[..., 0] + c[:, None] * rel[..., 1]
        inside = (jnp.abs(lx) <= 0.5 * robot.body_length) & (jnp.abs(ly) <= 0.5 * robot.body_width) & bv[None]
        return hit | jnp.any(inside)

    fn = jax.vmap(one)
    for i in range(0, trace.shape[0], chunk):
        sl = slice(i, i + chunk)
        out.append(np.asarray(fn(trace[sl], foot_trace[sl], terrain.box_pos[sl], terrain.box_half[sl],
                                 terrain.box_valid[sl])))
    return np.concatenate(out)


def field_params(ctrl: AvoidGaitController, fields: Fields, avoid_p: Optional[AvoidParams] = None,
                 gait: Optional[GaitParams] = None) -> AvoidGaitParams:
    """Per-env params (leading axis N) for `rollout(..., params_batched=True)`."""
    n = int(fields.start.shape[0])
    g = gait or fast_gait(ctrl)
    ap = avoid_p or small_robot_params(ctrl.robot, float(g.step_length), ctrl.advance(g))
    tile = lambda x: jnp.broadcast_to(jnp.asarray(x), (n,) + jnp.shape(x))
    return AvoidGaitParams(gait=jax.tree_util.tree_map(tile, g), avoid=jax.tree_util.tree_map(tile, ap),
                           target=fields.target, centres=fields.centres, radii=fields.radii, valid=fields.valid)


def run_closed_loop(n: int = 32, seed: int = 0, robot: str = "luneckas2020", n_T: int = 2,
                    duration: Optional[float] = None, chunk: int = 0, mesh=None, fields: Optional[Fields] = None,
                    blind: bool = False) -> Dict:
    """Closed-loop avoidance over n random fields (`small_fields`, or the given `fields`): the kinematic
    planner (`avoid.plan`, same params) and the MJX hexapod with `AvoidGaitController`, side by side.
    blind: the MJX robot's planner is not told of the obstacles (they are still in the terrain), the
    ablation that shows what the planner prevents. Returns a JSON-ready dict; the `_`-keys hold arrays for
    plots. A field counts as a closed-loop success when the robot stopped within goal_tol of the target,
    touched no obstacle, did not fall and stayed finite."""
    rb = get_robot(robot)
    ctrl = AvoidGaitController(rb, avoid=AvoidConfig(n_T=n_T, max_cycles=40))
    g = fast_gait(ctrl)
    ap = small_robot_params(rb, float(g.step_length), ctrl.advance(g))
    k_field, k_box, k_roll = jax.random.split(jax.random.PRNGKey(seed), 3)
    if fields is None:
        if not (isinstance(n, int) and n >= 1):
            raise ValueError(f"fields n={n!r}: must be an integer >= 1")
        fields = small_fields(k_field, n, float(ap.robot_radii[0]), float(ap.d_max))
    n = int(fields.start.shape[0])
    if np.any(np.asarray(fields.start) != 0):
        raise ValueError("fields.start: the MJX robot starts at (0, 0); give fields with start (0, 0)")
    avoid.check_inputs(fields.start, fields.target, fields.centres, fields.radii, fields.valid, ap, ctrl.avoid)
    kin = jax.jit(jax.vmap(lambda s, t, c, r, v: avoid.plan(s, t, c, r, v, ap, ctrl.avoid)))(
        fields.start, fields.target, fields.centres, fields.radii, fields.valid)
    kin_ok = np.asarray(kin.reached) & (np.asarray(kin.min_clearance) > 0)
    blocked = straight_line_blocked(fields, float(ap.robot_radii[0]))
    cycle = float(g.swing_time) * ctrl.pattern.period
    if duration is None:  # the slowest kinematic walk, plus two plan cycles and the stopping cycle
        duration = (int(np.max(np.asarray(kin.cycles))) + 2) * n_T * cycle + cycle
    terrain = obstacle_boxes(k_box, fields)
    params = field_params(ctrl, fields, ap, g)
    if blind:
        params = params.replace(valid=jnp.zeros_like(params.valid))
    cfg = RolloutConfig(record=True)
    chunk = chunk or n
    outs = []
    t0 = time.perf_counter()
    compile_s = 0.0
    for i in tqdm(range(0, n, chunk), desc="closed loop", unit="chunk", disable=n <= chunk):
        sl = lambda x: x[i:i + chunk]
        s = rollout(rb, jax.tree_util.tree_map(sl, terrain), ctrl, jax.tree_util.tree_map(sl, params), duration,
                    jax.random.fold_in(k_roll, i), config=cfg, params_batched=True, mesh=mesh)
        compile_s += rollout.last_compile_s
        touched = touches(rb, s.trace, s.foot_trace, jax.tree_util.tree_map(sl, terrain))
        outs.append((jax.device_get(s), touched))
    wall = time.perf_counter() - t0
    cat = lambda f: np.concatenate([np.asarray(f(o[0])) for o in outs])
    touched = np.concatenate([o[1] for o in outs])
    reached = cat(lambda s: s.final_state.done)
    fell, nan = cat(lambda s: s.fell), cat(lambda s: s.nan)
    end = cat(lambda s: s.end_pose)
    final_dist = np.linalg.norm(end[:, :2] - np.asarray(fields.target), axis=-1)
    ok = reached & ~touched & ~fell & ~nan
    traces = np.concatenate([np.asarray(o[0].trace) for o in outs])
    # clearance of the robot circle along the executed path (Eq. 1, centre = torso)
    d = jax.vmap(lambda tr, c, r, v: jnp.min(avoid.clearance(tr[:, :2], ap, c, r, v)))(
        jnp.asarray(traces), fields.centres, fields.radii, fields.valid)
    d = np.asarray(d)
    length = np.sum(np.linalg.norm(np.diff(traces[:, :, :2], axis=1), axis=-1), axis=1)
    straight = np.linalg.norm(np.asarray(fields.target - fields.start), axis=-1)
    env_steps = n * (int(round(cfg.settle_time / ctrl.dt)) + int(math.ceil(duration / ctrl.dt - 1e-9))) * 4
    frac = lambda m: float(m.mean()) if m.size else None
    res = {
        "config": {"robot": robot, "fields": n, "seed": seed, "blind": blind, "n_T_gait_cycles": n_T, "duration_s": duration,
                   "step_length": float(g.step_length), "swing_time": float(g.swing_time),
                   "advance_per_cycle": ctrl.advance(g), "robot_radius": float(ap.robot_radii[0]),
                   "d_min": float(ap.d_min), "d_max": float(ap.d_max), "goal_tol": float(ap.goal_tol),
                   "obstacle_height": OBSTACLE_HEIGHT, "device": str(jax.devices()[0].platform)},
        "obstacles_per_field": float(np.asarray(fields.valid).sum(-1).mean()),
        "straight_line_blocked": int(blocked.sum()),
        "kinematic": {"success_rate": frac(kin_ok), "collisions": int((np.asarray(kin.min_clearance) <= 0).sum()),
                      "cycles_mean": float(np.asarray(kin.cycles).mean())},
        "mjx": {
            "success_rate_where_kinematic_succeeds": frac(ok[kin_ok]),
            "success_rate_all": frac(ok),
            "success_rate_where_straight_line_blocked": frac(ok[kin_ok & blocked]),
            "reached": int(reached.sum()), "touched": int(touched.sum()), "fell": int(fell.sum()),
            "nan": int(nan.sum()),
            "touched_where_kinematic_succeeds": int(touched[kin_ok].sum()),
            "final_distance_m": {"median": float(np.median(final_dist)), "max": float(final_dist.max())},
            "circle_clearance_m": {"min": float(d.min()), "p5": float(np.percentile(d, 5)),
                                   "median": float(np.median(d))},
            "path_ratio_mean": float((length / straight)[ok].mean()) if ok.any() else None,
            "plans_mean": float(cat(lambda s: s.final_state.plans).mean()),
            "held_cycles": int(cat(lambda s: s.final_state.held).sum()),
        },
        "wall_s": wall, "compile_s": compile_s, "env_steps_per_s": env_steps / max(wall - compile_s, 1e-9),
        "_fields": fields, "_terrain": terrain, "_traces": traces, "_ok": ok, "_kin": kin, "_blocked": blocked,
    }
    return res


def plot_closed_loop(res: Dict, png: str, k: int = 6) -> None:
    """k fields, those whose straight line is blocked first: obstacle boxes (and their circles), the kinematic
    plan and the MJX torso path."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    f, tr, kin, ok = res["_fields"], res["_terrain"], res["_kin"], res["_ok"]
    order = np.concatenate([np.flatnonzero(res["_blocked"]), np.flatnonzero(~res["_blocked"])])[:k]
    k = len(order)
    cols = min(3, k)
    rows = int(math.ceil(k / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.6 * rows), squeeze=False)
    for slot, ax in enumerate(axes.ravel()):
        if slot >= k:
            ax.axis("off")
            continue
        i = int(order[slot])
        for p, h, v, c, r in zip(np.asarray(tr.box_pos[i]), np.asarray(tr.box_half[i]), np.asarray(tr.box_valid[i]),
                                 np.asarray(f.centres[i]), np.asarray(f.radii[i])):
            if not v:
                continue
            ax.add_patch(plt.Rectangle(p[:2] - h[:2], 2 * h[0], 2 * h[1], color="tab:red", alpha=0.6))
            ax.add_patch(plt.Circle(c, r, fill=False, color="tab:red", lw=0.5, ls="--"))
        n = int(kin.cycles[i])
        kp = np.asarray(kin.path[i])[: n + 1]
        ax.plot(kp[:, 0], kp[:, 1], "--o", ms=2, color="tab:green", lw=1, label="kinematic plan")
        t = res["_traces"][i]
        ax.plot(t[:, 0], t[:, 1], "-", color="k", lw=1.2, label="MJX torso")
        rad = res["config"]["robot_radius"]
        ax.add_patch(plt.Circle(t[-1, :2], rad, fill=False, color="tab:blue", lw=0.6))
        ax.plot(*np.asarray(f.target[i]), "*", color="tab:orange", ms=10)
        ax.set_aspect("equal")
        ax.set_xlim(-0.4, 2.4)
        ax.set_ylim(-0.9, 0.9)
        ax.set_title(f"field {i}{' (straight line blocked)' if res['_blocked'][i] else ''}: "
                     f"{'ok' if ok[i] else 'FAILED'}", fontsize=9)
        if slot == 0:
            ax.legend(fontsize=6, loc="lower right")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
