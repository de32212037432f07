"""What a controller needs to know of the terrain it is sent over: the per-cell params rules of the registry
(`ControllerEntry.cell_params`, `ControllerEntry.family_params`), read by robustness sweeps, the fidelity matrix and
the terrain families.

    params, batched = tactile_cell(ctrl, spec, terr, distance)   Eq. 7's h_k from the cell's highest obstacle
    params, batched = avoid_cell(ctrl, spec, terr, distance)     the cell's boxes as Zhao 2018 obstacle circles

`batched` says whether the params carry a leading env axis (one value per env of `terr`).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

# terrain kinds whose height_range is the height of what stands in the way (the tactile switch's H, Eq. 7)
HEIGHT_KINDS = ("obstacles", "step", "stairs", "boxes", "rough", "waves")


def tactile_cell(ctrl, spec, terr, distance: float):
    """The tactile gait's params for walks over terrain `spec`: h_k = H + 2 cm (Luneckas 2020 Eq. 7) with H the
    family's highest obstacle where something stands in the way (`HEIGHT_KINDS`), else the controller's own H;
    shared by every env."""
    from hexjax.control.tactile import overcome_height
    if spec.kind in HEIGHT_KINDS:
        return ctrl.default_params(overcome_height=overcome_height(spec.height_range[1])), False
    return ctrl.default_params(), False


def tactile_families(ctrl, specs: Sequence, batch: int):
    """The tactile gait's params for `batch` envs on each terrain of `specs` in turn (one rollout over every family
    and difficulty): h_k (Eq. 7) per env from its stairs' or boxes' height, H = 3 cm elsewhere."""
    import jax

    from hexjax.control.tactile import overcome_height
    h = np.array([s.height_range[1] if s.kind in ("stairs", "boxes") else 0.03 for s in specs])
    params = ctrl.default_params()
    params = jax.tree_util.tree_map(lambda x: np.broadcast_to(np.asarray(x), (len(specs) * batch,) + np.shape(x)),
                                    params)
    return params.replace(overcome_height=np.repeat(overcome_height(h), batch).astype(np.float32))


def avoid_cell(ctrl, spec, terr, distance: float):
    """Per-env params of the avoiding gait: target `distance` ahead, the terrain's boxes as its obstacle circles
    (Zhao 2018 Eq. 1) on obstacle and box terrains (elsewhere the boxes are the ground: none), less those
    that cover the start or the target (no walk could avoid them), goal tolerance 3 cm."""
    import jax.numpy as jnp

    from hexjax.control.avoid_gait import field_params
    from hexjax.plan.fields import Fields
    from hexjax.world.terrain import obstacle_circles
    c, r, v = obstacle_circles(terr)
    b = c.shape[0]
    target = jnp.broadcast_to(jnp.array([distance, 0.0]), (b, 2))
    p0 = field_params(ctrl, Fields(start=jnp.zeros((b, 2)), target=target, centres=c, radii=r, valid=v,
                                   lane=jnp.zeros((b, 2, 2))))
    margin = r + p0.avoid.robot_radii[:, :1]
    clear = (jnp.linalg.norm(c - target[:, None], axis=-1) > margin) & (jnp.linalg.norm(c, axis=-1) > margin)
    v = v & clear & (spec.kind in ("obstacles", "boxes"))
    return p0.replace(valid=v, avoid=p0.avoid.replace(goal_tol=jnp.full((b,), 0.03, jnp.float32))), True
