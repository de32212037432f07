"""hexjax's sphere-box and capsule-box contacts (`hexjax.sim.internals.collide`) against MuJoCo C's `mj_collision`,
pose by pose around a terrain-sized box: over faces, rims and corners, inside the box and just apart, with and
without a margin; and their derivatives against central differences. Also MJX's box-box contact under the same
context: its values unchanged, its gradient finite where the boxes are apart."""

import jax
import mujoco
import numpy as np
import pytest

from hexjax.sim.internals import collide

HALF = np.array([0.05, 0.05, 0.02])
RADIUS, HALF_LENGTH = {"sphere": 0.006, "capsule": 0.004}, 0.015
XML = """<mujoco><worldbody>
  <geom type="box" size="{h[0]} {h[1]} {h[2]}" pos="0.01 -0.02 0.03" euler="0 0 20" margin="{margin}"/>
  <body pos="0 0 0.5"><freejoint/>{probe}</body>
</worldbody></mujoco>"""
PROBE = {"sphere": '<geom type="sphere" size="0.006"/>', "capsule": '<geom type="capsule" size="0.004 0.015"/>'}


def _model(kind, margin=0.0):
    return mujoco.MjModel.from_xml_string(XML.format(h=HALF, margin=margin, probe=PROBE[kind]))


def _poses(rng, n, kind):
    """Probe poses in the box's frame, `n` per region: a point of the probe's axis (its centre for a sphere, any
    point of a capsule's segment) within -3 .. +3 mm of touching a face, an edge or a corner, or deep inside the
    box; random orientations. Returns (centres, quaternions, axes)."""
    reach, out = RADIUS[kind], []
    for _ in range(n):
        g = lambda: reach + rng.uniform(-0.003, 0.003)
        out.append([rng.uniform(-0.04, 0.04), rng.uniform(-0.04, 0.04), HALF[2] + g()])  # top face
        a, r = rng.uniform(0, np.pi / 2), g()
        out.append([HALF[0] + r * np.sin(a), rng.uniform(-0.04, 0.04), HALF[2] + r * np.cos(a)])  # top rim
        out.append([HALF[0] + g(), rng.uniform(-0.04, 0.04), rng.uniform(-0.015, 0.015)])  # side face
        u = np.abs(rng.normal(size=3))
        out.append(rng.choice([-1, 1], 3) * (HALF + u / np.linalg.norm(u) * g()))  # corner
        out.append(rng.uniform(-0.8, 0.8, 3) * HALF)  # inside
    quats = rng.normal(size=(len(out), 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    axes = np.array([mujoco_axis(q) for q in quats])
    along = rng.uniform(-1, 1, len(out)) * (HALF_LENGTH if kind == "capsule" else 0.0)
    return np.array(out) - along[:, None] * axes, quats, axes


def _c_contacts(m, d, p_local, quat):
    """MuJoCo C's contacts of the probe with the box: (dist, normal from probe to box, pos) each."""
    d.qpos[:3] = m.geom_pos[0] + _box_mat(m) @ p_local
    d.qpos[3:7] = quat
    mujoco.mj_kinematics(m, d)
    mujoco.mj_collision(m, d)
    return [(c.dist, c.frame[:3] * (1.0 if c.geom1 == 1 else -1.0), c.pos.copy()) for c in d.contact[:d.ncon]]


def _box_mat(m):
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, m.geom_quat[0])
    return mat.reshape(3, 3)


def _ours(kind, m, d):
    """hexjax's contacts for the probe's current pose: (dist (k,), normal (k, 3), pos (k, 3))."""
    bp, bm = d.geom_xpos[0], d.geom_xmat[0].reshape(3, 3)
    gp, gm = d.geom_xpos[1], d.geom_xmat[1].reshape(3, 3)
    if kind == "sphere":
        out = collide.sphere_box(gp, RADIUS[kind], bp, bm, HALF)
        return [np.asarray(x)[None] for x in out]
    return [np.asarray(x) for x in collide.capsule_box(gp, gm[:, 2], RADIUS[kind], HALF_LENGTH, bp, bm, HALF)]


@pytest.mark.parametrize("kind,margin", [("sphere", 0.0), ("capsule", 0.0), ("sphere", 0.002), ("capsule", 0.002)])
def test_contacts_match_mujoco_c(kind, margin):
    with jax.enable_x64(True):
        m = _model(kind, margin)
        d = mujoco.MjData(m)
        centres, quats, _ = _poses(np.random.default_rng(1), 60, kind)
        compared, worst = 0, np.zeros(3)
        for p, q in zip(centres, quats):
            theirs = _c_contacts(m, d, p, q)
            dist, pos, normal = _ours(kind, m, d)
            mine = [(dist[i], normal[i], pos[i]) for i in range(len(dist)) if dist[i] <= margin]
            assert len(mine) == len(theirs), (p, q, [c[0] for c in theirs], dist)
            for c_dist, c_normal, c_pos in theirs:
                o = min(mine, key=lambda c: np.abs(c[2] - c_pos).sum() + abs(c[0] - c_dist))
                worst = np.maximum(worst, [abs(o[0] - c_dist), np.abs(o[1] - c_normal).max(),
                                           np.abs(o[2] - c_pos).max()])
                compared += 1
    assert compared > (100 if kind == "sphere" else 200), compared
    assert worst[0] < 1e-6 and worst[1] < 1e-4 and worst[2] < 1e-6, worst


def test_capsule_box_second_contact_along_the_rim():
    """A pad (capsule) lying across a box's top rim, its inner end lowered onto the top face: MuJoCo C gives two
    contacts (the inner end and the rim), and so does hexjax; MJX's convex routine misses such contacts
    (`scripts/collide_compare.py`)."""
    with jax.enable_x64(True):
        m = _model("capsule")
        d = mujoco.MjData(m)
        pitch = np.deg2rad(80)  # the capsule's axis 10 deg above +x in the box's frame: its -x end lower
        local, world = np.array([np.cos(pitch / 2), 0, np.sin(pitch / 2), 0]), np.zeros(4)
        mujoco.mju_mulQuat(world, m.geom_quat[0], local)
        theirs = _c_contacts(m, d, np.array([HALF[0] + 0.002, 0.0, HALF[2] + 0.004]), world)
        dist, _, _ = _ours("capsule", m, d)
    assert len(theirs) == 2 and np.sum(dist <= 0) == 2
    np.testing.assert_allclose(np.sort(dist), np.sort([c[0] for c in theirs]), atol=1e-9)


@pytest.mark.parametrize("kind", ["sphere", "capsule"])
def test_contact_derivatives_match_central_differences(kind):
    """d(dist)/d(probe position) and d(normal)/d(probe position) of the first contact against central differences,
    over rims, faces and corners (poses within a few mm of a feature, where MuJoCo C's branch does not change over
    the finite difference's step)."""
    rng = np.random.default_rng(3)
    with jax.enable_x64(True):
        centres, _, axes = _poses(rng, 8, kind)

        def first(p, axis):
            if kind == "sphere":
                dist, _, n = collide.sphere_box(p, RADIUS[kind], np.zeros(3), np.eye(3), HALF)
                return jax.numpy.concatenate([dist[None], n])
            dist, _, n = collide.capsule_box(p, axis, RADIUS[kind], HALF_LENGTH, np.zeros(3), np.eye(3), HALF)
            return jax.numpy.concatenate([dist[:1], n[0]])

        jac = jax.jit(jax.jacfwd(first))
        f = jax.jit(first)
        checked, eps = 0, 1e-7
        for p, a in zip(centres, axes):
            fd = np.stack([(f(p + eps * e, a) - f(p - eps * e, a)) / (2 * eps) for e in np.eye(3)], -1)
            j = np.asarray(jac(p, a))
            assert np.all(np.isfinite(j))
            if np.abs(fd).max() > 1e4:  # a branch switch inside the step (a kink of MuJoCo C's choice)
                continue
            np.testing.assert_allclose(j, fd, atol=2e-5 * max(1.0, np.abs(fd).max()))
            checked += 1
    assert checked >= 30


def mujoco_axis(q):
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, q)
    return mat.reshape(3, 3)[:, 2]


TORSO_XML = """<mujoco><worldbody>
  <geom type="plane" size="5 5 .1"/>
  <geom type="box" size="0.002 0.5 0.02" pos="0.215 0 0.02"/>
  <body pos="0 0 0.1"><freejoint/><geom type="box" size="0.1 0.05 0.02"/></body>
</worldbody></mujoco>"""


def test_box_box_gradient_is_finite_with_the_boxes_apart():
    """The torso (a box) near an obstacle's face, tilted by 1e-7 .. 1e-2 rad, no contact active: MJX's own box-box
    contact gives a NaN gradient under jit at some of these poses (an edge parallel to a side plane up to
    rounding); under `c_box_contacts` its values are MJX's and every gradient is finite."""
    from mujoco import mjx
    m = mujoco.MjModel.from_xml_string(TORSO_XML)
    mx = mjx.put_model(m)
    d0 = mjx.make_data(mx)
    rng = np.random.default_rng(0)
    qs = []
    for _ in range(400):
        quat = np.zeros(4)
        mujoco.mju_euler2Quat(quat, rng.normal(size=3) * 10.0 ** rng.uniform(-7, -2, size=3), "xyz")
        qs.append(np.concatenate([[rng.uniform(-0.05, 0.12), rng.uniform(-0.02, 0.02), rng.uniform(0.06, 0.14)], quat]))
    qs = jax.numpy.asarray(np.array(qs), jax.numpy.float32)

    def contacts(q):
        d = mjx.collision(mx, mjx.kinematics(mx, d0.replace(qpos=q)))
        c = d._impl.contact
        return c.dist, c.pos, c.frame

    def inactive_sum(q):  # every contact of these poses is apart: the value is 0, so is the true gradient
        dist, pos, frame = contacts(q)
        on = dist < 0
        return jax.numpy.sum(jax.numpy.where(on, dist, 0.0)) + jax.numpy.sum(jax.numpy.where(on[:, None], pos, 0.0))

    plain = jax.jit(jax.vmap(contacts))(qs)
    with collide.c_box_contacts():
        ours = jax.jit(jax.vmap(contacts))(qs)
        grads = np.asarray(jax.jit(jax.vmap(jax.grad(inactive_sum)))(qs))
    assert plain[0].shape[1] == 4 + 4 and np.all(np.asarray(plain[0]) > 0)  # box-box and box-plane, 4 each, apart
    for a, b in zip(plain, ours):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert np.isfinite(grads).all(), f"{np.sum(~np.isfinite(grads).all(1))} of {len(grads)} poses"
    np.testing.assert_array_equal(grads, 0.0)
