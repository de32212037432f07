"""Digital elevation maps: 2.5D grids of terrain height, as Chen 2019's foothold planner reads the ground
(its map is given, Sect. 1), rasterised from a terrain's boxes."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hexjax.world.terrain import Terrain


@struct.dataclass
class DEM:
    """A 2.5D grid: heights (NX, NY) m of cells `cell` m wide, cell (0, 0) spanning origin .. origin + cell."""

    heights: jax.Array
    origin: jax.Array
    cell: jax.Array


def rasterise(terrain: Terrain, origin, shape, cell: float) -> jax.Array:
    """Top height (NX, NY) of one terrain at each cell centre of a grid (the highest box covering it, else
    the ground)."""
    nx, ny = shape
    xs = origin[0] + (jnp.arange(nx) + 0.5) * cell
    ys = origin[1] + (jnp.arange(ny) + 0.5) * cell
    top = terrain.box_pos[:, 2] + terrain.box_half[:, 2]

    def column(x):
        inx = jnp.abs(x - terrain.box_pos[:, 0]) <= terrain.box_half[:, 0]
        iny = jnp.abs(ys[:, None] - terrain.box_pos[None, :, 1]) <= terrain.box_half[None, :, 1]
        h = jnp.where(inx[None] & iny & terrain.box_valid[None], top[None], -jnp.inf)
        return jnp.maximum(jnp.max(h, -1), terrain.ground_z)

    return jax.lax.map(column, xs)


def dem_lookup(dem: DEM, xy):
    """Height (...) at points xy (..., 2) (nearest cell; points off the grid read its edge)."""
    ij = jnp.floor((xy - dem.origin) / dem.cell).astype(jnp.int32)
    i = jnp.clip(ij[..., 0], 0, dem.heights.shape[0] - 1)
    j = jnp.clip(ij[..., 1], 0, dem.heights.shape[1] - 1)
    return dem.heights[i, j]


def snap(dem: DEM, xy):
    """The centre of the cell holding each point xy (..., 2)."""
    return dem.origin + (jnp.floor((xy - dem.origin) / dem.cell) + 0.5) * dem.cell


# cell offsets of a 3 x 3 neighbourhood
NEIGHBOURS_3X3 = np.array([(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)], np.float32)


def dem_layout(spec, margin: float = 0.5):
    """(origin (2,) m, (nx, ny), cell m) of the DEM grid of `spec` terrains: the terrain's own grid, extended
    by `margin` m of ground on every side."""
    cell = spec.cell
    pad = int(round(margin / cell))
    nx, ny = spec._grid_shape()
    origin = np.array([spec.start_x - pad * cell, -0.5 * spec.width - pad * cell], np.float32)
    return origin, (nx + 2 * pad, ny + 2 * pad), cell


def dem_for(spec, terrain: Terrain, margin: float = 0.5) -> DEM:
    """Per-env DEMs (leading axis B) of a batch of `spec` terrains, laid out by `dem_layout`."""
    origin, shape, cell = dem_layout(spec, margin)
    h = jax.jit(jax.vmap(lambda t: rasterise(t, jnp.asarray(origin), shape, cell)))(terrain)
    b = h.shape[0]
    return DEM(heights=h, origin=jnp.broadcast_to(jnp.asarray(origin), (b, 2)), cell=jnp.full((b,), cell, jnp.float32))
