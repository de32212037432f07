"""Support planning of Chen et al. 2019, Sect. 2.2: the centre of the largest circle inside the support
polygon, found by the paper's iteration (Steps 1-5, Eqs. 1-2) and, beside it, exactly; the torso target over
the footholds (Sect. 2.2.1, Eq. 3), clamped splines (Eqs. 4-5), and foothold candidates on a DEM.

Polygons are convex, counter-clockwise, as (..., K, 2) vertices with a (..., K) `valid` mask (the valid
vertices first), so triangles and quadrilaterals share one shape and `vmap`.

* `incenter_iterative`: Step 1 starts at the midpoint of two non-adjacent vertices (vertices 0 and 2); a
  triangle has no such pair (the midpoint of two of its vertices lies on a side, where the iteration
  cannot move: C = S), so a triangle starts at its centroid.
  Step 2 finds the two sides nearest to the point S (feet A, B, distances L_A <= L_B). Step 3 takes C = A
  when A, B, S are collinear, else C on AB by Eq. 1. Step 4 moves S' = S + a (S - C) / |S - C| (Eq. 2).
  Step 5 keeps S' if its nearest-side distance grew, else halves a. The paper gives no start value of a
  and no stopping rule: a starts at a quarter of the polygon's smallest bounding-box side, and the loop
  runs a fixed `iterations` times (a `lax.scan`, so a batch shares one program); by then a has shrunk
  below float32 resolution for any polygon that keeps halving.
* `incenter_exact`: the Chebyshev centre. The largest inscribed circle touches at least three sides (or two
  parallel ones): it is the best feasible solution of the 3 x 3 systems n_i . x + r = b_i over every
  triple of sides (a vertex of the LP max r s.t. n_i . x + r <= b_i). K <= 8 sides make at most 56 triples.
  For triangles this is the classical incenter (weights = side lengths), which the tests check.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np

from hexjax.world.dem import DEM, NEIGHBOURS_3X3, dem_lookup, snap


def _side_geometry(poly, valid):
    """Side i runs from vertex i to the next valid vertex. Returns outward unit normals (K, 2) and offsets
    (K,) (inside a CCW polygon n . x <= b) and which sides are valid (K,)."""
    k = poly.shape[-2]
    nxt = jnp.where(jnp.arange(k) + 1 < jnp.sum(valid), jnp.arange(k) + 1, 0)
    d = poly[nxt] - poly
    length = jnp.linalg.norm(d, axis=-1)
    normal = jnp.stack([d[:, 1], -d[:, 0]], -1) / jnp.maximum(length, 1e-12)[:, None]
    return normal, jnp.sum(normal * poly, -1), valid & (length > 1e-9)


def side_distances(point, poly, valid):
    """(K,) signed distance from point to each side's line (> 0 inside a convex CCW polygon, inf for invalid
    sides) and (K, 2) the feet of the perpendiculars. Inside a convex polygon the smallest is the distance
    to the boundary; outside it is negative, so a step that leaves the polygon never counts as a gain."""
    normal, off, ok = _side_geometry(poly, valid)
    d = off - normal @ point
    foot = point + d[:, None] * normal
    return jnp.where(ok, d, jnp.inf), foot


def incenter_iterative(poly, valid, iterations: int = 60, collinear_tol: float = 1e-9):
    """Chen 2019 Steps 1-5 (module notes): (centre (2,), radius ()) for one polygon (K, 2), valid (K,)."""
    poly = jnp.asarray(poly, jnp.float32)
    n = jnp.sum(valid)
    centroid = jnp.sum(jnp.where(valid[:, None], poly, 0.0), 0) / jnp.maximum(n, 1)
    # Step 1: midpoint of two non-adjacent vertices; a triangle has none (that midpoint lies on a side),
    # so a triangle starts at its centroid
    s0 = jnp.where(n > 3, 0.5 * (poly[0] + poly[2]), centroid)
    masked = jnp.where(valid[:, None], poly, poly[0])
    span = masked.max(0) - masked.min(0)
    a0 = 0.25 * jnp.min(span)

    def nearest(s):
        d, foot = side_distances(s, poly, valid)
        i = jnp.argsort(d)[:2]
        return d[i[0]], foot[i[0]], d[i[1]], foot[i[1]]

    def body(carry, _):
        s, step = carry
        la, pa, lb, pb = nearest(s)  # Step 2
        la, lb = jnp.abs(la), jnp.abs(lb)
        cross = (pa[0] - s[0]) * (pb[1] - s[1]) - (pa[1] - s[1]) * (pb[0] - s[0])
        collinear = jnp.abs(cross) <= collinear_tol * jnp.maximum(1.0, la * lb)
        c = jnp.where(collinear, pa, pa + la / jnp.maximum(la + lb, 1e-12) * (pb - pa))  # Step 3, Eq. 1
        away = s - c
        norm = jnp.linalg.norm(away)
        s_new = s + step * away / jnp.maximum(norm, 1e-12)  # Step 4, Eq. 2
        l_new = jnp.min(side_distances(s_new, poly, valid)[0])
        better = (l_new > la) & (norm > 0)
        # Step 5: keep S' when its distance to the nearest side grew, else halve the step and retry from S
        return (jnp.where(better, s_new, s), jnp.where(better, step, 0.5 * step)), None

    (s, _), _ = jax.lax.scan(body, (s0, a0), None, length=iterations)
    return s, jnp.min(side_distances(s, poly, valid)[0])


_TRIPLES = {}


def _triples(k: int) -> np.ndarray:
    if k not in _TRIPLES:
        _TRIPLES[k] = np.array(list(itertools.combinations(range(k), 3)), np.int32)
    return _TRIPLES[k]


def _chebyshev(normal, off, ok, scale):
    """Largest circle inside the half-planes n_i . x <= b_i (rows where ok): (centre (2,), radius ()), by the
    best feasible solution of n_i . x + r = b_i over every triple (module notes); radius 0 if none is."""
    tri = _triples(normal.shape[-2])
    m = jnp.concatenate([normal[tri], jnp.ones(tri.shape + (1,))], -1)  # (T, 3, 3): n . x + r = b
    rhs = off[tri]
    det = jnp.linalg.det(m)
    good = ok[tri].all(-1) & (jnp.abs(det) > 1e-9)
    sol = jnp.linalg.solve(jnp.where(good[:, None, None], m, jnp.eye(3)), jnp.where(good[:, None], rhs, 0.0)[..., None])[..., 0]
    x, r = sol[:, :2], sol[:, 2]
    slack = off[None, :] - x @ normal.T - r[:, None]  # >= 0 where every side is respected
    feasible = good & jnp.all(jnp.where(ok[None, :], slack >= -1e-5 * scale, True), -1) & (r > 0)
    best = jnp.argmax(jnp.where(feasible, r, -jnp.inf))
    return x[best], jnp.where(feasible[best], r[best], 0.0)


def incenter_exact(poly, valid):
    """Chebyshev centre of a convex CCW polygon (K, 2), valid (K,): (centre (2,), radius ()) (module notes)."""
    poly = jnp.asarray(poly, jnp.float32)
    normal, off, ok = _side_geometry(poly, valid)
    return _chebyshev(normal, off, ok, jnp.max(jnp.abs(jnp.where(valid[:, None], poly, 0.0))) + 1.0)


def overlap_center(poly_a, valid_a, poly_b, valid_b):
    """Centre and radius of the largest circle inside both convex CCW polygons: Chen 2019 Sect. 2.2's O_2, the
    incenter of the overlap of the current and the next support triangles, where the CoG should be at the
    support-swing transition (Fig. 1). Radius 0 when they do not overlap."""
    pa, pb = jnp.asarray(poly_a, jnp.float32), jnp.asarray(poly_b, jnp.float32)
    na, oa, ka = _side_geometry(pa, valid_a)
    nb, ob, kb = _side_geometry(pb, valid_b)
    scale = jnp.maximum(jnp.max(jnp.abs(jnp.where(valid_a[:, None], pa, 0.0))),
                        jnp.max(jnp.abs(jnp.where(valid_b[:, None], pb, 0.0)))) + 1.0
    return _chebyshev(jnp.concatenate([na, nb]), jnp.concatenate([oa, ob]), jnp.concatenate([ka, kb]), scale)


def check_polygons(poly, valid) -> None:
    """Host-side checks before a batch is traced: at least 3 valid vertices, valid ones first, finite, convex
    and counter-clockwise with positive area; names the first bad polygon's index."""
    p, v = np.asarray(poly, float), np.asarray(valid, bool)
    if p.shape[-1] != 2 or v.shape != p.shape[:-1] or p.shape[-2] < 3:
        raise ValueError(f"polygons {p.shape}, valid {v.shape}: need (..., K >= 3, 2) vertices and (..., K) valid")
    p2, v2 = p.reshape(-1, p.shape[-2], 2), v.reshape(-1, v.shape[-1])
    n = v2.sum(-1)
    for i in range(len(p2)):
        k = int(n[i])
        if k < 3 or not v2[i, :k].all():
            raise ValueError(f"polygon {i}: needs >= 3 valid vertices, listed first (valid={v2[i].tolist()})")
        q = p2[i, :k]
        if not np.all(np.isfinite(q)):
            raise ValueError(f"polygon {i}: vertices must be finite")
        e = np.roll(q, -1, 0) - q
        cross = e[:, 0] * np.roll(e, -1, 0)[:, 1] - e[:, 1] * np.roll(e, -1, 0)[:, 0]
        area = 0.5 * np.sum(q[:, 0] * np.roll(q, -1, 0)[:, 1] - np.roll(q, -1, 0)[:, 0] * q[:, 1])
        if area <= 1e-12 * max(1.0, np.abs(q).max() ** 2):
            raise ValueError(f"polygon {i}: collinear or clockwise footholds (signed area {area:.3g}); the support "
                             f"polygon has no interior")
        if np.any(cross < -1e-9 * max(1.0, np.abs(q).max() ** 2)):
            raise ValueError(f"polygon {i}: not convex")


def random_polygons(key, n: int, k: int, k_max: int | None = None, min_gap: float = 0.25, stretch: float = 3.0):
    """n random convex CCW polygons with k vertices, padded to k_max by repeating vertex 0 (invalid): affine
    images of polygons inscribed in the unit circle. Consecutive vertices are at least `min_gap` x 2 pi / k
    apart in angle (no vanishing sides), and the affine map rotates, stretches by up to `stretch`:1 and
    rotates again (any convex polygon's shape class, without slivers). Returns (poly (n, k_max, 2),
    valid (n, k_max))."""
    k_max = k_max or k
    ks = jax.random.split(key, 5)
    gaps = jax.random.dirichlet(ks[0], jnp.ones(k), (n,)) * (1.0 - min_gap) + min_gap / k
    ang = jax.random.uniform(ks[1], (n, 1), maxval=2 * jnp.pi) + 2 * jnp.pi * jnp.cumsum(gaps, -1)
    pts = jnp.stack([jnp.cos(ang), jnp.sin(ang)], -1)

    def rot(t):
        c, s_ = jnp.cos(t), jnp.sin(t)
        return jnp.stack([jnp.stack([c, -s_], -1), jnp.stack([s_, c], -1)], -2)

    t1, t2 = (jax.random.uniform(kk, (n,), maxval=2 * jnp.pi) for kk in ks[2:4])
    sx = jax.random.uniform(ks[4], (n,), minval=1.0, maxval=stretch)
    m = rot(t2) @ (jnp.eye(2) * jnp.stack([sx, jnp.ones(n)], -1)[:, None, :]) @ rot(t1)
    poly = jnp.einsum("nij,nkj->nki", m, pts)
    pad = jnp.broadcast_to(poly[:, :1], (n, k_max - k, 2))
    valid = jnp.broadcast_to(jnp.arange(k_max) < k, (n, k_max))
    return jnp.concatenate([poly, pad], 1), valid


# Torso target and joint trajectories (Chen 2019 Sects. 2.2.1-2.2.2) -----------------------------------------
def foothold_plane(footholds, valid):
    """Least-squares plane z = g_x x + g_y y + c through the valid footholds (K, 3): (g_x, g_y, c)."""
    w = valid.astype(footholds.dtype)
    a = jnp.stack([footholds[:, 0], footholds[:, 1], jnp.ones_like(footholds[:, 0])], -1) * w[:, None]
    # a small ridge keeps 3 collinear footholds solvable (their check is `check_polygons`)
    return jnp.linalg.solve(a.T @ a + 1e-9 * jnp.eye(3), a.T @ (footholds[:, 2] * w))


def plane_pitch_roll(gradient, yaw):
    """Pitch and roll (rad) of a plane with gradient (g_x, g_y) for a torso heading `yaw`: pitch > 0 when the
    plane rises ahead (nose up), roll > 0 when it rises to the left."""
    fwd = jnp.array([jnp.cos(yaw), jnp.sin(yaw)])
    left = jnp.array([-jnp.sin(yaw), jnp.cos(yaw)])
    return jnp.arctan(gradient @ fwd), jnp.arctan(gradient @ left)


def torso_pitch_roll(quat, yaw=None):
    """Pitch and roll (rad) of a torso quaternion (w, x, y, z) in the convention of `plane_pitch_roll`: the
    rise of its forward (x) and left (y) axes."""
    w, x, y, z = quat[0], quat[1], quat[2], quat[3]
    fwd_z = 2.0 * (x * z - w * y)  # z component of the rotated x axis
    left_z = 2.0 * (y * z + w * x)  # z component of the rotated y axis
    return jnp.arcsin(jnp.clip(fwd_z, -1, 1)), jnp.arcsin(jnp.clip(left_z, -1, 1))


def torso_target(footholds, valid, yaw, height, measured_pitch, measured_roll, iterative: bool = True):
    """The torso's target state for the next support phase (Chen 2019 Sect. 2.2): horizontal position at the
    incenter of the support polygon (iterative Steps 1-5, or exact), height `height` above the fitted
    foothold plane there (Sect. 2.2.1), and pitch / roll by Eq. 3, the mean of the foothold plane's and the
    measured ones. footholds (K, 3) m, CCW in xy; valid (K,). Returns dict of xyz (3,), pitch, roll, yaw,
    and the stability margin (the inscribed radius, m)."""
    xy, valid_ = footholds[:, :2], valid
    c, r = (incenter_iterative if iterative else incenter_exact)(xy, valid_)
    g = foothold_plane(footholds, valid)
    z = g[0] * c[0] + g[1] * c[1] + g[2] + height
    p_sp, r_sp = plane_pitch_roll(g[:2], yaw)
    return {"xyz": jnp.concatenate([c, z[None]]), "pitch": 0.5 * (p_sp + measured_pitch),
            "roll": 0.5 * (r_sp + measured_roll), "yaw": jnp.asarray(yaw), "margin": r}


def clamped_spline(t, y):
    """Cubic spline through knots (t (N,), y (N, ...)) with zero velocity at both ends (Chen 2019 Eqs. 4-5):
    C2 at the interior knots, S'(t_1) = S'(t_N) = 0. Returns a function of query times (M,) -> (M, ...).
    Solves the N x N tridiagonal system for the knot slopes densely (N is a handful of path points)."""
    t = jnp.asarray(t)
    y = jnp.asarray(y)
    n = t.shape[0]
    h = jnp.diff(t)
    flat = y.reshape(n, -1)
    dy = jnp.diff(flat, axis=0) / h[:, None]
    # unknowns: slopes m_i. Interior rows: h_i m_{i-1} + 2 (h_{i-1} + h_i) m_i + h_{i-1} m_{i+1}
    #   = 3 (h_i dy_{i-1} + h_{i-1} dy_i)  (second-derivative continuity); end rows: m_1 = m_N = 0 (Eq. 5)
    i = jnp.arange(1, n - 1)
    a = jnp.zeros((n, n)).at[0, 0].set(1.0).at[n - 1, n - 1].set(1.0)
    a = a.at[i, i - 1].set(h[i]).at[i, i].set(2.0 * (h[i - 1] + h[i])).at[i, i + 1].set(h[i - 1])
    rhs = jnp.zeros_like(flat).at[i].set(3.0 * (h[i][:, None] * dy[i - 1] + h[i - 1][:, None] * dy[i]))
    m = jnp.linalg.solve(a, rhs)

    def s(tq):
        tq = jnp.asarray(tq)
        k = jnp.clip(jnp.searchsorted(t, tq, side="right") - 1, 0, n - 2)
        hk = h[k][:, None]
        u = ((tq - t[k]) / h[k])[:, None]
        h00, h10 = 2 * u ** 3 - 3 * u ** 2 + 1, u ** 3 - 2 * u ** 2 + u
        h01, h11 = -2 * u ** 3 + 3 * u ** 2, u ** 3 - u ** 2
        out = h00 * flat[k] + h10 * hk * m[k] + h01 * flat[k + 1] + h11 * hk * m[k + 1]
        return out.reshape(tq.shape + y.shape[1:])

    return s


# Footholds on a DEM (Chen 2019 Sect. 2.2, the loop of `hexjax.control.support_gait`) -----------------------
def foothold_candidates(dem: DEM, nominal, search: int, w_dist: float, w_height: float):
    """The DEM cell centres within `search` cells of `nominal` (2,) and their costs: spread of the 3 x 3
    neighbourhood + w_dist |offset| + w_height height. Returns (xy (C, 2), ground height (C,), cost (C,))."""
    r = np.arange(-search, search + 1, dtype=np.float32)
    offs = np.stack(np.meshgrid(r, r, indexing="ij"), -1).reshape(-1, 2)
    cand = snap(dem, nominal) + jnp.asarray(offs) * dem.cell  # (C, 2)
    nb = dem_lookup(dem, cand[:, None, :] + jnp.asarray(NEIGHBOURS_3X3) * dem.cell)  # (C, 9)
    h = nb[:, 4]
    cost = (jnp.max(nb, -1) - jnp.min(nb, -1)) + w_dist * jnp.linalg.norm(cand - nominal, axis=-1) + w_height * h
    return cand, h, cost


def max_along(dem: DEM, a, b, n: int = 10):
    """Highest DEM cell within one cell of the chord a -> b (2,)."""
    pts = a + (b - a) * jnp.linspace(0.0, 1.0, n)[:, None]
    return jnp.max(dem_lookup(dem, pts[:, None, :] + jnp.asarray(NEIGHBOURS_3X3) * dem.cell))
