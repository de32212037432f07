"""MuJoCo C's sphere-box and capsule-box contacts in JAX, for MJX's collision driver.

The pinned mujoco-mjx sends a sphere or a capsule against a box through its convex routines (`sphere_convex`,
`capsule_convex`): the box is a mesh, a separating-axis test on its face normals decides whether there is a contact
at all, and near a rim the contact takes one face's normal. MuJoCo C (`mjraw_SphereBox`, `mjraw_CapsuleBox` in
`engine_collision_box.c`) and MuJoCo Warp instead use the closest points of the box and the sphere (or the
capsule's segment), so a foot or a pad meeting an obstacle's edge is pushed along the rounded edge's normal, and a
capsule lying across a rim keeps its contact where MJX loses it (docs/physics.md, `scripts/collide_compare.py`).

The functions here follow MuJoCo C's algorithm step for step, each branch computed and the taken one selected, so
they vectorise and differentiate: outside the box the normal is the unit vector from the sphere's centre (or the
capsule's closest axis point) to the box's closest point, which turns smoothly from a face's normal through the
rim. Divisions are guarded so that an untaken branch never sends NaN into a gradient.

`c_box_contacts()` swaps them into MJX's table of collision functions while a rollout is traced; the number of
contacts per pair (1 for sphere-box, 2 for capsule-box) is MJX's own, so contact slots keep their layout.

MJX's box-box contact (the torso against an obstacle) stays MJX's, with one guard: where it clips a box edge
against a face's side plane it divides by the edge's component along the plane's normal, `jnp.clip`s the
result to the edge and so hides a huge quotient in the value; but under `jit` an edge that is parallel to the
plane up to rounding (a torso tilted by 1e-6 rad) gives a denominator of 1e-20 instead of 0, the quotient's
derivative overflows, and the clip's zero derivative times it is NaN: every gradient of a walk whose torso had
an obstacle in its slot came back NaN even with the boxes apart. `_segment_plane_point` takes the same value and
divides only where the point lies on the edge (where the derivative is the one MJX would give).
"""

from __future__ import annotations

import contextlib

import jax
import jax.numpy as jnp
import numpy as np

from hexjax.sim.internals.rules import mjx, swapped

MINVAL = 1e-15  # MuJoCo's mjMINVAL
FAR = 1e6  # m: the distance of a contact slot C would not fill (above any margin, so the solver skips it)
_BIG = 1e6  # stands in for a division by zero in a min()


def _safe_norm(v):
    """(|v|, v / |v|), with a zero vector giving (0, 0) and finite derivatives."""
    sq = jnp.sum(v * v)
    ok = sq > 0
    n = jnp.sqrt(jnp.where(ok, sq, 1.0))
    return jnp.where(ok, n, 0.0), jnp.where(ok, v / n, 0.0)


def _over(num, den):
    """num / |den|, or _BIG where den is zero (a limit that does not bind)."""
    a = jnp.abs(den)
    ok = a > 0
    return jnp.where(ok, num / jnp.where(ok, a, 1.0), _BIG)


def sphere_box(center, radius, box_pos, box_mat, half):
    """MuJoCo C's sphere-box contact (`mjraw_SphereBox`) without its margin test: (dist, pos, normal) in the world,
    the normal from the sphere to the box. Outside the box: the box's closest point to the centre; centre inside:
    the nearest face (first of -x, +x, -y, +y, -z, +z on ties)."""
    c = box_mat.T @ (center - box_pos)
    clamped = jnp.clip(c, -half, half)
    gap, n_out = _safe_norm(clamped - c)
    pos_out = 0.5 * (clamped + c + n_out * radius)

    face = jnp.stack([half[0] + c[0], half[0] - c[0], half[1] + c[1], half[1] - c[1], half[2] + c[2], half[2] - c[2]])
    k = jnp.argmin(jnp.abs(face))
    closest = jnp.abs(face)[k]
    nearest = jnp.zeros(3, c.dtype).at[k // 2].set(jnp.where(k % 2 == 1, -1.0, 1.0))
    pos_in = c + nearest * (radius - closest) / 2

    inside = gap <= MINVAL
    normal = jnp.where(inside, nearest, n_out)
    pos = jnp.where(inside, pos_in, pos_out)
    dist = jnp.where(inside, -closest, gap) - radius
    return dist, box_mat @ pos + box_pos, box_mat @ normal


# the box's 12 edges in MuJoCo C's order: axis j outer, corner i (bit j clear) inner
_EDGES = np.array([(i, j) for j in range(3) for i in range(8) if not i & (1 << j)])
_SIGNS = np.array([[1.0 if i & (1 << b) else -1.0 for b in range(3)] for i in range(8)])


def _closest_edge(pos, ha, half, hl):
    """Each edge against the capsule's segment (MuJoCo C's clamped line-line solve): squared distance, the segment
    and edge parameters x2, x1 in [-1, 1], the clamp code s1 * 3 + s2, and whether the solve was defined."""
    i, j = _EDGES[:, 0], _EDGES[:, 1]
    onehot = np.eye(3)[j]
    start = _SIGNS[i] * half * (1 - onehot)  # a corner with its j-th coordinate zeroed: the edge's middle
    hj, haj = half[j], ha[j]
    dif = start - pos
    u = -hj * jnp.sum(dif * onehot, -1)
    v = dif @ ha
    ma, mb, mc = hj * hj, -hj * haj, hl * hl
    det = ma * mc - mb * mb
    ok = jnp.abs(det) >= MINVAL
    idet = 1.0 / jnp.where(ok, det, 1.0)
    x1 = (mc * u - mb * v) * idet
    x2 = (ma * v - mb * u) * idet
    s1 = jnp.ones_like(x1, dtype=jnp.int32)
    s2 = jnp.ones_like(x1, dtype=jnp.int32)
    # the edge parameter clamped first, the segment's refitted
    hi, lo = x1 > 1, x1 < -1
    x2 = jnp.where(hi, (v - mb) / mc, jnp.where(lo, (v + mb) / mc, x2))
    s1 = jnp.where(hi, 2, jnp.where(lo, 0, s1))
    x1 = jnp.clip(x1, -1, 1)
    # then the segment's, the edge's refitted and clamped again
    hi2, lo2 = x2 > 1, x2 < -1
    x1r = jnp.where(hi2, (u - mb) / ma, (u + mb) / ma)
    s1r = jnp.where(x1r > 1, 2, jnp.where(x1r < -1, 0, 1))
    refit = hi2 | lo2
    x1 = jnp.where(refit, jnp.clip(x1r, -1, 1), x1)
    s1 = jnp.where(refit, s1r, s1)
    s2 = jnp.where(hi2, 2, jnp.where(lo2, 0, s2))
    x2 = jnp.clip(x2, -1, 1)
    d = dif - ha * x2[:, None] + onehot * (hj * x1)[:, None]
    return jnp.sum(d * d, -1), x2, x1, s1 * 3 + s2, ok


def _second_point(pos, axis, ha, half, best, boxpos, cltype, clface, clcorner, cledge):
    """Where along the segment MuJoCo C puts a capsule's second contact (its `secondpos`, in half lengths from the
    first), or -4 for none: along the box's edge or face the capsule lies over, clamped where it leaves the box."""
    axisdir = (ha[0] > 0) * 1 + (ha[1] > 0) * 2 + (ha[2] > 0) * 4
    absha = jnp.abs(ha)
    pick = jnp.take

    # the closest box point at a corner: the capsule along an edge or over a face from it
    c1 = jnp.bitwise_xor(axisdir, clcorner)
    mul_c = jnp.where((c1 == 1) | (c1 == 2) | (c1 == 4), 1.0, -1.0)
    c1n = jnp.where(mul_c > 0, c1, 7 - c1)
    ax = jnp.where(c1n == 1, 0, jnp.where(c1n == 2, 1, 2))
    ax1, ax2 = (ax + 1) % 3, (ax + 2) % 3
    along_edge = pick(axis, ax) ** 2 > 0.5
    sp_edge = jnp.minimum(1 - mul_c * best, 2 * _over(pick(half, ax), pick(ha, ax)))
    sp_face = -jnp.minimum(1 + mul_c * best, jnp.minimum(2 * _over(pick(half, ax1), pick(ha, ax1)),
                                                         2 * _over(pick(half, ax2), pick(ha, ax2))))
    corner = jnp.where(along_edge, sp_edge, sp_face) * mul_c
    corner = jnp.where((c1 == 0) | (c1 == 7), -4.0, corner)

    # the closest box point inside an edge: the capsule across it (an X, not a T)
    e = jnp.bitwise_and(jnp.bitwise_xor(axisdir, clcorner), 7 - jnp.left_shift(1, cledge))
    ax = cledge
    a1, a2 = (ax + 1) % 3, (ax + 2) % 3
    a1 = jnp.where(jnp.abs(pick(axis, a1)) > jnp.abs(pick(axis, a2)), a2, a1)
    a2 = 3 - ax - a1
    up = jnp.bitwise_and(e, jnp.left_shift(1, a2)) != 0
    mul_e = jnp.where(up, 1.0, -1.0)
    sp = jnp.minimum(jnp.where(up, 1 - best, 1 + best), 2 * _over(pick(half, a2), pick(ha, a2)))
    same = (jnp.bitwise_and(axisdir, jnp.left_shift(1, ax)) != 0) == up
    e2 = jnp.where(same, 1 - boxpos, 1 + boxpos)
    sp = jnp.minimum(sp, pick(half, ax) * _over(e2, pick(ha, ax)))  # e2 in [0, 2]
    edge = jnp.where((e == 1) | (e == 2) | (e == 4), sp * mul_e, -4.0)

    # an end of the capsule nearest a face: the other end clamped where the segment leaves the box's sides
    mul_f = jnp.where(cltype == -3, 1.0, -1.0)
    tip = pos - ha * mul_f
    ok = absha > 0
    hs = jnp.where(ok, ha, 1.0)
    lims = jnp.stack([(half - tip) / hs * mul_f, (-half - tip) / hs * mul_f])
    usable = ok & (jnp.arange(3) != clface) & (lims > 0) & (lims < 2)
    face = jnp.min(jnp.where(usable, lims, 2.0)) * mul_f
    face = jnp.where(clface == -1, -4.0, face)

    return jnp.where(cltype < 0, face, jnp.where(cltype // 3 == 1, edge, corner))


def capsule_box(cap_pos, cap_axis, radius, hl, box_pos, box_mat, half):
    """MuJoCo C's capsule-box contacts (`mjraw_CapsuleBox`): the segment's point closest to the box (an end over a
    face, or the closest points to one of the 12 edges), and where the capsule lies along the box a second point,
    each then a sphere-box contact. Returns (dist (2,), pos (2, 3), normal (2, 3)); a second contact C would not
    make has dist `FAR`."""
    pos = box_mat.T @ (cap_pos - box_pos)
    axis = box_mat.T @ cap_axis
    ha = axis * hl

    # an end of the segment over a face (at most one coordinate outside the box)
    tips = pos + jnp.array([-1.0, 1.0])[:, None] * ha
    lo, hi = tips < -half, tips > half
    nout = jnp.sum(lo | hi, -1)
    idx = jnp.arange(3)
    outax = jnp.max(jnp.where(lo | hi, idx, -1), -1)
    fd = jnp.sum((jnp.clip(tips, -half, half) - tips) ** 2, -1)
    fd = jnp.where(nout > 1, jnp.inf, fd)
    first = fd[1] < fd[0]  # the +1 end replaces the -1 end only when strictly closer
    bestdist = jnp.where(first, fd[1], fd[0])
    best = jnp.where(first, 1.0, -1.0)
    cltype = jnp.where(jnp.isfinite(bestdist), jnp.where(first, -1, -3), -4)
    clface = jnp.where(first, outax[1], outax[0])
    bestdist = jnp.where(jnp.isfinite(bestdist), bestdist, _BIG)

    # the 12 edges, in C's order, each replacing the best when closer by more than MINVAL
    dsq, x2, x1, code, ok = _closest_edge(pos, ha, half, hl)
    boxpos, clcorner, cledge = jnp.zeros_like(best), jnp.int32(0), jnp.int32(0)
    for k, (i, j) in enumerate(_EDGES):
        take = ok[k] & (dsq[k] < bestdist - MINVAL)
        bestdist = jnp.where(take, dsq[k], bestdist)
        best = jnp.where(take, x2[k], best)
        boxpos = jnp.where(take, x1[k], boxpos)
        clcorner = jnp.where(take, int(i) + (1 << int(j)) * (code[k] // 6), clcorner)
        cledge = jnp.where(take, int(j), cledge)
        cltype = jnp.where(take, code[k], cltype)

    second = _second_point(pos, axis, ha, half, best, boxpos, cltype, clface, clcorner, cledge)
    along = jnp.stack([best, second + best])
    centres = box_pos + (pos + along[:, None] * ha) @ box_mat.T
    dist, cpos, normal = jax.vmap(sphere_box, in_axes=(0, None, None, None, None))(
        centres, radius, box_pos, box_mat, half)
    dist = dist.at[1].set(jnp.where(second > -3, dist[1], FAR))
    return dist, cpos, normal


def _collider(fn, ncon: int):
    """`fn(geom info of the round geom, of the box)` as one of MJX's collision functions (`collision_driver`'s
    `func(m, d, key, geom)`: each pair's dist, pos and frame, `ncon` a pair)."""
    def collide(m, d, key, geom):
        g1, g2 = geom.T
        dist, pos, n = jax.vmap(fn)(d.geom_xpos[g1], d.geom_xmat[g1], m.geom_size[g1],
                                    d.geom_xpos[g2], d.geom_xmat[g2], m.geom_size[g2])
        frame = jax.vmap(mjx._src.math.make_frame)(n.reshape(-1, 3))
        return dist.reshape(-1), pos.reshape(-1, 3), frame
    collide.ncon = ncon
    return collide


def _sphere_box_pair(p1, m1, s1, p2, m2, s2):
    dist, pos, n = sphere_box(p1, s1[0], p2, m2, s2)
    return dist[None], pos[None], n[None]


def _capsule_box_pair(p1, m1, s1, p2, m2, s2):
    return capsule_box(p1, m1[:, 2], s1[0], s1[1], p2, m2, s2)


def _segment_plane_point(a, b, p0, plane_normal):
    """MJX's `_closest_segment_point_plane` (where segment a-b meets the plane through p0, clipped to the segment),
    the same value, differentiated without NaN: the quotient is taken only where it lies in [0, 1]; elsewhere the
    point is an end of the segment and does not move with the plane."""
    num = jnp.sum(p0 * plane_normal) - jnp.sum(plane_normal * a)  # MJX's order of operations: its value
    denom = jnp.sum(plane_normal * (b - a))
    t_mjx = jnp.clip(num / (denom + 1e-6 * (denom == 0.0)), 0, 1)  # MJX's value, kept where the end is taken
    on = (jnp.abs(denom) > 1e-30) & (num * denom >= 0) & (jnp.abs(num) <= jnp.abs(denom))
    t = jnp.where(on, num / jnp.where(on, denom, 1.0), jax.lax.stop_gradient(t_mjx))
    return a + t * (b - a)


@contextlib.contextmanager
def c_box_contacts():
    """While open, MJX's collision driver computes sphere-box and capsule-box contacts as MuJoCo C does (this
    module's functions in place of `sphere_convex` and `capsule_convex`), and its box-box contact clips edges with
    `_segment_plane_point`. Read when a rollout is traced."""
    from mujoco.mjx._src import collision_convex as cc
    from mujoco.mjx._src import collision_driver as cd
    box = mjx._src.types.GeomType.BOX
    table = dict(cd._COLLISION_FUNC)
    for kind, fn in ((mjx._src.types.GeomType.SPHERE, _collider(_sphere_box_pair, 1)),
                     (mjx._src.types.GeomType.CAPSULE, _collider(_capsule_box_pair, 2))):
        assert table[(kind, box)].ncon == fn.ncon, "MJX changed its contacts per pair; the slot layout would move"
        table[(kind, box)] = fn
    with swapped(cd, "_COLLISION_FUNC", table), swapped(cc, "_closest_segment_point_plane", _segment_plane_point):
        yield
