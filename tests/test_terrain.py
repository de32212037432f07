import jax
import numpy as np
import pytest

from hexjax.world.presets import get_terrain
from hexjax.world.files import preset_names
from hexjax.world.terrain import LUNECKAS2020_CATEGORIES, heightmap, obstacle_circles, sample

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
        np.testing.assert_allclose(bottom[valid], np.broadcast_to(np.where(spec.kind == "ditch", gz, 0.0)[:, None],
                                                                  bottom.shape)[valid], atol=1e-6, err_msg=name)
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
