"""The gate forms of `hexjax.control.gates`: hard, smooth and straight-through."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.control.cpg import CPGController
from hexjax.control.gates import hard_gate, sigmoid_gate, straight_through_gate
from hexjax.control.tactile import TactileGaitController
from hexjax.world.presets import get_robot


def test_straight_through_gate_has_the_step_value_and_the_sigmoid_derivatives():
    x = jnp.array([-0.4, -0.02, 0.0, 0.01, 0.3])
    temp = jnp.float32(0.05)
    np.testing.assert_array_equal(np.asarray(straight_through_gate(x, temp)), [0.0, 0.0, 0.0, 1.0, 1.0])
    np.testing.assert_array_equal(np.asarray(sigmoid_gate(x, temp, True)), np.asarray(hard_gate(x)))
    np.testing.assert_allclose(np.asarray(sigmoid_gate(x, temp)), np.asarray(jax.nn.sigmoid(x / temp)))
    # both partial derivatives equal the sigmoid's, under jit and vmap, and a broadcast temperature is summed
    for arg in (0, 1):
        st = jax.jit(jax.vmap(jax.grad(straight_through_gate, arg), (0, None)))(x, temp)
        soft = jax.vmap(jax.grad(lambda a, t: jax.nn.sigmoid(a / t), arg), (0, None))(x, temp)
        np.testing.assert_allclose(np.asarray(st), np.asarray(soft), rtol=1e-5, atol=1e-9)
        assert np.any(np.asarray(st) != 0.0)
    g_t = jax.grad(lambda t: jnp.sum(straight_through_gate(x, t)))(temp)
    np.testing.assert_allclose(float(g_t), float(jax.grad(lambda t: jnp.sum(jax.nn.sigmoid(x / t)))(temp)), rtol=1e-5)
    # forward mode too
    _, tan = jax.jvp(straight_through_gate, (x, temp), (jnp.ones_like(x), jnp.float32(0.0)))
    s = jax.nn.sigmoid(x / temp)
    np.testing.assert_allclose(np.asarray(tan), np.asarray(s * (1 - s) / temp), rtol=1e-5)


def test_straight_through_needs_the_smooth_form():
    """It changes the smooth form's derivative; asked of a hard controller it would do nothing, so it is refused."""
    with pytest.raises(ValueError, match="straight_through=True needs smooth=True"):
        CPGController(get_robot("yu2019"), straight_through=True)
    with pytest.raises(ValueError, match="straight_through=True needs smooth=True"):
        TactileGaitController(get_robot("luneckas2020"), straight_through=True)
    assert TactileGaitController(get_robot("luneckas2020"), smooth=True, straight_through=True).straight_through
