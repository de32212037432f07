"""MJX in JAX: the differentiable engine, and the compiled batched rollout that MuJoCo Warp shares.

Build for a batch: `SimModel` (`hexjax.sim.model`) puts the MuJoCo model on the device (`put_model`) with
terrain-box slots that follow the feet. Step: `lax.scan` of the control step (`hexjax.sim.step`) over time,
`vmap` over envs, `jit`, sharded over a device mesh along the batch axis where one is given. Read: the sensors
from the constraint solver's rows (`hexjax.sim.model.read_obs`). The MuJoCo Warp engine (`warp.py`) is this
engine with its model, data and sensor reads swapped.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Optional

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from hexjax.sim import perturb
from hexjax.sim import step as sim_step  # summarise on the module: tests/test_step.py watches it
from hexjax.sim.compiled import Compiled
from hexjax.sim.config import PhysicsConfig, RolloutConfig, SensorConfig, settle_steps
from hexjax.sim.engines.base import GRADIENTS, MESH, RANGE_SENSORS, TRACES, Engine
from hexjax.sim.internals import REMAT_POLICY, check_model, solver_context
from hexjax.sim.model import built, read_obs
from hexjax.sim.step import make_control_step, make_env_start, stop_derived
from hexjax.world.robot import RobotSpec


@dataclasses.dataclass(frozen=True)
class MJX(Engine):
    """MJX's JAX implementation: any JAX device, differentiable, shardable; every step a fixed set of geom pairs,
    so each leg collides with the few terrain boxes nearest its foot (`hexjax.sim.model.assign_slots`)."""

    contact_sensors: bool = False  # the model declares MuJoCo's contact sensors (what MuJoCo Warp and C read)
    keeps_programs: bool = True  # its compiled rollouts export and are kept on disk (`hexjax.sim.compiled`)
    data_template: bool = False  # the batched rollout takes an empty Data made for the whole batch (`make_data`)

    # Build ---------------------------------------------------------------------------------------------------
    def put_model(self, mj_model):
        """The device model of `mj_model`. On this process's own first device: MJX's default, jax.devices()[0],
        belongs to process 0 when several processes share a run (jax.distributed)."""
        from hexjax.sim.internals.rules import mjx
        return mjx.put_model(mj_model, device=jax.local_devices()[0])

    def make_data(self, sm, batch: int = 1):
        """An empty mjx.Data of one env."""
        from hexjax.sim.internals.rules import mjx
        return mjx.make_data(sm.mjx_model, device=jax.local_devices()[0])

    def place_slots(self, m, ids, geom_pos, geom_size, slot_size):
        """`m` with the slot geoms' positions and sizes set (already written into `geom_pos`, `geom_size`)."""
        return m.replace(geom_pos=geom_pos, geom_size=geom_size)

    def prepare(self, robot, physics) -> None:
        built(robot, physics, self)

    # Step ----------------------------------------------------------------------------------------------------
    def observe(self, sm, sensors: SensorConfig, terrain, m, d, slot_pos):
        """(data, `Obs`) of one env at the start of a control step, its slots at `slot_pos`."""
        return d, read_obs(sm, sensors, m, d)

    def detach(self, d):
        """`d` with gradients kept only through the fields the next step reads (`hexjax.sim.step.stop_derived`)."""
        return stop_derived(d)

    def keep_finite(self, d_new, d):
        """(d_new where its qpos and qvel are finite, else d; finite ())."""
        finite = state_finite(d_new)
        return jax.tree_util.tree_map(lambda a, b: jnp.where(finite, a, b), d_new, d), finite

    def overflow(self, d):
        """The engine's overflow flags of one env after a rollout (`hexjax.sim.engines.warp`); MJX has none."""
        return None

    # Roll out ------------------------------------------------------------------------------------------------
    def rollout(self, robot, terrain, controller, params, n_ctrl, keys, *, physics, sensors, config,
                params_batched, mesh, nthread, perturbation):
        perturbed = perturbation is not None
        sm, fn = compiled_rollout(self, robot, physics, sensors, controller, config, n_ctrl, params_batched,
                                  perturbed, mesh)
        b = int(terrain.box_pos.shape[0])
        model = sm.mjx_model
        if mesh is not None:
            if "batch" not in mesh.axis_names:
                raise ValueError(f"mesh.axis_names={mesh.axis_names!r}: need an axis named 'batch'")
            n_dev = mesh.shape["batch"]
            if b % n_dev:
                raise ValueError(f"terrain batch size={b} must be a multiple of the mesh's {n_dev} 'batch' devices")
            shard, replicated = NamedSharding(mesh, P("batch")), NamedSharding(mesh, P())
            terrain, keys = put_global(terrain, shard), put_global(keys, shard)
            params = put_global(params, shard if params_batched else replicated)
            model = put_global(model, replicated)
            if perturbed:
                perturbation = put_global(perturbation, shard)
        template = sm.make_data(b) if self.data_template else None
        out, cs = fn.call(model, params, terrain, keys, template, perturbation)
        if mesh is not None and jax.process_count() > 1:  # every process gets the whole batch's summary
            from jax.experimental import multihost_utils
            out = multihost_utils.process_allgather(out, tiled=True)
        return out, cs.compile_s, cs.source


# bytes_per_env: XLA's buffers of the compiled forward rollout (arguments, outputs, temporaries;
# `Compiled.memory_analysis()`) grow by 210,524 bytes an env from B = 32 to 64 (2 CPU cores);
# grad_bytes_per_env_step: the windowed value-and-gradient program of `tactile_tripod_validated` (0.2 s windows,
# remat, implicit solve) holds 1,859 bytes an env and control step on one H100 (`hexjax bench --grad --batches
# 4096 --walk 10`), 754 on 2 CPU cores (B = 4); the larger figure sizes a batch on either
MJX_ENGINE = MJX(name="mjx", title="MJX (JAX)", precision="float32", can=frozenset({GRADIENTS, MESH, RANGE_SENSORS,
                                                                                       TRACES}),
                 hosts=("cpu", "gpu"), culls=True, bytes_per_env=210_524, grad_bytes_per_env_step=1_859)


@functools.lru_cache(maxsize=32)
def compiled_rollout(engine: MJX, robot: RobotSpec, physics: PhysicsConfig, sensors: SensorConfig, controller,
                     cfg: RolloutConfig, n_ctrl: int, params_batched: bool, perturbed: bool = False,
                     mesh: Optional[Mesh] = None):
    """(SimModel, Compiled batched rollout) for one static setting on an MJX-family engine; cached, as its compile
    is the cost. The program takes (model, params, terrain, keys, data template or None, perturbation or None).
    With a `mesh`, each device runs the vmapped rollout of its own envs (`jax.shard_map` over the 'batch'
    axis)."""
    sm = built(robot, physics, engine)
    if cfg.grad_mode == "forward":
        check_model(sm.mjx_model)  # what forward mode's rule handles, before tracing
    n_settle = settle_steps(cfg, controller.dt)
    control_step = make_control_step(sm, sensors, cfg, controller, n_settle)
    env_start, _ = make_env_start(sm, cfg, controller)

    def single(m_shared, params, terrain, key, d_template, pert):
        (d0, cstate0, acc0), ctrl0, k_sense = env_start(m_shared, params, key, d_template)

        def body(carry, i):
            return control_step(carry, i, params, terrain, m_shared, ctrl0, pert, k_sense)

        if cfg.remat:
            policy = REMAT_POLICY if cfg.solver_grad == "implicit" else None
            body = jax.checkpoint(body, prevent_cse=False, policy=policy)
        carry0 = (d0, cstate0, acc0) + ((perturb.init_state(ctrl0),) if perturbed else ())
        window = cfg.grad_window if cfg.remat else 0
        (d, cstate, acc, *_), rec = windowed_scan(body, carry0, n_settle + n_ctrl, window)
        extra = {}
        if cfg.record:
            rec = jax.tree_util.tree_map(lambda a: a[n_settle:], rec)
            extra = dict(trace=rec["pose"], foot_trace=rec["feet"], ctrl_trace=rec["ctrl"], qpos_trace=rec["qpos"],
                         force_trace=rec["force"], tactile_trace=rec["tactile"])
        flags = engine.overflow(d)
        if flags is not None:
            extra["overflow"] = flags
        return sim_step.summarise(acc, d.qpos, cstate, **extra)

    def batched(m_shared, params, terrain, keys, d_template=None, pert=None):
        axes = (None, 0 if params_batched else None, 0, 0, None, 0 if perturbed else None)
        with solver_context(cfg, physics):
            return jax.vmap(single, in_axes=axes)(m_shared, params, terrain, keys, d_template, pert)

    run = batched
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

        run = sharded

    # a program with host callbacks (progress) or MuJoCo Warp's kernels does not export: keep none of it
    keep = engine.keeps_programs and not cfg.progress_every
    static = (robot, physics, sensors, controller, cfg, n_ctrl, params_batched, "jax") if keep else None
    if keep and perturbed:
        static += ("perturbed",)
    if keep and mesh is not None:
        static += (mesh,)
    return sm, Compiled(jax.jit(run), static=static)


def windowed_scan(body, carry0, n: int, window: int = 0):
    """`lax.scan(body, carry0, arange(n))`, and with `window` > 0 the same steps as windows of `window` steps, each
    window's forward recomputed in the backward pass (`jax.checkpoint`): reverse mode then keeps one carry per
    window and one window's steps at a time, not every step's carry, so a truncated gradient's memory follows its
    window, not the walk (the walk's last n % window steps run as a plain scan after the windows). The values
    and the gradient are the same either way."""
    if window <= 0 or n < 2 * window:
        return jax.lax.scan(body, carry0, jnp.arange(n))
    full = n // window

    def one_window(carry, k):
        return jax.lax.scan(lambda c, j: body(c, k * window + j), carry, jnp.arange(window))

    carry, rec = jax.lax.scan(jax.checkpoint(one_window, prevent_cse=False), carry0, jnp.arange(full))
    rec = jax.tree_util.tree_map(lambda a: a.reshape((full * window,) + a.shape[2:]), rec)
    if n == full * window:
        return carry, rec
    carry, tail = jax.lax.scan(body, carry, jnp.arange(full * window, n))
    return carry, jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), rec, tail)


def state_finite(d):
    """Whether one env's qpos and qvel are all finite (a step that is not is undone: `MJX.keep_finite`)."""
    return jnp.all(jnp.isfinite(d.qpos)) & jnp.all(jnp.isfinite(d.qvel))


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
