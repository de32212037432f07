"""Gradient tuning: Adam (or SGD) on windowed gradients of the smooth objective through MJX (optax), or on
the hybrid estimate that corrects them by a zeroth-order term (`hexjax.tune.hybrid`), with the papers' hand
rules as the start (docs/tuning.md, "How the gradient goes through a walk")."""

from __future__ import annotations

import time
from typing import Any, Dict, Optional

import jax
import optax
from tqdm.auto import tqdm

from hexjax.control.registry import CONTROLLERS, paper_controller
from hexjax.tune.config import TuneConfig
from hexjax.tune.driver import cached, config_digest, drive, nonfinite_note, program_digest
from hexjax.tune.hybrid import hybrid_value_and_grad
from hexjax.tune.objective import Problem


def make_optimizer(cfg: TuneConfig):
    """Adam or SGD at `learning_rate`, cosine-decayed to `decay_to` x that over `steps` when set, after an
    optional global-norm clip."""
    o = dict(cfg.optimizer)
    lr = float(o.get("learning_rate", 0.05))
    if o.get("decay_to"):
        lr = optax.cosine_decay_schedule(lr, cfg.steps, alpha=float(o["decay_to"]))
    opt = optax.adam(lr) if o.get("name", "adam") == "adam" else optax.sgd(lr)
    if o.get("clip_norm"):
        opt = optax.chain(optax.clip_by_global_norm(float(o["clip_norm"])), opt)
    return opt


def average_iterate(avg, u, step: int, beta: float):
    """The evaluated iterate under `optimizer.average` = beta: an exponential moving average of the optimiser's
    iterates in the unconstrained params, avg_1 = u_1 and avg_k = beta avg_(k-1) + (1 - beta) u_k (step k >= 1,
    counted after the update). beta = 0 returns u itself (no averaging)."""
    if beta == 0 or step <= 1:
        return u
    return jax.tree_util.tree_map(lambda a, x: beta * a + (1 - beta) * x, avg, u)


def tune(cfg: TuneConfig, out_dir: str, resume: bool = True, progress: bool = True,
         time_limit: Optional[float] = None) -> Dict[str, Any]:
    """Adam (or SGD) on the unconstrained params. Every step draws `train_batch` fresh terrains and takes
    one windowed gradient of the smooth objective; every `eval_every` steps (and at step 0 and the end) the
    hard held-out objective is measured. Params, optimiser state and the log are checkpointed to
    out_dir/checkpoint.npz after every step (a rerun resumes); the log goes to out_dir/log.json and a plot
    to out_dir/tune.png. `time_limit` (s) stops early, at a step boundary."""
    t_start = time.perf_counter()
    problem = Problem.build(cfg)
    problem.check_gradient_fits(cfg.train_batch, "tune.train_batch")
    if cfg.backward == "forward" and problem.physics().cone != "pyramidal":
        raise ValueError(f"tune.train_physics={cfg.train_physics!r}: its {problem.physics().cone} cone has no "
                         "forward-mode gradient (backward: forward needs the pyramidal cone); use backward: "
                         "sequential or parallel")
    iterations = problem.physics().iterations
    need = CONTROLLERS[paper_controller(cfg.controller)].grad_iterations
    if iterations < need:
        print(f"note: the {paper_controller(cfg.controller)} controller needs solver_iterations >= {need} for "
              f"gradients that agree with finite differences (docs/tuning.md); this config runs {iterations}")
    u0 = problem.space.init(problem.params0)
    opt = make_optimizer(cfg)
    beta = float(cfg.optimizer.get("average") or 0.0)
    digest, program = config_digest(cfg, "grad"), program_digest(cfg, "grad")
    if cfg.estimator == "hybrid":
        est = hybrid_value_and_grad(problem, problem.train_rollout(grad=True, params_batched=True),
                                    problem.train_rollout(grad=False, params_batched=True))
        vg = cached(program + "/hybrid", lambda: jax.jit(est), problem.static("grad/hybrid", program))
        zo_key = jax.random.PRNGKey(cfg.seed + 11)
        per_step = cfg.train_batch * (1 + 2 * cfg.zo_pairs)
    else:
        loss_vg = cached(program + "/vg", lambda: jax.jit(problem.gradient_program()),
                         problem.static("grad/vg", program))
        vg = lambda u, terr, keys, key: loss_vg(u, terr, keys)
        zo_key, per_step = None, cfg.train_batch

    def advance(state, step):
        u, opt_state = state[:2]
        terr, keys = problem.train_batch(step)
        key = None if zo_key is None else jax.random.fold_in(zo_key, step)
        (loss, _), g = vg(u, terr, keys, key)
        note = nonfinite_note(step, loss, g, cfg)
        ok = note is None
        if note:
            tqdm.write(note)
        if ok:
            upd, opt_state = opt.update(g, opt_state, u)
            u = optax.apply_updates(u, upd)
        new = (u, opt_state) + ((average_iterate(state[2], u, step + 1, beta),) if beta else ())
        return new, {"train_objective": float(loss), "grad_finite": ok,
                     "grad_norm": float(optax.global_norm(g)) if ok else None}

    # the evaluated (and returned) iterate: the optimiser's own, or their running average (`optimizer.average`,
    # then a third member of the state, so that checkpoints of runs without it keep their layout)
    state0 = (u0, opt.init(u0)) + ((u0,) if beta else ())
    return drive(problem, out_dir, method=cfg.estimator.replace("first_order", "grad"), digest=digest, state=state0,
                 params_of=lambda st: st[-1] if beta else st[0], advance=advance, n_steps=cfg.steps,
                 rollouts_per_step=per_step, should_eval=lambda step, *_: step % cfg.eval_every == 0, resume=resume,
                 progress=progress, time_limit=time_limit, t_start=t_start)
