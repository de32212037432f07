"""The batched rollout: lax.scan over control steps (mjx.step x substeps inside), vmap over envs, jit,
optionally sharded over a device mesh along the batch axis."""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import Any, Optional

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from hexjax.mjcf import PhysicsConfig
from hexjax.robot import RobotSpec, quat_yaw, wrap_angle
from hexjax.sim.model import SensorConfig, assign_slots, env_model, mjx, obs_from_sensordata, \
    place_static_geoms, read_obs, reversible_solver, sim_model
from hexjax.terrain import Terrain


@dataclasses.dataclass(frozen=True)
class RolloutConfig:
    """Static rollout settings (changing one recompiles)."""

    settle_time: float = 0.3  # s of standing before the controller starts; start pose is taken after it
    yaw_noise: float = math.radians(3.0)  # initial heading drawn from U(-yaw_noise, yaw_noise), rad
    fall_tilt: float = math.radians(60.0)  # torso tilt beyond this counts as a fall, rad
    fall_height: float = 0.03  # torso centre closer than this to the ground plane counts as a fall, m
    record: bool = False  # keep a per-control-step torso trace (B, T, 4): x, y, z, yaw
    # Reverse mode only: bound the norm of the gradient flowing back through the physics and controller
    # state at every control step (None: exact gradients). Gradients through stiff contacts grow ~100x per 0.1 s and
    # overflow within a second; a per-step bound keeps them finite and their direction local.
    grad_clip: Optional[float] = None
    # Reverse mode only: truncated gradients. Every `grad_window` control steps the physics and controller
    # state are cut from the gradient (stop_gradient), so the gradient of `Summary.travel` is the sum of the
    # per-window gradients with each window's start state held fixed (truncated backpropagation through
    # time; 0: no cut). Its value is unchanged.
    grad_window: int = 0
    # Recompute each control step in the backward pass instead of storing its internals (jax.checkpoint):
    # memory per env and step drops from every substep's solver residuals to one mjx.Data.
    remat: bool = False
    # Trace MJX's Newton iterations as a fixed-length scan (`hexjax.sim.model.reversible_solver`) so reverse
    # mode works with physics.iterations > 1. Without it, gradients need iterations=1, and one unconverged
    # Newton step makes the rollout non-smooth in the params (central differences flip sign with the step
    # size; tests/test_tune.py).
    reversible_solver: bool = False
    # Every this many control steps the compiled rollout reports its step index to the host (see
    # `progress_to`); 0: never. A host callback costs ~0.1 ms, so a few hundred calls are free.
    progress_every: int = 0

    def validate(self) -> None:
        if not (isinstance(self.grad_window, int) and self.grad_window >= 0):
            raise ValueError(f"rollout.grad_window={self.grad_window!r}: must be an integer >= 0")
        if not (isinstance(self.progress_every, int) and self.progress_every >= 0):
            raise ValueError(f"rollout.progress_every={self.progress_every!r}: must be an integer >= 0")
        if self.settle_time < 0:
            raise ValueError(f"rollout.settle_time={self.settle_time!r}: must be >= 0")
        if not 0 <= self.yaw_noise < math.pi:
            raise ValueError(f"rollout.yaw_noise={self.yaw_noise!r}: must be in [0, pi)")
        if not 0 < self.fall_tilt <= math.pi:
            raise ValueError(f"rollout.fall_tilt={self.fall_tilt!r}: must be in (0, pi]")
        if self.grad_clip is not None and not (math.isfinite(self.grad_clip) and self.grad_clip > 0):
            raise ValueError(f"rollout.grad_clip={self.grad_clip!r}: must be None or a finite number > 0")


_PROGRESS_SINK = [None]


def _report_progress(i):
    sink = _PROGRESS_SINK[0]
    if sink is not None:
        sink(int(i))


class progress_to:
    """Context manager: while open, a rollout compiled with `RolloutConfig.progress_every` > 0 calls
    `sink(control_step_index)` from the device every `progress_every` steps (e.g. to move a tqdm bar).
    The index counts settling steps too; the total is settle_time / dt + ceil(duration / dt)."""

    def __init__(self, sink):
        self.sink = sink

    def __enter__(self):
        self.prev, _PROGRESS_SINK[0] = _PROGRESS_SINK[0], self.sink
        return self

    def __exit__(self, *exc):
        _PROGRESS_SINK[0] = self.prev
        return False


def _clip_cotangent(tree, bound: float):
    """Identity on the float leaves of `tree`; in reverse mode their cotangent is scaled to global norm
    <= bound (and non-finite cotangents are zeroed)."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    is_f = [jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating) for x in leaves]
    fl = [x for x, f in zip(leaves, is_f) if f]

    @jax.custom_vjp
    def ident(xs):
        return xs

    def fwd(xs):
        return xs, None

    def bwd(_, gs):
        gs = [jnp.where(jnp.isfinite(g), g, 0.0) for g in gs]
        # the norm of cotangents near float32's limit overflows when squared (an inf norm would scale
        # everything to zero): take it relative to the largest entry
        big = jnp.maximum(jnp.max(jnp.stack([jnp.max(jnp.abs(g), initial=0.0) for g in gs])), 1e-30)
        norm = big * jnp.sqrt(sum(jnp.sum(jnp.square(g / big)) for g in gs))
        scale = jnp.minimum(1.0, bound / jnp.maximum(norm, 1e-30))
        return ([g * scale for g in gs],)

    ident.defvjp(fwd, bwd)
    out = iter(ident(fl))
    return jax.tree_util.tree_unflatten(treedef, [next(out) if f else x for x, f in zip(leaves, is_f)])


def _cut_gradient(tree, cut):
    """Identity in value; where the traced bool `cut` holds, the float leaves of `tree` pass no gradient."""
    def f(x):
        if not jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating):
            return x
        return jnp.where(cut, jax.lax.stop_gradient(x), x)
    return jax.tree_util.tree_map(f, tree)


@struct.dataclass
class Summary:
    """Per-env outcome of a rollout (leading axis B on every field). Poses are (x m, y m, yaw rad).

    start_pose / end_pose (B, 3)  torso pose after settling / at the end
    fell (B,) bool, fall_time (B,) s (inf if none)   torso tilt or height left the safe range
    nan (B,) bool                 the state went non-finite; the env was frozen at its last finite state
    energy (B,) J                 integral of |torque * joint rate| over all joints
    path_length (B,) m            horizontal distance travelled by the torso
    travel (B, 3)                 sum over control steps of the torso's (dx m, dy m, dyaw rad) in the world
                                  frame: end pose - start pose (yaw unwrapped), with gradients truncated at
                                  `RolloutConfig.grad_window` boundaries
    max_tilt (B,) rad, min_height (B,) m (torso centre above the ground plane)
    tactile_steps (B, 6)          control steps with each leg's tactile pad on
    trace (B, T, 4) or None       x, y, z, yaw per control step when RolloutConfig.record
    foot_trace (B, T, 6, 3) or None  foot centres, world frame, m, when RolloutConfig.record
    ctrl_trace or None            the controller's `trace(state, obs)` per step, when it has one and
                                  RolloutConfig.record
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


def _tilt(q):
    """Angle between the torso z axis and world z, rad, of quaternions q (..., 4)."""
    x, y = q[..., 1], q[..., 2]
    up_z = 1 - 2 * (x * x + y * y)
    # clipped inside (-1, 1) so the derivative stays finite for an upright torso (jax.grad)
    return jnp.arccos(jnp.clip(up_z / jnp.maximum(jnp.sum(q * q, -1), 1e-9), -1.0 + 1e-6, 1.0 - 1e-6))


def _substeps(physics: PhysicsConfig, ctrl_dt: float) -> int:
    n = ctrl_dt / physics.timestep
    if abs(n - round(n)) > 1e-6 or round(n) < 1:
        raise ValueError(f"controller.dt={ctrl_dt!r} must be a whole multiple of physics.timestep={physics.timestep!r}")
    return int(round(n))


BACKENDS = ("mjx", "warp", "c")

# mjx.Data fields that hold one env's state between control steps; with the Warp implementation only these
# are restored when a step goes non-finite (its contact pool is shared by all envs, so a per-env select
# over the whole Data is not possible; the rest is recomputed from them by the next step)
_STATE_FIELDS = ("qpos", "qvel", "act", "time", "qacc_warmstart")


@functools.lru_cache(maxsize=32)
def _compiled(robot: RobotSpec, physics: PhysicsConfig, sensors: SensorConfig, controller: Any,
              cfg: RolloutConfig, n_ctrl: int, params_batched: bool, impl: str = "jax"):
    sm = sim_model(robot, physics, impl)
    warp = impl == "warp"
    n_sub = _substeps(physics, controller.dt)
    n_settle = int(round(cfg.settle_time / controller.dt))
    n_total = n_settle + n_ctrl
    ctrl0_default = jnp.asarray(sm.ctrl0)
    has_init_action = hasattr(controller, "initial_action")
    has_trace = hasattr(controller, "trace")
    foot_sites = jnp.asarray(sm.foot_sites)
    dt = physics.timestep

    def observe(m, d):
        if warp:
            return obs_from_sensordata(sensors, d.qpos, d.qvel, d.sensordata, d.time)
        return read_obs(sm, sensors, m, d)

    def single(m_shared, params, terrain: Terrain, key, d_template):
        k_yaw, k_ctrl = jax.random.split(key)
        yaw0 = jax.random.uniform(k_yaw, (), minval=-cfg.yaw_noise, maxval=cfg.yaw_noise)
        d0 = sm.init_data(jnp.stack([0.0, 0.0, yaw0]), d_template)
        cstate0 = controller.init(params, k_ctrl)
        # a controller may ask to settle in its own first posture (the CPG starts mid-stride)
        ctrl0 = controller.initial_action(params) if has_init_action else ctrl0_default
        d0 = d0.replace(qpos=d0.qpos.at[7:].set(ctrl0), ctrl=ctrl0)

        def control_step(carry, i):
            d, cstate, acc = carry
            if cfg.progress_every:
                jax.lax.cond((i + 1) % cfg.progress_every == 0,
                             lambda: jax.debug.callback(_report_progress, i + 1), lambda: None)
            if cfg.grad_window:
                d, cstate = _cut_gradient((d, cstate), i % cfg.grad_window == 0)
            if cfg.grad_clip is not None:
                d, cstate = _clip_cotangent((d, cstate), cfg.grad_clip)
            foot_xy = d.site_xpos[foot_sites, :2]
            slot_pos, slot_size = assign_slots(sm, terrain, foot_xy, d.qpos[:2])
            m = env_model(sm, terrain, slot_pos, slot_size, base=m_shared)
            if warp:
                d = place_static_geoms(sm, d, terrain, slot_pos)
            obs = observe(m, d)
            new_cstate, action = controller.step(params, cstate, obs)
            walking = i >= n_settle
            action = jnp.where(walking, action, ctrl0)
            cstate = jax.tree_util.tree_map(lambda a, b: jnp.where(walking, a, b), new_cstate, cstate)
            if cfg.grad_clip is not None:  # the physics' gradient reaches the controller through the action
                action = _clip_cotangent(action, cfg.grad_clip)
            d = d.replace(ctrl=action)

            def sub(dd, _):
                dd = mjx.step(m, dd)
                power = jnp.sum(jnp.abs(dd.actuator_force * dd.qvel[6:]))
                return dd, power

            d_new, power = jax.lax.scan(sub, d, None, length=n_sub)
            finite = jnp.all(jnp.isfinite(d_new.qpos)) & jnp.all(jnp.isfinite(d_new.qvel))
            if warp:
                d_new = d_new.replace(**{f: jnp.where(finite, getattr(d_new, f), getattr(d, f)) for f in _STATE_FIELDS})
            else:
                d_new = jax.tree_util.tree_map(lambda a, b: jnp.where(finite, a, b), d_new, d)
            q = d_new.qpos[3:7]
            height = d_new.qpos[2] - terrain.ground_z
            tilt = _tilt(q)
            fallen_now = walking & ((tilt > cfg.fall_tilt) | (height < cfg.fall_height))
            t_now = (i + 1 - n_settle) * controller.dt
            dxy = d_new.qpos[:2] - d.qpos[:2]
            step_xy = jnp.sqrt(jnp.sum(dxy * dxy) + 1e-18)  # offset keeps the derivative finite at rest
            pose = jnp.stack([d_new.qpos[0], d_new.qpos[1], quat_yaw(q)])
            yaw_step = pose[2] - quat_yaw(d.qpos[3:7])
            dyaw = wrap_angle(yaw_step)
            acc = dict(
                start_pose=jnp.where(i == n_settle - 1, pose, acc["start_pose"]),
                fell=acc["fell"] | fallen_now,
                fall_time=jnp.where(fallen_now & ~acc["fell"], t_now, acc["fall_time"]),
                nan=acc["nan"] | ~finite,
                energy=acc["energy"] + jnp.where(walking & finite, jnp.sum(power) * dt, 0.0),
                path_length=acc["path_length"] + jnp.where(walking & finite, step_xy, 0.0),
                travel=acc["travel"] + jnp.where(walking, jnp.concatenate([dxy, dyaw[None]]), 0.0),
                max_tilt=jnp.maximum(acc["max_tilt"], jnp.where(walking, tilt, 0.0)),
                min_height=jnp.minimum(acc["min_height"], jnp.where(walking, height, jnp.inf)),
                tactile_steps=acc["tactile_steps"] + (walking & obs.tactile).astype(jnp.int32),
            )
            if cfg.record:
                out = dict(pose=jnp.concatenate([d_new.qpos[:3], quat_yaw(q)[None]]),
                           feet=d_new.site_xpos[foot_sites],
                           ctrl=controller.trace(cstate, obs) if has_trace else None,
                           qpos=d_new.qpos, force=obs.foot_force, tactile=obs.tactile)
            else:
                out = None
            return (d_new, cstate, acc), out

        start = jnp.stack([d0.qpos[0], d0.qpos[1], yaw0])
        acc0 = dict(start_pose=start, fell=jnp.asarray(False), fall_time=jnp.asarray(jnp.inf),
                    nan=jnp.asarray(False), energy=jnp.asarray(0.0), path_length=jnp.asarray(0.0),
                    travel=jnp.zeros(3),
                    max_tilt=jnp.asarray(0.0), min_height=jnp.asarray(jnp.inf),
                    tactile_steps=jnp.zeros(6, jnp.int32))
        # forward once so site positions exist before the first slot assignment
        d0 = mjx.forward(m_shared, d0)
        body = jax.checkpoint(control_step, prevent_cse=False) if cfg.remat else control_step
        (d, cstate, acc), rec = jax.lax.scan(body, (d0, cstate0, acc0), jnp.arange(n_total))
        end = jnp.stack([d.qpos[0], d.qpos[1], quat_yaw(d.qpos[3:7])])
        extra = {}
        if cfg.record:
            rec = jax.tree_util.tree_map(lambda a: a[n_settle:], rec)
            extra = dict(trace=rec["pose"], foot_trace=rec["feet"], ctrl_trace=rec["ctrl"], qpos_trace=rec["qpos"],
                         force_trace=rec["force"], tactile_trace=rec["tactile"])
        return Summary(end_pose=end, final_state=cstate, **extra, **acc)

    def batched(m_shared, params, terrain, keys, d_template=None):
        run = jax.vmap(single, in_axes=(None, 0 if params_batched else None, 0, 0, None))
        if cfg.reversible_solver:
            with reversible_solver(physics.iterations):
                return run(m_shared, params, terrain, keys, d_template)
        return run(m_shared, params, terrain, keys, d_template)

    return sm, _AotFunction(jax.jit(batched))


class _AotFunction:
    """A jitted function compiled ahead of time per input signature, recording compile seconds."""

    def __init__(self, jitted):
        self.jitted = jitted
        self.executables = {}
        self.last_compile_s = 0.0

    @staticmethod
    def _signature(args):
        leaves, tree = jax.tree_util.tree_flatten(args)
        return tree, tuple((np.shape(x), str(getattr(x, "dtype", type(x))),
                            str(getattr(x, "sharding", ""))) for x in leaves)

    def __call__(self, *args):
        sig = self._signature(args)
        exe = self.executables.get(sig)
        if exe is None:
            t0 = time.perf_counter()
            exe = self.jitted.lower(*args).compile()
            self.last_compile_s = time.perf_counter() - t0
            self.executables[sig] = exe
        else:
            self.last_compile_s = 0.0
        return exe(*args)


def rollout(robot: RobotSpec, terrain: Terrain, controller, params, duration: float, key, *,
            physics: PhysicsConfig = PhysicsConfig(), sensors: SensorConfig = SensorConfig(),
            config: RolloutConfig = RolloutConfig(), params_batched: bool = False,
            mesh: Optional[Mesh] = None, backend: str = "mjx", nthread: Optional[int] = None) -> Summary:
    """Roll out a batch of hexapods, one per terrain of `terrain` (leading axis B).

    backend: which engine steps the physics; the controller, sensors and summary are the same.
      'mjx'  MJX's JAX implementation (default): any device, differentiable (`rollout_function`), shardable.
      'warp' MJX with MuJoCo Warp kernels (`impl='warp'`; CUDA GPU or CPU; needs warp-lang). Forward only;
             observations come from MuJoCo contact sensors in the model.
      'c'    MuJoCo C on `nthread` host threads (default: all cores) through `mujoco.rollout`, every terrain
             box a static body found by MuJoCo's broadphase; the controller runs in JAX between control steps
             (`hexjax.sim.mujoco_c`). Forward only; no traces (record=False).

    robot: RobotSpec; terrain: batched Terrain from `hexjax.terrain.sample`; controller: an object
    following `hexjax.control.base.Controller`; params: its params pytree (shared, or batched with
    leading axis B when params_batched); duration: seconds of control after settling; key: PRNG key
    (initial heading noise and controller init per env); mesh: optional `jax.sharding.Mesh` with an
    axis named 'batch' to shard the envs over several devices. Returns a `Summary` with leading axis B.
    All inputs are checked on the host before anything is traced."""
    robot.validate(); physics.validate(); config.validate()
    if backend not in BACKENDS:
        raise ValueError(f"backend={backend!r}: use one of {BACKENDS}")
    if backend != "mjx" and (config.reversible_solver or config.grad_window or config.grad_clip is not None
                             or config.remat):
        raise ValueError(f"backend={backend!r} is forward only: the rollout config's gradient options "
                         f"(reversible_solver, grad_window, grad_clip, remat) need backend='mjx'")
    if backend != "mjx" and mesh is not None:
        raise ValueError(f"backend={backend!r}: a device mesh is supported with backend='mjx' only")
    if not hasattr(terrain, "box_pos") or np.ndim(terrain.box_pos) != 3:
        raise ValueError("terrain: expected a batched Terrain (box_pos of shape (B, M, 3)); use terrain.sample")
    b = int(terrain.box_pos.shape[0])
    if b < 1:
        raise ValueError(f"terrain batch size={b}: must be >= 1")
    if not (isinstance(duration, (int, float)) and math.isfinite(duration) and duration > 0):
        raise ValueError(f"duration={duration!r}: must be a finite number of seconds > 0")
    if hasattr(controller, "validate_params"):
        controller.validate_params(params)
    n_ctrl = int(math.ceil(duration / controller.dt - 1e-9))
    if backend == "c":
        from hexjax.sim.mujoco_c import rollout_c
        out = rollout_c(robot, terrain, controller, params, n_ctrl, key, physics=physics, sensors=sensors,
                        config=config, params_batched=params_batched, nthread=nthread)
        rollout.last_compile_s = rollout_c.last_compile_s
        return out
    impl = "warp" if backend == "warp" else "jax"
    sm, fn = _compiled(robot, physics, sensors, controller, config, n_ctrl, params_batched, impl)
    keys = jax.random.split(key, b)
    if mesh is not None:
        if "batch" not in mesh.axis_names:
            raise ValueError(f"mesh.axis_names={mesh.axis_names!r}: need an axis named 'batch'")
        n_dev = mesh.shape["batch"]
        if b % n_dev:
            raise ValueError(f"terrain batch size={b} must be a multiple of the mesh's {n_dev} 'batch' devices")
        shard, replicated = NamedSharding(mesh, P("batch")), NamedSharding(mesh, P())
        terrain = jax.device_put(terrain, shard)
        keys = jax.device_put(keys, shard)
        params = jax.device_put(params, shard if params_batched else replicated)
        model = jax.device_put(sm.mjx_model, replicated)
    else:
        model = sm.mjx_model
    out = fn(model, params, terrain, keys, sm.make_data(b)) if impl == "warp" else fn(model, params, terrain, keys)
    rollout.last_compile_s = fn.last_compile_s
    return out


rollout.last_compile_s = 0.0


def rollout_function(robot: RobotSpec, controller, duration: float, *, physics: PhysicsConfig = PhysicsConfig(),
                     sensors: SensorConfig = SensorConfig(), config: RolloutConfig = RolloutConfig(),
                     params_batched: bool = False):
    """(model, fn) with fn(model, params, terrain, keys) -> Summary the pure jitted batched rollout, for use
    inside `jax.grad`, `jax.jit` or `vmap` (e.g. tuning controller params). keys: (B, 2) PRNG keys, one per
    env. Same checks as `rollout` on the static inputs. For reverse-mode gradients set
    `RolloutConfig.reversible_solver` (or use a physics config with `iterations=1`): MJX runs its Newton
    iterations in a lax.while_loop, which JAX cannot reverse."""
    robot.validate(); physics.validate(); config.validate()
    if not (isinstance(duration, (int, float)) and math.isfinite(duration) and duration > 0):
        raise ValueError(f"duration={duration!r}: must be a finite number of seconds > 0")
    n_ctrl = int(math.ceil(duration / controller.dt - 1e-9))
    sm, fn = _compiled(robot, physics, sensors, controller, config, n_ctrl, params_batched)
    return sm.mjx_model, fn.jitted


def make_mesh(devices=None) -> Mesh:
    """A 1-D mesh named 'batch' over the given (default: all visible) devices."""
    devs = np.asarray(devices if devices is not None else jax.devices())
    return Mesh(devs.reshape(-1), ("batch",))
