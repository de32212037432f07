"""hexjax: differentiable, vectorised hexapod walking on JAX and MuJoCo MJX."""

import os as _os

# XLA's CPU runtime can wedge its Eigen thread pool on the large vmapped rollout graph: the process sits
# at 0 % CPU inside block_until_ready forever (seen here twice on 2 cores, jax 0.10.2; the same hang is
# reported upstream for vmap graphs, cured by this flag). Set before jax initialises its CPU client;
# HEXJAX_KEEP_XLA_FLAGS=1 leaves XLA_FLAGS untouched.
if not _os.environ.get("HEXJAX_KEEP_XLA_FLAGS"):
    _flags = _os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_multi_thread_eigen" not in _flags:
        _os.environ["XLA_FLAGS"] = (_flags + " --xla_cpu_multi_thread_eigen=false").strip()

from hexjax.control.gait import GAITS, GaitController, GaitParams  # noqa: E402
from hexjax.mjcf import PhysicsConfig, build_mjcf  # noqa: E402
from hexjax.robot import RobotSpec, get_robot, leg_fk, leg_ik, luneckas2020, yu2019  # noqa: E402
from hexjax.sim.model import Obs, SensorConfig, SimModel, sim_model  # noqa: E402
from hexjax.sim.rollout import RolloutConfig, Summary, make_mesh, rollout  # noqa: E402
from hexjax.terrain import Terrain, TerrainSpec, get_terrain, obstacle_circles, sample  # noqa: E402

__all__ = ["GAITS", "GaitController", "GaitParams", "PhysicsConfig", "build_mjcf", "RobotSpec", "get_robot",
           "leg_fk", "leg_ik", "luneckas2020", "yu2019", "Obs", "SensorConfig", "SimModel", "sim_model",
           "RolloutConfig", "Summary", "make_mesh", "rollout", "Terrain", "TerrainSpec", "get_terrain",
           "obstacle_circles", "sample"]
__version__ = "0.1.0"
