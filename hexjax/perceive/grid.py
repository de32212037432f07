"""A 2.5D grid map fused from scans (Zhao 2018 Sect. 5): the points fall into the cells of a horizontal grid by
their x, y; a cell's height is the mean z of the points it has received. Cells with no point are unknown.

The map lives in the world frame and is fused over time as the robot walks: every scan adds its points to
the cells' sums and counts (`fuse`), so an obstacle once seen stays on the map when it leaves the field of
view (the Kinect sees nothing nearer than 0.8 m). Zhao 2018 moves the points into the robot frame first;
with the robot's pose from the simulator, the world frame is that frame moved by a known pose, and a map
that outlives one scan needs a fixed frame.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hexjax.perceive.raycast import Scan
from hexjax.world.dem import DEM, dem_layout


@dataclasses.dataclass(frozen=True)
class GridSpec:
    """Static layout of a grid map: cell (0, 0) spans origin .. origin + cell (m, world frame); nx x ny cells."""

    origin: tuple = (-0.5, -1.0)
    cell: float = 0.04
    nx: int = 80
    ny: int = 50

    def validate(self) -> None:
        if not (isinstance(self.cell, (int, float)) and np.isfinite(self.cell) and self.cell > 0):
            raise ValueError(f"grid.cell={self.cell!r}: must be a length > 0 m")
        for f in ("nx", "ny"):
            v = getattr(self, f)
            if not (isinstance(v, int) and 1 <= v <= 4096):
                raise ValueError(f"grid.{f}={v!r}: must be a whole number of cells in [1, 4096]")
        if len(self.origin) != 2 or not np.all(np.isfinite(self.origin)):
            raise ValueError(f"grid.origin={self.origin!r}: must be 2 finite numbers (m)")

    def centres(self) -> np.ndarray:
        """(nx, ny, 2) cell centres, m."""
        x = self.origin[0] + (np.arange(self.nx) + 0.5) * self.cell
        y = self.origin[1] + (np.arange(self.ny) + 0.5) * self.cell
        return np.stack(np.meshgrid(x, y, indexing="ij"), -1).astype(np.float32)

    @classmethod
    def covering(cls, lo, hi, cell: float) -> "GridSpec":
        """The grid of `cell` m cells covering the rectangle lo .. hi (2,), m."""
        cls(cell=cell).validate()
        n = np.ceil((np.asarray(hi, float) - np.asarray(lo, float)) / cell).astype(int)
        spec = cls(origin=(float(lo[0]), float(lo[1])), cell=float(cell), nx=int(n[0]), ny=int(n[1]))
        spec.validate()  # e.g. a cell so small that the rectangle needs more than 4096 a side
        return spec


@struct.dataclass
class GridMap:
    """The fused map of one env: sum_z (nx, ny) m, the sum of the heights of the points in each cell; count
    (nx, ny), how many."""

    sum_z: jax.Array
    count: jax.Array

    @classmethod
    def empty(cls, spec: GridSpec) -> "GridMap":
        return cls(sum_z=jnp.zeros((spec.nx, spec.ny)), count=jnp.zeros((spec.nx, spec.ny)))

    def heights(self):
        """(mean height (nx, ny) m, 0 where unknown; known (nx, ny) bool)."""
        known = self.count > 0
        return jnp.where(known, self.sum_z / jnp.maximum(self.count, 1.0), 0.0), known


def dem_grid(terrain_spec, margin: float = 0.5) -> GridSpec:
    """The grid map laid out like the DEM `hexjax.world.dem.dem_for` rasterises for `terrain_spec` terrains (same
    origin, cell and size), so a perceived map and the true DEM compare cell by cell."""
    origin, (nx, ny), cell = dem_layout(terrain_spec, margin)
    return GridSpec(origin=(float(origin[0]), float(origin[1])), cell=float(cell), nx=nx, ny=ny)


def cell_index(spec: GridSpec, xy):
    """(ix, iy, inside) of points xy (..., 2): their cell and whether it lies on the grid."""
    ij = jnp.floor((xy - jnp.asarray(spec.origin, xy.dtype)) / spec.cell).astype(jnp.int32)
    inside = (ij[..., 0] >= 0) & (ij[..., 0] < spec.nx) & (ij[..., 1] >= 0) & (ij[..., 1] < spec.ny)
    return ij[..., 0], ij[..., 1], inside


def fuse(spec: GridSpec, grid: GridMap, scan: Scan) -> GridMap:
    """The map with one scan's valid points added (points off the grid are left out)."""
    ix, iy, inside = cell_index(spec, scan.points[:, :2])
    w = (scan.valid & inside).astype(grid.sum_z.dtype)
    ix, iy = jnp.where(inside, ix, 0), jnp.where(inside, iy, 0)
    return GridMap(sum_z=grid.sum_z.at[ix, iy].add(w * scan.points[:, 2]),
                   count=grid.count.at[ix, iy].add(w))


def fill_unknown(h, known, passes: int):
    """(heights, known) (nx, ny) with unknown cells next to known ones given the highest of their known 3 x 3
    neighbours, `passes` times over (each pass reaches one cell further). The highest, not the mean: a cell
    hidden behind a crest is more likely as high as the crest than as low as the floor in front of it, and a
    planner that overestimates a height lifts its swing foot higher instead of stubbing it."""
    nx, ny = h.shape

    def one(_, hk):
        h, k = hk
        p = jnp.pad(jnp.where(k, h, -jnp.inf), 1, constant_values=-jnp.inf)
        nb = jnp.max(jnp.stack([p[1 + a:1 + a + nx, 1 + b:1 + b + ny] for a in (-1, 0, 1) for b in (-1, 0, 1)]), 0)
        new = ~k & jnp.isfinite(nb)
        return jnp.where(new, nb, h), k | new

    return jax.lax.fori_loop(0, passes, one, (h, known))


def to_dem(spec: GridSpec, grid: GridMap, fill, passes: int = 0) -> DEM:
    """The map as a `DEM` (the Chen 2019 foothold planner's input): unknown cells within `passes` cells of a
    known one take a neighbour's height (`fill_unknown`), the rest the height `fill` (e.g. the ground
    height from `hexjax.perceive.ransac`)."""
    h, known = grid.heights()
    h, known = fill_unknown(h, known, passes)
    return DEM(heights=jnp.where(known, h, fill), origin=jnp.asarray(spec.origin, jnp.float32),
               cell=jnp.float32(spec.cell))
