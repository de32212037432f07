"""Perception (`hexjax.perceive`): exact ray casts, RANSAC ground, the fused grid map, obstacle circles, and
one-line errors for bad sensors and grids."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.perceive.grid import GridMap, GridSpec, fuse
from hexjax.perceive.obstacles import circles, label_components, map_obstacles, obstacle_cells
from hexjax.perceive.ransac import fit_plane
from hexjax.perceive.raycast import ray_box, ray_terrain, scan
from hexjax.perceive.sensors import RangeSensor, get_sensor
from hexjax.world.presets import luneckas2020
from hexjax.world.terrain import Terrain


def _ray_box_reference(o, d, pos, half, valid):
    """float64 numpy, face by face: the nearest t >= 0 where the ray crosses one of a box's six face planes
    inside that face; 0 for a ray starting inside a box; inf for no hit."""
    out = np.full(len(d), np.inf)
    for r, dr in enumerate(d):
        for p, h, v in zip(pos, half, valid):
            if not v:
                continue
            lo, hi = p - h, p + h
            if np.all(o >= lo) and np.all(o <= hi):
                out[r] = 0.0
                continue
            for ax in range(3):
                if dr[ax] == 0:
                    continue
                for plane in (lo[ax], hi[ax]):
                    t = (plane - o[ax]) / dr[ax]
                    if t < 0:
                        continue
                    q = o + t * dr
                    others = [a for a in range(3) if a != ax]
                    if np.all(q[others] >= lo[others] - 1e-12) and np.all(q[others] <= hi[others] + 1e-12):
                        out[r] = min(out[r], t)
    return out


def test_ray_box_distances_are_exact_against_a_numpy_reference():
    rng = np.random.default_rng(0)
    for trial in range(4):
        m, r = 12, 300
        pos = rng.uniform(-1, 1, (m, 3))
        half = rng.uniform(0.02, 0.3, (m, 3))
        valid = rng.random(m) < 0.8
        o = rng.uniform(-1.5, 1.5, 3)
        d = rng.normal(size=(r, 3))
        # half the rays aimed at a random point of a random box, so that hits and misses are both common
        k = rng.integers(0, m, r // 2)
        d[: r // 2] = pos[k] + rng.uniform(-1, 1, (r // 2, 3)) * half[k] - o
        d[:20, 2] = 0.0  # rays parallel to a pair of faces
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        ref = _ray_box_reference(o, d, pos, half, valid)
        got = np.asarray(jax.jit(ray_box)(*(jnp.asarray(x, jnp.float32) for x in (o, d, pos, half)),
                                          jnp.asarray(valid)))
        hit = np.isfinite(ref)
        assert 30 < hit.sum() < r - 30, hit.sum()  # both hits and misses are tested
        np.testing.assert_array_equal(np.isfinite(got), hit)
        np.testing.assert_allclose(got[hit], ref[hit], rtol=1e-5, atol=1e-5)
    # a ray starting inside a box meets it at 0; the ground below at its height
    t = Terrain(box_pos=jnp.array([[0.0, 0.0, 0.1]]), box_half=jnp.array([[0.1, 0.1, 0.1]]),
                box_valid=jnp.array([True]), ground_z=jnp.asarray(-0.5))
    dist = ray_terrain(jnp.array([0.0, 0.0, 0.1]), jnp.array([[1.0, 0, 0], [0, 0, -1.0]]), t)
    np.testing.assert_allclose(np.asarray(dist), [0.0, 0.0])
    dist = ray_terrain(jnp.array([0.5, 0.0, 0.1]), jnp.array([[0.0, 0, -1.0], [0, 0, 1.0]]), t)
    np.testing.assert_allclose(np.asarray(dist), [0.6, np.inf])


def test_ransac_recovers_a_tilted_plane_among_40_percent_outliers():
    """600 points on a plane tilted 12 deg (2 mm noise) and 400 outliers spread through a 2 m x 2 m x 0.6 m box:
    the normal within 1 deg and the height at the origin within 5 mm, for 8 planes and seeds."""
    rng = np.random.default_rng(1)
    for seed in range(8):
        tilt, az, h0 = np.radians(12.0), rng.uniform(0, 2 * np.pi), rng.uniform(-0.2, 0.2)
        n = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
        xy = rng.uniform(-1, 1, (600, 2))
        z = h0 - (n[0] * xy[:, 0] + n[1] * xy[:, 1]) / n[2] + rng.normal(0, 0.002, 600)
        inl = np.concatenate([xy, z[:, None]], 1)
        out = np.concatenate([rng.uniform(-1, 1, (400, 2)), rng.uniform(h0 - 0.3, h0 + 0.3, (400, 1))], 1)
        pts = rng.permutation(np.concatenate([inl, out]))
        plane = jax.jit(fit_plane)(jnp.asarray(pts, jnp.float32), jnp.ones(1000, bool), jax.random.PRNGKey(seed))
        angle = np.degrees(np.arccos(np.clip(np.asarray(plane.normal) @ n, -1, 1)))
        height = float(plane.height(jnp.zeros(2)))
        assert angle < 1.0 and abs(height - h0) < 0.005, (seed, angle, height, h0)
        assert 550 < int(plane.count) < 700


def _flat_scan(sensor, n_scans=1, key=0):
    flat = Terrain(box_pos=jnp.zeros((1, 3)), box_half=jnp.full((1, 3), 0.01), box_valid=jnp.zeros(1, bool),
                   ground_z=jnp.asarray(0.0))
    quat = jnp.array([1.0, 0, 0, 0])
    return [scan(sensor, jnp.array([0.0, 0.0, 0.1]), quat, flat, jax.random.PRNGKey(key + i)) for i in range(n_scans)]


def test_grid_map_of_flat_ground_is_flat_within_the_noise():
    """A noisy Kinect (its own noise model, 1.5 mm + 1.9 mm/m^2) over flat ground: every known cell's mean
    height lies within 4 sigma of 0 (sigma: the noise at the cell's range), RANSAC finds the ground, and no
    cell is an obstacle."""
    sensor = get_sensor("kinect_v1", n_h=64, n_v=48)
    spec = GridSpec.covering((0.0, -2.0), (4.5, 2.0), 0.05)
    g = GridMap.empty(spec)
    for s in _flat_scan(sensor, 3):
        assert bool(s.valid.any())
        g = fuse(spec, g, s)
    h, known = g.heights()
    h, known, cnt = np.asarray(h), np.asarray(known), np.asarray(g.count)
    assert known.sum() > 100
    rng = np.linalg.norm(spec.centres() - np.array([0.1, 0.0]), axis=-1)
    sigma = (0.0015 + 0.0019 * rng ** 2) / np.sqrt(np.maximum(cnt, 1))
    assert np.all(np.abs(h[known]) <= 4 * sigma[known] + 1e-4), np.abs(h[known]).max()
    assert np.abs(h[known]).max() > 0  # the noise is there
    cells = jnp.concatenate([jnp.asarray(spec.centres()).reshape(-1, 2), jnp.asarray(h).reshape(-1, 1)], -1)
    plane = fit_plane(cells, jnp.asarray(known).reshape(-1), jax.random.PRNGKey(0))
    assert abs(float(plane.height(jnp.zeros(2)))) < 0.005 and float(plane.tilt()) < np.radians(1.0)
    assert not bool(obstacle_cells(spec, g, plane, 0.05).any())


def test_camera_and_lidar_see_what_their_geometry_allows():
    """Camera: no ground return nearer than 0.8 m of depth or beyond 4 m; the returns lie inside its field of
    view. LiDAR (360 deg): returns all round; dropout 0.5 drops about half of them."""
    cam = get_sensor("kinect_v1")
    s = _flat_scan(cam)[0]
    p = np.asarray(s.points)[np.asarray(s.valid)]
    depth = p[:, 0] - float(s.origin[0])
    assert depth.min() >= 0.8 - 1e-3 and depth.max() <= 4.0 + 0.05
    assert np.all(np.abs(np.degrees(np.arctan2(p[:, 1], depth))) <= 28.5 + 0.1)
    lidar = get_sensor("velodyne_puck", noise_std=0.0)
    s = _flat_scan(lidar)[0]
    p = np.asarray(s.points)[np.asarray(s.valid)]
    az = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
    assert np.histogram(az, bins=8, range=(-180, 180))[0].min() > 0
    np.testing.assert_allclose(p[:, 2], 0.0, atol=1e-5)
    half = _flat_scan(dataclasses.replace(lidar, dropout=0.5))[0]
    ratio = float(half.valid.sum()) / float(s.valid.sum())
    assert 0.4 < ratio < 0.6, ratio


def test_components_and_circles_envelope_every_obstacle_cell():
    spec = GridSpec(origin=(0.0, 0.0), cell=0.1, nx=12, ny=10)
    mask = np.zeros((12, 10), bool)
    mask[1:3, 1:4] = True  # a 2 x 3 block
    mask[6, 6] = mask[7, 7] = True  # diagonal neighbours: one component (8-connected)
    mask[10, 1] = True
    lab = np.asarray(label_components(jnp.asarray(mask)))
    assert len(set(lab[mask].tolist())) == 3 and np.all(lab[~mask] == -1)
    assert lab[6, 6] == lab[7, 7] == 6 * 10 + 6  # the smallest flat index of its component
    c = circles(spec, jnp.asarray(mask), 5)
    valid = np.asarray(c.valid)
    assert valid.sum() == 3 and sorted(np.asarray(c.cells)[valid].tolist()) == [1, 2, 6]
    cen, rad = np.asarray(c.centres)[valid], np.asarray(c.radii)[valid]
    corners = np.array([(a, b) for a in (0, 1) for b in (0, 1)]) * spec.cell
    for i, j in zip(*np.nonzero(mask)):
        cell_corners = np.array(spec.origin) + np.array([i, j]) * spec.cell + corners
        inside = [np.all(np.linalg.norm(cell_corners - ce, axis=1) <= r + 1e-6) for ce, r in zip(cen, rad)]
        assert any(inside), (i, j)
    # with fewer slots than components, the ones nearest `near` are kept
    c = circles(spec, jnp.asarray(mask), 1, near=jnp.array([1.05, 0.15]))
    np.testing.assert_allclose(np.asarray(c.centres)[0], [1.05, 0.15], atol=1e-6)
    # a map of fewer cells than slots (a 2 x 1 grid, 4 slots): its one component, then empty slots
    c = circles(GridSpec(origin=(0.0, 0.0), cell=0.1, nx=2, ny=1), jnp.array([[True], [False]]), 4)
    assert np.asarray(c.valid).tolist() == [True, False, False, False] and np.asarray(c.cells).tolist() == [1, 0, 0, 0]
    np.testing.assert_allclose(np.asarray(c.centres), [[0.05, 0.05], [0, 0], [0, 0], [0, 0]], atol=1e-6)


@pytest.mark.parametrize("kw, msg", [
    ({"fov_h": 0.0}, "sensor.fov_h=0.0: must be in (0, 170]"),
    ({"fov_v": -5.0}, "sensor.fov_v=-5.0"),
    ({"range_min": 4.0, "range_max": 4.0}, "need 0 <= range_min < range_max"),
    ({"dropout": 1.0}, "sensor.dropout=1.0"),
    ({"kind": "sonar"}, "sensor.kind='sonar'"),
    ({"mount_pos": (0.0, 0.0, 0.0)}, "sensor.mount_pos=[0.0, 0.0, 0.0]: inside the torso of luneckas2020"),
])
def test_bad_sensors_fail_in_one_line(kw, msg):
    with pytest.raises(ValueError) as err:
        dataclasses.replace(RangeSensor(), **kw).validate(luneckas2020())
    assert "\n" not in str(err.value) and msg in str(err.value), str(err.value)


def test_bad_grids_and_sensor_files_fail_in_one_line(tmp_path):
    with pytest.raises(ValueError, match=r"^grid.cell=0.0: must be a length > 0 m$"):
        GridSpec(cell=0.0).validate()
    with pytest.raises(ValueError, match=r"^grid.nx=0"):
        GridSpec(nx=0).validate()
    with pytest.raises(ValueError, match=r"^grid.nx=3500000: must be a whole number of cells in \[1, 4096\]$"):
        GridSpec.covering((0.0, 0.0), (3.5, 1.0), 1e-6)  # was a 42 TB allocation
    bad = tmp_path / "cam.yaml"
    bad.write_text("kind: camera\nfov_h: -10\n")
    with pytest.raises(ValueError, match=r"cam.yaml: sensor.fov_h=-10.0: must be in \(0, 170\]"):
        get_sensor(str(bad))
    with pytest.raises(ValueError, match=r"cam.yaml: sensor.fov_h=-10.0: must be in \(0, 170\]"):
        get_sensor(str(bad), fov_h=60.0)  # the file is checked before a sweep's override replaces the key
    with pytest.raises(ValueError, match=r"kinect_v1.yaml: sensor.noise_std=-1.0"):
        get_sensor("kinect_v1", noise_std=-1.0)  # and the override itself
    bad.write_text("kind: camera\nfov_hh: 10\n")
    with pytest.raises(ValueError, match="cam.yaml: sensor.fov_hh: unknown key \\(did you mean 'fov_h'\\?\\)"):
        get_sensor(str(bad))


def test_perceived_circles_cover_the_observed_obstacle_area_on_64_fields():
    """The LiDAR preset scans 64 random zhao2018-mjx fields (0.25 m boxes) from four poses on the way to each
    target; the map, RANSAC ground and circles follow. Of the true boxes' footprint area that the scans
    observed (cells with returns), the perceived circles cover >= 95 % (measured 99.7 %). Walls 25 cm tall seen
    from 22 cm show only their near faces, so of the whole footprint of every box seen the circles cover less
    (measured 91 %; asserted >= 85 %); the ground is found within 5 mm everywhere."""
    from hexjax.control.avoid_gait import footprint_radius
    from hexjax.experiments.papers.zhao2018.closed_loop import obstacle_boxes
    from hexjax.plan.fields import small_fields
    rb = luneckas2020()
    n = 64
    sensor = get_sensor("velodyne_puck")
    k1, k2 = jax.random.split(jax.random.PRNGKey(0))
    f = small_fields(k1, n, footprint_radius(rb, 0.06), 0.12)
    terr = obstacle_boxes(k2, f)
    spec = GridSpec.covering((-0.5, -1.3), (2.8, 1.3), 0.04)

    def one(t, target, key):
        g = GridMap.empty(spec)
        d = target / jnp.linalg.norm(target)
        yaw = jnp.arctan2(d[1], d[0])
        q = jnp.array([jnp.cos(yaw / 2), 0, 0, jnp.sin(yaw / 2)])
        for j, x in enumerate((-0.3, 0.0, 0.2, 0.4)):
            g = fuse(spec, g, scan(sensor, jnp.array([x * d[0], x * d[1], 0.12]), q, t, jax.random.fold_in(key, j)))
        plane, _, c = map_obstacles(spec, g, key, 0.05, 24, near=jnp.zeros(2))
        return c, plane.height(jnp.zeros(2)), g.count

    c, ground, count = jax.jit(jax.vmap(one))(terr, f.target, jax.random.split(jax.random.PRNGKey(1), n))
    assert float(jnp.abs(ground).max()) < 0.005
    u = np.stack(np.meshgrid(np.linspace(-1, 1, 9), np.linspace(-1, 1, 9)), -1).reshape(-1, 2)
    observed_pts = observed_cov = 0
    seen_cov = []
    for i in range(n):
        cen, rad, ok = np.asarray(c.centres[i]), np.asarray(c.radii[i]), np.asarray(c.valid[i])
        for p, h, v in zip(np.asarray(terr.box_pos[i]), np.asarray(terr.box_half[i]), np.asarray(terr.box_valid[i])):
            if not v:
                continue
            pts = p[:2] + u * h[:2]  # 81 points over the footprint
            covered = ((np.linalg.norm(pts[:, None] - cen[None], axis=-1) <= rad[None]) & ok[None]).any(1)
            ij = np.floor((pts - np.array(spec.origin)) / spec.cell).astype(int)
            observed = np.asarray(count[i])[ij[:, 0], ij[:, 1]] > 0
            observed_pts += observed.sum()
            observed_cov += (covered & observed).sum()
            if observed.any():
                seen_cov.append(covered.mean())
    assert observed_pts > 2000 and len(seen_cov) > 300
    assert observed_cov / observed_pts >= 0.95, observed_cov / observed_pts
    assert np.mean(seen_cov) >= 0.85, np.mean(seen_cov)


def test_fill_unknown_takes_the_highest_known_neighbour_one_cell_per_pass():
    from hexjax.perceive.grid import fill_unknown
    h = jnp.zeros((5, 5)).at[0, 0].set(0.3).at[0, 1].set(0.1)
    known = jnp.zeros((5, 5), bool).at[0, 0].set(True).at[0, 1].set(True)
    h1, k1 = fill_unknown(h, known, 1)
    # one pass reaches the 3 x 3 neighbours of the known cells only, each taking its highest known neighbour
    assert np.array_equal(np.asarray(k1[:2, :3]), np.ones((2, 3), bool)) and int(k1.sum()) == 6
    assert float(h1[1, 0]) == pytest.approx(0.3) and float(h1[0, 2]) == pytest.approx(0.1)
    assert float(h1[1, 2]) == pytest.approx(0.1) and float(h1[0, 1]) == pytest.approx(0.1)  # known cells kept
    h4, k4 = fill_unknown(h, known, 4)
    # the 0.3 spreads along the diagonal; the cells nearer the 0.1 than the 0.3 take the 0.1
    assert bool(k4.all()) and float(h4[4, 4]) == pytest.approx(0.3) and float(h4[0, 4]) == pytest.approx(0.1)


def test_perceived_dem_of_a_wave_patch_matches_the_true_dem_where_seen():
    """A D435 on the Chen 2019 robot's torso, 6 scans walking up to a rugged wave patch: the fused map's cells
    that got returns hold the true column heights (measured: median error 0.6 mm, 90th percentile 3.2 mm) on
    the patch's first quarter."""
    from hexjax.control.perceive_support import PerceivingSupportPlan
    from hexjax.experiments.papers.chen2019.patch import patch_spec
    from hexjax.perceive.grid import dem_grid, to_dem
    from hexjax.world.dem import dem_for, dem_layout
    from hexjax.world.presets import get_robot
    from hexjax.world.terrain import sample

    spec = patch_spec()
    terr = sample(spec, jax.random.PRNGKey(3), 1)
    true = np.asarray(dem_for(spec, terr).heights[0])
    one = jax.tree_util.tree_map(lambda x: x[0], terr)
    origin, (nx, ny), cell = dem_layout(spec)
    grid = dem_grid(spec)
    ctrl = PerceivingSupportPlan(get_robot("chen2019"), sensor=get_sensor("realsense_d435"), grid=grid)
    g = GridMap.empty(grid)
    q = jnp.array([1.0, 0.0, 0.0, 0.0])
    for i, x in enumerate(np.linspace(-0.1, 0.15, 6)):
        s = scan(ctrl.sensor, jnp.array([x, 0.0, 0.17]), q, one, jax.random.PRNGKey(i))
        g = fuse(grid, g, s)
    h, known = g.heights()
    h, known = np.asarray(h), np.asarray(known)
    pad = int(round((spec.start_x - origin[0]) / cell))
    near = (slice(pad, pad + nx // 4), slice(pad + 10, pad + 30))  # the patch's first 0.2 m, its middle 0.4 m
    assert known[near].mean() > 0.75, known[near].mean()  # 0.875 measured
    err = (h - true)[near][known[near]]
    # mean heights: returns off a column's side pull a cell below its top, so the error is one-sided and small
    assert np.median(np.abs(err)) < 0.002 and np.percentile(np.abs(err), 90) < 0.01, np.percentile(np.abs(err), [50, 90])
    dem = np.asarray(to_dem(grid, g, 0.0, passes=3).heights)
    assert np.all(np.isfinite(dem)) and np.allclose(dem[known], h[known])


def test_perceiving_support_planner_bad_input_fails_in_one_line():
    from hexjax.control.perceive_support import PerceivingSupportPlan
    from hexjax.world.presets import get_robot
    rb = get_robot("chen2019")
    inside = dataclasses.replace(get_sensor("realsense_d435"), mount_pos=(0.1, 0.0, 0.0))
    for kw, msg in ((dict(sensor=inside), "sensor.mount_pos=.*inside the torso of chen2019"),
                    (dict(fill_passes=-1), "fill_passes=-1"), (dict(perceive_every=0), "perceive_every=0"),
                    (dict(grid=GridSpec(cell=0.0)), r"grid.cell=0.0")):
        with pytest.raises(ValueError, match=msg) as e:
            PerceivingSupportPlan(rb, **{"sensor": get_sensor("realsense_d435"), **kw})
        assert "\n" not in str(e.value)
