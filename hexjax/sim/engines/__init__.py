"""The engines that step hexjax's physics, one file each behind one protocol (`base.Engine`): build the model
for a batch, roll out its control steps, read its contacts and sensors. Each declares what it can do
(gradients, a device mesh, range sensors, traces), its precision and the hosts it runs on; callers ask it
(`Engine.can`, `Engine.lacks`) and never compare names. A new engine is one file and one entry here.

    mjx   MJX in JAX: differentiable, shardable, any JAX device (`mjx.py`)
    warp  MuJoCo Warp's kernels through MJX: a CUDA GPU's fast forward engine (`warp.py`)
    c     MuJoCo C in float64 on the host's cores: the reference (`c.py`)
"""

from __future__ import annotations

from typing import Dict

from hexjax.sim.engines.base import CAPABILITIES, GRADIENTS, MESH, RANGE_SENSORS, TRACES, Engine, host_cores
from hexjax.sim.engines.c import C_ENGINE
from hexjax.sim.engines.mjx import MJX_ENGINE
from hexjax.sim.engines.warp import WARP_ENGINE
from hexjax.sim.model import built

ENGINES: Dict[str, Engine] = {e.name: e for e in (MJX_ENGINE, WARP_ENGINE, C_ENGINE)}
NAMES = tuple(ENGINES)
# fastest first on each kind of host, as measured on the tactile gait over high-large (docs/benchmarks.md):
# MuJoCo C runs 19x MJX on 2 CPU cores; on one H100 MuJoCo Warp runs 5.5x MJX at B = 32k
ORDER = {"cpu": ("c", "mjx", "warp"), "gpu": ("warp", "mjx", "c")}

__all__ = ["CAPABILITIES", "ENGINES", "Engine", "GRADIENTS", "MESH", "NAMES", "ORDER", "RANGE_SENSORS", "TRACES",
           "get_engine", "host_cores", "host_kind", "sim_model"]


def get_engine(name) -> Engine:
    """The engine named `name` (an `Engine` is given back), or one ValueError line naming the known ones."""
    if isinstance(name, Engine):
        return name
    if name not in ENGINES:
        raise ValueError(f"engine={name!r}: use one of {', '.join(NAMES)}")
    return ENGINES[name]


def sim_model(robot, physics, engine="mjx"):
    """The cached `hexjax.sim.model.SimModel` of `robot` under `physics` (a `PhysicsConfig`) for an MJX-family
    engine (`engine`: its name or the engine; default MJX)."""
    return built(robot, physics, get_engine(engine))


def host_kind(platform=None) -> str:
    """'cpu' or 'gpu': what this process steps physics on (`platform`: JAX's default backend where None)."""
    if platform is None:
        import jax
        platform = jax.default_backend()
    return "cpu" if platform == "cpu" else "gpu"
