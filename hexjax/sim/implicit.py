"""Implicit differentiation of MJX's constraint solve: the backward pass of the contact forces by one linear
solve at the solution, instead of reverse mode through every Newton iteration and line-search step.

MJX finds the constrained acceleration `a` by minimising a convex cost (Gauss term plus constraint cost;
MuJoCo's documentation, "Computation: constraint solver"). Its gradient

    g(a, theta) = M a - qfrc_smooth - J^T f(J a - aref)

vanishes at the solution a*(theta), where theta stands for everything the solve reads from earlier in the step:
the mass matrix M, the smooth force qfrc_smooth, the constraint Jacobian J, its impedance D and reference
acceleration aref (all of them functions of the state, the controls and the model). For the pyramidal cone,
f(r) = -D r on the active rows, so the Hessian is H = M + J^T diag(D active) J, the matrix MJX's Newton
iteration already factors. The implicit function theorem gives

    d a* / d theta = -H^{-1} dg/dtheta      (active set held fixed).

`implicit_solve` computes this without a custom VJP:

    a = a_solved + delta - stop_gradient(delta),    delta = -H_sg^{-1} g(stop_gradient(a_solved), theta)

with H_sg the Hessian at the solution with its gradient stopped. In value `a` is MJX's own result, bit for bit
(the solve runs as MJX runs it: a while loop that stops once converged, cut from the gradient); in reverse mode
the cotangent goes through one Cholesky solve and one evaluation of g, whatever the number of iterations.
Constraint forces are recomputed from `a` the same way.

The derivative is that of the exact minimiser. When the solver stops before converging (`physics.iterations`
too small for the contacts), the forward value is an approximation and its implicit derivative belongs to the
converged map, not to the iterations actually run; `RolloutConfig(solver_grad='unrolled')` differentiates
the iterations themselves and stays as the reference (`tests/test_implicit.py` compares both).
"""

from __future__ import annotations

import contextlib

import jax
from jax.ad_checkpoint import checkpoint_name
from mujoco.mjx._src import solver, support
from mujoco.mjx._src.types import ConeType

_MJX_SOLVE = solver.solve  # MJX's own solver, whatever is patched in later
SOLUTION = "hexjax_constraint_solution"
# jax.checkpoint policy for a control step under implicit differentiation: keep the solver's outputs, recompute
# the rest (the iterations are then dead code in the recomputation)
REMAT_POLICY = jax.checkpoint_policies.save_only_these_names(SOLUTION)


def _stop(tree):
    """stop_gradient on the JAX-array leaves of an MJX Model or Data (numpy leaves stay static)."""
    return jax.tree_util.tree_map(lambda x: jax.lax.stop_gradient(x) if isinstance(x, jax.Array) else x, tree)


def implicit_solve(m, d):
    """MJX's `solver.solve(m, d)` in value; its derivative by the implicit function theorem (module docstring).
    Pyramidal cone only (hexjax's physics; `PhysicsConfig.cone`)."""
    if m.opt.cone != ConeType.PYRAMIDAL:
        raise ValueError("RolloutConfig.solver_grad='implicit' supports the pyramidal friction cone only")
    m_sg, d_sg = _stop(m), _stop(d)
    with jax.named_scope("hx.solve_mjx"):  # scopes name the pieces in profiles (scripts/profile_grad.py)
        out = _MJX_SOLVE(m_sg, d_sg)
    # named, so that a rematerialised step (`RolloutConfig.remat`, policy `REMAT_POLICY`) keeps the solution
    # and does not run the solver's iterations again in the backward pass
    a_star, frc, efc = (checkpoint_name(x, SOLUTION) for x in (out.qacc, out.qfrc_constraint, out._impl.efc_force))

    # H at the solution, cut from the gradient: M + J^T diag(D * active) J, factored once
    with jax.named_scope("hx.implicit_hessian"):
        ctx = solver.Context.create(m_sg, d_sg.replace(qacc=a_star), grad=False)
        j, dd = d_sg._impl.efc_J, d_sg._impl.efc_D
        h = support.full_m(m_sg, d_sg) + (j.T * (dd * ctx.active)) @ j
        h = 0.5 * (h + h.T)
        chol = jax.scipy.linalg.cho_factor(h)

    # g(a*, theta) with theta live: MJX's own constraint update, so every constraint kind is handled alike
    def residual(qacc):
        with jax.named_scope("hx.implicit_residual"):
            c = solver.Context.create(m, d.replace(qacc=qacc), grad=False)
            return c.Ma - d.qfrc_smooth - c.qfrc_constraint, c

    g, _ = residual(a_star)
    delta = -jax.scipy.linalg.cho_solve(chol, g)
    qacc = a_star + (delta - jax.lax.stop_gradient(delta))
    _, c = residual(qacc)  # forces at the differentiable acceleration (active set of a*: same as at qacc)
    live = lambda solved, x: solved + (x - jax.lax.stop_gradient(x))
    # every other field from the live `d`: `out` was made from the stopped copy
    return d.tree_replace({
        "qacc": qacc,
        "qfrc_constraint": live(frc, c.qfrc_constraint),
        "_impl.efc_force": live(efc, c.efc_force),
    })


@contextlib.contextmanager
def implicit_solver():
    """While open, MJX's forward dynamics calls `implicit_solve` in place of its constraint solver. Like
    `hexjax.sim.model.reversible_solver`, only tracing needs the context. Relies on MJX's `forward` module
    calling `solver.solve` through the module at each call (mujoco-mjx 3.17.0)."""
    prev = solver.solve
    solver.solve = implicit_solve
    try:
        yield
    finally:
        solver.solve = prev
