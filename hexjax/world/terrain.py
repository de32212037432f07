"""Terrains: the spec of a family (`TerrainSpec`, presets in configs/terrains/), its batched generators, and
views of a sampled terrain for planners and plots.

Every terrain is a set of axis-aligned boxes standing on (or, for ditches, around) a ground plane;
see docs/terrain.md for why boxes were chosen over a heightfield. A batch is sampled from PRNG keys
in one jitted, vmapped call and has fixed shapes: `max_boxes` per env, unused boxes masked off.

Categories (Luneckas 2020 Sect. 2.2, Eq. 16; Yu 2019 Sect. 6; Chen 2019 Sect. 3.1):
  obstacle fields: density low (R >= 15 cm) / high (10 < R < 15 cm) between obstacle centres,
                   height small (3-5 cm) / large (6-8 cm), length 2-3 cm, random width;
  step (40 mm), ditches (18 / 40 / 80 mm deep), rugged wave patch (400 x 800 mm, peaks ~178 mm),
  random uniform roughness, flat.
Families of the legged-robot benchmarks (legged_gym / Isaac Lab terrain generators, sized for a hexapod):
  slope up / down (a ramp of thin slices), stairs up / down, stepping stones over a pit, random boxes.

Difficulty: every family has a scale `difficulty` in [0, 1] (`TerrainSpec.at_difficulty`, table `DIFFICULTY`)
that sets the keys which make it hard (heights, slope, gaps) between an easy and a hard end. The lengths of
the table are for the Luneckas 2020 robot (femur + tibia 20.2 cm) and scale with the robot's leg
(`leg_scale`): stairs rise 1-8 cm for it.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

# the data types and the difficulty table live in terrain_spec; imported here so `hexjax.world.terrain` names them
from hexjax.world.terrain_spec import (  # noqa: F401
    DIFFICULTY,
    KINDS,
    LUNECKAS2020_LEG,
    MAX_BOXES,
    MAX_EXTENT,
    UNSCALED,
    Terrain,
    TerrainSpec,
    leg_scale,
)


def _obstacle_field(spec: TerrainSpec, key) -> Terrain:
    """Jittered, rotated hexagonal lattice clipped to the corridor (Luneckas 2020 Sect. 2.2).

    Lattice spacing a and jitter j bound every nearest-neighbour distance to [a - 2j, a + 2j];
    dropping sites only increases it, so presets pick a, j, drop to satisfy the category's R range."""
    ks = jax.random.split(key, 9)
    n = spec._lattice_n()
    a = jax.random.uniform(ks[0], (), minval=spec.spacing_range[0], maxval=spec.spacing_range[1])
    theta = jax.random.uniform(ks[1], (), maxval=math.pi / 3)
    offset = jax.random.uniform(ks[2], (2,)) * a
    i, j = jnp.meshgrid(jnp.arange(-n, n + 1), jnp.arange(-n, n + 1), indexing="ij")
    i, j = i.reshape(-1), j.reshape(-1)
    lx = a * (i + 0.5 * j) + offset[0]
    ly = a * (0.5 * math.sqrt(3) * j) + offset[1]
    c, s = jnp.cos(theta), jnp.sin(theta)
    centre = jnp.array([spec.start_x + 0.5 * spec.length, 0.0])
    px = c * lx - s * ly + centre[0]
    py = s * lx + c * ly + centre[1]
    r = spec.jitter * jnp.sqrt(jax.random.uniform(ks[3], px.shape))
    phi = jax.random.uniform(ks[4], px.shape, maxval=2 * math.pi)
    px, py = px + r * jnp.cos(phi), py + r * jnp.sin(phi)
    inside = ((px >= spec.start_x) & (px <= spec.start_x + spec.length) & (jnp.abs(py) <= 0.5 * spec.width))
    drop = jax.random.uniform(ks[5], ()) * spec.drop_max
    keep = inside & (jax.random.uniform(ks[6], px.shape) >= drop)
    order = jnp.argsort(~keep, stable=True)[: spec.max_boxes]
    m = spec.max_boxes
    h = jax.random.uniform(ks[7], (m,), minval=spec.height_range[0], maxval=spec.height_range[1])
    lw = jax.random.uniform(ks[8], (m, 2))
    length = spec.length_range[0] + lw[:, 0] * (spec.length_range[1] - spec.length_range[0])
    width = spec.width_range[0] + lw[:, 1] * (spec.width_range[1] - spec.width_range[0])
    valid = keep[order]
    pos = jnp.stack([px[order], py[order], 0.5 * h], axis=-1)
    half = jnp.stack([0.5 * length, 0.5 * width, 0.5 * h], axis=-1)
    return Terrain(box_pos=pos, box_half=half, box_valid=valid, ground_z=jnp.zeros(()))


def _step(spec: TerrainSpec, key) -> Terrain:
    """One step obstacle (Yu 2019 Sect. 6.1: 40 mm, on the right side of the path)."""
    k1, k2, k3 = jax.random.split(key, 3)
    h = jax.random.uniform(k1, (), minval=spec.height_range[0], maxval=spec.height_range[1])
    length = jax.random.uniform(k2, (), minval=spec.step_length_range[0], maxval=spec.step_length_range[1])
    x0 = spec.start_x + jax.random.uniform(k3, ()) * 0.25 * spec.length
    # the step runs 0.5 m past the corridor's side, so a robot that veers cannot walk round it
    w = 0.5 * spec.width + 0.5
    y_lo, y_hi = {"right": (-w, -0.06), "left": (0.06, w), "full": (-w, w)}[spec.step_side]
    pos = jnp.array([[x0 + 0.5 * length, 0.5 * (y_lo + y_hi), 0.5 * h]])
    half = jnp.array([[0.5 * length, 0.5 * (y_hi - y_lo), 0.5 * h]])
    return Terrain(box_pos=pos, box_half=half, box_valid=jnp.ones((1,), bool), ground_z=jnp.zeros(()))


def _ditch(spec: TerrainSpec, key) -> Terrain:
    """Striped ground with `ditch_count` ditches across the path (Yu 2019 Sect. 6.2: 18/40/80 mm deep).

    The ground plane sits at the ditch bottom; solid ground is a row of slabs with top at z = 0."""
    k1, k2, k3 = jax.random.split(key, 3)
    n = spec.ditch_count
    depth = jax.random.uniform(k1, (), minval=spec.height_range[0], maxval=spec.height_range[1])
    widths = jax.random.uniform(k2, (n,), minval=spec.ditch_width_range[0], maxval=spec.ditch_width_range[1])
    gaps = jax.random.uniform(k3, (n - 1,), minval=spec.ditch_gap_range[0], maxval=spec.ditch_gap_range[1])
    starts = spec.start_x + jnp.concatenate([jnp.zeros(1), jnp.cumsum(widths[:-1] + gaps)])
    ends = starts + widths
    x_lo = jnp.concatenate([jnp.array([-1.0]), ends])
    x_hi = jnp.concatenate([starts, jnp.array([spec.start_x + spec.length + 1.0])])
    x_hi = jnp.maximum(x_hi, x_lo + 0.01)
    pos = jnp.stack([0.5 * (x_lo + x_hi), jnp.zeros(n + 1), jnp.full(n + 1, -0.5) * depth], axis=-1)
    half = jnp.stack([0.5 * (x_hi - x_lo), jnp.full(n + 1, 0.5 * spec.width + 0.5), jnp.full(n + 1, 0.5) * depth], -1)
    return Terrain(box_pos=pos, box_half=half, box_valid=jnp.ones((n + 1,), bool), ground_z=-depth)


def _grid_boxes(spec: TerrainSpec, heights) -> Terrain:
    nx, ny = spec._grid_shape()
    xc = spec.start_x + (jnp.arange(nx) + 0.5) * spec.cell
    yc = (jnp.arange(ny) + 0.5) * spec.cell - 0.5 * spec.width
    x, y = jnp.meshgrid(xc, yc, indexing="ij")
    h = jnp.maximum(heights, 0.002)
    pos = jnp.stack([x, y, 0.5 * h], axis=-1).reshape(-1, 3)
    half = jnp.stack([jnp.full_like(h, 0.5 * spec.cell), jnp.full_like(h, 0.5 * spec.cell), 0.5 * h], -1).reshape(-1, 3)
    return Terrain(box_pos=pos, box_half=half, box_valid=jnp.ones((nx * ny,), bool), ground_z=jnp.zeros(()))


def _waves(spec: TerrainSpec, key) -> Terrain:
    """Rugged wave patch (Chen 2019 Sect. 3.1: 400 x 800 mm, peaks to ~178 mm) as a grid of columns:
    a sum of four random products of sinusoids, rescaled so its maximum is the sampled peak height."""
    k1, k2, k3 = jax.random.split(key, 3)
    nx, ny = spec._grid_shape()
    x = (jnp.arange(nx) + 0.5)[:, None] * spec.cell
    y = (jnp.arange(ny) + 0.5)[None, :] * spec.cell
    lam = jax.random.uniform(k1, (4, 2), minval=0.2, maxval=0.6)
    ph = jax.random.uniform(k2, (4, 2), maxval=2 * math.pi)
    f = sum(jnp.sin(2 * math.pi * x / lam[k, 0] + ph[k, 0]) * jnp.sin(2 * math.pi * y / lam[k, 1] + ph[k, 1])
            for k in range(4))
    f = (f - f.min()) / (f.max() - f.min() + 1e-9)
    peak = jax.random.uniform(k3, (), minval=spec.height_range[0], maxval=spec.height_range[1])
    if spec.taper > 0:  # a patch rising out of a flat floor: a smooth ramp from every edge
        ramp = lambda d: jnp.clip(d / spec.taper, 0.0, 1.0) ** 2 * (3.0 - 2.0 * jnp.clip(d / spec.taper, 0.0, 1.0))
        lx, ly = nx * spec.cell, ny * spec.cell
        f = f * ramp(jnp.minimum(x, lx - x)) * ramp(jnp.minimum(y, ly - y))
    return _grid_boxes(spec, peak * f)


def _rough(spec: TerrainSpec, key) -> Terrain:
    """Random uniform roughness: each grid cell an independent height in height_range."""
    nx, ny = spec._grid_shape()
    h = jax.random.uniform(key, (nx, ny), minval=spec.height_range[0], maxval=spec.height_range[1])
    return _grid_boxes(spec, h)


def _columns(x_lo, x_hi, top, bottom, half_y, valid=None):
    """(pos, half, valid) of boxes spanning x_lo..x_hi along x, |y| <= half_y, from z = bottom up to z = top
    (arrays (n,))."""
    n = x_lo.shape[0]
    height = jnp.maximum(top - bottom, 1e-3)
    pos = jnp.stack([0.5 * (x_lo + x_hi), jnp.zeros(n), bottom + 0.5 * height], -1)
    half = jnp.stack([0.5 * (x_hi - x_lo), jnp.full(n, half_y), 0.5 * height], -1)
    return pos, half, jnp.ones((n,), bool) if valid is None else valid


def _slope(spec: TerrainSpec, key) -> Terrain:
    """A ramp of angle slope_range over `length` from start_x, as slices `cell` long (a staircase of risers
    tan(angle) * cell, as the heightfield slopes of legged_gym are), then a landing. 'up' climbs from the
    ground; 'down' descends from a start platform at z = 0 to the ground plane below."""
    angle = jax.random.uniform(key, (), minval=spec.slope_range[0], maxval=spec.slope_range[1])
    n = spec._grid_shape()[0]
    dx = spec.length / n
    x_lo = spec.start_x + dx * jnp.arange(n + 1.0)
    x_hi = (x_lo + dx).at[-1].set(spec.start_x + spec.length + 1.0)
    rise = jnp.tan(angle) * dx * (jnp.arange(n + 1.0) + 0.5).at[-1].set(n)  # slice centres, then the landing
    half_y = 0.5 * spec.width + 0.5
    if spec.direction == "up":
        pos, half, valid = _columns(x_lo, x_hi, rise, jnp.zeros(n + 1), half_y)
        return Terrain(box_pos=pos, box_half=half, box_valid=valid, ground_z=jnp.zeros(()))
    ground = -jnp.tan(angle) * spec.length
    x_lo = jnp.concatenate([jnp.array([-1.0]), x_lo[:-1]])  # the start platform, then the slices
    x_hi = jnp.concatenate([jnp.array([spec.start_x]), x_hi[:-1]])
    top = -jnp.concatenate([jnp.zeros(1), rise[:-1]])
    pos, half, valid = _columns(x_lo, x_hi, top, jnp.full(n + 1, ground), half_y)
    return Terrain(box_pos=pos, box_half=half, box_valid=valid & (top > ground + 1e-3), ground_z=ground)


def _stairs(spec: TerrainSpec, key) -> Terrain:
    """`stair_count` steps from start_x, risers height_range and treads tread_range (drawn once per terrain),
    then a landing. 'up' climbs from the ground; 'down' descends from a start platform at z = 0 to the ground
    plane, which is the last step's tread."""
    k1, k2 = jax.random.split(key)
    n = spec.stair_count
    riser = jax.random.uniform(k1, (), minval=spec.height_range[0], maxval=spec.height_range[1])
    tread = jax.random.uniform(k2, (), minval=spec.tread_range[0], maxval=spec.tread_range[1])
    j = jnp.arange(n + 1.0)
    half_y = 0.5 * spec.width + 0.5
    if spec.direction == "up":  # steps 1..n, the last one the landing; entry n unused
        x_lo = spec.start_x + tread * j
        x_hi = jnp.where(j >= n - 1, spec.start_x + spec.length + 1.0, x_lo + tread)
        pos, half, valid = _columns(x_lo, x_hi, riser * (j + 1), jnp.zeros(n + 1), half_y, j < n)
        return Terrain(box_pos=pos, box_half=half, box_valid=valid, ground_z=jnp.zeros(()))
    ground = -riser * n
    x_lo = jnp.where(j == 0, -1.0, spec.start_x + tread * (j - 1))
    x_hi = spec.start_x + tread * j
    pos, half, valid = _columns(x_lo, x_hi, -riser * j, jnp.full(n + 1, ground), half_y, j < n)
    return Terrain(box_pos=pos, box_half=half, box_valid=valid, ground_z=ground)


def _stones(spec: TerrainSpec, key) -> Terrain:
    """Stepping stones: a grid of square stones (side stone_pitch - gap, gap from gap_range once per terrain)
    with tops at z = 0 over a pit height_range deep, between a start platform and a far landing."""
    k1, k2 = jax.random.split(key)
    nx, ny = spec._stone_grid()
    gap = jax.random.uniform(k1, (), minval=spec.gap_range[0], maxval=spec.gap_range[1])
    depth = jax.random.uniform(k2, (), minval=spec.height_range[0], maxval=spec.height_range[1])
    px, py = spec.length / nx, spec.width / ny
    x, y = jnp.meshgrid(spec.start_x + (jnp.arange(nx) + 0.5) * px, (jnp.arange(ny) + 0.5) * py - 0.5 * spec.width,
                        indexing="ij")
    m = nx * ny
    half_x = jnp.full(m, 0.5 * px) - 0.5 * gap
    half_y = jnp.full(m, 0.5 * py) - 0.5 * gap
    end = spec.start_x + spec.length
    # the platforms stop half a gap short of the stones, so the first and last rows stand alone too
    plat_lo = jnp.array([-1.0, end + 0.5 * gap])
    plat_hi = jnp.array([spec.start_x - 0.5 * gap, end + 1.0])
    pos = jnp.concatenate([jnp.stack([x.reshape(-1), y.reshape(-1), jnp.full(m, -0.5) * depth], -1),
                           jnp.stack([0.5 * (plat_lo + plat_hi), jnp.zeros(2), jnp.full(2, -0.5) * depth], -1)])
    half = jnp.concatenate([jnp.stack([half_x, half_y, jnp.full(m, 0.5) * depth], -1),
                            jnp.stack([0.5 * (plat_hi - plat_lo), jnp.full(2, 0.5 * spec.width + 0.5),
                                       jnp.full(2, 0.5) * depth], -1)])
    return Terrain(box_pos=pos, box_half=half, box_valid=jnp.ones((m + 2,), bool), ground_z=-depth)


def _boxes(spec: TerrainSpec, key) -> Terrain:
    """Discrete random boxes (legged_gym's 'discrete obstacles'): box_count boxes anywhere in the corridor,
    footprints length_range x width_range, heights height_range; they may overlap."""
    ks = jax.random.split(key, 5)
    n = spec.box_count
    u = lambda k, r: jax.random.uniform(k, (n,), minval=r[0], maxval=r[1])
    x = spec.start_x + spec.length * jax.random.uniform(ks[0], (n,))
    y = spec.width * (jax.random.uniform(ks[1], (n,)) - 0.5)
    h = jnp.maximum(u(ks[2], spec.height_range), 1e-3)
    pos = jnp.stack([x, y, 0.5 * h], -1)
    half = jnp.stack([0.5 * u(ks[3], spec.length_range), 0.5 * u(ks[4], spec.width_range), 0.5 * h], -1)
    return Terrain(box_pos=pos, box_half=half, box_valid=jnp.ones((n,), bool), ground_z=jnp.zeros(()))


def _flat(spec: TerrainSpec, key) -> Terrain:
    del spec, key
    return Terrain(box_pos=jnp.array([[0.0, 0.0, -5.0]]), box_half=jnp.full((1, 3), 0.01),
                   box_valid=jnp.zeros((1,), bool), ground_z=jnp.zeros(()))


_GENERATORS = {"flat": _flat, "obstacles": _obstacle_field, "step": _step, "ditch": _ditch,
               "waves": _waves, "rough": _rough, "slope": _slope, "stairs": _stairs, "stones": _stones,
               "boxes": _boxes}


@functools.partial(jax.jit, static_argnums=0)
def _sample(spec: TerrainSpec, keys) -> Terrain:
    return jax.vmap(functools.partial(_GENERATORS[spec.kind], spec))(keys)


def sample_one(spec: TerrainSpec, key) -> Terrain:
    """One terrain of family `spec` (no batch axis), pure JAX: for use inside a traced function (an env's
    reset). Check the spec first (`spec.validate()`); `sample` does that for batches."""
    return _GENERATORS[spec.kind](spec, key)


def sample(spec: TerrainSpec, key, batch: int) -> Terrain:
    """Sample `batch` terrains of family `spec` from one PRNG key: a Terrain with leading axis B."""
    spec.validate()
    if not isinstance(batch, (int, np.integer)) or batch < 1:
        raise ValueError(f"batch={batch!r}: must be an integer >= 1")
    return _sample(spec, jax.random.split(key, int(batch)))


# The four obstacle categories of Luneckas 2020 Sect. 2.2 (presets in configs/terrains/)
LUNECKAS2020_CATEGORIES = ("low-small", "low-large", "high-small", "high-large")


def pad_terrain(t: Terrain, m: int) -> Terrain:
    """A batched terrain padded to `m` boxes with invalid entries, so terrains of several families share one
    compiled rollout."""
    cur = t.box_pos.shape[-2]
    if cur > m:
        raise ValueError(f"terrain has {cur} boxes, more than the pad size {m}")
    if cur == m:
        return t
    pad = [(0, 0)] * (t.box_pos.ndim - 2) + [(0, m - cur), (0, 0)]
    return Terrain(box_pos=jnp.pad(t.box_pos, pad, constant_values=-5.0),
                   box_half=jnp.pad(t.box_half, pad, constant_values=0.01),
                   box_valid=jnp.pad(t.box_valid, pad[:-1], constant_values=False), ground_z=t.ground_z)


# Views for planners and plots ------------------------------------------------------------------
def obstacle_circles(terrain: Terrain):
    """Obstacles as circles for planners (Zhao 2018 Eq. 1): centres (..., M, 2) m, radii (..., M) m
    (half the footprint diagonal), valid (..., M) bool."""
    centres = terrain.box_pos[..., :2]
    radii = jnp.linalg.norm(terrain.box_half[..., :2], axis=-1)
    return centres, radii, terrain.box_valid


def heightmap(terrain: Terrain, x_range, y_range, res: float = 0.005) -> np.ndarray:
    """Top height of a single (unbatched) terrain on a regular grid, (nx, ny) m, numpy."""
    if not (np.isfinite(res) and res > 0):
        raise ValueError(f"res={res!r}: must be a finite number of metres > 0")
    for name, (lo, hi) in (("x_range", x_range), ("y_range", y_range)):
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise ValueError(f"{name}=({lo!r}, {hi!r}): must be finite, low < high")
    xs = np.arange(x_range[0], x_range[1], res) + 0.5 * res
    ys = np.arange(y_range[0], y_range[1], res) + 0.5 * res
    pos, half = np.asarray(terrain.box_pos), np.asarray(terrain.box_half)
    valid = np.asarray(terrain.box_valid)
    h = np.full((xs.size, ys.size), float(terrain.ground_z))
    for p, hh, v in zip(pos, half, valid):
        if not v:
            continue
        ix = (xs >= p[0] - hh[0]) & (xs <= p[0] + hh[0])
        iy = (ys >= p[1] - hh[1]) & (ys <= p[1] + hh[1])
        h[np.ix_(ix, iy)] = np.maximum(h[np.ix_(ix, iy)], p[2] + hh[2])
    return h
