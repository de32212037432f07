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
program is traced under `hexjax.sim.mjx_rules.integrator_rule` (the implicit integrator's linear solve differentiated
as a solve, not through its Cholesky factor); `--no-integrator-rule` traces them without it, for the A/B.

Prints one JSON line per program (compile s, best call s, env-steps/s, the gradient) and the share of the
forward's rate; --json writes them. Modes: forward (the objective alone), jvp (all param directions), jvp1 (one
direction, the sum of all: the cost of a single tangent), rev (the tuner's reverse-mode value_and_grad), and two
variants of jvp's rule (2026-11-27, tenth session): jvpk takes the Newton Hessian's Cholesky factor from the
solver's last iteration instead of rebuilding it (`_solve_keep`, a copy of MJX's solve that returns it), and
jvpm also writes the constraint update's derivative in theta out for the pyramidal cone, from the solver's last
state, instead of linearising MJX's update a second time (`_attach_forward`'s options). Both give jvp's gradient to
rounding (docs/tuning.md, "How the gradient goes through a walk"). jvpf also takes
the contact rows' dJ a, dJ^T f and dJ qvel matrix-free, so the tangent of efc_J is never formed: the rule that the
package now carries and this mode runs (`hexjax.sim.forward_mode`, `TuneConfig.backward: forward`, `hexjax bench
--grad --backward forward`). Each mode is traced after JAX's caches are
cleared: the rollout's inner jitted functions keep their traces, so before that fix a mode traced after another in
one process ran the first one's rule.

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
from mujoco.mjx._src import constraint, solver, support

from hexjax.experiments.bench_grad import _time, objective_program, physics_steps
from hexjax.sim import forward_mode as fm
from hexjax.sim import implicit, rollout
from hexjax.sim.mjx_rules import swapped
from hexjax.sim.rollout import rollout_function
from hexjax.tune.config import load_tune_config
from hexjax.tune.objective import Problem, per_env_objective


_KEPT = []  # the last solve's (Cholesky factor of H, Jaref, active), from `_solve_keep` to the rule that follows it


def _solve_keep(m, d):
    """MJX's `solver.solve` (Newton, pyramidal cone), the same values, by `hexjax.sim.forward_mode._solve_keep`; the
    factor of its last iteration and that iteration's Jaref and active set go to `_KEPT`."""
    qacc, frc, efc, last = fm._solve_keep(m, d)
    _KEPT.append(last)
    return d.tree_replace({"qfrc_constraint": frc, "qacc": qacc, "_impl.efc_force": efc})


def _attach_forward(m, d, a_star, frc, efc, kept: bool = False, written: bool = False):
    """`hexjax.sim.implicit._attach` for forward mode: (a_star, frc, efc) unchanged in value, with tangents from
    the float arrays of (m, d) by the implicit function theorem (module docstring).

    `kept` (modes jvpk, jvpm): solve with the Cholesky factor of H that `_solve_keep` kept from the solver's last
    iteration, in place of one rebuilt at the solution. `written` (jvpm): the constraint update's tangent in theta
    at fixed a also comes from the solver's last state (Jaref, active set) rather than a second linearisation. For
    the pyramidal cone with no friction loss, where MJX's update is f = -D (J a - aref) on the active rows and
    C_qfrc = J^T f:
        d f = -(dD Jaref + D (dJ a - daref)) active,   d C_qfrc = dJ^T f + J^T d f,   d(M a) = dM a.
    Mode jvpf does not come here: it runs the package's rule (`hexjax.sim.forward_mode.forward_solve`)."""
    if written and (m._impl.dof_hasfrictionloss.any() or m._impl.tendon_hasfrictionloss.any()):
        raise ValueError("jvpm writes the derivative for models without friction loss only")
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
            e1 = -(td._impl.efc_D * jaref + dd * (td._impl.efc_J @ a - td._impl.efc_aref)) * active
            q1 = td._impl.efc_J.T @ e + j.T @ e1
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
    reverse one (`hexjax.sim.implicit._attach`); jvpk and jvpm also run `_solve_keep` as the solver. jvpf: the
    package's rule, `hexjax.sim.forward_mode.forward_solver`'s two swaps, with the implicit solve's place taken."""
    kept = mode in ("jvpk", "jvpm")
    with contextlib.ExitStack() as stack:
        if mode == "jvpf":
            stack.enter_context(swapped(implicit, "implicit_solve", fm.forward_solve))
            stack.enter_context(swapped(constraint, "_efc_contact_pyramidal", fm._pyramidal_no_tangent))
            yield
            return
        if kept:
            stack.enter_context(swapped(implicit, "_MJX_SOLVE", _solve_keep))
        stack.enter_context(swapped(implicit, "_attach", functools.partial(
            _attach_forward, kept=kept, written=mode == "jvpm")))
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
                         "(hexjax.sim.mjx_rules.integrator_rule replaced by a no-op): the rule's A/B")
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
