"""hexjax: differentiable, vectorised hexapod walking on JAX and MuJoCo MJX."""

import os as _os

# On obstacle terrain (convex box collisions inside the scanned, vmapped step) XLA:CPU's concurrency-
# optimized scheduler left every worker thread waiting for work and the process idle in
# block_until_ready forever: 3 of 5 runs on 2 cores with jax 0.10.2. Neither async dispatch off,
# single-threaded Eigen, nor replacing lax.top_k cured it; this flag did. It must be set before jax
# creates its CPU client; HEXJAX_KEEP_XLA_FLAGS=1 leaves XLA_FLAGS untouched.
if not _os.environ.get("HEXJAX_KEEP_XLA_FLAGS"):
    _flags = _os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_enable_concurrency_optimized_scheduler" not in _flags:
        _os.environ["XLA_FLAGS"] = (_flags + " --xla_cpu_enable_concurrency_optimized_scheduler=false").strip()

from hexjax.control.cpg import CPG_GAITS, CPGController, CPGParams, CPGState  # noqa: E402
from hexjax.control.gait import GAITS, GaitController, GaitParams  # noqa: E402
from hexjax.control.tactile import TactileGaitController, TactileParams, TactileState  # noqa: E402
from hexjax.control.vdp import NetworkParams  # noqa: E402
from hexjax.mjcf import PhysicsConfig, build_mjcf  # noqa: E402
from hexjax.robot import RobotSpec, get_robot, leg_fk, leg_ik, luneckas2020, yu2019  # noqa: E402
from hexjax.sim.model import Obs, SensorConfig, SimModel, sim_model  # noqa: E402
from hexjax.sim.rollout import RolloutConfig, Summary, make_mesh, rollout, rollout_function  # noqa: E402
from hexjax.terrain import Terrain, TerrainSpec, get_terrain, obstacle_circles, sample  # noqa: E402

__all__ = ["CPG_GAITS", "CPGController", "CPGParams", "CPGState", "NetworkParams", "GAITS", "GaitController",
           "GaitParams", "TactileGaitController", "TactileParams", "TactileState", "PhysicsConfig", "build_mjcf", "RobotSpec", "get_robot",
           "leg_fk", "leg_ik", "luneckas2020", "yu2019", "Obs", "SensorConfig", "SimModel", "sim_model",
           "RolloutConfig", "Summary", "make_mesh", "rollout", "rollout_function", "Terrain", "TerrainSpec", "get_terrain",
           "obstacle_circles", "sample"]
__version__ = "0.1.0"
