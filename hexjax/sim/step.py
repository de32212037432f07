"""One control step of one env, written once: what the MJX rollout scans, what the Brax env steps, and what
the MuJoCo C backend's summary is accumulated with.

A control step (period `controller.dt`, `substeps` physics steps):
  1. terrain slots follow the feet, giving the env's model (`env_view`), and the sensors are read;
  2. `controller_phase`: the controller maps (params, state, obs) to joint targets, held at the settle posture
     while settling, with a perturbation's sensing and action effects around it;
  3. `physics` runs the substeps; a step that goes non-finite is undone (the engine's `keep_finite`) and flagged;
  4. `accumulate` folds the step into the env's `Summary` fields: the fall test (`fall_state`), the start
     pose, energy, path length, travel, tilt and height extremes, tactile counts.
`make_control_step` composes 1-4 (with the rollout's gradient truncation and bounds) for `lax.scan`; the
windowed gradient (`hexjax.sim.windows`) runs that same step, and the MuJoCo C engine (`hexjax.sim.engines.c`)
calls `start_yaw`, `controller_phase`, `accumulate` and `summarise` between its physics calls, so every
engine's start, controller phase and summary are these functions. What differs between the MJX-family engines
(how sensors are read, which fields a non-finite step restores, where gradients stop) is asked of the model's
engine (`sm.engine`); this module imports none.
"""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Any, Optional

import jax
import jax.numpy as jnp
from flax import struct

from hexjax.perceive import raycast
from hexjax.sim import perturb
from hexjax.sim.internals import implicit
from hexjax.sim.config import RolloutConfig, SensorConfig, substeps
from hexjax.sim.grad import clip_cotangent, cut_gradient
from hexjax.sim.model import SimModel, assign_slots, env_model, mjx
from hexjax.sim.slip import slip
from hexjax.world.robot import quat_yaw, wrap_angle
from hexjax.world.terrain import Terrain

# mjx.Data fields that hold one env's state between control steps; on the warp engine only these
# are restored when a step goes non-finite (its contact pool is shared by all envs, so a per-env select
# over the whole Data is not possible; the rest is recomputed from them by the next step)
STATE_FIELDS = ("qpos", "qvel", "act", "time", "qacc_warmstart")

# mjx.Data fields through which the next physics or control step depends on this one: the integration state
# (MJX's `step` recomputes everything else from it) and what hexjax reads from the last step's Data (foot sites
# for the slot assignment in `env_view`, contact forces and frames in `read_obs`). Every other field is derived
# and never read across steps, so its gradient there is zero; `stop_derived` makes that zero symbolic, or the
# scan's transpose would carry a dense cotangent of the whole Data (~55 kB an env) through every step and
# run the backward of every derived field on it.
GRAD_FIELDS = frozenset({".qpos", ".qvel", ".act", ".time", ".qacc_warmstart", ".ctrl", ".mocap_pos", ".mocap_quat",
                         ".qfrc_applied", ".xfrc_applied", ".site_xpos", "._impl.efc_force",
                         "._impl.contact.frame", "._impl.contact.friction"})


def stop_derived(d):
    """`d` (MJX-JAX Data) with the gradient stopped on every float field outside `GRAD_FIELDS`; the same in value."""
    def f(path, x):
        if jax.tree_util.keystr(path) in GRAD_FIELDS or not jnp.issubdtype(jnp.asarray(x).dtype, jnp.inexact):
            return x
        return jax.lax.stop_gradient(x)
    return jax.tree_util.tree_map_with_path(f, d)


@struct.dataclass
class Summary:
    """Per-env outcome of a rollout (leading axis B on every field). Poses are (x m, y m, yaw rad).

    start_pose / end_pose (B, 3)  torso pose after settling / at the end
    fell (B,) bool, fall_time (B,) s (inf if none)   torso tilt or height left the safe range (`fall_state`)
    nan (B,) bool                 the state went non-finite; the env was frozen at its last finite state
    energy (B,) J                 integral of |torque * joint rate| over all joints
    path_length (B,) m            horizontal distance travelled by the torso
    travel (B, 3)                 sum over control steps of the torso's (dx m, dy m, dyaw rad) in the world
                                  frame: end pose - start pose (yaw unwrapped), with gradients truncated at
                                  `RolloutConfig.grad_window` boundaries
    max_tilt (B,) rad, min_height (B,) m (torso centre above the ground plane)
    tactile_steps (B, 6)          control steps with each leg's tactile pad on
    foot_slip (B,) m              horizontal distance the feet slid while they stood: the point of each foot
                                  that touched the ground, summed over control steps and feet in contact at the
                                  step's start that did not rise during it (`hexjax.sim.slip.slip`)
    overflow (B,) int or None     the engine's overflow flags over the walk (MuJoCo Warp: a bitmask of the
                                  limits and pools each world hit, `hexjax.sim.engines.warp.overflow_counts`)
    trace (B, T, 4) or None       x, y, z, yaw per control step when RolloutConfig.record
    foot_trace (B, T, 6, 3) or None  foot centres, world frame, m, when RolloutConfig.record
    ctrl_trace or None            the controller's `trace(state, obs)` per step, when RolloutConfig.record
    qpos_trace (B, T, 25) or None  full generalised position (torso xyz, quat, 18 joints) per step, when
                                  RolloutConfig.record (what `hexjax.render` replays)
    force_trace (B, T, 6, 3), tactile_trace (B, T, 6) or None  each foot's terrain force (N, world) and
                                  tactile pad on/off per step, when RolloutConfig.record
    final_state                   the controller state after the last step (reflex counters etc.)
    """

    start_pose: jax.Array
    end_pose: jax.Array
    fell: jax.Array
    fall_time: jax.Array
    nan: jax.Array
    energy: jax.Array
    path_length: jax.Array
    travel: jax.Array
    max_tilt: jax.Array
    min_height: jax.Array
    tactile_steps: jax.Array
    trace: Optional[jax.Array] = None
    foot_trace: Optional[jax.Array] = None
    ctrl_trace: Any = None
    final_state: Any = None
    qpos_trace: Optional[jax.Array] = None
    force_trace: Optional[jax.Array] = None
    tactile_trace: Optional[jax.Array] = None
    foot_slip: Optional[jax.Array] = None
    overflow: Optional[jax.Array] = None


# The fall test and the accumulators ------------------------------------------------------------------------
def tilt(q):
    """Angle between the torso z axis and world z, rad, of quaternions q (..., 4)."""
    x, y = q[..., 1], q[..., 2]
    up_z = 1 - 2 * (x * x + y * y)
    # clipped inside (-1, 1) so the derivative stays finite for an upright torso (jax.grad)
    return jnp.arccos(jnp.clip(up_z / jnp.maximum(jnp.sum(q * q, -1), 1e-9), -1.0 + 1e-6, 1.0 - 1e-6))


def fall_state(cfg: RolloutConfig, qpos, ground_z):
    """(fallen, tilt rad, height m) of one env's state: fallen when the torso tilts past `cfg.fall_tilt` or its
    centre comes closer than `cfg.fall_height` to the ground plane."""
    height = qpos[2] - ground_z
    t = tilt(qpos[3:7])
    return (t > cfg.fall_tilt) | (height < cfg.fall_height), t, height


def init_acc(start_pose):
    """Summary accumulators of one env before its first step; `start_pose` (3,) until settling ends."""
    return dict(start_pose=start_pose, fell=jnp.asarray(False), fall_time=jnp.asarray(jnp.inf),
                nan=jnp.asarray(False), energy=jnp.asarray(0.0), path_length=jnp.asarray(0.0),
                travel=jnp.zeros(3), max_tilt=jnp.asarray(0.0), min_height=jnp.asarray(jnp.inf),
                tactile_steps=jnp.zeros(6, jnp.int32), foot_slip=jnp.asarray(0.0))


@dataclasses.dataclass(frozen=True)
class StepClock:
    """Where a control step lies in a rollout: `i` its index (0-based, settling included; traced in a scan), after
    `n_settle` settling steps of `dt` s each. Both engines' control steps take it (`controller_phase`,
    `accumulate`)."""

    i: Any
    n_settle: int
    dt: float

    @property
    def walking(self):
        """Whether the step is past settling."""
        return self.i >= self.n_settle

    @property
    def t_walk(self):
        """Seconds walked when the step begins (negative while settling)."""
        return (self.i - self.n_settle) * self.dt


def accumulate(acc, cfg: RolloutConfig, clock: StepClock, q_old, q_new, finite, energy, tactile, ground_z,
               slipped=0.0):
    """The accumulators after the control step at `clock` of one env: q_old, q_new
    (nq,) the generalised positions before and after it (q_new already reset where the step was not
    finite), energy () J of the step, tactile (6,) pads on, slipped () m the feet slid (`hexjax.sim.slip.slip`).
    Settling steps count only for the start pose."""
    i, n_settle, walking = clock.i, clock.n_settle, clock.walking
    fallen, t, height = fall_state(cfg, q_new, ground_z)
    fallen_now = walking & fallen
    t_now = (i + 1 - n_settle) * clock.dt
    dxy = q_new[:2] - q_old[:2]
    step_xy = jnp.sqrt(jnp.sum(dxy * dxy) + 1e-18)  # offset keeps the derivative finite at rest
    pose = jnp.stack([q_new[0], q_new[1], quat_yaw(q_new[3:7])])
    dyaw = wrap_angle(pose[2] - quat_yaw(q_old[3:7]))
    return dict(
        start_pose=jnp.where(i == n_settle - 1, pose, acc["start_pose"]),
        fell=acc["fell"] | fallen_now,
        fall_time=jnp.where(fallen_now & ~acc["fell"], t_now, acc["fall_time"]),
        nan=acc["nan"] | ~finite,
        energy=acc["energy"] + jnp.where(walking & finite, energy, 0.0),
        path_length=acc["path_length"] + jnp.where(walking & finite, step_xy, 0.0),
        travel=acc["travel"] + jnp.where(walking, jnp.concatenate([dxy, dyaw[None]]), 0.0),
        max_tilt=jnp.maximum(acc["max_tilt"], jnp.where(walking, t, 0.0)),
        min_height=jnp.minimum(acc["min_height"], jnp.where(walking, height, jnp.inf)),
        tactile_steps=acc["tactile_steps"] + (walking & tactile).astype(jnp.int32),
        foot_slip=acc["foot_slip"] + jnp.where(walking & finite, slipped, 0.0),
    )


def end_pose(qpos):
    """(x, y, yaw) (..., 3) of generalised positions (..., nq)."""
    return jnp.stack([qpos[..., 0], qpos[..., 1], quat_yaw(qpos[..., 3:7])], -1)


def summarise(acc, qpos_end, final_state, **traces) -> Summary:
    """The `Summary` of a rollout from its accumulators (`accumulate`), the generalised positions at its end
    (..., nq), the controller state after its last step and any of the per-step traces (`Summary`'s *_trace
    fields). Every backend builds its summary here."""
    return Summary(end_pose=end_pose(qpos_end), final_state=final_state, **traces, **acc)


# The controller phase -----------------------------------------------------------------------------------------
def start_yaw(cfg: RolloutConfig, key):
    """(heading rad (), the controller's init key) of one env from its key: the heading uniform within
    +-`cfg.yaw_noise`."""
    k_yaw, k_ctrl = jax.random.split(key)
    return jax.random.uniform(k_yaw, (), minval=-cfg.yaw_noise, maxval=cfg.yaw_noise), k_ctrl


def controller_phase(controller, sensors: SensorConfig, params, cstate, obs, clock: StepClock, ctrl0, pert=None,
                     pstate=None, sense=None):
    """The controller's part of the control step at `clock` of one env: (controller state, joint targets,
    perturbation state, what the controller read). While settling the targets are `ctrl0`
    and the state stays as it was. With `pert` (one env's `Perturbation`) the controller reads the draw's
    perturbed sensing (`hexjax.sim.perturb.observe`) and the targets go through its latency and locked leg
    (`hexjax.sim.perturb.act`, with `pstate`); `obs` stays the true reading. `sense(cstate) -> cstate`, if given,
    runs before the controller's step (the range sensor's scan)."""
    t_walk = clock.t_walk
    seen = obs if pert is None else perturb.observe(obs, pert, clock.i, t_walk, sensors)
    if sense is not None:
        cstate = sense(cstate)
    with jax.named_scope("hx.controller"):
        new_cstate, action = controller.step(params, cstate, seen)
    walking = clock.walking
    action = jnp.where(walking, action, ctrl0)
    cstate = jax.tree_util.tree_map(lambda a, b: jnp.where(walking, a, b), new_cstate, cstate)
    if pert is not None:
        pstate, action = perturb.act(pstate, action, obs.qpos, pert, t_walk)
    return cstate, action, pstate, seen


# Model, sensors and physics of one env ---------------------------------------------------------------------
def env_view(sm: SimModel, sensors: SensorConfig, terrain: Terrain, d, base=None):
    """(model, data, obs) of one env at data d: slots moved onto the terrain boxes nearest the feet and torso
    (`base`: the shared model, default `sm.mjx_model`), then the sensors read as the model's engine reads them."""
    slot_pos, slot_size = assign_slots(sm, terrain, d.site_xpos[jnp.asarray(sm.foot_sites), :2], d.qpos[:2])
    m = env_model(sm, terrain, slot_pos, slot_size, base=base)
    d, obs = sm.engine.observe(sm, sensors, terrain, m, d, slot_pos)
    return m, d, obs


def physics(m, d, n_sub: int, detach=None, unroll: bool = False):
    """`n_sub` mjx.step calls: (data after them, actuator power |torque * joint rate| (n_sub,) W). `detach`:
    applied to the data after each step (the engine's: MJX passes gradient from step to step through
    `GRAD_FIELDS` only, `stop_derived`). `unroll`: trace the steps one after another instead of as a loop
    (`RolloutConfig.unroll_substeps`)."""
    def sub(dd, _):
        dd = mjx.step(m, dd)
        power = jnp.sum(jnp.abs(dd.actuator_force * dd.qvel[6:]))
        return (detach(dd) if detach is not None else dd), power

    channel = implicit.solutions_channel()
    if channel is None:
        return jax.lax.scan(sub, d, None, length=n_sub, unroll=unroll)

    # inside `hexjax.sim.internals.implicit.solutions` (the windowed backward, `hexjax.sim.windows`): each substep's
    # constraint solution is kept, or taken from those kept before
    def sub_channel(dd, given):
        with implicit.solution_slot(given) as slot:
            dd, power = sub(dd, None)
        return dd, (power, slot["kept"])

    d, (power, kept) = jax.lax.scan(sub_channel, d, channel["given"], length=n_sub, unroll=unroll)
    channel["kept"] = kept
    return d, power


# The start of an env ----------------------------------------------------------------------------------------
def make_env_start(sm: SimModel, cfg: RolloutConfig, controller):
    """(start, settle_action): `start(m_shared, params, key, d_template) -> ((d0, cstate0, acc0), ctrl0, sense_key)`
    of one env, and `settle_action(params) -> ctrl0` alone. The env starts with its
    heading drawn from `key` within `cfg.yaw_noise`, the legs in the controller's first posture (its
    `initial_action`, else the model's `ctrl0`), forwarded once so that site positions exist before the first
    slot assignment; `ctrl0` the targets held while settling; `sense_key` the range sensor's noise key (None
    for controllers without a `sensor`). With MJX-JAX, gradients cross control steps through the state only
    (`GRAD_FIELDS`)."""
    ctrl0_default = jnp.asarray(sm.ctrl0)

    def settle_action(params):
        # a controller may ask to settle in its own first posture (the CPG starts mid-stride)
        ctrl0 = controller.initial_action(params)
        return ctrl0_default if ctrl0 is None else ctrl0

    def start(m_shared, params, key, d_template=None):
        yaw0, k_ctrl = start_yaw(cfg, key)
        d0 = sm.init_data(jnp.stack([0.0, 0.0, yaw0]), d_template)
        cstate0 = controller.init(params, k_ctrl)
        ctrl0 = settle_action(params)
        d0 = d0.replace(qpos=d0.qpos.at[7:].set(ctrl0), ctrl=ctrl0)
        acc0 = init_acc(jnp.stack([d0.qpos[0], d0.qpos[1], yaw0]))
        d0 = sm.engine.detach(mjx.forward(m_shared, d0))
        if cfg.grad_clip is not None:
            # Every leaf of the state one per env. Under `vmap` a leaf that starts equal for all envs and never
            # reads an env's data (the gait clock, Data.time) stays one unbatched value, and reverse mode sums its
            # cotangent over the batch: the per-env bound (`clip_cotangent`) then saw that batch sum in its norm
            # and bound each env by the others (docs/tuning.md, 2026-11-27). Adding the env's own zero batches it.
            zero = 0.0 * yaw0
            d0, cstate0 = jax.tree_util.tree_map(lambda x: x + zero.astype(jnp.asarray(x).dtype), (d0, cstate0))
        # the range sensor's noise (controllers with a `sensor` only: other programs stay as they were)
        k_sense = jax.random.fold_in(key, 1) if getattr(controller, "sensor", None) is not None else None
        return (d0, cstate0, acc0), ctrl0, k_sense

    return start, settle_action


# The control step, as the rollout scans it -----------------------------------------------------------------
_PROGRESS_SINK = [None]


def _report_progress(i):
    sink = _PROGRESS_SINK[0]
    if sink is not None:
        sink(int(i))


@contextlib.contextmanager
def progress_to(sink):
    """While open, a rollout compiled with `RolloutConfig.progress_every` > 0 calls `sink(control_step_index)`
    from the device every `progress_every` steps (e.g. to move a tqdm bar). The index counts settling steps too;
    the total is settle_time / dt + ceil(duration / dt)."""
    prev, _PROGRESS_SINK[0] = _PROGRESS_SINK[0], sink
    try:
        yield
    finally:
        _PROGRESS_SINK[0] = prev


def make_control_step(sm: SimModel, sensors: SensorConfig, cfg: RolloutConfig, controller, n_settle: int):
    """`step(carry, i, params, terrain, m_shared, ctrl0, pert=None, sense_key=None) -> (carry, record)` of one env for
    `lax.scan`, with carry = (mjx.Data, controller state, accumulators) and record the step's traces (None
    unless `cfg.record`). `ctrl0` (18,): the joint targets held while settling. With `pert` (one env's
    `Perturbation`) the carry has a fourth member, a `hexjax.sim.perturb.PerturbState`, and the draw acts on
    the env's model, its sensor readings and the action (`hexjax.sim.perturb`); the summary's tactile counts
    and the recorded forces stay the true ones. A controller with a range `sensor` gets a scan of the terrain
    from the torso's simulated pose every `perceive_every` steps of the walk (`controller.perceive`, before its
    step); `sense_key` (one env's PRNG key) draws the scans' noise. The scan is a `lax.cond` on the step index,
    which is the same for every env, so under `vmap` it runs on scan steps only."""
    n_sub = substeps(sm.physics, controller.dt)
    foot_sites = jnp.asarray(sm.foot_sites)
    dt = sm.physics.timestep

    sensor = getattr(controller, "sensor", None)
    every = int(getattr(controller, "perceive_every", 1))

    def sense(cstate, i, params, terrain, d, key):
        k_scan, k_map = jax.random.split(jax.random.fold_in(key, i))
        scan = raycast.scan(sensor, d.qpos[:3], d.qpos[3:7], terrain, k_scan)
        return controller.perceive(params, cstate, scan, k_map)

    def step(carry, i, params, terrain, m_shared, ctrl0, pert=None, sense_key=None):
        d, cstate, acc = carry[:3]
        if cfg.progress_every:
            jax.lax.cond((i + 1) % cfg.progress_every == 0,
                         lambda: jax.debug.callback(_report_progress, i + 1), lambda: None)
        if cfg.grad_window:
            d, cstate = cut_gradient((d, cstate), i % cfg.grad_window == 0)
        if cfg.grad_clip is not None:
            d, cstate = clip_cotangent((d, cstate), cfg.grad_clip)
        with jax.named_scope("hx.env_view"):  # scopes name the stages in profiles (scripts/profile_grad.py)
            m, d, obs = env_view(sm, sensors, terrain, d, base=m_shared)
        if pert is not None:
            m = perturb.model(sm, m, pert, (i - n_settle) * controller.dt)
        if sensor is not None and sense_key is None:
            raise ValueError(f"{type(controller).__name__} has a range sensor: its control step needs a "
                             "sense_key (one PRNG key per env) to draw the scans' noise")

        def scan(c):
            return jax.lax.cond((i >= n_settle) & ((i - n_settle) % every == 0),
                                lambda c: sense(c, i, params, terrain, d, sense_key), lambda c: c, c)

        clock = StepClock(i, n_settle, controller.dt)
        cstate, action, pstate, seen = controller_phase(controller, sensors, params, cstate, obs, clock, ctrl0,
                                                        pert, carry[3] if pert is not None else None,
                                                        scan if sensor is not None else None)
        if cfg.grad_clip is not None:  # the physics' gradient reaches the controller through the action
            action = clip_cotangent(action, cfg.grad_clip)
        d = d.replace(ctrl=action)
        d_new, power = physics(m, d, n_sub, detach=sm.engine.detach, unroll=cfg.unroll_substeps)
        d_new, finite = sm.engine.keep_finite(d_new, d)
        with jax.named_scope("hx.accumulate"):
            acc = accumulate(acc, cfg, clock, d.qpos, d_new.qpos, finite, jnp.sum(power) * dt, obs.tactile,
                             terrain.ground_z, slip(sm.robot, d.qpos, d_new.qpos, obs.foot_contact))
        out = None
        if cfg.record:
            out = dict(pose=jnp.concatenate([d_new.qpos[:3], quat_yaw(d_new.qpos[3:7])[None]]),
                       feet=d_new.site_xpos[foot_sites], ctrl=controller.trace(cstate, seen),
                       qpos=d_new.qpos, force=obs.foot_force, tactile=obs.tactile)
        carry = (d_new, cstate, acc) if pert is None else (d_new, cstate, acc, pstate)
        return carry, out

    return step
