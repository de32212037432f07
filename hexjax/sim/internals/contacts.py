"""What `hexjax.sim.model` reads of MJX's and MuJoCo Warp's private code: the order of MJX's contact slots, the
contact forces decoded from the solver's rows, and Warp's overflow flags. Each relies on private names of the
pinned mujoco-mjx (`hexjax.private_reach`)."""

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


def warn_overflow_but_iterations(mjx_model):
    """A MuJoCo Warp model that keeps Warp's overflow messages for contacts and constraint rows and drops the one
    for the iteration limit (hexjax runs a fixed, small number of Newton iterations on purpose)."""
    from mujoco.mjx.third_party.mujoco_warp._src.types import OverflowType
    warn = int(mjx_model.opt._impl.warn_overflow) & ~int(OverflowType.ITERATIONS)
    return mjx_model.tree_replace({"opt._impl.warn_overflow": warn})
