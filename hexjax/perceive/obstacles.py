"""Obstacles from a grid map (Zhao 2018 Sect. 5): a known cell whose mean height stands more than `threshold`
above the ground plane is an obstacle cell; 8-connected obstacle cells form one obstacle, and each obstacle
is enveloped by a circle (Zhao 2018 Eq. 1: the planner sees robot and obstacles as circles), the circle about
the cells' centroid that holds every one of its cells whole. A fixed number Q of circles is returned (the
planner's input has a static shape): the obstacles nearest to a given point when there are more.

Components are found by label propagation: every obstacle cell starts with its own index as label and takes
the smallest label among its obstacle neighbours until nothing changes (`lax.while_loop`), so each
component ends labelled by its smallest cell index. Pure JAX; vmap it over envs.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hexjax.perceive.grid import GridMap, GridSpec
from hexjax.perceive.ransac import Plane, fit_plane


@struct.dataclass
class Circles:
    """Q obstacle circles: centres (Q, 2) m, radii (Q,) m, valid (Q,) bool; cells (Q,) obstacle cells in each."""

    centres: jax.Array
    radii: jax.Array
    valid: jax.Array
    cells: jax.Array


def obstacle_cells(spec: GridSpec, grid: GridMap, ground: Plane, threshold: float, min_points: int = 1):
    """(nx, ny) bool: cells with at least `min_points` points whose mean height is more than `threshold` m
    above the ground plane at the cell's centre."""
    h, _ = grid.heights()
    g = ground.height(jnp.asarray(spec.centres()))
    return (grid.count >= min_points) & (h - g > threshold)


def label_components(mask):
    """(nx, ny) int32: each 8-connected component of `mask` labelled by its smallest flat cell index; -1 off
    the mask."""
    nx, ny = mask.shape
    big = jnp.int32(nx * ny)
    lab0 = jnp.where(mask, jnp.arange(nx * ny, dtype=jnp.int32).reshape(nx, ny), big)

    def sweep(lab):
        p = jnp.pad(lab, 1, constant_values=big)
        nb = jnp.min(jnp.stack([p[1 + a:1 + a + nx, 1 + b:1 + b + ny] for a in (-1, 0, 1) for b in (-1, 0, 1)]), 0)
        return jnp.where(mask, nb, big)

    def body(c):
        lab, _ = c
        new = sweep(lab)
        return new, jnp.any(new != lab)

    lab, _ = jax.lax.while_loop(lambda c: c[1], body, (lab0, jnp.asarray(True)))
    return jnp.where(mask, lab, -1)


def circles(spec: GridSpec, mask, q: int, near=None) -> Circles:
    """Up to `q` circles, one per 8-connected component of the obstacle mask (nx, ny) (module docstring);
    `near` (2,) m: keep the components whose centroids lie nearest to it (default: the largest ones)."""
    n = spec.nx * spec.ny
    lab = label_components(mask).reshape(-1)
    xy = jnp.asarray(spec.centres()).reshape(-1, 2)
    seg = jnp.where(lab >= 0, lab, n)  # off-mask cells go to an extra segment
    w = (lab >= 0).astype(xy.dtype)
    cnt = jax.ops.segment_sum(w, seg, num_segments=n + 1)[:n]
    cen = jax.ops.segment_sum(xy * w[:, None], seg, num_segments=n + 1)[:n] / jnp.maximum(cnt, 1.0)[:, None]
    # radius: the farthest cell centre from the centroid plus half a cell's diagonal (the cell held whole)
    d = jnp.linalg.norm(xy - cen[jnp.clip(seg, 0, n - 1)], axis=-1)
    rad = jax.ops.segment_max(jnp.where(lab >= 0, d, 0.0), seg, num_segments=n + 1)[:n]
    rad = rad + spec.cell * np.sqrt(0.5)
    root = cnt > 0
    score = -jnp.linalg.norm(cen - near, axis=-1) if near is not None else cnt
    _, top = jax.lax.top_k(jnp.where(root, score, -jnp.inf), min(q, n))
    if n < q:  # a map of fewer cells than circles: the rest are empty slots
        top = jnp.concatenate([top, jnp.full(q - n, n, top.dtype)])
        root, cen, rad, cnt = (jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)])
                               for x in (root, cen, rad, cnt))
    ok = root[top]
    return Circles(centres=jnp.where(ok[:, None], cen[top], 0.0), radii=jnp.where(ok, rad[top], 0.0), valid=ok,
                   cells=jnp.where(ok, cnt[top], 0.0).astype(jnp.int32))


def map_ground(spec: GridSpec, grid: GridMap, key, n_hyp: int = 128, inlier: float = 0.01) -> Plane:
    """The ground `Plane` of a fused map: RANSAC (`n_hyp` hypotheses, inliers within `inlier` m) over the known
    cells' mean heights at their centres."""
    h, known = grid.heights()
    cells = jnp.concatenate([jnp.asarray(spec.centres()).reshape(-1, 2), h.reshape(-1, 1)], -1)
    return fit_plane(cells, known.reshape(-1), key, n_hyp, inlier)


def map_obstacles(spec: GridSpec, grid: GridMap, key, threshold: float, q: int, near=None, n_hyp: int = 128,
                  inlier: float = 0.01):
    """(ground `Plane`, obstacle mask (nx, ny), `Circles`) of a fused map: the ground (`map_ground`), cells more
    than `threshold` m above that plane, and up to `q` circles (nearest to `near` first)."""
    plane = map_ground(spec, grid, key, n_hyp, inlier)
    mask = obstacle_cells(spec, grid, plane, threshold)
    return plane, mask, circles(spec, mask, q, near=near)
