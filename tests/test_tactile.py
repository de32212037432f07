"""Tactile obstacle overcoming (Luneckas 2020 Eqs. 5-7): the switch, its geometry, hard vs smooth, and MJX."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.control.gait import GaitController
from hexjax.control.tactile import TactileGaitController, overcome_height
from hexjax.sim.model import Obs
from hexjax.world.presets import luneckas2020
from hexjax.world.robot import N_LEGS, body_to_leg, leg_fk, neutral_feet_body


def _obs(force):
    z = jnp.zeros
    return Obs(qpos=z(18), qvel=z(18), torso_pos=z(3), torso_quat=jnp.array([1.0, 0, 0, 0]), foot_force=z((6, 3)),
               foot_contact=jnp.zeros(6, bool), tactile_force=force, tactile=force > 0.3, time=z(()))


def _drive(ctrl, params, forces):
    """Run ctrl.step over a (T, 6) schedule of pad forces; returns per-tick foot targets (T, 6, 3) in the
    torso frame (from the joint command through FK), gates (T, 6) and swing phase s (T, 6)."""
    robot = ctrl.robot

    def tick(st, f):
        st2, q = ctrl.step(params, st, _obs(f))
        feet_leg = leg_fk(robot, q.reshape(6, 3))
        return st2, (feet_leg, st2.gate, st.t)

    st0 = ctrl.init(params, jax.random.PRNGKey(0))
    _, (feet_leg, gates, ts) = jax.jit(lambda f: jax.lax.scan(tick, st0, f))(forces)
    p = ctrl.pattern
    s = np.mod(np.asarray(ts)[:, None] / float(params.swing_time) - np.asarray(p.phases)[None], p.period)
    return np.asarray(feet_leg), np.asarray(gates), s


@pytest.mark.parametrize("gait", ["tripod", "wave"])
def test_switch_never_changes_mid_swing(gait):
    """Acceptance: forced tactile pulses, many of them mid-swing. Each swing keeps one gate from lift-off to
    touchdown; a pulse changes only the leg's next step, never the step it fires in; a step after a pulse is
    the overcoming one (apex h_k), a step after a quiet step is the basic one (apex h_i)."""
    robot = luneckas2020()
    ctrl = TactileGaitController(robot, gait=gait, max_obstacle_height=0.05)
    params = ctrl.default_params()
    n = int(8 * ctrl.cycle_time / ctrl.dt)
    rng = np.random.default_rng(0)
    forces = np.zeros((n, N_LEGS), np.float32)
    pat = ctrl.pattern
    s_all = np.mod(np.arange(n)[:, None] * ctrl.dt / float(params.swing_time) - np.asarray(pat.phases)[None], pat.period)
    for leg in range(N_LEGS):  # per leg: 1-3 tick pulses in the middle of two random swings and one in stance
        mids = np.nonzero((np.abs(s_all[:, leg] - 0.5) < 0.5 * ctrl.dt / float(params.swing_time))
                          & (np.arange(n) > n // 8) & (np.arange(n) < n - 40))[0]
        stance = np.nonzero((s_all[:, leg] > 1.3) & (np.arange(n) > n // 8) & (np.arange(n) < n - 40))[0]
        for t0 in list(rng.choice(mids, 2, replace=False)) + [rng.choice(stance)]:
            forces[t0:t0 + rng.integers(1, 4), leg] = 2.0
    feet, gates, s = _drive(ctrl, params, jnp.asarray(forces))
    quiet, _, _ = _drive(ctrl, params, jnp.zeros((n, N_LEGS)))
    swing = s < 1.0
    pulses_mid_swing = 0
    hi, hk = float(params.step_height), float(params.overcome_height)
    z0 = np.asarray(body_to_leg(robot, jnp.asarray(neutral_feet_body(robot))))[:, 2]
    for leg in range(N_LEGS):
        starts = np.nonzero(swing[1:, leg] & ~swing[:-1, leg])[0] + 1
        for j, a in enumerate(starts):
            b = a + np.argmax(~swing[a:, leg]) if (~swing[a:, leg]).any() else n
            if b - a < 3 or b >= n:
                continue
            assert np.all(gates[a:b, leg] == gates[a, leg]), f"gate changed mid-swing, leg {leg}, ticks {a}-{b}"
            # the previous step of this leg: from the tick after its lift-off to this lift-off (the reading at
            # a lift-off tick still belongs to the step that ends there)
            lo = starts[j - 1] + 1 if j > 0 else 0
            touched_before = forces[lo:a + 1, leg].max() > 0.3
            assert gates[a, leg] == float(touched_before)
            apex = feet[a:b, leg, 2].max() - z0[leg]
            assert apex == pytest.approx(hk if touched_before else hi, abs=0.004)
            pulses_mid_swing += int(forces[a + 1:b - 1, leg].max() > 0)
            # a pulse inside this swing leaves this swing as in the quiet run, as long as this step and the
            # one before it were basic in both runs
            if forces[:a + 1, leg].max() == 0:
                np.testing.assert_allclose(feet[a:b, leg], quiet[a:b, leg], atol=1e-6)
    assert pulses_mid_swing >= 8  # the schedule did fire in the middle of swings


def test_basic_steps_are_eqs_2_to_4_and_overcoming_geometry():
    """With no touch the targets are the seed-000 trajectory (Eqs. 2-4, same as GaitController). An
    overcoming step lands l_k - l_i further forward at apex h_k; every stance moves the foot back at the
    basic pace (l_i over T - 1 slots, no slip against the other stance legs); the next basic step lands at
    +l_i / 2 again."""
    robot = luneckas2020()
    for gait in ("tripod", "wave"):
        ctrl = TactileGaitController(robot, gait=gait)
        p = ctrl.default_params()
        base = GaitController(robot, gait=gait)
        bp = base.default_params()
        T = ctrl.pattern.period
        tt = jnp.linspace(ctrl.cycle_time * 1.01, ctrl.cycle_time * 3, 97)
        z6 = jnp.zeros(6)
        ours = jax.vmap(lambda t: ctrl.foot_offsets(p, t, z6, z6))(tt)
        ref = jax.vmap(lambda t: base.foot_targets(bp, t))(tt) - jnp.asarray(neutral_feet_body(robot))
        np.testing.assert_allclose(np.asarray(ours), np.asarray(ref), atol=1e-6)
        li, lk, hk = float(p.step_length), float(p.overcome_length), float(p.overcome_height)
        sw = float(p.swing_time)
        leg = list(ctrl.pattern.phases).index(0)  # its swing spans [k T, k T + 1) swing units
        t_cycle = 2 * T * sw  # a time after the ramp-in, at a lift-off of leg 0
        one, zero = z6.at[leg].set(1.0), z6
        f = lambda u, g, gp: np.asarray(ctrl.foot_offsets(p, t_cycle + u * sw, g, gp))[leg]
        assert f(0.0, one, zero)[0] == pytest.approx(-0.5 * li, abs=1e-6)  # lifts off where the basic stance ended
        assert f(0.5, one, zero)[2] == pytest.approx(hk, abs=1e-6)  # apex h_k
        assert f(1.0, one, zero)[0] == pytest.approx(lk - 0.5 * li, abs=1e-6)  # transfer of l_k
        # stance at the basic pace
        slope = (f(1.0 + 0.5 * (T - 1), one, zero)[0] - f(1.0, one, zero)[0]) / (0.5 * (T - 1))
        assert slope == pytest.approx(-li / (T - 1), rel=1e-4)
        # the next step, basic, starts where that stance ended and lands at +l_i / 2
        assert f(0.0, zero, one)[0] == pytest.approx(lk - 1.5 * li, abs=1e-6)
        assert f(1.0 - 1e-6, zero, one)[0] == pytest.approx(0.5 * li, abs=1e-5)
        assert f(0.5, zero, one)[2] == pytest.approx(float(p.step_height), abs=1e-6)
        # with l_k = l_i and h_k = h_i the overcoming step is the basic one
        p_same = p.replace(overcome_length=p.step_length, overcome_height=p.step_height)
        np.testing.assert_allclose(np.asarray(ctrl.foot_offsets(p_same, t_cycle + 0.3 * sw, one, one)),
                                   np.asarray(ctrl.foot_offsets(p_same, t_cycle + 0.3 * sw, zero, zero)), atol=1e-7)


def test_paper_hand_rules_and_validation():
    robot = luneckas2020()
    c = TactileGaitController(robot, gait="wave", max_obstacle_height=0.08)
    p = c.default_params()
    assert float(p.overcome_length) == pytest.approx(2 * float(p.step_length))  # Eq. 6
    assert float(p.overcome_height) == pytest.approx(0.08 + 0.02)  # Eq. 7
    assert float(overcome_height(0.05)) == pytest.approx(0.07)
    assert float(c.default_params(enable=0.0).enable) == 0.0
    with pytest.raises(ValueError, match=r"tactile.wingspan: unknown parameter"):
        c.default_params(wingspan=1.0)
    with pytest.raises(ValueError, match="overcome_height"):
        c.validate_params(p.replace(overcome_height=jnp.asarray(-0.01)))
    with pytest.raises(ValueError, match="tactile_threshold"):
        c.validate_params(p.replace(tactile_threshold=jnp.asarray(float("nan"))))
    with pytest.raises(ValueError, match="enable"):
        c.validate_params(p.replace(enable=jnp.asarray(2.0)))
    with pytest.raises(ValueError, match="max_obstacle_height"):
        TactileGaitController(robot, max_obstacle_height=-1.0)
    with pytest.raises(ValueError, match="gait='trot'"):
        TactileGaitController(robot, gait="trot")
    # the commanded advance reaches the planned distance at the end of the walk (ramps included)
    n, _ = c.duration_for(1.0, p)
    c2 = TactileGaitController(robot, gait="wave", n_cycles=n)
    assert float(c2.commanded_advance(p, 1e3)) == pytest.approx(1.0, abs=1e-4)


def test_smooth_gate_tends_to_hard_and_has_gradients():
    robot = luneckas2020()
    hard = TactileGaitController(robot, gait="tripod")
    smooth = TactileGaitController(robot, gait="tripod", smooth=True)
    p = hard.default_params()
    forces = jnp.array([0.0, 0.1, 0.29, 0.31, 0.5, 3.0])
    g_hard = np.asarray(hard._gate(p, forces))
    np.testing.assert_array_equal(g_hard, [0, 0, 0, 1, 1, 1])
    for temp, tol in ((1e-2, 0.5), (1e-3, 1e-4)):
        g = np.asarray(smooth._gate(p.replace(temperature=jnp.asarray(temp)), forces))
        assert np.max(np.abs(g - g_hard)) <= tol
    # d(foot apex)/d(h_k) through the smooth gate, and d/d(threshold) near the threshold
    t = 2 * hard.cycle_time + 0.5 * float(p.swing_time)

    def apex(prm):
        g = smooth._gate(prm, jnp.full(6, 0.32))
        return smooth.foot_offsets(prm, t, g, jnp.zeros(6))[:, 2].sum()

    gr = jax.grad(apex)(p)
    assert float(gr.overcome_height) > 0 and float(gr.tactile_threshold) < 0
    assert all(np.isfinite(float(x)) for x in jax.tree_util.tree_leaves(gr))


@pytest.mark.cost(50)
def test_mjx_pad_touch_raises_the_next_step():
    """In MJX: one wide, 5 cm high bar across the path. With the method, legs whose pads touch it take
    overcoming steps (gates recorded), the feet rise higher than the basic swing allows, and the robot ends
    further along than without the method on the same terrain."""
    from hexjax.sim.config import RolloutConfig
    from hexjax.sim.rollout import rollout
    from hexjax.world.terrain import Terrain

    robot = luneckas2020()
    ctrl = TactileGaitController(robot, gait="tripod", max_obstacle_height=0.05, n_cycles=9)
    bar = Terrain(box_pos=jnp.array([[0.26, 0.0, 0.025]]), box_half=jnp.array([[0.012, 0.35, 0.025]]),
                  box_valid=jnp.array([True]), ground_z=jnp.zeros(()))
    terr = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), bar)
    params = jax.tree_util.tree_map(lambda *a: jnp.stack(a), ctrl.default_params(enable=0.0),
                                    ctrl.default_params(enable=1.0))
    _, dur = ctrl.duration_for(0.6)
    s = rollout(robot, terr, ctrl, params, dur, jax.random.PRNGKey(0), params_batched=True,
                config=RolloutConfig(record=True, yaw_noise=0.0))
    n_over = np.asarray(s.final_state.n_overcome).sum(-1)
    assert n_over[0] == 0 and n_over[1] >= 2
    assert np.asarray(s.tactile_steps)[0].sum() > 0  # the bar does touch the pads
    gates = np.asarray(s.ctrl_trace["gate"][1])
    assert gates.max() == 1.0
    feet_z = np.asarray(s.foot_trace)[..., 2]
    assert feet_z[1].max() > feet_z[0].max() + 0.01
    adv = np.asarray(s.end_pose[:, 0] - s.start_pose[:, 0])
    assert adv[1] > adv[0] + 0.05
    assert not np.asarray(s.nan).any()
