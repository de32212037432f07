"""Gates of the papers' switching controllers, in three forms for three uses.

A gate is 1 where x > 0 and 0 elsewhere: the tactile switch of Luneckas 2020 (Eq. 5's touch test) and the
sensory neurons and event tests of Yu 2019 (Eqs. 8-11) are all of this kind.

  hard              the step function: what the papers run and what every evaluation runs; its derivative
                    is 0 almost everywhere, so no gradient passes a switching decision.
  smooth            sigmoid(x / temp): differentiable, but the rollout it drives is another controller. For
                    the Yu 2019 CPG at Table 1's rate the difference is large (docs/tuning.md: the smooth robot
                    advances 7 mm in 20 s where the hard one advances 0.23-0.57 m).
  straight-through  the step function's value with the sigmoid's derivative (the straight-through estimator
                    of Bengio et al. 2013, "Estimating or propagating gradients through stochastic neurons"):
                    the rollout is the hard one, bit for bit, and reverse mode sees each gate as the sigmoid
                    of `temp` it would be in the smooth form, evaluated at the hard rollout's x.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def hard_gate(x):
    """1 where x > 0, else 0, in x's dtype."""
    return (x > 0).astype(jnp.result_type(x))


@jax.custom_jvp
def straight_through_gate(x, temp):
    """`hard_gate(x)` in value; derivative that of sigmoid(x / temp) (module docstring). x and temp broadcast."""
    return jnp.broadcast_to(hard_gate(x), jnp.broadcast_shapes(jnp.shape(x), jnp.shape(temp)))


@straight_through_gate.defjvp
def _straight_through_jvp(primals, tangents):
    x, temp = primals
    dx, dtemp = tangents
    s = jax.nn.sigmoid(x / temp)
    slope = s * (1.0 - s) / temp  # d sigmoid(x / temp) / dx
    return straight_through_gate(x, temp), slope * (dx - x * dtemp / temp)


def sigmoid_gate(x, temp, straight_through: bool = False):
    """The gate a smooth controller uses: sigmoid(x / temp), or with `straight_through` (static) the hard
    value with the sigmoid's derivative."""
    return straight_through_gate(x, temp) if straight_through else jax.nn.sigmoid(x / temp)
