import jax
import numpy as np
import pytest

from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.files import preset_names
from hexjax.world.terrain import DIFFICULTY, LUNECKAS2020_CATEGORIES, heightmap, leg_scale, obstacle_circles, sample

B = 64


def _nearest_neighbour(pos, valid):
    out = []
    for p, v in zip(pos, valid):
        q = p[v][:, :2]
        d = np.linalg.norm(q[:, None] - q[None], axis=-1)
        np.fill_diagonal(d, np.inf)
        out.append(d.min(1))
    return np.concatenate(out)


@pytest.mark.parametrize("name", LUNECKAS2020_CATEGORIES)
def test_seed000_categories_match_definitions(name):
    """Luneckas 2020 Sect. 2.2: R >= 15 cm (low) or 10 < R < 15 cm (high) between obstacle centres;
    H in 3-5 cm (small) or 6-8 cm (large); length 2-3 cm."""
    spec = get_terrain(name)
    t = sample(spec, jax.random.PRNGKey(7), B)
    pos, half, valid = (np.asarray(x) for x in (t.box_pos, t.box_half, t.box_valid))
    assert valid.sum(1).min() >= 8  # every field has obstacles
    assert valid.sum(1).max() < spec.max_boxes  # no field was truncated by the static size
    nn = _nearest_neighbour(pos, valid)
    if name.startswith("low"):
        assert nn.min() >= 0.15
    else:
        assert nn.min() > 0.10 and nn.max() < 0.15
    h = 2 * half[valid][:, 2]
    lo, hi = (0.03, 0.05) if name.endswith("small") else (0.06, 0.08)
    assert h.min() >= lo - 1e-6 and h.max() <= hi + 1e-6
    length = 2 * half[valid][:, 0]
    assert length.min() >= 0.02 - 1e-6 and length.max() <= 0.03 + 1e-6
    np.testing.assert_allclose(pos[valid][:, 2], half[valid][:, 2], atol=1e-6)  # standing on z = 0
    # obstacles start ahead of the robot and stay inside the corridor
    assert pos[valid][:, 0].min() >= spec.start_x - 0.01
    assert np.abs(pos[valid][:, 1]).max() <= 0.5 * spec.width + 0.01
    # different keys give different fields
    assert not np.allclose(pos[0], pos[1])


def test_step_ditch_waves_rough():
    k = jax.random.PRNGKey(3)
    step = sample(get_terrain("step40"), k, 8)
    np.testing.assert_allclose(2 * np.asarray(step.box_half)[:, 0, 2], 0.04, atol=1e-6)  # Yu 2019: 40 mm
    assert np.all(np.asarray(step.box_pos)[:, 0, 1] < 0)  # on the right side
    for depth in (18, 40, 80):
        d = sample(get_terrain(f"ditch{depth}"), k, 8)
        np.testing.assert_allclose(np.asarray(d.ground_z), -depth / 1000, atol=1e-6)
        top = np.asarray(d.box_pos)[..., 2] + np.asarray(d.box_half)[..., 2]
        np.testing.assert_allclose(top, 0.0, atol=1e-6)  # solid ground flush with z = 0
        hm = heightmap(jax.tree_util.tree_map(lambda x: x[0], d), (0.0, 1.5), (-0.1, 0.1), 0.005)
        assert hm.min() == pytest.approx(-depth / 1000, abs=1e-6) and hm.max() == pytest.approx(0.0, abs=1e-6)
    w = sample(get_terrain("waves"), k, 8)
    peaks = (np.asarray(w.box_pos)[..., 2] + np.asarray(w.box_half)[..., 2]).max(1)
    assert peaks.min() >= 0.15 - 1e-6 and peaks.max() <= 0.178 + 1e-6  # Chen 2019: peaks to ~178 mm
    spec = get_terrain("waves")
    assert spec.length == pytest.approx(0.8) and spec.width == pytest.approx(0.4)  # 400 x 800 mm patch
    r = sample(get_terrain("rough"), k, 8)
    hr = 2 * np.asarray(r.box_half)[..., 2]
    assert hr.max() <= 0.02 + 1e-6 and hr.std() > 0.003


def test_obstacle_circles_cover_boxes():
    """Zhao 2018 Eq. 1 envelopes each obstacle by a circle: every corner of every valid box footprint lies
    inside (or on) its circle, and the circle is no larger than that (its radius is the half diagonal)."""
    t = sample(get_terrain("high-large"), jax.random.PRNGKey(0), 4)
    c, r, v = (np.asarray(x) for x in obstacle_circles(t))
    assert c.shape == t.box_pos.shape[:-1] + (2,) and r.shape == v.shape
    pos, half = np.asarray(t.box_pos)[..., :2], np.asarray(t.box_half)[..., :2]
    for sx in (-1, 1):
        for sy in (-1, 1):
            corner = pos + half * np.array([sx, sy])
            d = np.linalg.norm(corner - c, axis=-1)
            assert np.all(d[v] <= r[v] * (1 + 1e-6)), (d - r)[v].max()
    np.testing.assert_allclose(r[v], np.linalg.norm(half[v], axis=-1), rtol=1e-6)  # tight: a corner touches


def test_all_presets_sample_inside_their_spec():
    """Every shipped terrain preset samples terrains of its static size whose valid boxes have positive
    extents, stand on or in the ground (no box floats or is sunk below the ditch bottom), top out within the
    preset's height range (obstacles, steps, waves) and lie within the corridor's length (step and ditch slabs
    reach past it by design)."""
    for name in preset_names("terrains"):
        spec = get_terrain(name)
        t = sample(spec, jax.random.PRNGKey(1), 3)
        pos, half, valid = (np.asarray(x) for x in (t.box_pos, t.box_half, t.box_valid))
        gz = np.asarray(t.ground_z)
        assert pos.shape == (3, spec.max_boxes, 3) and np.all(np.isfinite(pos)) and np.all(np.isfinite(gz)), name
        if spec.kind == "flat":
            assert not valid.any(), name
            continue
        assert valid.any(1).all(), name
        assert np.all(half[valid] > 0), name
        bottom, top = (pos - half)[..., 2], (pos + half)[..., 2]
        # every box stands on the ground plane (at the ditch / pit bottom, or below the stairs and slopes down)
        np.testing.assert_allclose(bottom[valid], np.broadcast_to(gz[:, None], bottom.shape)[valid], atol=1e-6,
                                   err_msg=name)
        lo, hi = spec.height_range
        if spec.kind in ("obstacles", "step"):
            assert np.all((top[valid] >= lo - 1e-6) & (top[valid] <= hi + 1e-6)), name
        if spec.kind == "waves":
            assert np.all(top.max(1) >= lo - 1e-6) and np.all(top.max(1) <= hi + 1e-6), name
        if spec.kind in ("obstacles", "waves", "rough"):
            x = pos[..., 0][valid]
            assert x.min() >= spec.start_x - 0.02 and x.max() <= spec.start_x + spec.length + 0.02, name


@pytest.mark.parametrize("kwargs,match", [
    (dict(height_range=(0.08, 0.03)), r"height_range=\(0.08, 0.03\): min must be <= max"),
    (dict(length=-1.0), "length"),
    (dict(kind="lava"), "kind"),
])
def test_invalid_terrain_specs(kwargs, match):
    with pytest.raises(ValueError, match=match):
        get_terrain("low-small", **kwargs)


def test_unknown_preset_and_empty_batch():
    with pytest.raises(ValueError, match="unknown"):
        get_terrain("mountains")
    with pytest.raises(ValueError, match="batch=0"):
        sample(get_terrain("flat"), jax.random.PRNGKey(0), 0)
    one = jax.tree_util.tree_map(lambda x: x[0], sample(get_terrain("flat"), jax.random.PRNGKey(0), 1))
    with pytest.raises(ValueError, match=r"res=0.0: must be a finite number of metres > 0"):
        heightmap(one, (0.0, 1.0), (0.0, 1.0), 0.0)
    with pytest.raises(ValueError, match=r"y_range=\(1.0, 0.0\): must be finite, low < high"):
        heightmap(one, (0.0, 1.0), (1.0, 0.0), 0.01)


def _tops(t):
    pos, half, valid = (np.asarray(x) for x in (t.box_pos, t.box_half, t.box_valid))
    return pos, half, valid, (pos + half)[..., 2]


@pytest.mark.parametrize("d", [0.0, 0.5, 1.0])
def test_stairs_follow_their_difficulty(d):
    """Stairs rise 1 cm at difficulty 0 to 8 cm at 1 for the Luneckas 2020 robot: up, the valid boxes' tops
    are riser * (1..n) from start_x on; down, the robot's platform is at z = 0, the steps below it go down by
    one riser each and the ground plane is the n-th."""
    riser = 0.01 + 0.07 * d
    up = get_terrain("stairs-up", difficulty=d)
    assert up.height_range == pytest.approx((riser, riser))
    pos, half, valid, top = _tops(sample(up, jax.random.PRNGKey(0), 4))
    n = up.stair_count
    for e in range(4):
        np.testing.assert_allclose(np.sort(top[e][valid[e]]), riser * np.arange(1, n + 1), atol=1e-6)
        lo = np.sort((pos - half)[e, valid[e], 0])
        tread = np.diff(lo)
        assert lo[0] == pytest.approx(up.start_x) and np.all((tread >= 0.1 - 1e-6) & (tread <= 0.12 + 1e-6))
    down = sample(get_terrain("stairs-down", difficulty=d), jax.random.PRNGKey(0), 4)
    pos, half, valid, top = _tops(down)
    np.testing.assert_allclose(np.asarray(down.ground_z), -riser * n, atol=1e-6)
    for e in range(4):
        np.testing.assert_allclose(np.sort(top[e][valid[e]])[::-1], -riser * np.arange(n), atol=1e-6)
        hm = heightmap(jax.tree_util.tree_map(lambda x: x[e], down), (-0.2, 0.2), (-0.05, 0.05), 0.01)
        assert hm.max() == pytest.approx(0.0, abs=1e-6) and hm.min() == pytest.approx(0.0, abs=1e-6)  # start


@pytest.mark.parametrize("name", ["slope-up", "slope-down"])
def test_slope_rises_at_its_angle(name):
    """The ramp's top follows tan(angle) * (x - start_x) within half a slice's rise, up or down; the angle is
    34 deg (0.6 rad) at difficulty 1 and flat ground at 0."""
    for d, deg in ((1.0, 34.38), (0.5, 17.19)):
        spec = get_terrain(name, difficulty=d)
        t = jax.tree_util.tree_map(lambda x: x[0], sample(spec, jax.random.PRNGKey(2), 1))
        xs = np.arange(spec.start_x + 0.05, spec.start_x + spec.length - 0.05, 0.01) + 0.005
        hm = heightmap(t, (xs[0] - 0.005, xs[-1] + 0.005), (-0.01, 0.01), 0.01)[:, 0]
        sign = 1.0 if spec.direction == "up" else -1.0
        want = sign * np.tan(np.radians(deg)) * (xs - spec.start_x)
        np.testing.assert_allclose(hm[:xs.size], want, atol=0.5 * np.tan(np.radians(deg)) * spec.cell + 2e-3)
    flat = sample(get_terrain(name, difficulty=0.0), jax.random.PRNGKey(2), 2)
    _, _, valid, top = _tops(flat)
    assert np.all(np.abs(top[valid]) < 1.1e-3) and np.abs(np.asarray(flat.ground_z)).max() < 1e-6


def test_stones_gaps_and_boxes_heights():
    """Stepping stones: tops at z = 0 over a pit 20 cm deep, neighbours apart by the gap (0 at difficulty 0, i.e.
    solid ground; 5 cm at 1); random boxes: heights in the difficulty's range, inside the corridor."""
    for d in (0.0, 1.0):
        spec = get_terrain("stones", difficulty=d)
        t = sample(spec, jax.random.PRNGKey(4), 2)
        pos, half, valid, top = _tops(t)
        np.testing.assert_allclose(top[valid], 0.0, atol=1e-6)
        np.testing.assert_allclose(np.asarray(t.ground_z), -0.2, atol=1e-6)
        nx, ny = spec._stone_grid()
        stones = pos[0, : nx * ny].reshape(nx, ny, 3), half[0, : nx * ny].reshape(nx, ny, 3)
        gap_x = (stones[0][1:, :, 0] - stones[1][1:, :, 0]) - (stones[0][:-1, :, 0] + stones[1][:-1, :, 0])
        gap_y = (stones[0][:, 1:, 1] - stones[1][:, 1:, 1]) - (stones[0][:, :-1, 1] + stones[1][:, :-1, 1])
        np.testing.assert_allclose(gap_x, 0.05 * d, atol=1e-6)
        np.testing.assert_allclose(gap_y, 0.05 * d, atol=1e-6)
    for d in (0.0, 1.0):
        spec = get_terrain("boxes", difficulty=d)
        pos, half, valid, top = _tops(sample(spec, jax.random.PRNGKey(5), 8))
        lo, hi = DIFFICULTY["boxes"]["height_range"][int(d)]
        assert valid.all() and top.min() >= min(lo, 1e-3) - 1e-6 and top.max() <= hi + 1e-6
        assert np.abs(pos[..., 1]).max() <= 0.5 * spec.width + 1e-6


def test_difficulty_scales_with_the_robot_and_is_checked():
    """The table's lengths scale with the robot's leg (angles do not); a difficulty outside [0, 1] fails in one
    line naming it, from a preset override and from `at_difficulty`."""
    yu = get_robot("yu2019")
    k = leg_scale(yu)
    assert k == pytest.approx((yu.femur_length + yu.tibia_length) / 0.202)
    base = get_terrain("stairs-up")
    assert base.at_difficulty(1.0, k).height_range == pytest.approx((0.08 * k, 0.08 * k), rel=1e-5)
    slope = get_terrain("slope-up")
    assert slope.at_difficulty(1.0, k).slope_range == slope.at_difficulty(1.0).slope_range
    big = get_terrain("stones").at_difficulty(1.0, 1.6)  # stones grow with the robot: gaps stay below the pitch
    assert big.stone_pitch == pytest.approx(0.128) and big.gap_range == pytest.approx((0.08, 0.08))
    # every family gets harder along its own key: the keys' values grow with difficulty
    for kind, keys in DIFFICULTY.items():
        ranges = {k: v for k, v in keys.items() if isinstance(v[0], tuple)}
        assert ranges, kind
        for key, (easy, hard) in ranges.items():
            assert all(h >= e for e, h in zip(easy, hard)) and any(h > e for e, h in zip(easy, hard)), (kind, key)
    with pytest.raises(ValueError, match=r"terrain.difficulty=1.5: must be in \[0, 1\]"):
        get_terrain("stairs-up", difficulty=1.5)
    with pytest.raises(ValueError, match=r"terrain.difficulty=-0.1"):
        base.at_difficulty(-0.1)
    with pytest.raises(ValueError, match="terrain.direction='sideways'"):
        get_terrain("stairs-up", direction="sideways")
    with pytest.raises(ValueError, match="gap_range"):
        get_terrain("stones", gap_range=[0.09, 0.09])


FAMILIES = ("stairs-up", "stairs-down", "slope-up", "slope-down", "stones", "boxes")
LEVELS = (0.0, 1 / 3, 2 / 3, 1.0)


@pytest.mark.cost(300)
def test_families_walkable_at_zero_and_harder_with_difficulty(tmp_path, default_xla_env):
    """The open-loop Luneckas 2020 tripod (3 cm swing) walks 0.2 m on each new family, 16 envs per family (4 at
    each of difficulties 0, 1/3, 2/3, 1), all in one rollout on the `validated` physics: `hexjax families`, run
    as a user runs it, in a process of its own, on the fastest engine `validated` certifies on the host (MuJoCo C
    with the reference's settings on a CPU: about 20 s, against 5 min of one of 2 cores on MJX).
    At difficulty 0 every env succeeds (upright, within 10 cm of the goal, finite).
    - Stairs up and down, slope up, boxes: success never rises from one level to the next by more than one env's
      share (1/4) and ends at least 75 points below difficulty 0 (they read 0 % at difficulty 1).
    - Slope down: its steepest ramp, 34 deg, is inside the friction cone (tan 34 deg = 0.67 < mu = 1), so a
      converged contact solve holds the stance feet and the tripod walks down at every level: every env
      succeeds, none falls, and the advance at difficulty 1 is within 5 cm of difficulty 0's. (Its earlier 0 %
      at difficulty 1 was the 2-iteration pyramidal solve letting the feet slide: 42 cm advanced on a 20 cm walk.)
    - Stepping stones: harder means shorter, not fallen: the tripod stalls on 5 cm gaps but stays up (its earlier
      falls at 2 Newton iterations were that solver's; docs/robustness.md), so at difficulty 1 it advances at
      least 3 cm less than at 0 and at most 1 of 4 envs falls.
    The features begin at x = 0.1 m, under the front feet, so a 0.2 m walk crosses them."""
    import json
    import subprocess
    import sys

    n, out = 4, tmp_path / "families.json"
    r = subprocess.run([sys.executable, "-m", "hexjax.cli", "families", "--controllers", "gait", "--batch", str(n),
                        "--levels", ",".join(repr(v) for v in LEVELS), "--families", ",".join(FAMILIES),
                        "--distance", "0.2", "--start-x", "0.1", "--json", str(out)],
                       env=default_xla_env, capture_output=True, text=True, timeout=3000)
    assert r.returncode == 0, r.stderr[-2000:]
    assert f"gait x {len(FAMILIES) * len(LEVELS) * n} envs" in r.stderr  # its progress bar over the walk
    res = json.loads(out.read_text())
    from hexjax.sim.physics import pick
    assert res["physics"]["name"] == "validated"
    assert res["physics"]["engine"] == res["config"]["engine"] == pick("validated").engine.name
    rows = {(row["family"], row["difficulty"]): row for row in res["rows"]}
    for f in FAMILIES:
        fam = [rows[(f, d)] for d in LEVELS]
        rates = np.array([row["success_pct"] / 100 for row in fam])
        adv = np.array([row["advance_cm"] / 100 for row in fam])
        falls = np.array([round(row["fall_pct"] * n / 100) for row in fam])
        assert all(row["nan_envs"] == 0 for row in fam), f
        assert rates[0] == 1.0, (f, rates)
        if f == "stones":
            assert adv[-1] <= adv[0] - 0.03 and falls[-1] <= 1, (f, adv, falls)
            continue
        if f == "slope-down":
            assert np.all(rates == 1.0) and falls.sum() == 0 and abs(adv[-1] - adv[0]) < 0.05, (f, rates, adv)
            continue
        assert np.all(np.diff(rates) <= 1 / n + 1e-9), (f, rates)
        assert rates[-1] <= rates[0] - 0.75, (f, rates)
