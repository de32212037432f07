"""hexjax: differentiable, vectorised hexapod walking on JAX and MuJoCo MJX (docs/architecture.md).

The public names below load on first use, so `import hexjax` (and `hexjax --help`) imports no JAX.
"""

import importlib as _importlib
import os as _os

from hexjax import cache as _cache

# On obstacle terrain (convex box collisions inside the scanned, vmapped step) XLA:CPU's concurrency-
# optimized scheduler left every worker thread waiting for work and the process idle in
# block_until_ready forever: 3 of 5 runs on 2 cores with jax 0.10.2. Neither async dispatch off,
# single-threaded Eigen, nor replacing lax.top_k cured it; this flag did. It must be set before jax
# creates its CPU client; HEXJAX_KEEP_XLA_FLAGS=1 leaves XLA_FLAGS untouched.
if not _os.environ.get("HEXJAX_KEEP_XLA_FLAGS"):
    _flags = _os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_enable_concurrency_optimized_scheduler" not in _flags:
        _os.environ["XLA_FLAGS"] = (_flags + " --xla_cpu_enable_concurrency_optimized_scheduler=false").strip()


def _lapack_pool_threads(environ=_os.environ) -> "str | None":
    """The size to give XLA:CPU's intra-op thread pool (env PJRT_NPROC), or None to leave it.

    jaxlib 0.10.x (0.10.0 up to 0.11.0; this project's CPU pin is 0.10.2, and 0.11.1+ needs Python >= 3.12)
    splits a batched LAPACK call (Cholesky, triangular solve: MJX's mass-matrix factor, its solver, the
    implicit backward) over that pool and blocks its own worker until the parts are done. When as many such
    calls run at once as the pool has threads, every thread waits and the program hangs at 0 % CPU. The pool
    is as large as the machine has cores, so on 2 cores two concurrent factorisations suffice: the gradient of
    the tactile objective at B = 64 hung in its first call (native stacks: two workers in
    `jax::ParallelBatchMap` under `lapack_spotrf_ffi`), as did four independent batched Choleskys in one
    program. With 16 threads the same runs finish, give the same numbers, and run no slower within the noise
    of the 2-core dev machine (docs/benchmarks.md, issue 19, fifth session). Set PJRT_NPROC (or NPROC)
    yourself to choose another size."""
    if "PJRT_NPROC" in environ or "NPROC" in environ:
        return None
    try:
        from importlib.metadata import version
        major, minor, patch = (int(v) for v in version("jaxlib").split(".")[:3])
    except Exception:  # not installed the usual way: leave the pool as jaxlib sizes it
        return None
    if not (0, 10, 0) <= (major, minor, patch) < (0, 11, 1):
        return None
    cores = len(_os.sched_getaffinity(0)) if hasattr(_os, "sched_getaffinity") else (_os.cpu_count() or 1)
    return str(max(16, cores))


_pool = _lapack_pool_threads()
if _pool is not None:  # read when jax creates its CPU client, so before any computation
    _os.environ["PJRT_NPROC"] = _pool

_cache.enable()

_EXPORTS = {
    "hexjax.world.robot": ["RobotSpec", "leg_fk", "leg_ik"],
    "hexjax.world.presets": ["get_robot", "get_terrain", "luneckas2020", "yu2019", "chen2019"],
    "hexjax.world.terrain": ["Terrain", "TerrainSpec", "obstacle_circles", "pad_terrain", "sample"],
    "hexjax.sim.config": ["PhysicsConfig", "RolloutConfig", "SensorConfig"],
    "hexjax.sim.mjcf": ["build_mjcf"],
    "hexjax.sim.model": ["Obs", "SimModel", "sim_model"],
    "hexjax.sim.step": ["Summary"],
    "hexjax.sim.rollout": ["RolloutStats", "make_mesh", "rollout", "rollout_function"],
    "hexjax.control.base": ["Controller"],
    "hexjax.control.gait": ["GAITS", "GaitController", "GaitParams"],
    "hexjax.control.tactile": ["TactileGaitController", "TactileParams", "TactileState"],
    "hexjax.control.cpg": ["CPG_GAITS", "CPGController", "CPGParams", "CPGState", "gait_fields"],
    "hexjax.control.vdp": ["NetworkParams"],
    "hexjax.control.avoid_gait": ["AvoidGaitController"],
    "hexjax.control.support_gait": ["SupportPlanController"],
    "hexjax.experiments.metrics": ["goal_errors"],
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}
__all__ = sorted(_WHERE)
__version__ = "0.1.0"


def __getattr__(name):
    if name in _WHERE:
        value = getattr(_importlib.import_module(_WHERE[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'hexjax' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)
