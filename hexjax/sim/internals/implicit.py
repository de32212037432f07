"""Implicit differentiation of MJX's constraint solve: the backward pass of the contact forces by one linear
solve at the solution, instead of reverse mode through every Newton iteration and line-search step.

MJX finds the constrained acceleration `a` by minimising a convex cost (Gauss term plus constraint cost;
MuJoCo's documentation, "Computation: constraint solver"). Its gradient

    g(a, theta) = M a - qfrc_smooth - J^T f(J a - aref)

vanishes at the solution a*(theta), where theta stands for everything the solve reads from earlier in the step:
the mass matrix M, the smooth force qfrc_smooth, the constraint Jacobian J, its impedance D and reference
acceleration aref (all of them functions of the state, the controls and the model). For the pyramidal cone,
f(r) = -D r on the active rows, so the Hessian is H = M + J^T diag(D active) J, the matrix MJX's Newton
iteration already factors. For the elliptic cone each contact's rows are in one of three zones of the cone
(MuJoCo's documentation, "Computation: elliptic cones"): above it (no force), below it (the rows are
quadratic, as pyramidal rows: diag(D)), or on its surface, where the cost 0.5 Dm (n - mu |t|)^2 of the
contact's normal and tangential residuals (n, t) has a dense condim x condim block. H is then
M + J^T C J with C block-diagonal: diag(D active) plus the surface contacts' blocks, again the matrix of MJX's
Newton iteration (its `_update_gradient`). The implicit function theorem gives

    d a* / d theta = -H^{-1} dg/dtheta      (active set held fixed).

`implicit_solve` runs MJX's solve as MJX runs it (a while loop that stops once converged), cut from the gradient,
so in value its outputs are MJX's, bit for bit. A custom VJP (`_attach`) then hands their cotangents to
everything the solve read, by one linearisation of MJX's own constraint update at the solution and one Cholesky
solve with H (`_cotangent`), whatever the number of iterations. Written as a custom VJP rather than as
`a* + delta - stop_gradient(delta)` (the first version), the forward pass computes nothing for the derivative,
and the backward pass keeps only the arrays whose values it reads: the mass matrix and the constraint rows.

The derivative is that of the exact minimiser. When the solver stops before converging (`physics.iterations`
too small for the contacts), the forward value is an approximation and its implicit derivative belongs to the
converged map, not to the iterations actually run; `RolloutConfig(solver_grad='unrolled')` differentiates
the iterations themselves and stays as the reference (`tests/test_implicit.py` compares both).
"""

from __future__ import annotations

import contextlib
import contextvars

import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name
from mujoco.mjx._src import solver, support
from mujoco.mjx._src.types import ConeType

from hexjax.sim.internals.rules import swapped

_MJX_SOLVE = solver.solve  # MJX's own solver, whatever is patched in later
SOLUTION = "hexjax_constraint_solution"
# jax.checkpoint policy for a control step under implicit differentiation: keep the solver's outputs, recompute
# the rest (the iterations are then dead code in the recomputation)
REMAT_POLICY = jax.checkpoint_policies.save_only_these_names(SOLUTION)


def _stop(tree):
    """stop_gradient on the JAX-array leaves of an MJX Model or Data (numpy leaves stay static)."""
    return jax.tree_util.tree_map(lambda x: jax.lax.stop_gradient(x) if isinstance(x, jax.Array) else x, tree)


def _cotangent(m, d, a_star, cts, rebuild, xf):
    """Cotangent of the float leaves xf of (m, d) (`rebuild(xf)` gives them back) from cotangents
    cts = (of qacc, of qfrc_constraint, of efc_force) of the solve's outputs at its solution a_star.

    The outputs as functions of theta: qacc(theta) is the minimiser (module docstring), and the forces are MJX's
    constraint update at it, C(qacc(theta), theta). With one linearisation of F(a, theta) = (M a - qfrc_smooth,
    C(a, theta)) at (a_star, theta), and g = F_1 - C_qfrc:
      1. the forces' cotangents reach a and theta directly: (a1, t1) = F^T (0, cts_qfrc, cts_efc);
      2. qacc's whole cotangent, cts_qacc + a1, goes through the minimiser: u = H^{-1} (cts_qacc + a1) and
         t2 = -(dg/dtheta)^T u = F^T (-u, u, 0) on theta;
    the answer is t1 + t2, with H the Newton Hessian at a_star (`newton_solve`; H is symmetric)."""
    ca, cf, ce = cts

    def f(a, xf_):
        m_, d_ = rebuild(xf_)
        with jax.named_scope("hx.implicit_residual"):
            c = solver.Context.create(m_, d_.replace(qacc=a), grad=False)
            return (c.Ma - d_.qfrc_smooth, c.qfrc_constraint, c.efc_force), (c.active, c.h)

    (f1, _, efc), f_vjp, (active, cone_h) = jax.vjp(f, a_star, xf, has_aux=True)
    a1, t1 = f_vjp((jnp.zeros_like(f1), cf, ce))
    u = newton_solve(m, d, active, ca + a1, cone_h)
    _, t2 = f_vjp((-u, u, jnp.zeros_like(efc)))
    return jax.tree_util.tree_map(jnp.add, t1, t2)


def newton_solve(m, d, active, rhs, cone_h=None):
    """H^{-1} rhs with the Newton Hessian of the constraint solve at its solution (module docstring), by a
    Cholesky factorisation of H (symmetrised against rounding): H = M + J^T diag(D active) J for the pyramidal
    cone; for the elliptic cone the contacts on the cone's surface add their blocks `cone_h` (ncon, 6, 6: MJX's
    `Context.h`, zero for the other contacts), each on its own condim rows, as MJX's Newton step does."""
    with jax.named_scope("hx.implicit_hessian"):
        j, dd = d._impl.efc_J, d._impl.efc_D
        if m.opt.cone == ConeType.ELLIPTIC and d._impl.contact.dim.size:
            c = jnp.diag(dd * active)
            cons = d._impl.contact
            for i, (condim, addr) in enumerate(zip(cons.dim[cons.dim > 1], cons.efc_address[cons.dim > 1])):
                c = c.at[addr:addr + condim, addr:addr + condim].add(cone_h[i, :condim, :condim])
            h = support.full_m(m, d) + j.T @ c @ j
        else:
            h = support.full_m(m, d) + (j.T * (dd * active)) @ j
        return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(0.5 * (h + h.T)), rhs)


def _floats(xs) -> list:
    """Indices of the float arrays in xs."""
    return [k for k, x in enumerate(xs) if jnp.issubdtype(x.dtype, jnp.inexact)]


def _put(xs, idx, vals) -> list:
    """A copy of the list xs with xs[idx[j]] = vals[j]."""
    ys = list(xs)
    for k, v in zip(idx, vals):
        ys[k] = v
    return ys


def traced_leaves(m, d):
    """(xs, fl, ints, rebuild): the JAX-array leaves xs of (m, d) (numpy leaves are static), the indices of the
    float ones and of the others in xs, and rebuild(xs') -> (m, d) with xs' in their place. What a custom rule
    around the solve (`_attach`, or a forward-mode one) takes apart and puts back together."""
    leaves, treedef = jax.tree_util.tree_flatten((m, d))
    traced = [i for i, x in enumerate(leaves) if isinstance(x, jax.Array)]

    def rebuild(xs):
        return jax.tree_util.tree_unflatten(treedef, _put(leaves, traced, xs))

    xs = [leaves[i] for i in traced]
    fl = _floats(xs)
    return xs, fl, sorted(set(range(len(xs))) - set(fl)), rebuild


def _read_by_backward(m, d, a_star, rebuild, traced) -> list:
    """For each leaf index in `traced`, whether `_cotangent` reads it: only those are kept for the backward
    pass (the others, most of mjx.Data, would be stored for every physics step for nothing). Found by tracing
    `_cotangent` once and removing dead code from its jaxpr; all, if JAX's internals for that have moved."""
    def backward(a, cts, *xs):
        fl = _floats(xs)
        rebuild_f = lambda xf_: rebuild(_put(xs, fl, xf_))  # noqa: E731
        return _cotangent(*rebuild(xs), a, cts, rebuild_f, [xs[i] for i in fl])
    try:
        from jax._src.interpreters import partial_eval as pe
        shape = lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype)  # noqa: E731
        cts = (shape(a_star), shape(d.qfrc_constraint), shape(d._impl.efc_force))
        closed = jax.make_jaxpr(backward)(shape(a_star), cts, *map(shape, traced))
        _, used = pe.dce_jaxpr(closed.jaxpr, [True] * len(closed.jaxpr.outvars))
        return list(used[4:])  # after a and the three cotangents
    except (ImportError, AttributeError, TypeError):
        return [True] * len(traced)


def _attach(m, d, a_star, frc, efc):
    """(a_star, frc, efc), MJX's solution, unchanged in value; in reverse mode their cotangents go to the float
    arrays of (m, d) by the implicit function theorem (`_cotangent`). A custom VJP, so that the forward pass
    computes nothing for the derivative (the backward pass builds the Hessian and the constraint update from
    the control step's recomputed inputs), and it keeps for the backward pass only the arrays whose values
    `_cotangent` reads (the mass matrix and the constraint rows); the others get their cotangents all the same."""
    xs, fl, ints, rebuild = traced_leaves(m, d)
    read = [k for k, u in enumerate(_read_by_backward(m, d, a_star, rebuild, xs)) if u]

    @jax.custom_vjp
    def attach(xf, xi, a, f, e):
        return a, f, e

    def fwd(xf, xi, a, f, e):
        ys = dict(zip(fl, xf)) | dict(zip(ints, xi))
        return (a, f, e), ([ys[k] for k in read], a)

    def bwd(res, cts):
        saved, a = res
        # the leaves not saved are zeros of their shape: the backward pass does not read their values
        ys = _put([jnp.zeros(x.shape, x.dtype) for x in xs], read, saved)
        rebuild_f = lambda xf_: rebuild(_put(ys, fl, xf_))  # noqa: E731
        xf = [ys[k] for k in fl]
        gf = _cotangent(*rebuild_f(xf), a, cts, rebuild_f, xf)
        zero_int = [np.zeros(xs[k].shape, jax.dtypes.float0) for k in ints]
        return (gf, zero_int) + tuple(jnp.zeros_like(x) for x in (a, *cts[1:]))

    attach.defvjp(fwd, bwd)
    return attach([xs[k] for k in fl], [xs[k] for k in ints], a_star, frc, efc)


# The solution channel, open only while tracing (`solutions`): one dict per traced physics step, through which
# `implicit_solve` hands out the solution it computed ("kept") or takes one computed before ("given") instead
# of running the solver. `hexjax.sim.windows` keeps each physics step's solution in its forward rollout and
# gives it back when its backward pass runs the step again, so that pass does not solve a second time.
# The open channels, innermost last, are context variables: a trace runs in its caller's thread, and each thread
# (fidelity's rollouts run in several) traces with its own channels.
_SLOTS: contextvars.ContextVar = contextvars.ContextVar("hexjax_solution_slots", default=())  # per mjx.step
_STEPS: contextvars.ContextVar = contextvars.ContextVar("hexjax_solution_steps", default=())  # per control step


@contextlib.contextmanager
def _channel(var: contextvars.ContextVar, given):
    channel = {"given": given, "kept": None}
    token = var.set(var.get() + (channel,))
    try:
        yield channel
    finally:
        var.reset(token)


def _innermost(var: contextvars.ContextVar):
    open_ = var.get()
    return open_[-1] if open_ else None


def solution_slot(given=None):
    """While open (around the trace of one `mjx.step`), `implicit_solve` takes `given` = (qacc, qfrc_constraint,
    efc_force) as the solve's solution, or with `given=None` records the one it computes in the slot's "kept"
    (None if the step solved nothing: no constraint rows)."""
    return _channel(_SLOTS, given)


def solutions(given=None):
    """While open (around the trace of one control step), `hexjax.sim.step.physics` runs each of its substeps in
    a `solution_slot`: with `given=None` it stacks the substeps' solutions into the channel's "kept" (leading axis
    the substep), and with `given` (so stacked) each substep takes its own. Only the implicit solve
    (`implicit_solver`) reads or fills the slots."""
    return _channel(_STEPS, given)


def solutions_channel():
    """The innermost open `solutions` channel, or None."""
    return _innermost(_STEPS)


def implicit_solve(m, d):
    """MJX's `solver.solve(m, d)` in value; its derivative by the implicit function theorem (module docstring).
    Either friction cone (`PhysicsConfig.cone`). Inside a `solution_slot` with a given solution the solver does
    not run: the step takes that solution, with the same derivative."""
    slot = _innermost(_SLOTS)
    if slot is not None and slot["given"] is not None:
        a_star, frc, efc = (jax.lax.stop_gradient(x) for x in slot["given"])
    else:
        with jax.named_scope("hx.solve_mjx"):  # scopes name the pieces in profiles (scripts/profile_grad.py)
            out = _MJX_SOLVE(_stop(m), _stop(d))
        # named, so that a rematerialised step (`RolloutConfig.remat`, policy `REMAT_POLICY`) keeps the solution
        # and does not run the solver's iterations again in the backward pass
        a_star, frc, efc = (checkpoint_name(x, SOLUTION) for x in (out.qacc, out.qfrc_constraint,
                                                                    out._impl.efc_force))
        if slot is not None:
            slot["kept"] = (a_star, frc, efc)
    qacc, frc, efc = _attach(m, d, a_star, frc, efc)
    # every other field from the live `d`: `out` was made from the stopped copy
    return d.tree_replace({"qacc": qacc, "qfrc_constraint": frc, "_impl.efc_force": efc})


def implicit_solver():
    """While open, MJX's forward dynamics calls `implicit_solve` in place of its constraint solver. Like
    `hexjax.sim.internals.rules.reversible_solver`, only tracing needs the context. Relies on MJX's `forward` module
    calling `solver.solve` through the module at each call (mujoco-mjx 3.17.0)."""
    return swapped(solver, "solve", implicit_solve)
