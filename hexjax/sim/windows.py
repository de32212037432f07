"""The windowed gradient of a rollout with the windows' backward passes side by side.

With `RolloutConfig.grad_window` = W control steps, the physics and controller state are cut from the gradient
at every W-th step, so the gradient of the rollout's summary is a sum over windows, each window's with its
start state held fixed (`hexjax.sim.grad.cut_gradient`). Reverse mode through the rollout's `lax.scan` still
walks back over all T control steps one after another, T backward control steps in a row for B envs: on a GPU
at the batch sizes tuning uses (B = 64-256) each of them is latency-bound, and the backward pass costs two to
four forward rollouts.

Here the same gradient is taken in two phases inside one program:
1. the forward rollout (the same control step, `hexjax.sim.step.make_control_step`), keeping each step's
   input state: the fields through which the next step depends on this one (`hexjax.sim.step.GRAD_FIELDS`,
   a few kB an env), the controller state and the accumulators;
2. the backward passes of the K = ceil(T / W) windows side by side, B x K of them in one `vmap`, each a
   reverse loop of W steps that runs one control step again from its kept input (`jax.vjp`) and hands the
   cotangent to the step before. A window's end receives the loss's cotangent of the summary's accumulators
   (their sum over steps carries it to each window; a running maximum or minimum to the window that set it),
   and the last window that of the end state as well.

The value is the rollout's and the gradient that of reverse mode through the rollout's scan with the same
config, to float32 rounding (`tests/test_windows.py`), with a backward pass W steps long instead of T. With the
implicit solve the forward also keeps each physics step's constraint solution (qacc, the joint and the row
forces: a few hundred floats a physics step and env), and the backward's steps take it in place of solving
again (`hexjax.sim.internals.implicit.solutions`; the checkpointed scan does the same through
`hexjax.sim.internals.implicit.REMAT_POLICY`), so a backward control step costs a forward one without its solver,
plus its transpose. What the form saves is time in a row, not arithmetic: it pays where a device has room for
B x K envs at once (2.7x on an H100 at B = 256; docs/tuning.md).
"""

from __future__ import annotations

import contextlib
import math

import jax
import jax.numpy as jnp
import numpy as np

from hexjax.sim.internals import implicit, solver_context
from hexjax.sim.config import PhysicsConfig, RolloutConfig, SensorConfig, settle_steps
from hexjax.sim.engines import sim_model
from hexjax.sim.rollout import check_static
from hexjax.sim.step import GRAD_FIELDS, make_control_step, make_env_start, summarise
# accumulators that are running extremes, not sums: a window's end passes their cotangent on only if the
# extreme at that end is the rollout's final one (no later window moved it)
_EXTREMES = ("max_tilt", "min_height")
# B x K backward passes in flight at most; more windows run in turns (`lax.map`), bounding the memory of one
# backward control step
MAX_PARALLEL = 32768


def _is_float(x) -> bool:
    return jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating)


def _floats(tree):
    """(float leaves of `tree`, rebuild(float leaves) -> tree with its other leaves as they are)."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    mask = [_is_float(x) for x in leaves]

    def rebuild(fl):
        it = iter(fl)
        return jax.tree_util.tree_unflatten(treedef, [next(it) if m else x for x, m in zip(leaves, mask)])

    return [x for x, m in zip(leaves, mask) if m], rebuild


def _part(path, x) -> int:
    """Which of `_data_parts`'s lists an mjx.Data leaf belongs to: 0 state, 1 fixed, 2 derived."""
    if not _is_float(x):
        return 1
    return 0 if jax.tree_util.keystr(path) in GRAD_FIELDS else 2


def _data_parts(d):
    """(state, fixed, derived) leaf lists of one env's mjx.Data: the float fields of `GRAD_FIELDS`, the
    non-float fields, every other float field (recomputed by the next step from the first two)."""
    parts = ([], [], [])
    for path, x in jax.tree_util.tree_flatten_with_path(d)[0]:
        parts[_part(path, x)].append(x)
    return parts


def _assemble(like, state, fixed, derived):
    """The mjx.Data of `like`'s structure from its three parts (`_data_parts`)."""
    its = (iter(state), iter(fixed), iter(derived))
    leaves = [next(its[_part(path, x)]) for path, x in jax.tree_util.tree_flatten_with_path(like)[0]]
    return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(like), leaves)


def _make_backward_window(step, settle_action, kept_solutions, w: int, t_all: int):
    """backward_window(params, terrain, m, like, kept_w, derived0, k_sense, ct_end, k): window k's sum over its steps
    of their params' cotangent, from the cotangent `ct_end` at the window's end, by reverse mode through each step
    from its kept input state."""

    def backward_window(params, terrain, m, like, kept_w, derived0, k_sense, ct_end, k):
        """Sum over the window's steps of their params' cotangent, from `ct_end` at the window's end."""
        p_fl, p_rebuild = _floats(params)

        def rev(carry, j):
            ct, gsum = carry
            i = k * w + j
            state, fixed, cs, acc, solved = jax.tree_util.tree_map(lambda a: a[j], kept_w)
            x_fl, x_rebuild = _floats((state, cs, acc))

            def f(pf, xf):
                p = p_rebuild(pf)
                st, c, a = x_rebuild(xf)
                d = _assemble(like, st, fixed, derived0)
                with kept_solutions(solved):
                    (nd, nc, na), _ = step((d, c, a), i, p, terrain, m, settle_action(p), None, k_sense)
                return _floats((_data_parts(nd)[0], nc, na))[0]

            _, vjp = jax.vjp(f, p_fl, x_fl)
            gp, gx = vjp(ct)
            valid = i < t_all  # the last window's padding passes the cotangent on untouched
            gx = [jnp.where(valid, a, b) for a, b in zip(gx, ct)]
            gsum = [s + jnp.where(valid, g, 0.0) for s, g in zip(gsum, gp)]
            return (gx, gsum), None

        (_, gsum), _ = jax.lax.scan(rev, (ct_end, [jnp.zeros_like(x) for x in p_fl]), jnp.arange(w)[::-1])
        return gsum

    return backward_window


def _end_cotangents(ct_fin, acc_kept, acc_f, k_win: int, w: int, t_all: int):
    """Each window's end cotangent (B, K, ...) as float leaves, from the loss's cotangent `ct_fin` of the final
    (state, controller state, accumulators): the state's at the last window only; the accumulators' at every
    window, a running extreme's only where the window's end already holds the final value."""
    acc_ends = jax.tree_util.tree_map(lambda a, af: jnp.concatenate([a[:, w::w], af[:, None]], axis=1), acc_kept,
                                      acc_f)
    last = (jnp.arange(k_win) == k_win - 1)

    def at_end(ct, name=None, ends=None, final=None):
        ct = jnp.broadcast_to(ct[:, None], (ct.shape[0], k_win) + ct.shape[1:])
        if name in _EXTREMES:
            return jnp.where(ends == final[:, None], ct, 0.0)
        return ct

    def at_last(c):
        return jnp.where(last.reshape((1, -1) + (1,) * (c.ndim - 1)), at_end(c), 0.0) if _is_float(c) else c

    ct_state = jax.tree_util.tree_map(at_last, ct_fin[:2])  # Data's state leaves and the controller's
    ct_acc = {n: (at_end(c, n, acc_ends[n], acc_f[n]) if _is_float(c) else c) for n, c in ct_fin[2].items()}
    return _floats((*ct_state, ct_acc))[0]


def _windows(a, k_win: int, w: int, t_all: int):
    """A kept input (B, T, ...) as (B, K, W, ...): the last window padded with copies of the last step."""
    pad = k_win * w - t_all
    a = jnp.concatenate([a, jnp.repeat(a[:, -1:], pad, axis=1)], axis=1) if pad else a
    return a.reshape((a.shape[0], k_win, w) + a.shape[2:])


def windowed_value_and_grad(robot, controller, duration: float, loss, *, physics: PhysicsConfig = PhysicsConfig(),
                            sensors: SensorConfig = SensorConfig(), config: RolloutConfig = RolloutConfig(),
                            params_batched: bool = False, max_parallel: int = MAX_PARALLEL,
                            keep_solutions: bool = True):
    """(model, f) with f(model, params, terrain, keys) -> ((summary, J), grad): the rollout's `Summary` (B envs),
    J = loss(summary) (B,) and the gradient of sum(J) in params (the params' structure, summed over envs; with
    `params_batched`, per env), through the windowed backward passes side by side (module docstring).
    duration: seconds of control after settling; config: the gradient rollout's (`grad_window`, `grad_clip`,
    `solver_grad`; `remat` has no effect here, nothing is stored but each step's input state). With
    `solver_grad='implicit'` and `keep_solutions` the forward also keeps each physics step's constraint solution,
    and the backward's steps take it instead of solving again (`hexjax.sim.internals.implicit.solutions`)."""
    n_ctrl = check_static(robot, controller, duration, physics, config)
    if config.record or config.progress_every:
        raise ValueError("windowed_value_and_grad: rollout.record and rollout.progress_every are forward-only "
                         "settings; leave them off")
    if config.solver_grad not in ("implicit", "unrolled") and physics.iterations != 1:
        raise ValueError(f"rollout.solver_grad={config.solver_grad!r} with physics.iterations={physics.iterations}: "
                         "reverse mode needs 'implicit' or 'unrolled'")
    sm = sim_model(robot, physics, "mjx")
    n_settle = settle_steps(config, controller.dt)
    t_all = n_settle + n_ctrl
    w = config.grad_window or t_all
    k_win = math.ceil(t_all / w)
    step = make_control_step(sm, sensors, config, controller, n_settle)
    start, settle_action = make_env_start(sm, config, controller)
    p_axis = 0 if params_batched else None
    keep = keep_solutions and config.solver_grad == "implicit"

    def kept_solutions(given=None):
        return implicit.solutions(given) if keep else contextlib.nullcontext({"kept": None})

    def forward_env(m, params, terrain, key):
        carry0, ctrl0, k_sense = start(m, params, key)

        def body(carry, i):
            d, cs, acc = carry
            state, fixed, _ = _data_parts(d)
            with kept_solutions() as channel:
                carry, _ = step(carry, i, params, terrain, m, ctrl0, None, k_sense)
            return carry, (state, fixed, cs, acc, channel["kept"])

        final, kept = jax.lax.scan(body, carry0, jnp.arange(t_all))
        return final, kept, _data_parts(carry0[0])[2], k_sense

    backward_window = _make_backward_window(step, settle_action, kept_solutions, w, t_all)

    def f(m, params, terrain, keys):
        with solver_context(config, physics):
            final, kept, derived0, k_sense = jax.vmap(forward_env, in_axes=(None, p_axis, 0, 0))(
                m, params, terrain, keys)
            d_f, cs_f, acc_f = final
            like = jax.tree_util.tree_map(lambda x: x[0], d_f)  # one env's Data structure
            st_f = jax.vmap(lambda d: _data_parts(d)[0])(d_f)

            # the loss's cotangent of the final state, controller state and accumulators
            fin_fl, fin_rebuild = _floats((st_f, cs_f, acc_f))

            def total(xf):
                st, cs, acc = fin_rebuild(xf)
                d = jax.vmap(lambda s, d0: _assemble(like, s, *_data_parts(d0)[1:]))(st, d_f)
                summary = summarise(acc, d.qpos, cs)
                j = loss(summary)
                return jnp.sum(j), (summary, j)

            _, vjp, (summary, j) = jax.vjp(total, fin_fl, has_aux=True)
            ct_fin = fin_rebuild(vjp(jnp.ones(()))[0])

            ct_end = _end_cotangents(ct_fin, kept[3], acc_f, k_win, w, t_all)
            kept_w = jax.tree_util.tree_map(lambda a: _windows(a, k_win, w, t_all), kept)
            # windows in turns of at most max_parallel / B: equal turns, the last padded with windows past the end
            # (every step of theirs is padding), so that one traced backward serves every turn
            turns = math.ceil(k_win * int(terrain.box_pos.shape[0]) / max_parallel)
            per_turn = math.ceil(k_win / turns)
            extra = turns * per_turn - k_win

            def env_backward(params_e, terrain_e, kept_e, derived_e, k_sense_e, ct_e):
                one = lambda xs: backward_window(params_e, terrain_e, m, like, xs[0], derived_e, k_sense_e, xs[1],
                                                 xs[2])
                xs = (kept_e, ct_e, jnp.arange(k_win + extra))
                if extra:
                    xs = (*jax.tree_util.tree_map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], extra, axis=0)]),
                                                  xs[:2]), xs[2])
                if turns == 1:
                    g = jax.vmap(one)(xs)
                else:
                    xs = jax.tree_util.tree_map(lambda a: a.reshape((turns, per_turn) + a.shape[1:]), xs)
                    g = jax.lax.map(jax.vmap(one), xs)
                    g = [x.reshape((-1,) + x.shape[2:]) for x in g]
                return [jnp.sum(x, axis=0) for x in g]

            g = jax.vmap(env_backward, in_axes=(p_axis, 0, 0, 0, 0, 0))(params, terrain, kept_w, derived0, k_sense,
                                                                         ct_end)
            if not params_batched:
                g = [jnp.sum(x, axis=0) for x in g]
            return (summary, j), _floats_with_zeros(params, g)

    return sm.mjx_model, f


def _floats_with_zeros(params, float_grads):
    """The cotangent of `params` from the cotangents of its float leaves (float0 zeros for the others)."""
    leaves, treedef = jax.tree_util.tree_flatten(params)
    it = iter(float_grads)
    out = [next(it) if _is_float(x) else np.zeros(np.shape(x), jax.dtypes.float0) for x in leaves]
    return jax.tree_util.tree_unflatten(treedef, out)
