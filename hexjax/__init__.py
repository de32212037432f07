"""hexjax: differentiable, vectorised hexapod walking on JAX and MuJoCo MJX (docs/architecture.md).

The public names below load on first use, so `import hexjax` (and `hexjax --help`) imports no JAX.
"""

import importlib as _importlib
import os as _os
from importlib import metadata as _metadata

from hexjax import cache as _cache

# On obstacle terrain (convex box collisions inside the scanned, vmapped step) XLA:CPU's concurrency-
# optimized scheduler left every worker thread waiting for work and the process idle in
# block_until_ready forever: 3 of 5 runs on 2 cores with jax 0.10.2. Neither async dispatch off,
# single-threaded Eigen, nor replacing lax.top_k cured it; this flag did. It must be set before jax
# creates its CPU client; HEXJAX_KEEP_XLA_FLAGS=1 leaves XLA_FLAGS untouched.
#
# XLA:CPU in jaxlib 0.11 hands reductions to YNNPACK ("ynn_fusion" kernels); in a CPU profile of the tuning
# objective three of them, inside MJX's constraint solver, took more time than the rest of the step. Without them
# (`-reduce`) `make bench`'s rollouts ran 39-55 % faster at B = 64 and 256, a tactile one at B = 1,024 21-33 %;
# values move at float32 rounding (summation order; docs/modelling.md, docs/benchmarks.md 2026-11-27). GPU
# backends ignore the flag; it is set on jaxlib 0.11 only, where it was measured and where XLA knows it.
_DEFAULT_FLAGS = {"xla_cpu_enable_concurrency_optimized_scheduler": "false"}
try:
    if _metadata.version("jaxlib").startswith("0.11."):
        _DEFAULT_FLAGS["xla_cpu_experimental_ynn_fusion_type"] = "-reduce"
except _metadata.PackageNotFoundError:  # no jaxlib metadata: leave XLA's defaults
    pass
if not _os.environ.get("HEXJAX_KEEP_XLA_FLAGS"):
    _flags = _os.environ.get("XLA_FLAGS", "")
    for _name, _value in _DEFAULT_FLAGS.items():
        if _name not in _flags:
            _flags = f"{_flags} --{_name}={_value}".strip()
    _os.environ["XLA_FLAGS"] = _flags


# jaxlib 0.10.x split each batched LAPACK call (MJX's Cholesky, the implicit backward's solves) over XLA:CPU's
# intra-op pool and blocked its worker until the parts finished, so on 2 cores two concurrent calls deadlocked;
# hexjax sized that pool (PJRT_NPROC) while it ran on 0.10.2. jaxlib 0.11.1 removed that path, and hexjax now
# needs jax 0.11.2 (tests/test_runtime.py).

_cache.enable()

_EXPORTS = {
    "hexjax.world.robot": ["RobotSpec", "leg_fk", "leg_ik"],
    "hexjax.world.presets": ["get_robot", "get_terrain", "luneckas2020", "yu2019", "chen2019"],
    "hexjax.world.terrain": ["Terrain", "TerrainSpec", "obstacle_circles", "pad_terrain", "sample"],
    "hexjax.sim.config": ["PhysicsConfig", "RolloutConfig", "SensorConfig"],
    "hexjax.sim.physics": ["get_physics", "pick"],
    "hexjax.sim.mjcf": ["build_mjcf"],
    "hexjax.sim.model": ["Obs", "SimModel", "sim_model"],
    "hexjax.sim.step": ["Summary"],
    "hexjax.sim.rollout": ["RolloutStats", "make_mesh", "rollout", "rollout_function"],
    "hexjax.control.base": ["Controller"],
    "hexjax.control.registry": ["CONTROLLERS", "make_controller"],
    "hexjax.control.gait": ["GAITS", "GaitController", "GaitParams"],
    "hexjax.control.tactile": ["TactileGaitController", "TactileParams", "TactileState"],
    "hexjax.control.cpg": ["CPG_GAITS", "CPGController", "CPGParams", "CPGState", "gait_fields"],
    "hexjax.control.vdp": ["NetworkParams"],
    "hexjax.control.avoid_gait": ["AvoidGaitController"],
    "hexjax.control.support_gait": ["SupportPlanController"],
    "hexjax.sim.metrics": ["goal_errors"],
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
