"""The MuJoCo C engine's own machinery: terrain boxes as world-body geoms whose bounding-volume tree is refitted
per env (`hexjax.sim.engines.c_models`), and the two lanes that overlap one lane's controller with the other's
physics (`hexjax.sim.engines.c`)."""

import re

import jax
import mujoco
import numpy as np
import pytest

from hexjax.control.registry import make_controller
from hexjax.sim.config import PhysicsConfig, RolloutConfig, SensorConfig
from hexjax.sim.engines.c import rollout_c
from hexjax.sim.engines.c_models import _models, _refit, _slot_layout, _template
from hexjax.sim.mjcf import build_mjcf, compile_mjcf
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import sample

ROBOT = get_robot("luneckas2020")
PHYS = PhysicsConfig(slots_per_leg=0, torso_slots=0)


@pytest.mark.parametrize("k", [1, 2, 5])
def test_the_refit_of_the_placeholder_grid_is_the_compilers_tree(k):
    """Refitted from the template's own placeholder boxes, every node of the world body's tree is the box MuJoCo's
    compiler made for it, to the bit: the refit reads the tree's leaves and levels as the compiler laid them."""
    tp = _template(ROBOT, PHYS, k)
    m = tp.model
    aabb = _refit(tp, m.geom_pos[tp.box_geoms][None], m.geom_size[tp.box_geoms][None])[0]
    assert aabb.shape == (2 * k * k - 1, 6)
    np.testing.assert_array_equal(aabb, m.bvh_aabb[tp.bvh0:tp.bvh0 + len(aabb)])


def test_slot_layout_keeps_every_box_once_and_neighbours_together():
    """Each env's valid boxes land in distinct slots, once each, and each grid column holds boxes sorted by y whose
    x ranges follow the columns' order; an empty slot is a point that never collides."""
    rng = np.random.default_rng(0)
    n, m, k = 3, 40, 7
    pos = rng.uniform(-1, 1, (n, m, 3))
    half = rng.uniform(0.01, 0.05, (n, m, 3))
    valid = np.zeros((n, m), bool)
    valid[0] = True
    valid[1, :7] = True  # env 2: none
    s_pos, s_half, s_valid = _slot_layout(pos, half, valid, k)
    for e in range(n):
        got = sorted(map(tuple, s_pos[e][s_valid[e]]))
        assert got == sorted(map(tuple, pos[e][valid[e]]))
        grid, ok = s_pos[e].reshape(k, k, 3), s_valid[e].reshape(k, k)
        cols = [grid[c][ok[c]] for c in range(k) if ok[c].any()]
        assert all(np.all(np.diff(col[:, 1]) >= 0) for col in cols)
        assert all(a[:, 0].max() <= b[:, 0].min() for a, b in zip(cols, cols[1:]))
    assert np.all(s_half[~s_valid] < 1e-5) and s_valid.sum() == m + 7


@pytest.mark.cost(20)
@pytest.mark.parametrize("terrain,difficulty", [("waves", 1.0), ("stones", 1.0), ("high-large", None)])
def test_world_geom_boxes_meet_the_robot_as_a_freshly_compiled_model(terrain, difficulty):
    """With the robot lowered onto its terrain at random poses, an env's refitted model finds the same contacts (geoms,
    depths, points) and accelerations as a model compiled from scratch with those boxes in place, whose tree
    MuJoCo built itself: the refit misses no box and invents none."""
    spec = get_terrain(terrain, length=0.8)
    spec = spec if difficulty is None else spec.at_difficulty(difficulty)
    t = sample(spec, jax.random.PRNGKey(3), 2)
    bp, bh, gz = (np.asarray(x, np.float64) for x in (t.box_pos, t.box_half, t.ground_z))
    bv = np.asarray(t.box_valid, bool)
    tp = _template(ROBOT, PHYS, int(np.ceil(np.sqrt(bv.sum(1).max()))))
    models = _models(tp, bp, bh, bv, gz)
    xml = build_mjcf(ROBOT, PHYS, contact_sensors=True, terrain_boxes=1)
    rng = np.random.default_rng(1)
    n_contacts = 0
    for i, mi in enumerate(models):
        boxes = "".join(f'<geom type="box" pos="{" ".join(f"{v:.17g}" for v in bp[i, j])}" '
                        f'size="{" ".join(f"{v:.17g}" for v in bh[i, j])}" conaffinity="3"/>'
                        for j in np.flatnonzero(bv[i]))
        fresh = compile_mjcf(re.sub(r'<geom name="terrain_0"[^>]*/>', boxes, xml))
        fresh.geom_pos[0, 2] = gz[i]
        for _ in range(15):
            j = rng.choice(np.flatnonzero(bv[i]))
            q = mi.key_qpos[0].copy()
            q[:2] = bp[i, j, :2] + rng.normal(0, 0.05, 2)
            q[2] = bp[i, j, 2] + bh[i, j, 2] + rng.uniform(-0.03, 0.08)
            q[7:] += rng.normal(0, 0.3, 18)
            seen = []
            for mm in (mi, fresh):
                d = mujoco.MjData(mm)
                d.qpos[:] = q
                mujoco.mj_forward(mm, d)
                name = lambda g: ("box" if mm.geom_bodyid[g] == 0 and g
                                  else mujoco.mj_id2name(mm, mujoco.mjtObj.mjOBJ_GEOM, g))
                seen.append((sorted((name(c.geom1), name(c.geom2), round(c.dist, 9), *np.round(c.pos, 9))
                                    for c in d.contact[:d.ncon]), d.qacc.copy()))
            assert seen[0][0] == seen[1][0]
            np.testing.assert_allclose(seen[0][1], seen[1][1], rtol=1e-7, atol=1e-7)
            n_contacts += len(seen[0][0])
    assert n_contacts > 50, "the poses should press feet, pads or the torso into boxes"


@pytest.mark.cost(25)
def test_two_lanes_walk_as_one():
    """Overlapping one lane's controller with the other lane's physics changes no number: four tactile walkers on
    high-large obstacles as one chunk of two lanes give, to the bit, the summary and traces of two chunks of one
    lane each (two envs a controller call either way; every terrain here takes the same 9 x 9 slot grid)."""
    ctrl = make_controller("tactile", ROBOT)
    t = sample(get_terrain("high-large"), jax.random.PRNGKey(0), 4)
    keys = jax.random.split(jax.random.PRNGKey(4), 4)
    run = lambda chunk, lanes: rollout_c(ROBOT, t, ctrl, ctrl.default_params(), 250, keys, physics=PhysicsConfig(),
                                         sensors=SensorConfig(), config=RolloutConfig(record=True), chunk=chunk,
                                         lanes=lanes, nthread=2)[0]
    two, one = run(4, 2), run(2, 1)
    assert np.asarray(two.tactile_steps).sum() > 20 and two.trace.shape[:2] == (4, 250)  # pads met boxes
    leaves = lambda s: jax.tree_util.tree_flatten_with_path(s)[0]
    assert len(leaves(one)) == len(leaves(two)) > 15
    for (path, a), (_, b) in zip(leaves(one), leaves(two)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=jax.tree_util.keystr(path))


@pytest.mark.cost(25)
def test_lanes_split_a_mixed_batch_by_box_count_and_give_each_env_back_in_place():
    """Stairs (6 boxes) and obstacle fields (about 25) interleaved in one batch: the lanes sort them by box count,
    each lane with its own slot grid, and every env's summary comes back in its place, equal to the bit to a run
    of that terrain family alone (the same slot grid, the same keys)."""
    from hexjax.world.terrain import pad_terrain
    ctrl = make_controller("tactile", ROBOT)
    stairs = sample(get_terrain("stairs-up"), jax.random.PRNGKey(5), 2)
    field = sample(get_terrain("low-small"), jax.random.PRNGKey(6), 2)
    m = max(stairs.box_pos.shape[1], field.box_pos.shape[1])
    a, b = pad_terrain(stairs, m), pad_terrain(field, m)
    mixed = jax.tree_util.tree_map(lambda x, y: np.stack([y[0], x[0], y[1], x[1]]), a, b)  # field, stairs, ...
    keys = jax.random.split(jax.random.PRNGKey(7), 4)
    run = lambda t, k, lanes: rollout_c(ROBOT, t, ctrl, ctrl.default_params(), 60, k, physics=PhysicsConfig(),
                                        sensors=SensorConfig(), config=RolloutConfig(), lanes=lanes, nthread=2)[0]
    both = run(mixed, keys, 2)
    alone = {"field": run(b, keys[0::2], 1), "stairs": run(a, keys[1::2], 1)}
    assert np.ptp(np.asarray(both.end_pose)[:, 2]) > 0
    for k in ("end_pose", "travel", "energy", "tactile_steps"):
        got = np.asarray(getattr(both, k))
        np.testing.assert_array_equal(got[0::2], np.asarray(getattr(alone["field"], k)), err_msg=k)
        np.testing.assert_array_equal(got[1::2], np.asarray(getattr(alone["stairs"], k)), err_msg=k)
