"""Forward mode against reverse mode for the windowed gradient of a tuning objective (issue 19, 2026-11-27,
seventh session).

The tuned controllers have few params (5 for tactile_tripod). So the gradient can also be taken in forward mode:
one JVP per param direction (`jax.jacfwd`, the directions side by side under `vmap`), carried along the rollout's
scan with the primal. That needs no second copy of the control step (no `remat`, no stored residuals) and no
reverse loop. The windows cut the state's tangent at their starts (`hexjax.sim.grad.cut_gradient` is a
stop_gradient), which gives the same windowed gradient as reverse mode.

MJX's constraint solve is made differentiable in forward mode as `RolloutConfig.solver_grad='implicit'` makes it in
reverse mode, by the implicit function theorem at the solution (`hexjax.sim.implicit`). This script adds the
forward-mode rule in place of the reverse one while it traces (`_attach_forward`, a custom JVP):

    d a* = -H^{-1} (dg/dtheta) d theta,   g(a, theta) = M a - qfrc_smooth - qfrc_constraint(a, theta),

with H = M + J^T diag(D active) J. The forces' tangents follow from MJX's constraint update, linearised at a*:
dC/dtheta d theta from the linearisation and dC/da d a = -D active J d a on the rows (pyramidal cone).
`RolloutConfig.grad_clip` bounds a cotangent and has no forward-mode counterpart, so the forward rows take the
exact windowed gradient; the reverse row (`rev`) is the tuner's, with the config's `grad_clip`. Every gradient
program is traced under `hexjax.sim.model.integrator_rule` (the implicit integrator's linear solve differentiated
as a solve, not through its Cholesky factor); `--no-integrator-rule` traces them without it, for the A/B.

Prints one JSON line per program (compile s, best call s, env-steps/s, the gradient) and the share of the
forward's rate; --json writes them. Modes: forward (the objective alone), jvp (all param directions), jvp1 (one
direction, the sum of all: the cost of a single tangent), rev (the tuner's reverse-mode value_and_grad), and two
variants of jvp's rule (2026-11-27, tenth session): jvpk takes the Newton Hessian's Cholesky factor from the
solver's last iteration instead of rebuilding it (`_solve_keep`, a copy of MJX's solve that returns it), and
jvpm also writes the constraint update's derivative in theta out for the pyramidal cone, from the solver's last
state, instead of linearising MJX's update a second time (`_attach_forward`'s options). Both give jvp's gradient to rounding
(docs/tuning.md, "Both taken from the solver, measured").

    python scripts/forward_grad_probe.py --batch 8 --modes forward,jvp1,jvp,rev --json out/fwd_probe.json
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from mujoco.mjx._src import math as mjx_math
from mujoco.mjx._src import constraint, solver, support
from mujoco.mjx._src.types import ConstraintType, DisableBit, JointType

from hexjax.experiments.bench_grad import _time, objective_program, physics_steps
from hexjax.sim import implicit, rollout
from hexjax.sim.model import swapped
from hexjax.sim.rollout import rollout_function
from hexjax.tune.config import load_tune_config
from hexjax.tune.objective import Problem, per_env_objective


_KEPT = []  # the last solve's (Cholesky factor of H, Jaref, active), from `_solve_keep` to the rule that follows it


def _gradient_keep(m, d, ctx):
    """MJX's `solver._update_gradient` for the Newton solver and the pyramidal cone, op for op, that also returns
    the Cholesky factor of H (upper triangle, as `cho_factor` gives it)."""
    grad = ctx.Ma - d.qfrc_smooth - ctx.qfrc_constraint
    h = support.full_m(m, d) + (d._impl.efc_J.T * d._impl.efc_D * ctx.active) @ d._impl.efc_J
    c = jax.scipy.linalg.cho_factor((h + h.T) * 0.5)
    return ctx.replace(grad=grad, Mgrad=jax.scipy.linalg.cho_solve(c, grad)), c[0]


def _solve_keep(m, d):
    """MJX's `solver.solve` (mujoco-mjx 3.17.0; Newton, pyramidal cone), the same values, with the factor of its
    last `_update_gradient` (at the solution) and that iteration's Jaref and active set kept in `_KEPT`."""
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
    _KEPT.append((chol, ctx.Jaref, ctx.active))
    return d.tree_replace({"qfrc_constraint": ctx.qfrc_constraint, "qacc": ctx.qacc,
                           "_impl.efc_force": ctx.efc_force})


def _pyramidal_no_tangent(m, d, condim):
    """MJX's pyramidal contact rows with the Jacobian's tangent cut (mode jvpf): its value is MJX's, and
    `_attach_forward` takes the products of its tangent from `_rows_times` and `_rows_t_times` instead, so
    the tangent of the (rows x nv) matrix is never formed."""
    efc = _MJX_PYRAMIDAL(m, d, condim)
    return None if efc is None else efc.replace(J=jax.lax.stop_gradient(efc.J))


_MJX_PYRAMIDAL = constraint._efc_contact_pyramidal


def _ancestors(m) -> np.ndarray:
    """(nbody, nv): 1 where the dof moves body b (its body is b or an ancestor of b). `support.jac`'s mask for
    every body at once, made static."""
    parent, nb = np.asarray(m.body_parentid), m.nbody
    anc = np.zeros((nb, nb), np.float32)
    for b in range(nb):
        a = b
        while True:
            anc[b, a] = 1.0
            if a == 0:
                break
            a = parent[a]
    return anc[:, np.asarray(m.dof_bodyid)]


def _contact_parts(d):
    """The float inputs of MJX's pyramidal contact rows (`constraint._efc_contact_pyramidal`), those that carry
    tangents: cdof, subtree_com, and the contacts' points, frames and friction."""
    c = d._impl.contact
    return d.cdof, d.subtree_com, c.pos, c.frame, c.friction


def _rows_times(m, parts, bodies, active, x):
    """J_c x for the 4 pyramidal rows of every contact (condim 3), without forming J_c: the motion of each body
    under x (the ancestors' cdof times x), moved to the contact point and read in the contact frame. Row order as
    MJX's: n + mu1 t1, n - mu1 t1, n + mu2 t2, n - mu2 t2, contact by contact."""
    cdof, com, pos, frame, fric = parts
    s = jnp.asarray(_ancestors(m)) @ (cdof * x[:, None])  # (nbody, 6): (rotation, translation)
    root = jnp.asarray(m.body_rootid)

    def point(b):
        return s[b, 3:] + jnp.cross(s[b, :3], pos - com[root[b]])

    u = jnp.einsum("cij,cj->ci", frame, point(bodies[:, 1]) - point(bodies[:, 0]))
    t1, t2 = fric[:, :1] * u[:, 1:2], fric[:, 1:2] * u[:, 2:3]
    rows = jnp.concatenate([u[:, :1] + t1, u[:, :1] - t1, u[:, :1] + t2, u[:, :1] - t2], axis=1)
    return (rows * active[:, None]).reshape(-1)


def _rows_t_times(m, parts, bodies, active, f):
    """J_c^T f for the pyramidal contact rows, without forming J_c: each contact's force in world axes, as a
    spatial force about the root's subtree centre of mass on its two bodies, summed per body and read by every
    dof that moves the body."""
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


def _check_free(m, d):
    """Mode jvpf handles models whose rows are hinge/slide limits (constant rows) then condim-3 pyramidal
    contacts; anything else raises before tracing goes on."""
    c = d._impl.contact
    typ = constraint.make_efc_type(m, np.asarray(c.dim))
    n0 = typ.size - 4 * c.dim.size
    limited = np.asarray(m.jnt_limited).astype(bool)
    ok = (np.all(np.asarray(c.dim) == 3) and np.all(typ[:n0] == ConstraintType.LIMIT_JOINT)
          and np.all(np.isin(np.asarray(m.jnt_type)[limited], (JointType.HINGE, JointType.SLIDE)))
          and np.all(typ[n0:] == ConstraintType.CONTACT_PYRAMIDAL) and m.opt.cone == 0)
    if not ok:
        raise ValueError("jvpf handles joint-limit rows and condim-3 pyramidal contacts only")
    return n0


def _attach_forward(m, d, a_star, frc, efc, kept: bool = False, written: bool = False, free: bool = False):
    """`hexjax.sim.implicit._attach` for forward mode: (a_star, frc, efc) unchanged in value, with tangents from
    the float arrays of (m, d) by the implicit function theorem (module docstring).

    `kept` (modes jvpk, jvpm): solve with the Cholesky factor of H that `_solve_keep` kept from the solver's last
    iteration, in place of one rebuilt at the solution. `written` (jvpm): the constraint update's tangent in theta
    at fixed a also comes from the solver's last state (Jaref, active set) rather than a second linearisation. For
    the pyramidal cone with no friction loss, where MJX's update is f = -D (J a - aref) on the active rows and
    C_qfrc = J^T f:
        d f = -(dD Jaref + D (dJ a - daref)) active,   d C_qfrc = dJ^T f + J^T d f,   d(M a) = dM a.
    `free` (jvpf, with both): the contact rows' dJ a, dJ^T f and dJ qvel (in daref: MJX's aref has
    -b J qvel) are directional derivatives of `_rows_times` and `_rows_t_times`, matrix-free; the tangent of
    efc_J is cut where MJX makes the rows (`_pyramidal_no_tangent`), so it is never formed."""
    if written and (m._impl.dof_hasfrictionloss.any() or m._impl.tendon_hasfrictionloss.any()):
        raise ValueError("jvpm writes the derivative for models without friction loss only")
    n0 = _check_free(m, d) if free else 0  # the first contact row
    last = tuple(jax.lax.stop_gradient(x) for x in _KEPT.pop()) if kept else ()  # (factor, Jaref, active)
    xs, fl, ints, rebuild = implicit.traced_leaves(m, d)

    @jax.custom_jvp
    def attach(xf, xi, a, f, e, last_):
        return a, f, e

    def rule(primals, tangents):
        xf, xi, a, f, e, last_ = primals
        ys = implicit._put(implicit._put(list(xs), fl, xf), ints, xi)
        rebuild_f = lambda xf_: rebuild(implicit._put(ys, fl, xf_))  # noqa: E731
        m_, d_ = rebuild_f(xf)
        j, dd = d_._impl.efc_J, d_._impl.efc_D
        if written:
            _, jaref, active = last_
            _, td = rebuild_f(tangents[0])
            if free:
                parts, tparts, c = _contact_parts(d_), _contact_parts(td), d_._impl.contact
                bodies = jnp.asarray(m.geom_bodyid)[c.geom]
                on = (c.dist - c.includemargin) < 0

                def dj(x):  # dJ x on every row (the limit rows' J is constant)
                    t = jax.jvp(lambda p: _rows_times(m, p, bodies, on, x), (parts,), (tparts,))[1]
                    return jnp.concatenate([jnp.zeros(n0, t.dtype), t])

                b = jax.vmap(lambda sr, si: constraint._kbi(m_, sr, si, jnp.zeros(()))[1])(c.solref, c.solimp)
                b = jnp.concatenate([jnp.zeros(n0, b.dtype), jnp.repeat(b, 4)])
                daref = td._impl.efc_aref - b * dj(d_.qvel)
                djt_e = jax.jvp(lambda p: _rows_t_times(m, p, bodies, on, e[n0:]), (parts,), (tparts,))[1]
            else:
                daref, djt_e = td._impl.efc_aref, td._impl.efc_J.T @ e
                dj = lambda x: td._impl.efc_J @ x  # noqa: E731
            e1 = -(td._impl.efc_D * jaref + dd * (dj(a) - daref)) * active
            q1 = djt_e + j.T @ e1
            g1 = support.mul_m(m_, d_.tree_replace({"_impl.M": td._impl.M}), a) - td.qfrc_smooth
        else:
            def update(a_, xf_):
                mm, d2 = rebuild_f(xf_)
                c = solver.Context.create(mm, d2.replace(qacc=a_), grad=False)
                return (c.Ma - d2.qfrc_smooth, c.qfrc_constraint, c.efc_force), c.active

            _, lin, active = jax.linearize(update, a, xf, has_aux=True)
            g1, q1, e1 = lin(jnp.zeros_like(a), tangents[0])  # d theta's part, at fixed a
        if kept:
            da = -jax.scipy.linalg.cho_solve((last_[0], False), g1 - q1)
        else:
            da = -implicit.newton_solve(m_, d_, active, g1 - q1)
        e2 = -(dd * active) * (j @ da)  # the constraint update's own derivative in a
        return (a, f, e), (da, q1 + j.T @ e2, e1 + e2)

    attach.defjvp(rule)
    return attach([xs[k] for k in fl], [xs[k] for k in ints], a_star, frc, efc, last)


@contextlib.contextmanager
def forward_rule(mode: str):
    """While open, a program traced takes the forward-mode rule of `mode` (jvp, jvp1, jvpk, jvpm) in place of the
    reverse one (`hexjax.sim.implicit._attach`); jvpk and jvpm also run `_solve_keep` as the solver."""
    kept, free = mode in ("jvpk", "jvpm", "jvpf"), mode == "jvpf"
    with contextlib.ExitStack() as stack:
        if kept:
            stack.enter_context(swapped(implicit, "_MJX_SOLVE", _solve_keep))
        if free:
            stack.enter_context(swapped(constraint, "_efc_contact_pyramidal", _pyramidal_no_tangent))
        stack.enter_context(swapped(implicit, "_attach", functools.partial(
            _attach_forward, kept=kept, written=mode in ("jvpm", "jvpf"), free=free)))
        yield


def jvp_program(pb: Problem, one: bool, duration: float | None = None):
    """f(u, terrain, keys) -> ((mean J, per-env J), d mean J / du) by forward mode (module docstring); `one`: a single
    tangent, the sum of all param directions, its derivative written into every entry; `duration`: walk s instead of
    the config's."""
    # the tuner's gradient rollout (its windows), without what only reverse mode uses: remat and the bound
    rc = dataclasses.replace(pb._rollout_config(grad=True), remat=False, grad_clip=None)
    walk = pb.duration if duration is None else duration
    model, fn = rollout_function(pb.robot, pb.train_ctrl, walk, physics=pb.physics(), config=rc)
    unravel = ravel_pytree(pb.space.init(pb.params0))[1]

    def total(x, terr, keys):
        j = per_env_objective(fn(model, pb.space.apply(unravel(x), pb.params0), terr, keys), pb.cfg.distance,
                              pb.cfg.objective)
        return jnp.sum(j), j

    def f(u, terr, keys):
        x = ravel_pytree(u)[0]
        if one:
            (_, j), (dt, _) = jax.jvp(lambda y: total(y, terr, keys), (x,), (jnp.ones_like(x),))
            g = jnp.full_like(x, dt)
        else:
            g, j = jax.jacfwd(lambda y: total(y, terr, keys), has_aux=True)(x)
        return (jnp.mean(j), j), unravel(g / j.shape[0])

    return jax.jit(f)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tune", default="tactile_tripod")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--modes", default="forward,jvp,rev")
    ap.add_argument("--duration", type=float, default=None, help="walk s instead of the config's")
    ap.add_argument("--no-integrator-rule", action="store_true",
                    help="trace every program with JAX's own derivative of the implicit integrator's Cholesky solve "
                         "(hexjax.sim.model.integrator_rule replaced by a no-op): the rule's A/B")
    ap.add_argument("--json", default="")
    a = ap.parse_args()
    modes = a.modes.split(",")
    bad = [m for m in modes if m not in ("forward", "jvp", "jvp1", "jvpk", "jvpm", "jvpf", "rev")]
    if bad or modes[0] != "forward":
        raise SystemExit(f"--modes {a.modes!r}: forward first, then any of jvp, jvp1, jvpk, jvpm, jvpf, rev")
    pb = Problem.build(dataclasses.replace(load_tune_config(a.tune), solver_grad="implicit"))
    u0 = pb.space.init(pb.params0)
    terr, keys = pb.train_batch(0, a.batch)
    n_phys = physics_steps(pb, a.duration)
    rows = []
    for mode in modes:
        # the rollout's inner jitted functions keep their traces by argument; a rule swapped in below would not
        # reach a program whose inner trace a previous mode left in JAX's caches
        jax.clear_caches()
        if mode in ("forward", "rev"):
            f, rule = objective_program(pb, grad=mode == "rev", duration=a.duration), contextlib.nullcontext()
        else:  # the forward-mode rule in place of the reverse one while the program traces
            f, rule = jvp_program(pb, one=mode == "jvp1", duration=a.duration), forward_rule(mode)
        with rule, (swapped(rollout, "integrator_rule", contextlib.nullcontext) if a.no_integrator_rule
                    else contextlib.nullcontext()):
            compile_s, run_s, out = _time(f, (u0, terr, keys), a.repeats)
        row = dict(mode=mode, batch=a.batch, compile_s=round(compile_s, 2), run_s=round(run_s, 4),
                   env_steps_per_s=round(a.batch * n_phys / run_s, 1))
        if mode != "forward":
            row["grad"] = [float(v) for v in np.asarray(ravel_pytree(out[1])[0])]
            row["rate_vs_forward"] = round(row["env_steps_per_s"] / rows[0]["env_steps_per_s"], 4)
            row["compile_vs_forward"] = round(compile_s / rows[0]["compile_s"], 2)
        rows.append(row)
        print(json.dumps(row), flush=True)
    grads = {r["mode"]: np.array(r["grad"]) for r in rows if r["mode"] in ("jvp", "jvpk", "jvpm", "jvpf", "rev")}
    res = dict(tune=a.tune, backend=jax.default_backend(), device=str(jax.devices()[0].device_kind),
               physics_steps_per_env=n_phys, duration=a.duration,
               integrator_rule=not a.no_integrator_rule, jax=jax.__version__, date=time.strftime("%Y-%m-%d"),
               rows=rows)
    if "jvp" in grads and "rev" in grads:
        x, y = grads["jvp"], grads["rev"]
        res["cosine_jvp_rev"] = float(x @ y / (np.linalg.norm(x) * np.linalg.norm(y)))
        print(f"cosine(jvp, rev) {res['cosine_jvp_rev']:.4f}")
    for k in ("jvpk", "jvpm", "jvpf"):  # the rule's variants give jvp's gradient, to rounding
        if "jvp" in grads and k in grads:
            x, y = grads["jvp"], grads[k]
            res[f"max_rel_diff_{k}_jvp"] = float(np.max(np.abs(y - x)) / np.max(np.abs(x)))
            print(f"{k} against jvp: largest difference {res[f'max_rel_diff_{k}_jvp']:.2e} of the largest entry")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
