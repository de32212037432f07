"""The Zhao 2018 avoidance gait steered by what it perceives (Sect. 5, Fig. 15): a range sensor on the torso
scans the terrain, the points fill a 2.5D grid map fused as the robot walks, RANSAC finds the ground, cells
standing above it are obstacles, and each connected obstacle is enveloped by a circle (Eq. 1). The direction
selection (Eqs. 2-6, `AvoidGaitController`) then plans round these circles instead of the true ones.

`PerceivingAvoidGait` differs from `AvoidGaitController` only in where its circles come from: the params keep
the true circles (for the target check and for a privileged run of the same fields), the state holds the
map and the perceived circles, refreshed by `perceive` every `perceive_every` control steps (the control
step casts the rays: `hexjax.sim.step`). The robot's pose comes from the simulator (Zhao 2018's robot
location block; no localisation error is modelled), and the robot does not see itself (rays meet the terrain
only).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hexjax.control.avoid_gait import AvoidGaitController, AvoidGaitParams, AvoidGaitState
from hexjax.perceive import grid as gridmap
from hexjax.perceive.grid import GridMap, GridSpec
from hexjax.perceive.obstacles import Circles, map_obstacles
from hexjax.perceive.sensors import RangeSensor, validate_perceiver


@struct.dataclass
class PerceiveState:
    """avoid: the planner-gait's state; grid: the fused map; circ: the perceived obstacle circles; ground:
    (normal (3,), offset ()) of the last RANSAC ground plane; scans: scans taken."""

    avoid: AvoidGaitState
    grid: GridMap
    circ: Circles
    ground_normal: jax.Array
    ground_offset: jax.Array
    scans: jax.Array


@dataclasses.dataclass(frozen=True)
class PerceivingAvoidGait(AvoidGaitController):
    """`AvoidGaitController` planning round perceived obstacles (module docstring). Static: the sensor, the
    map's grid, the scan period (control steps), the obstacle threshold above the ground (m; lower things the
    gait walks over), the number of circles handed to the planner, RANSAC's hypotheses and inlier distance.
    Every scan refits the ground to the whole map's known cells and re-extracts the circles, nearest to the
    robot first."""

    sensor: RangeSensor = RangeSensor()  # the Kinect V1's fields of view and ranges by default
    grid: GridSpec = GridSpec()  # the map: world frame, fixed for the walk
    perceive_every: int = 5  # control steps between scans
    obstacle_threshold: float = 0.05  # m above the RANSAC ground
    n_circles: int = 24  # circles handed to the planner (nearest first)
    ransac_hypotheses: int = 64
    ransac_threshold: float = 0.01  # m: a cell within this of a plane is its inlier

    def __post_init__(self):
        super().__post_init__()
        validate_perceiver(self)
        if not self.obstacle_threshold > 0:
            raise ValueError(f"obstacle_threshold={self.obstacle_threshold!r}: must be > 0 m")
        if not (isinstance(self.n_circles, int) and 1 <= self.n_circles <= 256):
            raise ValueError(f"n_circles={self.n_circles!r}: must be in [1, 256]")

    def init(self, params: AvoidGaitParams, key) -> PerceiveState:
        q = self.n_circles
        empty = Circles(centres=jnp.zeros((q, 2)), radii=jnp.zeros(q), valid=jnp.zeros(q, bool),
                        cells=jnp.zeros(q, jnp.int32))
        return PerceiveState(avoid=super().init(params, key), grid=GridMap.empty(self.grid), circ=empty,
                             ground_normal=jnp.array([0.0, 0.0, 1.0]), ground_offset=jnp.asarray(0.0),
                             scans=jnp.int32(0))

    def perceive(self, params: AvoidGaitParams, state: PerceiveState, scan, key) -> PerceiveState:
        g = gridmap.fuse(self.grid, state.grid, scan)
        plane, _, circ = map_obstacles(self.grid, g, key, self.obstacle_threshold, self.n_circles,
                                       near=scan.origin[:2], n_hyp=self.ransac_hypotheses,
                                       inlier=self.ransac_threshold)
        return state.replace(grid=g, circ=circ, ground_normal=plane.normal, ground_offset=plane.offset,
                             scans=state.scans + 1)

    def step(self, params: AvoidGaitParams, state: PerceiveState, obs):
        seen = params.replace(centres=state.circ.centres, radii=state.circ.radii, valid=state.circ.valid)
        avoid_state, action = super().step(seen, state.avoid, obs)
        return state.replace(avoid=avoid_state), action

    def trace(self, state: PerceiveState, obs):
        """The planner's trace and the number of perceived circles."""
        return jnp.concatenate([super().trace(state.avoid, obs), jnp.sum(state.circ.valid)[None].astype(jnp.float32)])


def map_bounds(fields, margin: float = 0.5):
    """(lo, hi) (2,) m of a map covering the start (0, 0), every target and every place an obstacle could stand
    in `fields` (the centres drawn, kept or not: the corridor, not which obstacles are there), with `margin` m
    round them."""
    pts = np.concatenate([np.zeros((1, 2)), np.asarray(fields.target).reshape(-1, 2),
                          np.asarray(fields.centres).reshape(-1, 2)])
    return pts.min(0) - margin, pts.max(0) + margin
