"""The batched rollout: one call walks a batch of hexapods, each on its own terrain, on the engine its physics
names (`hexjax.sim.engines`: MJX's `lax.scan` of the control step, `vmap`, `jit` and sharding; MuJoCo Warp's
kernels in the same program; or MuJoCo C on the host's cores). This module checks the call and dispatches."""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from typing import Optional, Tuple

import jax
import numpy as np
from jax.sharding import Mesh

from hexjax.control.base import Controller
from hexjax.sim.config import PhysicsConfig, RolloutConfig, SensorConfig, control_steps, total_physics_steps
from hexjax.sim.engines import GRADIENTS, MESH, RANGE_SENSORS, TRACES, get_engine
from hexjax.sim.engines.mjx import compiled_rollout, make_mesh, put_global  # noqa: F401 (make_mesh, put_global: API)
from hexjax.sim.engines.warp import overflow_counts, overflow_line
from hexjax.world.robot import RobotSpec
from hexjax.world.terrain import Terrain


@dataclasses.dataclass(frozen=True)
class RolloutStats:
    """How a `rollout(..., stats=True)` call went. compile_s: seconds spent tracing and compiling (or loading
    a kept executable, `hexjax.sim.compiled`; 0 when this process had it already); wall_s: the whole call, compile
    included, outputs ready; env_steps: envs x physics steps (settling included); env_steps_per_s: env_steps
    over the call less its compile."""

    compile_s: float
    wall_s: float
    env_steps: int
    engine: str
    compiled: str = "process"  # where the program came from: 'compiled' now, 'disk' (kept), or this 'process'
    overflow: Optional[dict] = None  # MuJoCo Warp: envs that hit its limits (`hexjax.sim.engines.warp.overflow_counts`)

    @property
    def run_s(self) -> float:
        return max(self.wall_s - self.compile_s, 1e-9)

    @property
    def env_steps_per_s(self) -> float:
        return self.env_steps / self.run_s


def job_needs(controller, config: RolloutConfig, mesh) -> frozenset:
    """What a rollout call needs of its engine (`hexjax.sim.engines.base.CAPABILITIES`): gradients for any of
    the rollout config's gradient options, a device mesh, traces beyond the torso's, range sensors for a
    controller with a `sensor`."""
    needs = set()
    if config.solver_grad != "none" or config.grad_window or config.grad_clip is not None or config.remat:
        needs.add(GRADIENTS)
    if mesh is not None:
        needs.add(MESH)
    if config.record:
        needs.add(TRACES)
    if getattr(controller, "sensor", None) is not None:
        needs.add(RANGE_SENSORS)
    return frozenset(needs)


def resolve_physics(physics, engine: Optional[str], terrain, controller, config: RolloutConfig,
                    mesh) -> Tuple[PhysicsConfig, object]:
    """(PhysicsConfig, engine) of a `rollout` call from its `physics` and `engine` arguments (`rollout`'s
    docstring): a `Physics` as chosen (`hexjax.sim.physics.pick`), a preset's fastest certified engine that can
    run the call, or a `PhysicsConfig` on MJX (or `engine`); one ValueError line for an engine that cannot run
    the call."""
    needs = job_needs(controller, config, mesh)
    if isinstance(physics, PhysicsConfig):
        e = get_engine(engine or "mjx")
        lacks = e.lacks(needs)
        if lacks:
            raise ValueError(f"engine={e.name!r}: this rollout needs {' and '.join(lacks)}, which {e.title} does "
                             "not give (hexjax.sim.engines)")
        return physics, e
    from hexjax.sim.physics import Physics, PhysicsPreset, pick
    if not (physics is None or isinstance(physics, (str, os.PathLike, PhysicsPreset, Physics))):
        raise ValueError(f"physics={physics!r}: give a preset name (validated, reference, fast), a .yaml path, a "
                         "PhysicsPreset, a Physics (hexjax.sim.physics.pick) or a PhysicsConfig")
    chosen = pick(physics, engine, needs=needs)
    flat = hasattr(terrain, "box_valid") and not np.any(np.asarray(terrain.box_valid))
    return chosen.config(kind="flat" if flat else None), chosen.engine


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
            mesh: Optional[Mesh] = None, engine: Optional[str] = None, nthread: Optional[int] = None,
            stats: bool = False, perturbation=None, say_limits: bool = True):
    """Roll out a batch of hexapods, one per terrain of `terrain` (leading axis B).

    physics: the physics a command chose (`hexjax.sim.physics.pick`: a `Physics`), a physics preset (its name, a
    .yaml path or a `PhysicsPreset`; default None: `validated`, the physics every hexjax result reports) or a
    `PhysicsConfig` of raw solver settings. A preset's slot counts for the terrain boxes are its own or 2 per leg
    and 2 for the torso (none on flat ground); for a terrain preset's own (8 torso slots on stepping stones) pass
    `get_physics(name).config(terrain_spec)`.
    engine: which engine steps the physics (`hexjax.sim.engines`); the control step, sensors and summary are the
    same. None: a `Physics`'s own; with a preset, the fastest engine certified for it on this host that can run
    the call (MuJoCo C on a CPU-only host, MuJoCo Warp on a GPU; MJX where the call needs gradients or a mesh);
    with a `PhysicsConfig`, 'mjx'.
      'mjx'  MJX in JAX: any device, differentiable (`rollout_function`), shardable.
      'warp' MuJoCo Warp kernels through MJX (CUDA GPU or CPU; needs warp-lang). Forward only; observations
             come from MuJoCo contact sensors in the model; `Summary.overflow` holds its limit flags.
      'c'    MuJoCo C on `nthread` host threads (default: the cores this process may use) through
             `mujoco.rollout`, every terrain box a geom of the world body found by MuJoCo's mid-phase tree; the
             controller runs in JAX between control steps (`hexjax.sim.engines.c`). Forward only, every trace
             kept.

    robot: RobotSpec; terrain: batched Terrain from `hexjax.world.terrain.sample`; controller: a
    `hexjax.control.Controller`; params: its params pytree (shared, or batched with leading axis B when
    params_batched); duration: seconds of control after settling; key: PRNG key split into one per env (initial
    heading noise and controller init), or B keys stacked (rows that must share an env's noise, e.g. the
    variants of a paired comparison in one batch); mesh: optional `jax.sharding.Mesh` with an axis named 'batch'
    to shard the envs over several devices; perturbation: optional batched
    `hexjax.world.randomization.Perturbation` (leading axis B, from `sample_perturbation`): per-env dynamics,
    sensing and faults, applied in every control step (`hexjax.sim.perturb`; every engine: on 'c' the model
    fields are set in each env's MjModel). Returns a `Summary` with leading axis B, or (Summary, RolloutStats)
    with `stats`. A MuJoCo Warp rollout whose envs hit its limits prints one line saying how many (stderr), unless
    `say_limits` is False (a caller that sums them over many rollouts: `RolloutStats.overflow` holds them).
    All inputs are checked on the host before anything is traced."""
    t0 = time.perf_counter()
    physics, eng = resolve_physics(physics, engine, terrain, controller, config, mesh)
    n_ctrl = check_static(robot, controller, duration, physics, config)
    if not hasattr(terrain, "box_pos") or np.ndim(terrain.box_pos) != 3:
        raise ValueError("terrain: expected a batched Terrain (box_pos of shape (B, M, 3)); use terrain.sample")
    b = int(terrain.box_pos.shape[0])
    if b < 1:
        raise ValueError(f"terrain batch size={b}: must be >= 1")
    per_env_keys = check_key(key, b)
    if params_batched:
        check_params_batch(params, b)
    controller.validate_params(params)
    if perturbation is not None:
        check_perturbation(perturbation, b)
    keys = key if per_env_keys else jax.random.split(key, b)
    out, compile_s, source = eng.rollout(robot, terrain, controller, params, n_ctrl, keys, physics=physics,
                                         sensors=sensors, config=config, params_batched=params_batched, mesh=mesh,
                                         nthread=nthread, perturbation=perturbation)
    counts = overflow_counts(out.overflow, physics)
    if say_limits and counts and (counts["line_search_limit"] or counts["iteration_limit"] or counts["other"]):
        print(overflow_line(counts), file=sys.stderr, flush=True)
    if not stats:
        return out
    jax.block_until_ready(out)
    n_steps = total_physics_steps(config, physics, controller.dt, n_ctrl)
    return out, RolloutStats(compile_s=compile_s, wall_s=time.perf_counter() - t0, env_steps=b * n_steps,
                             engine=eng.name, compiled=source, overflow=counts)


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
    sm, fn = compiled_rollout(get_engine("mjx"), robot, physics, sensors, controller, config, n_ctrl, params_batched,
                              perturbed)
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
