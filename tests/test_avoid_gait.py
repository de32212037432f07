"""The avoidance planner steering the MJX hexapod (hexjax.control.avoid_gait, hexjax.experiments.papers.zhao2018:
Zhao 2018 Sect. 3.2 in the loop)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.control.avoid_gait import AvoidGaitController, field_params
from hexjax.experiments.papers.zhao2018.closed_loop import obstacle_boxes, run_closed_loop, touches
from hexjax.plan.fields import Fields, dist_to_polyline, small_fields
from hexjax.sim.model import Obs
from hexjax.sim.rollout import rollout
from hexjax.world.presets import get_robot
from hexjax.world.terrain import Terrain

ROBOT = get_robot("luneckas2020")


def _one_block(n=2):
    """n copies of a field with one obstacle (r 0.12 m) on the straight line to the target 1.6 m ahead."""
    return Fields(start=jnp.zeros((n, 2)), target=jnp.tile(jnp.array([[1.6, 0.05]]), (n, 1)),
                  centres=jnp.tile(jnp.array([[[0.8, 0.0]]]), (n, 1, 1)), radii=jnp.full((n, 1), 0.12),
                  valid=jnp.ones((n, 1), bool), lane=jnp.zeros((n, 2, 2)))


@pytest.mark.cost(80)
def test_planner_steers_the_mjx_robot_round_an_obstacle_a_blind_one_hits_it():
    """Acceptance, in small: with the planner the simulated robot reaches the target without touching the
    box on its straight line; with the same planner told of no obstacles it walks into the box."""
    f = _one_block()
    res = run_closed_loop(fields=f, seed=1)
    m = res["mjx"]
    assert res["kinematic"]["success_rate"] == 1.0
    assert m["success_rate_all"] == 1.0 and m["touched"] == 0 and m["fell"] == 0
    assert m["final_distance_m"]["max"] <= res["config"]["goal_tol"] + 0.03
    assert m["circle_clearance_m"]["min"] > 0.0  # the enveloping circle never overlapped the obstacle's
    assert m["path_ratio_mean"] > 1.01  # it went round
    blind = run_closed_loop(fields=f, seed=1, blind=True, duration=res["config"]["duration_s"])
    assert blind["mjx"]["touched"] == 2 and blind["mjx"]["success_rate_all"] == 0.0


def test_perceiving_planner_finds_the_obstacle_and_steers_round_it():
    """Zhao 2018 Sect. 5 in the loop: the same field, the planner told nothing but what the LiDAR preset finds.
    The control step scans every `perceive_every` steps; the map's RANSAC ground is the floor; a circle stands
    where the box is; the robot reaches the target without touching it, going round as the privileged one does."""
    from hexjax.control.perceive_gait import PerceivingAvoidGait
    from hexjax.perceive.grid import GridSpec
    from hexjax.perceive.sensors import get_sensor
    f = _one_block()
    ctrl = PerceivingAvoidGait(ROBOT, sensor=get_sensor("velodyne_puck"), perceive_every=5,
                               grid=GridSpec.covering((-0.5, -1.0), (2.2, 1.0), 0.04))
    res = run_closed_loop(fields=f, seed=1, controller=ctrl)
    m, fin = res["mjx"], res["_final"]
    n_ctrl = int(np.ceil(res["config"]["duration_s"] / ctrl.dt - 1e-9))
    assert np.all(np.asarray(fin.scans) == -(-n_ctrl // 5))
    np.testing.assert_allclose(np.asarray(fin.ground_normal), [[0, 0, 1]] * 2, atol=2e-3)
    assert np.all(np.abs(np.asarray(fin.ground_offset)) < 0.005)
    cen, valid = np.asarray(fin.circ.centres), np.asarray(fin.circ.valid)
    near = np.linalg.norm(cen - np.array([0.8, 0.0]), axis=-1) < 0.15
    assert np.all((near & valid).any(1)), (cen, valid)
    assert m["success_rate_all"] == 1.0 and m["touched"] == 0 and m["fell"] == 0
    assert m["path_ratio_mean"] > 1.01


def test_direction_changes_only_at_plan_cycles_and_feet_stay_continuous():
    """Without physics: a torso carried along a line past an obstacle. The chosen heading changes only at
    gait-time multiples of n_T cycles, and the joint targets move by less than 0.15 rad per 20 ms step."""
    ctrl = AvoidGaitController(ROBOT)
    f = _one_block(1)
    p = jax.tree_util.tree_map(lambda x: x[0], field_params(ctrl, f))
    cycle = float(p.gait.swing_time) * ctrl.pattern.period
    n = int(6 * cycle / ctrl.dt)

    def body(st, i):
        x = 0.15 + 0.1 * i * ctrl.dt / 6  # the torso creeps towards the obstacle
        obs = Obs(qpos=jnp.zeros(18), qvel=jnp.zeros(18), torso_pos=jnp.array([x, 0.0, 0.1]),
                  torso_quat=jnp.array([1.0, 0, 0, 0]), foot_force=jnp.zeros((6, 3)), foot_contact=jnp.zeros(6, bool),
                  tactile_force=jnp.zeros(6), tactile=jnp.zeros(6, bool), time=i * ctrl.dt)
        st2, a = ctrl.step(p, st, obs)
        return st2, (a, st2.heading_to, st.k * ctrl.dt, st2.plans)

    _, (act, head, t, plans) = jax.lax.scan(body, ctrl.init(p, None), jnp.arange(n))
    act, head, t, plans = map(np.asarray, (act, head, t, plans))
    changed = np.flatnonzero(np.diff(plans) > 0) + 1
    plan_t = t[changed]
    period = ctrl.avoid.n_T * cycle
    assert plans[-1] == 3 and np.allclose(plan_t / period, np.round(plan_t / period), atol=1e-3)
    assert np.all(np.diff(head)[np.diff(plans) == 0] == 0)  # no heading change between plans
    assert abs(head[-1]) > 0.2  # it turned away from the obstacle ahead
    assert np.max(np.abs(np.diff(act, axis=0))) < 0.15


def test_touch_check_sees_a_box_under_a_leg_and_not_one_beside_it():
    t = 5
    trace = np.zeros((2, t, 4))
    trace[:, :, 0] = np.linspace(0, 0.2, t)
    foot = np.tile(np.array([[0.18, 0.16, 0], [0.0, 0.2, 0], [-0.18, 0.16, 0], [0.18, -0.16, 0], [0.0, -0.2, 0],
                             [-0.18, -0.16, 0]]), (2, t, 1, 1)) + trace[:, :, None, :3] * np.array([1, 1, 0])
    # env 0: a small box between the hip and foot of LM; env 1: the same box 10 cm beyond the foot
    pos = np.array([[[0.1, 0.15, 0.1]], [[0.1, 0.32, 0.1]]])
    terr = Terrain(box_pos=jnp.asarray(pos), box_half=jnp.full((2, 1, 3), 0.02), box_valid=jnp.ones((2, 1), bool),
                   ground_z=jnp.zeros(2))
    hit = touches(ROBOT, jnp.asarray(trace), jnp.asarray(foot), terr)
    assert hit.tolist() == [True, False]


def test_closed_loop_bad_input():
    ctrl = AvoidGaitController(ROBOT)
    f = _one_block(1)
    bad = f.replace(target=jnp.array([[0.8, 0.02]]))  # inside the obstacle
    terr = obstacle_boxes(jax.random.PRNGKey(0), f)
    with pytest.raises(ValueError, match="target inside an obstacle"):
        rollout(ROBOT, terr, ctrl, field_params(ctrl, bad), 1.0, jax.random.PRNGKey(0), params_batched=True)
    p = field_params(ctrl, f)
    with pytest.raises(ValueError, match=r"d_min=0.2, d_max=0.12"):
        rollout(ROBOT, terr, ctrl, p.replace(avoid=p.avoid.replace(d_min=jnp.full((1,), 0.2))), 1.0,
                jax.random.PRNGKey(0), params_batched=True)
    with pytest.raises(ValueError, match="at least one candidate direction"):
        rollout(ROBOT, terr, ctrl, p.replace(avoid=p.avoid.replace(angles=jnp.zeros((1, 0)),
                                                                    capacity=jnp.zeros((1, 0)))),
                1.0, jax.random.PRNGKey(0), params_batched=True)
    with pytest.raises(ValueError, match="start"):
        run_closed_loop(fields=f.replace(start=jnp.ones((1, 2))))
    with pytest.raises(ValueError, match="avoid.n_T"):
        AvoidGaitController(ROBOT, avoid=ctrl.avoid.__class__(n_T=0))


def test_small_fields_keep_a_lane_free():
    f = small_fields(jax.random.PRNGKey(0), 64, 0.256, 0.12)
    d = np.asarray(dist_to_polyline(f.centres, f.lane))
    v = np.asarray(f.valid)
    assert np.all(d[v] > 0.256 + 0.12 + np.asarray(f.radii)[v])
    assert np.all(np.asarray(f.target)[:, 0] == 2.0) and np.all(np.abs(np.asarray(f.target)[:, 1]) <= 0.3)
