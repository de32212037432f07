"""What `hexjax.sim.model` reads of MJX's and MuJoCo Warp's private code: the order of MJX's contact slots, the
contact forces decoded from the solver's rows, and Warp's overflow flags (its prints off, its per-world bitmask
read). Each relies on private names of the pinned mujoco-mjx (`hexjax.private_reach`)."""

from __future__ import annotations

import numpy as np

from hexjax.sim.internals.rules import mjx


def contact_geoms(mx, d) -> np.ndarray:
    """(ncon, 2) geom ids of MJX's contact slots, in the order mjx.forward fills them."""
    from mujoco.mjx._src import collision_driver as cd
    groups = cd._contact_groups(mx, d)
    return np.concatenate([np.repeat(np.asarray(c.geom), cd._COLLISION_FUNC[k.types].ncon, axis=0)
                           for k, c in groups.items()])


def contact_forces(m, d):
    """(force (ncon, 3) in each contact's frame: normal, tangent 1, tangent 2; the contact index of each row) of
    one env, from the constraint solver's forces (MuJoCo's mj_contactForce, any cone)."""
    return mjx._src.support.contact_force_dim(m, d, 3)


def quiet_overflow(mjx_model):
    """A MuJoCo Warp model whose kernels print nothing when a world overflows (a limit or a pool); the flags are
    still set in each world's `overflow` (`overflow_flags`). Read when the kernels are built, so set before the
    first step is traced."""
    return mjx_model.tree_replace({"opt._impl.warn_overflow": 0})


# MuJoCo Warp's `OverflowType` bits for the Newton loop's and the line search's limits (its types.py; importing it
# loads Warp, so they are written here and tests/test_backends.py holds them against it)
OVERFLOW_ITERATIONS, OVERFLOW_LS_ITERATIONS = 1 << 9, 1 << 10


def overflow_flags(d):
    """One env's MuJoCo Warp overflow bitmask (int32 ()): every flag its world raised since the Data was made
    (the flags stay set from step to step)."""
    import jax
    import jax.numpy as jnp
    f = jnp.asarray(d._impl.overflow, jnp.int32).reshape(-1)
    return jax.lax.reduce(f, jnp.int32(0), jax.lax.bitwise_or, (0,))
