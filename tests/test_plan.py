"""The Zhao 2018 avoidance planner (Eqs. 1, 3, 5, 6; experiment 1 against Table 2; batched random fields with
a free lane by construction; degenerate inputs), Chen 2019's incenters, torso target and splines, Zhao 2018's
motion planner and Chen 2019's swing optimisation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.plan.avoid import AvoidConfig, capacity_line, clearance, fan, octopus_params, penalty, plan, scores
from hexjax.experiments.papers.zhao2018.table2 import TABLE2, zhao2018_experiment
from hexjax.plan.fields import dist_to_polyline, plan_batch, random_fields


def test_penalty_is_eq5():
    d_min, d_max = 0.05, 0.2
    d = jnp.array([-1.0, 0.0, 0.05, 0.0501, 0.1, 0.125, 0.15, 0.1999, 0.2, 3.0])
    c = np.asarray(penalty(d, d_min, d_max))
    assert c[0] == c[1] == c[2] == 1.0 and c[-1] == c[-2] == 0.0  # the two outer branches, ends included
    assert c[3] > 0.999 and c[-3] < 0.001  # continuous at both ends
    assert np.all(np.diff(c) <= 0)  # falls monotonically from d_min to d_max
    mid = 0.5 * (1 + np.tanh(1 / (0.1 - d_min) + 1 / (0.1 - d_max)))
    assert c[4] == pytest.approx(mid, rel=1e-6)
    assert c[5] == pytest.approx(0.5, abs=1e-6)  # symmetric: 1/(d - d_min) + 1/(d - d_max) = 0 mid-way


def test_clearance_is_eq1():
    p = octopus_params().replace(robot_offsets=jnp.array([[0.0, 0.5], [0.0, -0.5]]), robot_radii=jnp.array([0.3, 0.2]))
    centres = jnp.array([[3.0, 0.5], [0.0, -2.0]])
    radii = jnp.array([0.4, 0.1])
    d = np.asarray(clearance(jnp.array([0.0, 0.0]), p, centres, radii, jnp.array([True, False])))
    assert d[0, 0] == pytest.approx(3.0 - 0.3 - 0.4, abs=1e-6)
    assert d[1, 0] == pytest.approx(np.hypot(3.0, 1.0) - 0.2 - 0.4, abs=1e-6)
    assert np.all(np.isinf(d[:, 1]))  # an invalid obstacle never counts


def test_capacity_line_properties():
    """|w| of Fig. 6 (not in the text), as hexjax reads it: the most at the forward direction (1), falling
    linearly and symmetrically with the angle off forward, floored at 0.1, periodic in 2 pi. These hold
    whatever numbers were read off Table 2."""
    a = np.radians(np.arange(-180.0, 181.0, 5.0))
    w = np.asarray(capacity_line(a + np.pi / 2))
    assert w.max() == pytest.approx(1.0) and a[np.argmax(w)] == 0.0
    np.testing.assert_allclose(w, w[::-1], atol=1e-6)  # symmetric about forward
    off = np.abs(np.degrees(a))
    assert np.all(np.diff(w[off <= 90][np.argsort(off[off <= 90])]) <= 1e-6)  # falls away from forward
    assert w.min() == pytest.approx(0.1) and np.all(w >= 0.1 - 1e-7)
    np.testing.assert_allclose(np.asarray(capacity_line(a + np.pi / 2 + 2 * np.pi)), w, atol=1e-5)
    assert len(fan()) == 36 and np.degrees(fan())[-1] == pytest.approx(175.0)


def test_capacity_reading_is_consistent_with_table2():
    """A consistency check of the reading, not evidence for it: the capacity line's slope (1/150 per deg)
    and the 0.75 m cycle were read off these very Table 2 lengths, so this only guards the constants
    against a typo. What the planner does with them is tested apart (experiment 1 below)."""
    lengths = 0.75 * np.asarray(capacity_line(np.radians([90.0, 75.0, 105.0, 60.0, 135.0, 85.5])))
    steps = np.linalg.norm(np.diff(np.vstack([[0, 0], TABLE2]), axis=0), axis=1)
    # cycles 6, 4, 2, 5, 1, 3 of Table 2 walked at 90, 75, 105, 60, 135 and the target direction (85.5 deg)
    assert lengths == pytest.approx(steps[[5, 3, 1, 4, 0, 2]], abs=2e-3)


def test_scores_prefer_the_target_and_avoid_obstacles():
    p, cfg = octopus_params(), AvoidConfig()
    free = scores(jnp.zeros(2), jnp.array([0.0, 8.0]), p, cfg, jnp.zeros((1, 2)) + 50.0, jnp.ones(1), jnp.ones(1, bool))
    f = np.asarray(free[0])
    assert np.argmin(f) in (18, 36)  # 90 deg or the target direction: both point at (0, 8)
    assert f[36] == pytest.approx(1 / (1 + 1.0), abs=1e-6)  # Eq. 3 with u_i = u_T, |w| = 1, no penalty
    # an obstacle straight ahead makes every candidate that walks into it worse than a sidestep
    blocked = scores(jnp.zeros(2), jnp.array([0.0, 8.0]), p, cfg, jnp.array([[0.0, 1.2]]), jnp.array([0.3]),
                     jnp.ones(1, bool))
    fb = np.asarray(blocked[0])
    assert fb[18] > fb[np.argmin(fb)] and np.argmin(fb) not in (18, 36)
    assert bool(np.asarray(blocked[3])[18])  # walking straight on would overlap the obstacle


def test_experiment1_reaches_the_target_without_overlap():
    """Acceptance: experiment 1 of seed 004 reaches (0, 8) with no circle overlap at any step (checked at
    8 points per time-step), in Table 2's 13 plan cycles, every cycle within 0.2 m of Table 2."""
    r = zhao2018_experiment()
    assert r["reached"] and not r["overlap"]
    assert r["min_clearance"] > r["d_min"]
    assert r["cycles"] == 13
    assert r["max_distance_to_table2"] < 0.2 and r["mean_distance_to_table2"] < 0.1
    end = np.asarray(r["path"][-1])
    assert np.linalg.norm(end - np.array([0.0, 8.0])) <= 0.1


def test_random_fields_batch_plans_every_field_safely():
    fields = random_fields(jax.random.PRNGKey(3), 256, n_obstacles=24)
    # the lane is free by construction: every kept obstacle clears it by the lane's half-width
    d = np.asarray(dist_to_polyline(fields.centres, fields.lane))
    v = np.asarray(fields.valid)
    assert np.all(d[v] > 1.0 + np.asarray(fields.radii)[v])
    assert v.sum(1).min() >= 1
    res, out = plan_batch(fields, repeats=1)
    assert res["collisions"] == 0 and res["min_clearance"]["min"] > 0
    assert res["success_rate"] >= 0.95
    # the batched call plans each field as a single call would
    p, cfg = octopus_params(), AvoidConfig()
    for i in (0, 7, 100):
        one = plan(fields.start[i], fields.target[i], fields.centres[i], fields.radii[i], fields.valid[i], p, cfg)
        np.testing.assert_allclose(np.asarray(one.path), np.asarray(out.path[i]), atol=1e-5)


def test_degenerate_inputs():
    c, r, v = np.array([[0.0, 8.0]]), np.array([0.3]), np.array([True])
    p = octopus_params()
    with pytest.raises(ValueError, match="target inside an obstacle in field"):
        plan_batch(random_fields(jax.random.PRNGKey(0), 2).replace(centres=jnp.zeros((2, 1, 2)) + jnp.array([0.0, 8.0]),
                                                                   radii=jnp.ones((2, 1)) * 0.3,
                                                                   valid=jnp.ones((2, 1), bool),
                                                                   target=jnp.array([[0.0, 8.0], [0.0, 8.0]])))
    from hexjax.plan.avoid import check_inputs
    with pytest.raises(ValueError, match="at least one candidate direction"):
        check_inputs([0, 0], [0, 5], c, r, v, p.replace(angles=jnp.zeros(0), capacity=jnp.zeros(0)), AvoidConfig())
    with pytest.raises(ValueError, match=r"d_min=0.2, d_max=0.2"):
        check_inputs([0, 0], [0, 5], c, r, v, p.replace(d_min=jnp.float32(0.2)), AvoidConfig())
    with pytest.raises(ValueError, match="n_T=0"):
        check_inputs([0, 0], [0, 5], c, r, v, p, AvoidConfig(n_T=0))
    # start at the target: reached with no plan cycle; boxed in on every side: holds, counted stuck
    at = plan(jnp.zeros(2), jnp.zeros(2), jnp.array([[5.0, 5.0]]), jnp.array([0.3]), jnp.ones(1, bool), p)
    assert bool(at.reached) and int(at.cycles) == 0 and float(at.length) == 0.0
    ring = 1.2 * np.stack([np.cos(np.linspace(0, 2 * np.pi, 24, endpoint=False)),
                           np.sin(np.linspace(0, 2 * np.pi, 24, endpoint=False))], -1)
    boxed = plan(jnp.zeros(2), jnp.array([0.0, 8.0]), jnp.asarray(ring), jnp.full(24, 0.35), jnp.ones(24, bool), p,
                 AvoidConfig(max_cycles=4))
    assert not bool(boxed.reached) and int(boxed.stuck) == 4 and float(boxed.length) == 0.0
    assert float(boxed.min_clearance) == pytest.approx(1.2 - 0.1 - 0.6 - 0.35, abs=1e-5)  # it never moved


def test_exact_incenter_is_the_classical_one_on_triangles():
    from hexjax.plan.support import incenter_exact, random_polygons
    poly, valid = random_polygons(jax.random.PRNGKey(5), 2000, 3, 4)  # padded to 4: the mask is honoured
    c, r = jax.vmap(incenter_exact)(poly, valid)
    t = np.asarray(poly[:, :3], float)
    side = np.stack([np.linalg.norm(t[:, 1] - t[:, 2], axis=1), np.linalg.norm(t[:, 2] - t[:, 0], axis=1),
                     np.linalg.norm(t[:, 0] - t[:, 1], axis=1)], 1)  # side opposite each vertex
    centre = np.einsum("nk,nkj->nj", side, t) / side.sum(1, keepdims=True)
    area = 0.5 * np.abs(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]))
    np.testing.assert_allclose(np.asarray(c), centre, atol=2e-5)
    np.testing.assert_allclose(np.asarray(r), 2 * area / side.sum(1), rtol=2e-5)
    # a 2 x 1 rectangle: radius 0.5, centre on its mid-line
    rc, rr = incenter_exact(jnp.array([[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [0.0, 1.0]]), jnp.ones(4, bool))
    assert float(rr) == pytest.approx(0.5, abs=1e-6) and float(rc[1]) == pytest.approx(0.5, abs=1e-6)
    assert 0.5 - 1e-6 <= float(rc[0]) <= 1.5 + 1e-6


def test_iterative_incenter_error_distribution():
    """Chen 2019 Steps 1-5 against the exact centre on 4 x 5000 random convex polygons: never better than
    exact (it is a feasible point), converged on triangles, and within 1e-3 of the exact radius on >= 99 %
    of quadrilaterals to hexagons (the rest stall: its step can only shrink, docs/planning.md)."""
    from hexjax.experiments.papers.chen2019.incenter import incenter_study
    res = incenter_study(jax.random.PRNGKey(11), 5000)
    for k, d in res["by_sides"].items():
        assert d["iterative_exceeds_exact"] == 0, k
        assert d["radius_shortfall"]["p50"] < 1e-5, k
        assert d["within_1e-3"] >= (1.0 if k == "3" else 0.99), (k, d)


def test_boxed_in_robot_holds_its_place_without_collision():
    """Every candidate overlapping an obstacle: the robot holds for every cycle (counted as stuck), never moves
    into one."""
    p, cfg = octopus_params(), AvoidConfig(max_cycles=5)
    ang = np.radians(np.arange(0, 360, 20))
    centres = np.stack([1.2 * np.cos(ang), 1.2 * np.sin(ang)], -1)  # a ring just outside the robot circles
    out = plan(np.zeros(2), np.array([0.0, 8.0]), centres, np.full(len(ang), 0.3), np.ones(len(ang), bool), p, cfg)
    assert int(out.stuck) == 5 and not bool(out.reached)
    np.testing.assert_allclose(np.asarray(out.path), 0.0, atol=1e-6)
    assert float(out.min_clearance) > 0.0


def test_support_polygon_checks():
    from hexjax.plan.support import check_polygons
    ok = np.array([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]])
    check_polygons(ok, np.ones((1, 3), bool))
    with pytest.raises(ValueError, match="polygon 0: collinear or clockwise footholds"):
        check_polygons(np.array([[[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]]), np.ones((1, 3), bool))
    with pytest.raises(ValueError, match="collinear or clockwise"):
        check_polygons(ok[:, ::-1], np.ones((1, 3), bool))
    with pytest.raises(ValueError, match="polygon 1: needs >= 3 valid vertices"):
        check_polygons(np.concatenate([ok, ok]), np.array([[1, 1, 1], [1, 1, 0]], bool))
    with pytest.raises(ValueError, match="not convex"):
        check_polygons(np.array([[[0.0, 0.0], [2.0, 0.0], [0.5, 0.5], [0.0, 2.0]]]), np.ones((1, 4), bool))


def test_clamped_spline_is_eqs4_5():
    from scipy.interpolate import CubicSpline

    from hexjax.plan.support import clamped_spline
    t = np.array([0.0, 0.3, 0.7, 1.2, 2.0])
    y = np.random.default_rng(0).normal(size=(5, 3))  # three joints' path points
    s = clamped_spline(t, y)
    tq = np.linspace(0.0, 2.0, 81)
    np.testing.assert_allclose(np.asarray(s(jnp.asarray(tq))), CubicSpline(t, y, bc_type="clamped")(tq), atol=2e-6)
    np.testing.assert_allclose(np.asarray(s(jnp.asarray(t))), y, atol=1e-6)  # through every path point
    v = (np.asarray(s(jnp.array([1e-3, 2.0]))) - np.asarray(s(jnp.array([0.0, 2.0 - 1e-3])))) / 1e-3
    assert np.abs(v).max() < 0.05  # S'(t_1) = S'(t_N) = 0 (Eq. 5), up to the O(h) of the difference


def test_torso_target_follows_the_foothold_plane_and_eq3():
    from hexjax.plan.support import torso_pitch_roll, torso_target
    # a rectangle of four footholds on a plane rising 0.1 forward (x) and 0.05 to the left (y)
    xy = np.array([[-0.2, -0.15], [0.2, -0.15], [0.2, 0.15], [-0.2, 0.15]])
    z = 0.1 * xy[:, 0] + 0.05 * xy[:, 1] + 0.03
    f = jnp.asarray(np.c_[xy, z])
    out = torso_target(f, jnp.ones(4, bool), 0.0, 0.17, measured_pitch=0.0, measured_roll=0.2, iterative=False)
    assert float(out["margin"]) == pytest.approx(0.15, abs=1e-6)
    x, y, zc = np.asarray(out["xyz"])
    assert abs(y) < 1e-6 and abs(x) <= 0.05 + 1e-6  # a 0.4 x 0.3 rectangle's centres: a segment on y = 0
    assert zc == pytest.approx(0.1 * x + 0.05 * y + 0.03 + 0.17, abs=1e-5)  # h above the plane at the incenter
    assert float(out["pitch"]) == pytest.approx(0.5 * np.arctan(0.1), abs=1e-6)  # Eq. 3
    assert float(out["roll"]) == pytest.approx(0.5 * (np.arctan(0.05) + 0.2), abs=1e-6)
    # facing +y instead, the forward rise is the y gradient and the left rise is minus the x gradient
    turned = torso_target(f, jnp.ones(4, bool), np.pi / 2, 0.17, 0.0, 0.0, iterative=False)
    assert float(turned["pitch"]) == pytest.approx(0.5 * np.arctan(0.05), abs=1e-6)
    assert float(turned["roll"]) == pytest.approx(-0.5 * np.arctan(0.1), abs=1e-6)
    # the measured pose in the same convention: nose up 0.2 rad (about -y), left side up 0.3 rad (about +x)
    q_pitch = jnp.array([np.cos(-0.1), 0.0, np.sin(-0.1), 0.0])
    q_roll = jnp.array([np.cos(0.15), np.sin(0.15), 0.0, 0.0])
    assert np.allclose(np.asarray(torso_pitch_roll(q_pitch)), [0.2, 0.0], atol=1e-6)
    assert np.allclose(np.asarray(torso_pitch_roll(q_roll)), [0.0, 0.3], atol=1e-6)


def _neutral_feet(robot):
    from hexjax.world.robot import hip_positions, mount_yaws
    yaw = mount_yaws(robot)
    return hip_positions(robot)[:, :2] + robot.stance_radial * np.stack([np.cos(yaw), np.sin(yaw)], -1)


@pytest.mark.parametrize("alpha", [0.0, np.pi / 2, 2.5])
def test_tripod_motion_planner_keeps_margin_and_reach(alpha):
    """Zhao 2018 Eqs. 7-18 on the luneckas2020 robot, six tripod steps along alpha: every body target keeps
    delta_s inside its support triangle and every foot inside its workspace; the body moves along alpha
    (Eq. 8), and one candidate further would break a constraint (Eq. 7: the farthest valid move)."""
    from hexjax.plan.motion import TRIPODS, body_move, edge_margins, footholds, motion_params_for
    from hexjax.world.presets import luneckas2020
    robot = luneckas2020()
    p = motion_params_for(robot)
    feet = jnp.asarray(_neutral_feet(robot), jnp.float32)
    body = jnp.zeros(2)
    u = np.array([np.cos(alpha), np.sin(alpha)])
    total = 0.0
    for k in range(6):
        sup, sw = TRIPODS[k % 2], TRIPODS[1 - k % 2]
        target, d, ok = body_move(body, 0.0, alpha, feet[sup], jnp.asarray(sup), p, n=64)
        assert bool(ok) and float(d) > 0
        assert np.allclose(np.asarray(target - body), float(d) * u, atol=1e-5)  # Eq. 8
        assert float(jnp.min(edge_margins(target, feet[sup]))) > float(p.delta_s)  # Eq. 9
        step = float(p.max_step) / 63
        beyond = body + (float(d) + step) * jnp.asarray(u)
        hips = beyond + p.hips[sup]
        dist = np.linalg.norm(np.asarray(feet[sup] - hips), axis=-1)
        broken = (float(jnp.min(edge_margins(beyond, feet[sup]))) <= float(p.delta_s)
                  or np.any(dist < float(p.w_min)) or np.any(dist > float(p.w_max)) or float(d) + step > float(p.max_step))
        assert broken  # Eq. 7: the next candidate is invalid
        new, stride, ok_f = footholds(target, 0.0, alpha, feet[sw], jnp.asarray(sw), p)
        assert bool(ok_f)
        moved = np.asarray(new - feet[sw])
        assert np.allclose(np.cross(moved, u), 0.0, atol=1e-5) and np.all(moved @ u >= -1e-6)  # Eq. 14
        assert float(jnp.min(edge_margins(target, new))) > float(p.delta_s)  # Eq. 15
        dist = np.linalg.norm(np.asarray(new - (target + p.hips[sw])), axis=-1)
        assert np.all(dist >= float(p.w_min)) and np.all(dist <= float(p.w_max))  # Eqs. 16-18
        feet = feet.at[sw].set(new)
        total += float(d)
        body = target
    assert total > 0.2  # six steps walk on (CPU figures: 0.28-0.70 m for these directions)


def test_semi_ellipse_swing():
    from hexjax.plan.motion import swing_path
    a, b = jnp.array([0.0, 0.0, 0.0]), jnp.array([0.1, 0.02, 0.01])
    path = np.asarray(swing_path(a, b, 0.05, jnp.linspace(0.0, 1.0, 101)))
    assert np.allclose(path[0], a) and np.allclose(path[-1], b, atol=1e-6)
    assert path[50, 2] == pytest.approx(0.005 + 0.05, abs=1e-6)  # apex above the chord's midpoint
    assert np.all(path[1:-1, 2] > np.linspace(0, 0.01, 101)[1:-1] - 1e-9)  # never below the chord


def test_swing_optimisation_clears_terrain_batched():
    """Chen 2019 Sect. 2.3 as a batched JAX optimisation: over 32 random boxes 0-7 cm high under the swing
    chord of `luneckas2020`, every planned swing starts and ends at its footholds, keeps the clearance
    constraint to 0.5 mm, respects the joint limits, and needs less effort than its semi-ellipse start
    where that start was feasible."""
    from hexjax.plan.swing import SwingConfig, optimise_swing
    from hexjax.world.presets import luneckas2020
    robot = luneckas2020()
    h = robot.hip_height - robot.foot_radius
    start, end = jnp.array([0.13, -0.04, -h]), jnp.array([0.13, 0.04, -h])
    key = jax.random.PRNGKey(0)
    pos = jax.random.uniform(key, (32,), minval=0.3, maxval=0.7)
    top = jax.random.uniform(jax.random.fold_in(key, 1), (32,), minval=0.0, maxval=0.07)
    grid = jnp.linspace(0.0, 1.0, 32)
    profile = -robot.hip_height + top[:, None] * (jnp.abs(grid[None] - pos[:, None]) < 0.15)
    cfg = SwingConfig()
    out = jax.jit(jax.vmap(lambda pr: optimise_swing(robot, cfg, start, end, pr)))(profile)
    foot = np.asarray(out["foot"])
    assert np.allclose(foot[:, 0], np.asarray(start), atol=2e-5) and np.allclose(foot[:, -1], np.asarray(end), atol=2e-5)
    assert float(jnp.max(out["violation"])) < 5e-4
    assert float(jnp.max(out["limit_violation"])) < 1e-3
    ratio = np.asarray(out["effort"] / out["start_effort"])
    feasible_start = np.asarray(out["start_violation"]) <= 1e-4  # an infeasible start may need more effort
    assert feasible_start.sum() >= 8 and np.all(ratio[feasible_start] < 1.0) and np.median(ratio) < 0.6
    # the tallest box is cleared by the margin mid-swing: the foot rises above it
    i = int(jnp.argmax(top))
    assert foot[i, :, 2].max() - robot.foot_radius > float(profile[i].max())
