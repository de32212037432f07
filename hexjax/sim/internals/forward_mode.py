"""Forward mode through MJX's constraint solve: the tangent of its solution by the implicit function theorem, for
gradients taken with `jax.jacfwd` (one tangent per tuned number, carried along the rollout beside the primal;
`RolloutConfig.grad_mode='forward'`, `TuneConfig.backward: forward`).

With few tuned numbers (5 for the tactile preset) this is the cheaper program: one loop, with no second copy of the
control step (`remat`) and no reverse loop (docs/tuning.md, "How the gradient goes through a walk"). It is the forward-mode twin of
`hexjax.sim.internals.implicit`: MJX's solve runs as MJX runs it, cut from the derivative, and a custom JVP gives its
solution a* the tangent

    d a* = -H^{-1} (dg/dtheta) d theta,    g(a, theta) = M a - qfrc_smooth - J^T f(J a - aref),

with H = M + J^T diag(D active) J, the Newton Hessian. For the pyramidal cone f = -D (J a - aref) on the active
rows, so at fixed a (the solver's last Jaref = J a - aref and active set)

    d f = -(dD Jaref + D (dJ a - daref)) active,    d(J^T f) = dJ^T f + J^T d f,    d(M a) = dM a,

and the forces' own change with a adds -D active J d a to d f. Three things make the rule cheap, each measured on
an H100 (docs/tuning.md):
- the Cholesky factor of H is the one the solver's last iteration made (`_solve_keep`, MJX's Newton solve op for
  op, which keeps it), not a second one built at the solution;
- the update's tangent is written out as above, not a second linearisation of MJX's update;
- the contact rows' dJ a, dJ^T f and dJ qvel (the last inside daref: MJX's aref holds -b J qvel) are directional
  derivatives of matrix-free products (`rows_times`, `rows_t_times`): the motion of a contact point under a
  velocity, and a contact force spread over the dofs that move its body. The tangent of efc_J itself is cut where
  MJX builds the rows, so the (rows x nv) tangent is never formed for any direction.

What it handles (`check_model`, before tracing): MJX's Newton solver, the pyramidal cone, condim-3 contacts, and
joint-limit rows on hinge and slide joints (constant rows). Equality, friction-loss and tendon rows are refused.
The derivative is that of the converged solution, as for `hexjax.sim.internals.implicit`.
"""

from __future__ import annotations

import contextlib

import jax
import jax.numpy as jnp
import numpy as np
from mujoco.mjx._src import collision_driver, constraint, solver, support
from mujoco.mjx._src import math as mjx_math
from mujoco.mjx._src.types import ConeType, ConstraintType, DisableBit, JointType, SolverType

from hexjax.sim.internals import implicit
from hexjax.sim.internals.rules import swapped

_MJX_PYRAMIDAL = constraint._efc_contact_pyramidal  # MJX's own, whatever is patched in later


def check_model(m) -> int:
    """The first contact row of `m`'s constraint rows, after checking that forward mode handles the model
    (module docstring); a ValueError naming what it does not handle otherwise."""
    if m.opt.cone != ConeType.PYRAMIDAL:
        raise ValueError("rollout.grad_mode='forward' supports the pyramidal friction cone only (physics.cone)")
    if m.opt.solver != SolverType.NEWTON:
        raise ValueError(f"rollout.grad_mode='forward' supports MJX's Newton solver only (model solver "
                         f"{int(m.opt.solver)})")
    dims = np.asarray(collision_driver.make_condim(m))
    if np.any(dims != 3):
        raise ValueError(f"rollout.grad_mode='forward' supports condim-3 contacts only (the model has condim "
                         f"{sorted(set(dims.tolist()))})")
    typ = np.asarray(constraint.make_efc_type(m, dims))
    n0 = typ.size - 4 * dims.size
    kinds = set(typ[:n0].tolist()) - {int(ConstraintType.LIMIT_JOINT)}
    if kinds:
        names = sorted(ConstraintType(k).name for k in kinds)
        raise ValueError(f"rollout.grad_mode='forward' supports joint-limit and contact rows only (the model has "
                         f"{names} rows)")
    jt = np.asarray(m.jnt_type)[np.asarray(m.jnt_limited).astype(bool)]
    if np.any((jt != JointType.HINGE) & (jt != JointType.SLIDE)):
        raise ValueError("rollout.grad_mode='forward' supports limits on hinge and slide joints only")
    return int(n0)


def _ancestors(m) -> np.ndarray:
    """(nbody, nv): 1 where the dof moves body b (the dof's body is b or one of its ancestors). `support.jac`'s
    mask, for every body at once and static."""
    parent = np.asarray(m.body_parentid)
    anc = np.zeros((m.nbody, m.nbody), np.float32)
    for b in range(m.nbody):
        a = b
        while True:
            anc[b, a] = 1.0
            if a == 0:
                break
            a = parent[a]
    return anc[:, np.asarray(m.dof_bodyid)]


def contact_parts(d):
    """The float inputs of MJX's pyramidal contact rows that carry tangents: cdof, subtree_com, and the contacts'
    points, frames and friction (`constraint._efc_contact_pyramidal`)."""
    c = d._impl.contact
    return d.cdof, d.subtree_com, c.pos, c.frame, c.friction


def rows_times(m, parts, bodies, active, x):
    """J_c x for the 4 pyramidal rows of every condim-3 contact, without forming J_c: each body's motion under x
    (its ancestors' cdof times x), moved to the contact point, the difference of the two bodies' read in the
    contact frame. Rows in MJX's order, contact by contact: n + mu1 t1, n - mu1 t1, n + mu2 t2, n - mu2 t2."""
    cdof, com, pos, frame, fric = parts
    s = jnp.asarray(_ancestors(m)) @ (cdof * x[:, None])  # (nbody, 6): rotation, translation
    root = jnp.asarray(m.body_rootid)

    def point(b):
        return s[b, 3:] + jnp.cross(s[b, :3], pos - com[root[b]])

    u = jnp.einsum("cij,cj->ci", frame, point(bodies[:, 1]) - point(bodies[:, 0]))
    t1, t2 = fric[:, :1] * u[:, 1:2], fric[:, 1:2] * u[:, 2:3]
    rows = jnp.concatenate([u[:, :1] + t1, u[:, :1] - t1, u[:, :1] + t2, u[:, :1] - t2], axis=1)
    return (rows * active[:, None]).reshape(-1)


def rows_t_times(m, parts, bodies, active, f):
    """J_c^T f for the pyramidal contact rows, without forming J_c: each contact's force in world axes, as a spatial
    force about its body's root subtree centre of mass, summed per body (+ on the second, - on the first) and read
    by every dof that moves the body."""
    cdof, com, pos, frame, fric = parts
    f = f.reshape(-1, 4) * active[:, None]
    g = jnp.stack([f.sum(1), fric[:, 0] * (f[:, 0] - f[:, 1]), fric[:, 1] * (f[:, 2] - f[:, 3])], axis=1)
    w = jnp.einsum("cij,ci->cj", frame, g)
    root = jnp.asarray(m.body_rootid)

    def on_body(b):
        off = pos - com[root[b]]
        return jax.nn.one_hot(b, m.nbody, dtype=w.dtype).T @ jnp.concatenate([jnp.cross(off, w), w], axis=1)

    per_body = on_body(bodies[:, 1]) - on_body(bodies[:, 0])  # (nbody, 6)
    return jnp.sum(cdof * (jnp.asarray(_ancestors(m)).T @ per_body), axis=1)


def _contacts(m, d):
    """(bodies (ncon, 2), active (ncon,)) of `d`'s contacts, as MJX's pyramidal rows read them."""
    c = d._impl.contact
    return jnp.asarray(m.geom_bodyid)[c.geom], (c.dist - c.includemargin) < 0


def _pyramidal_no_tangent(m, d, condim):
    """MJX's pyramidal contact rows with the Jacobian's tangent cut: its value is MJX's; the rule takes the products
    of its tangent from `rows_times` and `rows_t_times` instead."""
    efc = _MJX_PYRAMIDAL(m, d, condim)
    return None if efc is None else efc.replace(J=jax.lax.stop_gradient(efc.J))


def _gradient_keep(m, d, ctx):
    """MJX's `solver._update_gradient` for the Newton solver, op for op, also returning the Cholesky factor of H
    (upper triangle, as `cho_factor` gives it)."""
    grad = ctx.Ma - d.qfrc_smooth - ctx.qfrc_constraint
    h = support.full_m(m, d) + (d._impl.efc_J.T * d._impl.efc_D * ctx.active) @ d._impl.efc_J
    c = jax.scipy.linalg.cho_factor((h + h.T) * 0.5)
    return ctx.replace(grad=grad, Mgrad=jax.scipy.linalg.cho_solve(c, grad)), c[0]


def _solve_keep(m, d):
    """MJX's `solver.solve` (mujoco-mjx 3.17.0; Newton, pyramidal cone), the same values, also returning the factor
    of its last `_update_gradient` (at the solution) and that iteration's Jaref and active set."""
    def cond(carry):
        ctx = carry[0]
        done = ctx.solver_niter >= m.opt.iterations
        done |= solver._rescale(m, d, ctx.prev_cost - ctx.cost) < m.opt.tolerance
        done |= solver._rescale(m, d, mjx_math.norm(ctx.grad)) < m.opt.tolerance
        return ~done

    def body(carry):
        ctx = solver._update_constraint(m, d, solver._linesearch(m, d, carry[0]))
        ctx, chol = _gradient_keep(m, d, ctx)
        return ctx.replace(search=-ctx.Mgrad, solver_niter=ctx.solver_niter + 1), chol

    qacc = d.qacc_smooth
    if not m.opt.disableflags & DisableBit.WARMSTART:
        warm = solver.Context.create(m, d.replace(qacc=d.qacc_warmstart), grad=False)
        smth = solver.Context.create(m, d.replace(qacc=d.qacc_smooth), grad=False)
        qacc = jnp.where(warm.cost < smth.cost, d.qacc_warmstart, d.qacc_smooth)
    d = d.replace(qacc=qacc)
    ctx, chol = _gradient_keep(m, d, solver.Context.create(m, d, grad=False))
    carry = (ctx.replace(search=-ctx.Mgrad), chol)
    ctx, chol = body(carry) if m.opt.iterations == 1 else jax.lax.while_loop(cond, body, carry)
    return ctx.qacc, ctx.qfrc_constraint, ctx.efc_force, (chol, ctx.Jaref, ctx.active)


def _attach(m, d, a_star, frc, efc, last, n0: int):
    """(a_star, frc, efc) unchanged in value, with tangents from the float arrays of (m, d) by the rule of the module
    docstring; `last` = (factor of H, Jaref, active) from the solver's last iteration; `n0` the first contact row."""
    xs, fl, ints, rebuild = implicit.traced_leaves(m, d)

    @jax.custom_jvp
    def attach(xf, xi, a, f, e, last_):
        return a, f, e

    def rule(primals, tangents):
        xf, xi, a, f, e, (chol, jaref, active) = primals
        ys = implicit._put(implicit._put(list(xs), fl, xf), ints, xi)
        rebuild_f = lambda xf_: rebuild(implicit._put(ys, fl, xf_))  # noqa: E731
        m_, d_ = rebuild_f(xf)
        _, td = rebuild_f(tangents[0])
        j, dd = d_._impl.efc_J, d_._impl.efc_D
        parts, tparts, c = contact_parts(d_), contact_parts(td), d_._impl.contact
        bodies, on = _contacts(m, d_)

        def dj(x):  # dJ x on every row; the limit rows' J is constant
            t = jax.jvp(lambda p: rows_times(m, p, bodies, on, x), (parts,), (tparts,))[1]
            return jnp.concatenate([jnp.zeros(n0, t.dtype), t])

        b = jax.vmap(lambda sr, si: constraint._kbi(m_, sr, si, jnp.zeros(()))[1])(c.solref, c.solimp)
        b = jnp.concatenate([jnp.zeros(n0, b.dtype), jnp.repeat(b, 4)])
        daref = td._impl.efc_aref - b * dj(d_.qvel)  # MJX's aref = -b J qvel - k imp pos
        djt_e = jax.jvp(lambda p: rows_t_times(m, p, bodies, on, e[n0:]), (parts,), (tparts,))[1]
        e1 = -(td._impl.efc_D * jaref + dd * (dj(a) - daref)) * active  # d f at fixed a
        q1 = djt_e + j.T @ e1
        g1 = support.mul_m(m_, d_.tree_replace({"_impl.M": td._impl.M}), a) - td.qfrc_smooth
        da = -jax.scipy.linalg.cho_solve((chol, False), g1 - q1)
        e2 = -(dd * active) * (j @ da)  # the forces' own change with a
        return (a, f, e), (da, q1 + j.T @ e2, e1 + e2)

    attach.defjvp(rule)
    return attach([xs[k] for k in fl], [xs[k] for k in ints], a_star, frc, efc, last)


def forward_solve(m, d):
    """MJX's `solver.solve(m, d)` in value; in forward mode its tangent by the rule of the module docstring."""
    n0 = check_model(m)
    with jax.named_scope("hx.solve_mjx"):  # scopes name the pieces in profiles (scripts/profile_grad.py)
        a_star, frc, efc, last = _solve_keep(implicit._stop(m), implicit._stop(d))
    last = tuple(jax.lax.stop_gradient(x) for x in last)
    qacc, frc, efc = _attach(m, d, a_star, frc, efc, last, n0)
    return d.tree_replace({"qacc": qacc, "qfrc_constraint": frc, "_impl.efc_force": efc})


@contextlib.contextmanager
def forward_solver():
    """While open, MJX's forward dynamics calls `forward_solve` in place of its constraint solver, and builds its
    pyramidal contact rows with the Jacobian's tangent cut. Only tracing needs the context (mujoco-mjx 3.17.0: MJX
    looks both names up in their modules at each call)."""
    with swapped(solver, "solve", forward_solve), \
            swapped(constraint, "_efc_contact_pyramidal", _pyramidal_no_tangent):
        yield
