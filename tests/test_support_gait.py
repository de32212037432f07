"""Chen 2019 support planning in the loop on the rugged patch (hexjax.control.support_gait,
hexjax.experiments.papers.chen2019), and the DEM it plans on (hexjax.world.dem)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.control.support_gait import SupportPlanController, rotation
from hexjax.experiments.papers.chen2019.patch import patch_spec, run_chen2019
from hexjax.plan.support import incenter_exact, overlap_center, side_distances
from hexjax.sim.model import Obs
from hexjax.world.dem import DEM, dem_for, dem_lookup
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import heightmap, sample

ROBOT = get_robot("chen2019")


def test_dem_is_the_terrain_height():
    spec = patch_spec()
    terr = sample(spec, jax.random.PRNGKey(2), 2)
    dem = dem_for(spec, terr)
    one = jax.tree_util.tree_map(lambda x: x[1], terr)
    d1 = jax.tree_util.tree_map(lambda x: x[1], dem)
    pts = np.random.default_rng(0).uniform([-0.3, -0.6], [1.4, 0.6], (200, 2))
    ours = np.asarray(dem_lookup(d1, jnp.asarray(pts, jnp.float32)))
    ref = np.array([heightmap(one, (x - 1e-4, x + 1e-4), (y - 1e-4, y + 1e-4), 2e-4)[0, 0] for x, y in pts])
    np.testing.assert_allclose(ours, ref, atol=1e-6)
    assert ours.max() > 0.1  # the patch is there
    # the taper brings the patch down to the floor at its edges
    h = np.asarray(terr.box_pos[..., 2] + terr.box_half[..., 2]).reshape(2, 40, 40)
    assert h[:, 0, :].max() < 0.01 and h[:, :, 0].max() < 0.01 and h.max() > 0.14


def test_taper_is_checked():
    with pytest.raises(ValueError, match="terrain.taper=0.3"):
        get_terrain("waves", width=0.4, taper=0.3)


def test_overlap_center_lies_in_both_triangles():
    a = jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    b = a + jnp.array([0.4, 0.1])
    ones = jnp.ones(3, bool)
    c, r = overlap_center(a, ones, b, ones)
    assert 0 < float(r) < float(incenter_exact(a, ones)[1])
    for tri in (a, b):
        assert float(jnp.min(side_distances(c, tri, ones)[0])) >= float(r) - 1e-5
    c2, r2 = overlap_center(a, ones, a, ones)
    np.testing.assert_allclose(np.asarray(c2), np.asarray(incenter_exact(a, ones)[0]), atol=1e-5)
    assert float(overlap_center(a, ones, a + 5.0, ones)[1]) == 0.0  # no overlap


def _kinematic_walk(dem, n_steps):
    """The controller fed its own commanded torso pose as the measured one (perfect tracking, no physics)."""
    ctrl = SupportPlanController(ROBOT)
    p = ctrl.default_params(dem=dem)

    def quat(pose):
        from jax.scipy.spatial.transform import Rotation
        q = Rotation.from_matrix(rotation(pose[3], pose[4], pose[5])).as_quat()
        return jnp.array([q[3], q[0], q[1], q[2]])

    def body(carry, i):
        st, pose = carry
        obs = Obs(qpos=jnp.zeros(18), qvel=jnp.zeros(18), torso_pos=pose[:3], torso_quat=quat(pose),
                  foot_force=jnp.zeros((6, 3)), foot_contact=jnp.zeros(6, bool), tactile_force=jnp.zeros(6),
                  tactile=jnp.zeros(6, bool), time=0.0)
        st2, q = ctrl.step(p, st, obs)
        u = jnp.clip(st2.k * ctrl.dt / p.phase_time - st2.phase, 0.0, 1.0)
        d = st2.torso_to - st2.torso_from
        new = st2.torso_from + d * u * u * (3 - 2 * u)
        return (st2, new), (q, new, st2.land, st2.phase)

    (st, _), out = jax.lax.scan(body, (ctrl.init(p, None), jnp.array([0.0, 0.0, ROBOT.hip_height, 0.0, 0.0, 0.0])),
                                jnp.arange(n_steps))
    return ctrl, p, st, out


def test_planned_walk_on_flat_ground_is_straight_level_and_smooth():
    dem = DEM(heights=jnp.zeros((80, 60)), origin=jnp.array([-0.4, -0.6]), cell=jnp.asarray(0.02))
    ctrl, p, st, (q, pose, land, phase) = _kinematic_walk(dem, 400)  # 8 s: 16 phases
    q, pose = np.asarray(q), np.asarray(pose)
    assert int(st.unreachable) == 0
    assert abs(pose[-1, 0] - 16 * float(p.stride)) < 0.01  # one stride per phase
    assert np.max(np.abs(pose[:, 1])) < 0.005 and np.allclose(pose[:, 2], ROBOT.hip_height, atol=1e-3)
    assert np.max(np.abs(np.diff(q, axis=0))) < 0.12  # no jumps in the joint targets
    assert float(st.min_margin) >= float(p.delta_s) - 1e-3


def test_planned_footholds_are_grid_cells_on_the_terrain():
    spec = patch_spec()
    terr = sample(spec, jax.random.PRNGKey(0), 1)
    dem = jax.tree_util.tree_map(lambda x: x[0], dem_for(spec, terr))
    ctrl, p, st, (q, pose, land, phase) = _kinematic_walk(dem, 500)
    land = np.asarray(land)[-1]
    cell = float(dem.cell)
    idx = (land[:, :2] - np.asarray(dem.origin)) / cell - 0.5
    assert np.allclose(idx, np.round(idx), atol=1e-3)  # cell centres
    ground = np.asarray(dem_lookup(dem, jnp.asarray(land[:, :2])))
    np.testing.assert_allclose(land[:, 2], ground + ROBOT.foot_radius, atol=1e-5)
    assert np.asarray(pose)[:, 2].max() > ROBOT.hip_height + 0.02  # the torso rose over the waves


@pytest.mark.cost(75)
def test_planned_motion_crosses_the_patch_upright():
    """The MJX robot under support planning crosses two randomised patches without capsizing."""
    res = run_chen2019(n=2, seed=3, fixed_step_heights=())
    r = res["planned"]
    assert r["crossed"] == 2 and r["capsized"] == 0 and r["nan"] == 0
    assert r["max_tilt_deg"]["max"] < 30.0
    assert r["min_stability_margin_m"]["min"] > 0.0


def test_support_planner_bad_input():
    ctrl = SupportPlanController(ROBOT)
    p = ctrl.default_params()
    with pytest.raises(ValueError, match="support.stride"):
        ctrl.validate_params(p.replace(stride=jnp.float32(0.0)))
    with pytest.raises(ValueError, match="support.dem.heights"):
        ctrl.validate_params(p.replace(dem=p.dem.replace(heights=jnp.full((4, 4), jnp.nan))))
    with pytest.raises(ValueError, match="controller.search"):
        SupportPlanController(ROBOT, search=-1)
    with pytest.raises(ValueError, match="batch n=0"):
        run_chen2019(n=0)
