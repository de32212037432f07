"""Chen 2019's support planner on a map it builds itself: the DEM the foothold and torso planning read
(`SupportPlanController`, Chen 2019 Sects. 2.2 and 3.1) comes from a range sensor on the torso instead of the
true terrain. Chen 2019 takes the map as given (Sect. 1) and names the 2.5D elevation map it would come from;
Zhao 2018 Sect. 5 builds such a map from a depth camera's points (mean height per cell), as here.

Every `perceive_every` control steps the control step casts the sensor's rays (`hexjax.sim.step`); the points
are fused into a world-frame grid map laid out like the true DEM (same origin, cell and size, so the two
runs differ only in the heights); RANSAC fits the ground to the known cells; unknown cells next to known
ones take their highest known neighbour (`hexjax.perceive.grid.fill_unknown`) and the rest the ground's
height. The planner reads this DEM at its next support-swing transition. What it gets wrong, it gets wrong
as a real robot would: cells never seen (behind crests, under the robot, outside the field of view), mean
heights lowered by returns from column sides, and range noise.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from hexjax.control.support_gait import SupportParams, SupportPlanController, SupportState
from hexjax.perceive import grid as gridmap
from hexjax.perceive.grid import GridMap, GridSpec
from hexjax.perceive.obstacles import map_ground
from hexjax.perceive.sensors import RangeSensor, validate_perceiver
from hexjax.world.dem import DEM


@struct.dataclass
class PerceiveSupportState:
    """support: the planner's state; grid: the fused map; heights (nx, ny) m: the DEM the planner reads (the
    map with its unknown cells filled); scans: scans taken."""

    support: SupportState
    grid: GridMap
    heights: jax.Array
    scans: jax.Array


@dataclasses.dataclass(frozen=True)
class PerceivingSupportPlan(SupportPlanController):
    """`SupportPlanController` on a perceived DEM (module docstring). Static: the sensor, the map's grid (lay it
    out like the true DEM, `hexjax.world.dem.dem_layout`), the scan period (control steps), the fill's reach
    (cells) and RANSAC's hypotheses and inlier distance. The params' `dem` is not read (it may hold the true
    one, for a privileged run of the same patches)."""

    sensor: RangeSensor = RangeSensor()
    grid: GridSpec = GridSpec()
    perceive_every: int = 5
    fill_passes: int = 3
    ransac_hypotheses: int = 64
    ransac_threshold: float = 0.01

    def __post_init__(self):
        super().__post_init__()
        validate_perceiver(self)
        if not (isinstance(self.fill_passes, int) and self.fill_passes >= 0):
            raise ValueError(f"fill_passes={self.fill_passes!r}: must be a whole number of cells >= 0")

    def init(self, params: SupportParams, key) -> PerceiveSupportState:
        g = GridMap.empty(self.grid)
        return PerceiveSupportState(support=super().init(params, key), grid=g, heights=jnp.zeros_like(g.sum_z),
                                    scans=jnp.int32(0))

    def _dem(self, state: PerceiveSupportState) -> DEM:
        return DEM(heights=state.heights, origin=jnp.asarray(self.grid.origin, jnp.float32),
                   cell=jnp.float32(self.grid.cell))

    def perceive(self, params: SupportParams, state: PerceiveSupportState, scan, key) -> PerceiveSupportState:
        g = gridmap.fuse(self.grid, state.grid, scan)
        plane = map_ground(self.grid, g, key, self.ransac_hypotheses, self.ransac_threshold)
        dem = gridmap.to_dem(self.grid, g, plane.height(jnp.asarray(self.grid.centres())), self.fill_passes)
        return state.replace(grid=g, heights=dem.heights, scans=state.scans + 1)

    def step(self, params: SupportParams, state: PerceiveSupportState, obs):
        support, action = super().step(params.replace(dem=self._dem(state)), state.support, obs)
        return state.replace(support=support), action

    def trace(self, state: PerceiveSupportState, obs):
        return super().trace(state.support, obs)
