import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.control.gait import GAITS, GaitController, leg_trajectory
from hexjax.world.presets import luneckas2020
from hexjax.world.robot import body_to_leg, leg_fk


def test_leg_trajectory_hand_values():
    """Luneckas 2020 Eqs. 2-4 (continuous reading), l = 0.04 m, h = 0.03 m, T = 2, phi = 0."""
    f = jax.jit(lambda t: leg_trajectory(t, 0.0, 2, 0.04, 0.03, 0.0))
    x, y, z = f(jnp.array([0.0, 0.5, 1.0, 1.5, 2.0]))
    np.testing.assert_allclose(np.asarray(x), [-0.02, 0.0, 0.02, 0.0, -0.02], atol=1e-7)
    np.testing.assert_allclose(np.asarray(z), [0.0, 0.03, 0.0, 0.0, 0.0], atol=1e-7)
    np.testing.assert_allclose(np.asarray(y), 0.0, atol=1e-7)
    # direction eps rotates the stroke: eps = 90 deg moves along y
    x, y, _ = jax.jit(lambda t: leg_trajectory(t, 0.0, 2, 0.04, 0.03, math.pi / 2))(jnp.array(0.5 + 0.25))
    assert abs(float(x)) < 1e-7 and float(y) == pytest.approx(0.01, abs=1e-7)


def test_leg_trajectory_continuous_and_periodic():
    for period in (2, 6):
        t = jnp.linspace(0, 3 * period, 6001)
        x, _, z = jax.jit(lambda t: leg_trajectory(t, 1.0, period, 0.05, 0.03, 0.0))(t)
        dt = float(t[1] - t[0])
        assert np.abs(np.diff(np.asarray(x))).max() <= 0.05 * dt * 1.01  # no jumps: slope <= l per unit
        assert np.abs(np.diff(np.asarray(z))).max() <= 0.03 * math.pi * dt * 1.01


def test_gait_leg_orders():
    """Tripod: LM, RF, RH swing in the first half; LF, LH, RM in the second. Wave: LF, LM, LH, RF, RM, RH."""
    tri = GAITS["tripod"]
    first = {n for n, p in zip(("LF", "LM", "LH", "RF", "RM", "RH"), tri.phases) if p == 0}
    assert first == {"LM", "RF", "RH"}
    assert GAITS["wave"].phases == (0, 1, 2, 3, 4, 5)
    # paper's speeds and steps per metre (Sect. 3.3)
    assert tri.cycle_advance * 13 == pytest.approx(1.0)
    assert tri.cycle_advance / (tri.swing_time * 2) == pytest.approx(0.036)
    wave = GAITS["wave"]
    assert wave.cycle_advance / (wave.swing_time * 6) == pytest.approx(0.013)


def test_controller_targets_track_trajectory_through_ik():
    spec = luneckas2020()
    c = GaitController(spec, gait="wave", n_cycles=4)
    p = c.default_params()
    st = c.init(p, jax.random.PRNGKey(0))
    step = jax.jit(lambda s: c.step(p, s, None))
    for _ in range(int(1.5 * c.cycle_time / c.dt)):  # past the ramp-in
        st, q = step(st)
    feet = c.foot_targets(p, st.t - c.dt)
    fk = leg_fk(spec, q.reshape(6, 3))
    np.testing.assert_allclose(np.asarray(fk), np.asarray(body_to_leg(spec, feet)), atol=1e-5)
    # exactly one wave leg off the ground at a time
    lifted = np.asarray(feet[:, 2] - c.foot_targets(p, 0.0)[:, 2]) > 1e-4
    assert lifted.sum() <= 1


def test_grad_of_gait_params_matches_finite_differences():
    """jax.grad of a foot-target function reaches every swept gait param with the sign and size of central
    differences (the trajectory is smooth in them away from the swing boundaries)."""
    spec = luneckas2020()
    c = GaitController(spec)
    p = c.default_params()
    f = jax.jit(lambda prm: c.foot_targets(prm, 1.7)[0, 0] + c.foot_targets(prm, 0.3)[:, 2].sum()
                + c.foot_targets(prm, 2.6)[3, 1])
    g = jax.grad(f)(p)
    eps = 1e-4
    for name in ("step_length", "step_height", "swing_time", "direction"):
        v = float(getattr(p, name))
        at = lambda x: float(f(p.replace(**{name: jnp.asarray(x)})))
        fd = (at(v + eps) - at(v - eps)) / (2 * eps)
        ad = float(getattr(g, name))
        assert abs(fd) > 1e-3, (name, fd)  # the function does depend on it here
        assert np.sign(ad) == np.sign(fd) and abs(ad - fd) <= 2e-2 * abs(fd), (name, ad, fd)


def test_bad_gait_and_params():
    spec = luneckas2020()
    with pytest.raises(ValueError, match="gait='gallop'"):
        GaitController(spec, gait="gallop")
    c = GaitController(spec)
    with pytest.raises(ValueError, match="step_length"):
        c.validate_params(c.default_params().replace(step_length=jnp.asarray(-0.01)))
