"""A gait steered by the avoidance planner: Zhao 2018 Sect. 3.2's direction selection, run on the simulated
Luneckas 2020 robot instead of Octopus-III.

`AvoidGaitController` wraps the Luneckas 2020 gait (`hexjax.control.gait`, Eqs. 2-4). Every n_T gait cycles,
at a cycle boundary, it reads the torso position from the simulator, scores the candidate directions with
Zhao Eqs. 1-6 (`hexjax.plan.avoid.scores`, predicting n_T gait cycles ahead) and sets the gait's walking
direction eps (Luneckas Eq. 2) to the chosen world heading minus the measured yaw. The obstacle circles,
the target and every planner number are traced params, so `rollout(..., params_batched=True)` walks
thousands of different fields in one call (`hexjax.experiments.papers.zhao2018`).

Readings and choices (also in docs/planning.md):
  * One planner time-step is one gait cycle; the planner's `step` is the gait's advance per cycle
    (l T / (T - 1)), so its predictions are where the gait would put the robot.
  * A new direction (and stroke scale) is blended in linearly over one gait cycle, from the plan time (a
    cycle boundary). The foot offsets are cos/sin(eps) times the stroke, so an abrupt eps would make every
    foot jump; blended, the feet stay continuous and the stance feet, which share one stroke phase per
    tripod, all move together.
  * Walking capacity |w_i| scales the stroke: the chosen candidate's w is the stroke scale. The Luneckas
    2020 gait moves the same stroke in any direction (measured: 0.90-0.97 m in 4 s at 0, 45, 90, -90 and
    135 deg), so `small_robot_params` sets |w| = 1 over a forward half-fan of 36 directions.
  * Where every candidate would overlap an obstacle the robot marks time (stroke 0, legs still stepping)
    until the next plan, as the kinematic planner holds its place. Within `goal_tol` of the target it stops
    for good: the stroke shrinks to 0 over one cycle.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hexjax.control.gait import GaitController, GaitParams, GaitState, PatternClock
from hexjax.plan import avoid
from hexjax.plan.avoid import AvoidConfig, AvoidParams
from hexjax.plan.fields import Fields
from hexjax.world.robot import RobotSpec, neutral_feet_body, quat_yaw, wrap_angle


@struct.dataclass
class AvoidGaitParams:
    """Traced params of one env (batch them all for per-env fields). gait: the Luneckas 2020 gait's numbers
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
    """The Luneckas 2020 gait steered by the Zhao 2018 planner (module docstring). Static: the robot, the gait
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

    params_prefix = "avoid_gait"

    def params_defaults(self) -> AvoidGaitParams:
        """The fast gait of `fast_gait`, `small_robot_params`, a target 2 m ahead and no obstacles."""
        g = fast_gait(self)
        return AvoidGaitParams(gait=g, avoid=small_robot_params(self.robot, float(g.step_length),
                                                                 advance=self.advance(g)),
                               target=jnp.array([2.0, 0.0]), centres=jnp.zeros((1, 2)),
                               radii=jnp.full((1,), 0.1), valid=jnp.zeros((1,), bool))

    def for_distance(self, distance: float, params=None):
        """Room for a detour of twice `distance` m at the fast gait, plus two cycles; the gait stops by itself
        at its target, so no stop is set."""
        g = fast_gait(self) if params is None else params.gait
        cycle = float(np.mean(g.swing_time)) * self.pattern.period
        return self, (math.ceil(2 * distance / self.advance(g)) + 2) * cycle

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
    """The Luneckas 2020 tripod at l = 6 cm, swing 0.25 s: 0.12 m per gait cycle, 0.24 m/s (measured on flat
    ground: 0.90 m in 4 s, heading within 4 deg of eps in every direction). The paper's 0.036 m/s would make
    a 2 m field a minute of simulated time."""
    return GaitParams(step_length=jnp.asarray(0.06), step_height=jnp.asarray(ctrl.step_height),
                      swing_time=jnp.asarray(0.25), direction=jnp.asarray(0.0),
                      body_height_offset=jnp.asarray(0.0))


def small_robot_params(robot: RobotSpec, step_length: float, advance: float, d_min: float = 0.03,
                       d_max: float = 0.12, n_dirs: int = 36) -> AvoidParams:
    """Planner params for a Luneckas 2020-sized robot facing +x: 36 directions over the forward half-plane
    (-90..85 deg, the paper's fan turned to +x), |w| = 1 (the gait walks every direction alike), one circle
    of `footprint_radius`, d_min / d_max scaled from the paper's 0.05 / 0.2 m for a 1.3 m robot to ~0.5 m
    (0.03 / 0.12 m), one time-step = one gait cycle (`advance` m), goal tolerance 0.1 m."""
    a = avoid.fan(n_dirs, 180.0, -90.0)
    return AvoidParams(angles=jnp.asarray(a, jnp.float32), capacity=jnp.ones(n_dirs, jnp.float32),
                       robot_offsets=jnp.zeros((1, 2)),
                       robot_radii=jnp.array([footprint_radius(robot, step_length)], jnp.float32),
                       d_min=jnp.float32(d_min), d_max=jnp.float32(d_max), step=jnp.float32(advance),
                       goal_tol=jnp.float32(0.1))


def field_params(ctrl: AvoidGaitController, fields: Fields, avoid_p: Optional[AvoidParams] = None,
                 gait: Optional[GaitParams] = None) -> AvoidGaitParams:
    """Per-env params (leading axis N) for `rollout(..., params_batched=True)`."""
    n = int(fields.start.shape[0])
    g = gait or fast_gait(ctrl)
    ap = avoid_p or small_robot_params(ctrl.robot, float(g.step_length), ctrl.advance(g))
    tile = lambda x: jnp.broadcast_to(jnp.asarray(x), (n,) + jnp.shape(x))
    return AvoidGaitParams(gait=jax.tree_util.tree_map(tile, g), avoid=jax.tree_util.tree_map(tile, ap),
                           target=fields.target, centres=fields.centres, radii=fields.radii, valid=fields.valid)


