"""The batched rollout: `lax.scan` of the control step (`hexjax.sim.step`) over time, `vmap` over envs, `jit`,
optionally sharded over a device mesh along the batch axis; or the same control step with the physics of
MuJoCo Warp or MuJoCo C (`backend=`)."""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import time
from typing import Optional, Tuple

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from hexjax.control.base import Controller
from hexjax.sim import perturb
from hexjax.sim import step as sim_step  # summarise on the module: tests/test_step.py watches it
from hexjax.sim.backends.mujoco_c import rollout_c
from hexjax.sim.compiled import Compiled
from hexjax.sim.config import PhysicsConfig, RolloutConfig, SensorConfig
from hexjax.sim.internals import REMAT_POLICY, check_model, solver_context
from hexjax.sim.model import sim_model
from hexjax.sim.step import control_steps, make_control_step, make_env_start, settle_steps, total_physics_steps
from hexjax.world.robot import RobotSpec
from hexjax.world.terrain import Terrain

BACKENDS = ("mjx", "warp", "c")


@dataclasses.dataclass(frozen=True)
class RolloutStats:
    """How a `rollout(..., stats=True)` call went. compile_s: seconds spent tracing and compiling (or loading
    a kept executable, `hexjax.sim.compiled`; 0 when this process had it already); wall_s: the whole call, compile
    included, outputs ready; env_steps: envs x physics steps (settling included); env_steps_per_s: env_steps
    over the call less its compile."""

    compile_s: float
    wall_s: float
    env_steps: int
    backend: str
    compiled: str = "process"  # where the program came from: 'compiled' now, 'disk' (kept), or this 'process'

    @property
    def run_s(self) -> float:
        return max(self.wall_s - self.compile_s, 1e-9)

    @property
    def env_steps_per_s(self) -> float:
        return self.env_steps / self.run_s


@functools.lru_cache(maxsize=32)
def _compiled(robot: RobotSpec, physics: PhysicsConfig, sensors: SensorConfig, controller: Controller,
              cfg: RolloutConfig, n_ctrl: int, params_batched: bool, impl: str = "jax", perturbed: bool = False,
              mesh: Optional[Mesh] = None):
    """(SimModel, Compiled batched rollout) for one static setting; cached, as its compile is the cost. With a
    `mesh`, each device runs the vmapped rollout of its own envs (`jax.shard_map` over the 'batch' axis)."""
    sm = sim_model(robot, physics, impl)
    if cfg.grad_mode == "forward":
        check_model(sm.mjx_model)  # what forward mode's rule handles, before tracing
    n_settle = settle_steps(cfg, controller.dt)
    control_step = make_control_step(sm, sensors, cfg, controller, n_settle)
    env_start, _ = make_env_start(sm, cfg, controller)

    def single(m_shared, params, terrain: Terrain, key, d_template, pert):
        (d0, cstate0, acc0), ctrl0, k_sense = env_start(m_shared, params, key, d_template)

        def body(carry, i):
            return control_step(carry, i, params, terrain, m_shared, ctrl0, pert, k_sense)

        if cfg.remat:
            policy = REMAT_POLICY if cfg.solver_grad == "implicit" else None
            body = jax.checkpoint(body, prevent_cse=False, policy=policy)
        carry0 = (d0, cstate0, acc0) + ((perturb.init_state(ctrl0),) if perturbed else ())
        (d, cstate, acc, *_), rec = jax.lax.scan(body, carry0, jnp.arange(n_settle + n_ctrl))
        extra = {}
        if cfg.record:
            rec = jax.tree_util.tree_map(lambda a: a[n_settle:], rec)
            extra = dict(trace=rec["pose"], foot_trace=rec["feet"], ctrl_trace=rec["ctrl"], qpos_trace=rec["qpos"],
                         force_trace=rec["force"], tactile_trace=rec["tactile"])
        return sim_step.summarise(acc, d.qpos, cstate, **extra)

    def batched(m_shared, params, terrain, keys, d_template=None, pert=None):
        run = jax.vmap(single, in_axes=(None, 0 if params_batched else None, 0, 0, None, 0 if perturbed else None))
        with solver_context(cfg, physics):
            return run(m_shared, params, terrain, keys, d_template, pert)

    if mesh is not None:
        # Left to jit's automatic partitioning, the vmapped MJX solver's while-loop runs until every env of the
        # whole batch has converged, so every Newton iteration of every physics step all-reduced its stopping
        # flag over the devices (over the network with several processes), a synchronisation per iteration.
        # Here each device's loop waits for its own envs only; each env's numbers are the same either way (a
        # converged env's iterate is held while the others go on).
        env, shared = P("batch"), P()
        specs = (shared, env if params_batched else shared, env, env, env if perturbed else shared)

        def sharded(m_shared, params, terrain, keys, d_template=None, pert=None):
            def local(m, p, t, k, pe):  # MJX only: no data template
                return batched(m, p, t, k, None, pe)
            return _shard_map_without_empty_arrays(local, mesh, specs, env, (m_shared, params, terrain, keys, pert))

    # a program with host callbacks (progress) or MuJoCo Warp's kernels does not export: keep none of it
    keep = impl == "jax" and not cfg.progress_every
    static = (robot, physics, sensors, controller, cfg, n_ctrl, params_batched, impl) if keep else None
    if keep and perturbed:
        static += ("perturbed",)
    if keep and mesh is not None:
        static += (mesh,)
    return sm, Compiled(jax.jit(batched if mesh is None else sharded), static=static)


def _shard_map_without_empty_arrays(f, mesh: Mesh, specs, out_specs, args):
    """`jax.shard_map(f, ...)(*args)` with no empty array among the manual computation's inputs.

    Such inputs are the empty arrays among `args` (MJX's model holds some: no tendons, no equality constraints)
    and those `f` closes over, which `shard_map` passes in as well; jaxlib 0.11.2's Shardy pass segfaults on an
    empty input (`ManualComputationUnusedInputsPattern`). So `f` is traced once to a jaxpr at one device's
    shapes and evaluated inside the `shard_map` with every empty argument and constant made there as `jnp.zeros`
    of its shape, which Shardy compiles. The values are the same: an empty array holds none."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    leaf_specs = [s for a, s in zip(args, specs) for _ in jax.tree_util.tree_leaves(a)]
    local = [NamedSharding(mesh, s).shard_shape(x.shape) for x, s in zip(leaves, leaf_specs)]
    closed, out_shape = jax.make_jaxpr(lambda *ls: f(*jax.tree_util.tree_unflatten(tree, ls)), return_shape=True)(
        *(jax.ShapeDtypeStruct(sh, x.dtype) for sh, x in zip(local, leaves)))
    full = [i for i, x in enumerate(leaves) if np.size(x)]

    def g(*xs):
        given = dict(zip(full, xs))
        ins = [given[i] if i in given else jnp.zeros(sh, x.dtype) for i, (x, sh) in enumerate(zip(leaves, local))]
        consts = [c if np.size(c) else jnp.zeros(np.shape(c), c.dtype) for c in closed.consts]
        out = jax.extend.core.jaxpr_as_fun(jax.extend.core.ClosedJaxpr(closed.jaxpr, consts))(*ins)
        return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(out_shape), out)
    return jax.shard_map(g, mesh=mesh, in_specs=tuple(leaf_specs[i] for i in full), out_specs=out_specs,
                         check_vma=False)(*(leaves[i] for i in full))


def resolve_physics(physics, backend: Optional[str], terrain, controller, config: RolloutConfig,
                    mesh) -> Tuple[PhysicsConfig, str]:
    """(PhysicsConfig, backend) of a `rollout` call from its `physics` and `backend` arguments (`rollout`'s
    docstring): a preset's config for the terrain and its fastest certified engine that can run the call."""
    if isinstance(physics, PhysicsConfig):
        return physics, backend or "mjx"
    from hexjax.sim.physics import NOT_MJX, PhysicsPreset, get_physics, pick_engine
    if not (physics is None or isinstance(physics, (str, os.PathLike, PhysicsPreset))):
        raise ValueError(f"physics={physics!r}: give a preset name (validated, reference, fast), a .yaml path, a "
                         "PhysicsPreset or a PhysicsConfig")
    exclude = set()
    if mesh is not None or config.solver_grad != "none" or config.grad_window or config.remat:
        exclude = NOT_MJX
    elif config.record or getattr(controller, "sensor", None) is not None:
        exclude = {"c"}
    engine = pick_engine(get_physics(physics), backend, exclude=exclude)
    flat = hasattr(terrain, "box_valid") and not np.any(np.asarray(terrain.box_valid))
    return engine.preset.config(kind="flat" if flat else None), engine.backend


def check_static(robot: RobotSpec, controller, duration, physics: PhysicsConfig, config: RolloutConfig) -> int:
    """Host-side checks of what a compiled rollout is specialised on; returns the control steps."""
    robot.validate(); physics.validate(); config.validate()
    if not isinstance(controller, Controller):
        raise ValueError(f"controller={type(controller).__name__}: derive it from hexjax.control.Controller "
                         "(the protocol the rollout calls)")
    if not (isinstance(duration, (int, float)) and math.isfinite(duration) and duration > 0):
        raise ValueError(f"duration={duration!r}: must be a finite number of seconds > 0")
    n_ctrl = control_steps(duration, controller.dt)
    n_all = total_physics_steps(config, physics, controller.dt, n_ctrl)
    if n_all > 2 ** 31 - 1:  # the scan's step index and the step counts are int32
        raise ValueError(f"duration={duration!r}: {n_all:,} physics steps, more than a rollout counts (2**31 - 1)")
    return n_ctrl


def rollout(robot: RobotSpec, terrain: Terrain, controller: Controller, params, duration: float, key, *,
            physics=None, sensors: SensorConfig = SensorConfig(),
            config: RolloutConfig = RolloutConfig(), params_batched: bool = False,
            mesh: Optional[Mesh] = None, backend: Optional[str] = None, nthread: Optional[int] = None,
            stats: bool = False, perturbation=None):
    """Roll out a batch of hexapods, one per terrain of `terrain` (leading axis B).

    physics: a physics preset (its name, a .yaml path or a `PhysicsPreset`; default None: `validated`, the
    physics every hexjax result reports) or a `PhysicsConfig` of raw solver settings. A preset's slot counts for
    the terrain boxes are its own or 2 per leg and 2 for the torso (none on flat ground); for a terrain preset's own
    (8 torso slots on stepping stones) pass `get_physics(name).config(terrain_spec)`.
    backend: which engine steps the physics; the control step, sensors and summary are the same. None: with a
    preset, the fastest engine certified for it on this host (`hexjax.sim.physics.pick_engine`: MuJoCo C on a
    CPU-only host, MuJoCo Warp or MJX on a GPU) among those that can run the call (MJX for a mesh; MJX or Warp
    for traces beyond the torso's or a range sensor); with a `PhysicsConfig`, 'mjx'.
      'mjx'  MJX's JAX implementation: any device, differentiable (`rollout_function`), shardable.
      'warp' MJX with MuJoCo Warp kernels (`impl='warp'`; CUDA GPU or CPU; needs warp-lang). Forward only;
             observations come from MuJoCo contact sensors in the model.
      'c'    MuJoCo C on `nthread` host threads (default: all cores) through `mujoco.rollout`, every terrain
             box a static body found by MuJoCo's broadphase; the controller runs in JAX between control steps
             (`hexjax.sim.backends.mujoco_c`). Forward only; of the traces only the torso's (`record`).

    robot: RobotSpec; terrain: batched Terrain from `hexjax.world.terrain.sample`; controller: a
    `hexjax.control.Controller`; params: its params pytree (shared, or batched with leading axis B when
    params_batched); duration: seconds of control after settling; key: PRNG key split into one per env (initial
    heading noise and controller init), or B keys stacked (rows that must share an env's noise, e.g. the
    variants of a paired comparison in one batch); mesh: optional `jax.sharding.Mesh` with an axis named 'batch'
    to shard the envs over several devices; perturbation: optional batched
    `hexjax.world.randomization.Perturbation` (leading axis B, from `sample_perturbation`): per-env dynamics,
    sensing and faults, applied in every control step (`hexjax.sim.perturb`; every backend: on 'c' the model
    fields are set in each env's MjModel). Returns a `Summary` with leading axis B, or (Summary, RolloutStats)
    with `stats`.
    All inputs are checked on the host before anything is traced."""
    t0 = time.perf_counter()
    physics, backend = resolve_physics(physics, backend, terrain, controller, config, mesh)
    n_ctrl = check_static(robot, controller, duration, physics, config)
    if backend not in BACKENDS:
        raise ValueError(f"backend={backend!r}: use one of {BACKENDS}")
    if backend != "mjx" and (config.solver_grad != "none" or config.grad_window or config.grad_clip is not None
                             or config.remat):
        raise ValueError(f"backend={backend!r} is forward only: the rollout config's gradient options "
                         f"(solver_grad, grad_window, grad_clip, remat) need backend='mjx'")
    if backend == "c" and getattr(controller, "sensor", None) is not None:
        raise ValueError(f"backend='c': {type(controller).__name__} scans the terrain with a range sensor, which "
                         "the MJX control step casts; use backend='mjx' or 'warp'")
    if backend != "mjx" and mesh is not None:
        raise ValueError(f"backend={backend!r}: a device mesh is supported with backend='mjx' only")
    if not hasattr(terrain, "box_pos") or np.ndim(terrain.box_pos) != 3:
        raise ValueError("terrain: expected a batched Terrain (box_pos of shape (B, M, 3)); use terrain.sample")
    b = int(terrain.box_pos.shape[0])
    if b < 1:
        raise ValueError(f"terrain batch size={b}: must be >= 1")
    per_env_keys = check_key(key, b)
    if params_batched:
        check_params_batch(params, b)
    controller.validate_params(params)
    perturbed = perturbation is not None
    if perturbed:
        check_perturbation(perturbation, b)
    keys = key if per_env_keys else jax.random.split(key, b)
    if backend == "c":
        out, compile_s = rollout_c(robot, terrain, controller, params, n_ctrl, keys, physics=physics,
                                   sensors=sensors, config=config, params_batched=params_batched, nthread=nthread,
                                   perturbation=perturbation)
        compiled = "compiled" if compile_s else "process"
    else:
        impl = "warp" if backend == "warp" else "jax"
        sm, fn = _compiled(robot, physics, sensors, controller, config, n_ctrl, params_batched, impl, perturbed,
                           mesh)
        model = sm.mjx_model
        if mesh is not None:
            if "batch" not in mesh.axis_names:
                raise ValueError(f"mesh.axis_names={mesh.axis_names!r}: need an axis named 'batch'")
            n_dev = mesh.shape["batch"]
            if b % n_dev:
                raise ValueError(f"terrain batch size={b} must be a multiple of the mesh's {n_dev} 'batch' devices")
            shard, replicated = NamedSharding(mesh, P("batch")), NamedSharding(mesh, P())
            terrain = put_global(terrain, shard)
            keys = put_global(keys, shard)
            params = put_global(params, shard if params_batched else replicated)
            model = put_global(model, replicated)
            if perturbed:
                perturbation = put_global(perturbation, shard)
        args = (model, params, terrain, keys) + ((sm.make_data(b),) if impl == "warp" else ())
        if perturbed:  # after the data template (warp's, or None)
            args += ((perturbation,) if impl == "warp" else (None, perturbation))
        out, cs = fn.call(*args)
        compile_s, compiled = cs.compile_s, cs.source
        if mesh is not None and jax.process_count() > 1:  # every process gets the whole batch's summary
            from jax.experimental import multihost_utils
            out = multihost_utils.process_allgather(out, tiled=True)
    if not stats:
        return out
    jax.block_until_ready(out)
    n_steps = total_physics_steps(config, physics, controller.dt, n_ctrl)
    return out, RolloutStats(compile_s=compile_s, wall_s=time.perf_counter() - t0, env_steps=b * n_steps,
                             backend=backend, compiled=compiled)


def rollout_function(robot: RobotSpec, controller: Controller, duration: float, *,
                     physics: PhysicsConfig = PhysicsConfig(), sensors: SensorConfig = SensorConfig(),
                     config: RolloutConfig = RolloutConfig(), params_batched: bool = False, kept: bool = False,
                     perturbed: bool = False):
    """(model, fn) with fn(model, params, terrain, keys) -> Summary the pure jitted batched rollout, for use
    inside `jax.grad`, `jax.jit` or `vmap` (e.g. tuning controller params). keys: (B, 2) PRNG keys, one per
    env. Same checks as `rollout` on the static inputs. For reverse-mode gradients set
    `RolloutConfig.solver_grad` to 'implicit' or 'unrolled' (or use a physics config with `iterations=1`):
    MJX runs its Newton iterations in a lax.while_loop, which JAX cannot reverse. kept=True: fn is the
    compiled program that `rollout` runs, kept on disk (`hexjax.sim.compiled`), to call with arrays, not
    inside a transformation. perturbed=True: fn(model, params, terrain, keys, None, perturbation) takes a
    batched `Perturbation` as well (differentiable in its float fields)."""
    n_ctrl = check_static(robot, controller, duration, physics, config)
    sm, fn = _compiled(robot, physics, sensors, controller, config, n_ctrl, params_batched, "jax", perturbed)
    return sm.mjx_model, (fn if kept else fn.jitted)


def check_key(key, b: int) -> bool:
    """Whether `key` holds one key per env (True) or one key the rollout splits (False): a PRNG key
    (`jax.random.PRNGKey(seed)` or `jax.random.key(seed)`) or `b` of them stacked; else one ValueError line."""
    dtype, shape = getattr(key, "dtype", None), np.shape(key)
    typed = dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key)
    if typed and shape in ((), (b,)) or not typed and dtype == np.uint32 and shape in ((2,), (b, 2)):
        return len(shape) == (1 if typed else 2)
    raise ValueError(f"key: got {type(key).__name__} of shape {shape} and dtype {dtype}: give one PRNG key, "
                     f"jax.random.PRNGKey(seed) or jax.random.key(seed) (the rollout splits it per env), or {b} "
                     "of them stacked (one per env)")


def check_params_batch(params, b: int):
    """With `params_batched`, every leaf of `params` has a leading axis of the terrain's `b` envs, or one
    ValueError line naming the first leaf that has not."""
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        shape = np.shape(leaf)
        if not shape or shape[0] != b:
            raise ValueError(f"params{jax.tree_util.keystr(path)}: shape {shape}; params_batched=True needs a "
                             f"leading axis of the terrain's {b} envs on every leaf")


def check_perturbation(perturbation, b: int):
    """A batched Perturbation of `b` envs, or one ValueError line naming what is wrong."""
    from hexjax.world.randomization import Perturbation
    if not isinstance(perturbation, Perturbation):
        raise ValueError(f"perturbation: expected a batched hexjax.world.randomization.Perturbation (from "
                         f"sample_perturbation), got {type(perturbation).__name__}")
    n = np.shape(perturbation.friction)
    if len(n) != 1 or n[0] != b:
        raise ValueError(f"perturbation batch size={n[0] if n else 'unbatched'}: must equal the terrain's {b} envs")


def put_global(tree, sharding: NamedSharding):
    """`tree` placed with `sharding`. In one process, `jax.device_put`. Across processes (`jax.distributed`,
    a mesh over several hosts' devices) every process holds the same whole arrays (drawn from the same keys)
    and gives each of its devices its own slice."""
    if jax.process_count() == 1:
        return jax.device_put(tree, sharding)

    def one(x):
        if not hasattr(x, "shape"):  # static leaves of the model
            return x
        a = np.asarray(x)
        return jax.make_array_from_callback(a.shape, sharding, lambda idx: a[idx])
    return jax.tree_util.tree_map(one, tree)


def make_mesh(devices=None) -> Mesh:
    """A 1-D mesh named 'batch' over the given (default: all visible) devices."""
    devs = np.asarray(devices if devices is not None else jax.devices())
    return Mesh(devs.reshape(-1), ("batch",))
