"""Gradient treatment of the rollout's control step (`RolloutConfig.grad_clip`, `grad_window`): identities in
value that bound or cut the cotangent flowing back through the physics and controller state."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def clip_cotangent(tree, bound: float):
    """Identity on the float leaves of `tree`; in reverse mode their cotangent is scaled to global norm
    <= bound (and non-finite cotangents are zeroed)."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    is_f = [jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating) for x in leaves]
    fl = [x for x, f in zip(leaves, is_f) if f]

    @jax.custom_vjp
    def ident(xs):
        return xs

    def fwd(xs):
        return xs, None

    def bwd(_, gs):
        gs = [jnp.where(jnp.isfinite(g), g, 0.0) for g in gs]
        # the norm of cotangents near float32's limit overflows when squared (an inf norm would scale
        # everything to zero): take it relative to the largest entry
        big = jnp.maximum(jnp.max(jnp.stack([jnp.max(jnp.abs(g), initial=0.0) for g in gs])), 1e-30)
        norm = big * jnp.sqrt(sum(jnp.sum(jnp.square(g / big)) for g in gs))
        scale = jnp.minimum(1.0, bound / jnp.maximum(norm, 1e-30))
        return ([g * scale for g in gs],)

    ident.defvjp(fwd, bwd)
    out = iter(ident(fl))
    return jax.tree_util.tree_unflatten(treedef, [next(out) if f else x for x, f in zip(leaves, is_f)])


def cut_gradient(tree, cut):
    """Identity in value; where the traced bool `cut` holds, the float leaves of `tree` pass no gradient."""
    def f(x):
        if not jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating):
            return x
        return jnp.where(cut, jax.lax.stop_gradient(x), x)
    return jax.tree_util.tree_map(f, tree)
