"""The evolution-strategy baseline: an evosax strategy on the same unconstrained params, smooth objective and
terrain stream as the gradient tuner, given its rollout budget or its wall time (docs/tuning.md): CMA-ES for a
few numbers, sep-CMA-ES (a diagonal covariance) or SNES where a full covariance would not pay (`es_strategy`)."""

from __future__ import annotations

import time
from typing import Any, Dict, Optional, Sequence

import jax
import jax.numpy as jnp
from evosax.algorithms import CMA_ES, SNES, Sep_CMA_ES

from hexjax.tune.config import ES_FULL_MAX, TuneConfig
from hexjax.tune.driver import cached, config_digest, drive, program_digest
from hexjax.tune.objective import Problem, per_env_objective


STRATEGIES = {"cma_es": CMA_ES, "sep_cma_es": Sep_CMA_ES, "snes": SNES}
LIMIT_KEYS = ("envs", "line_search_limit", "iteration_limit", "other")  # MuJoCo Warp's, summed over generations


def strategy(cfg: TuneConfig, u0) -> str:
    """The strategy `cfg.es_strategy` names; for 'auto', CMA-ES up to `ES_FULL_MAX` numbers in u0, else
    sep-CMA-ES (a full covariance of n^2 entries, learnt from a population of 8, does not pay at n = 1,000)."""
    if cfg.es_strategy != "auto":
        return cfg.es_strategy
    n = sum(int(jnp.size(x)) for x in jax.tree_util.tree_leaves(u0))
    return "cma_es" if n <= ES_FULL_MAX else "sep_cma_es"


def population_objective(problem: Problem, pop: int, batch: int):
    """f(population u (pop, ...), terrains, keys of `batch` envs) -> each member's mean J over the same envs:
    params batched over pop x batch envs. `es_rollouts: training` jits it with MJX's rollout on the training
    physics (a kept program); `certified` runs the hard rollout on the evaluation physics on the fastest
    engine certified for it here (`hexjax.sim.rollout.rollout`)."""
    cfg = problem.cfg
    hard = cfg.es_objective == "hard"
    start = problem.eval_params0 if hard else problem.params0
    tile = lambda x: jnp.tile(x, (pop,) + (1,) * (x.ndim - 1))

    def member_params(pop_u):
        flat_p = jax.vmap(lambda uu: problem.space.apply(uu, start))(pop_u)
        return jax.tree_util.tree_map(lambda x: jnp.repeat(x, batch, axis=0), flat_p)

    if cfg.es_rollouts == "certified":
        # the certified engines check every member's params on the host as a user's would be (e.g. the CPG's
        # elevated clearance >= its clearance, which the space's per-field bounds do not keep): a member that
        # fails walks as the start does and scores +inf, the worst of its generation (a death penalty)
        u_start = problem.space.init(start)

        def feasible(pop_u):
            flat_p = jax.vmap(lambda uu: problem.space.apply(uu, start))(pop_u)
            ok = []
            for i in range(pop):
                try:
                    problem.eval_ctrl.validate_params(jax.tree_util.tree_map(lambda x: x[i], flat_p))
                    ok.append(True)
                except ValueError:
                    ok.append(False)
            return jnp.asarray(ok)

        def certified(pop_u, terr, keys):
            ok = feasible(pop_u)
            pop_u = jax.tree_util.tree_map(
                lambda x, x0: jnp.where(ok.reshape((pop,) + (1,) * (x.ndim - 1)), x, x0), pop_u, u_start)
            s = problem.certified_rollout(member_params(pop_u), jax.tree_util.tree_map(tile, terr), tile(keys),
                                          params_batched=True, limits=certified.limits)
            fit = per_env_objective(s, cfg.distance, cfg.objective).reshape(pop, batch).mean(1)
            return jnp.where(ok, fit, jnp.inf)
        certified.limits = []  # MuJoCo Warp's limit counts, one per generation: the tuner logs them, not a line each
        return certified

    model, fn = (problem.hard_rollout(params_batched=True) if hard else
                 problem.train_rollout(grad=False, params_batched=True))

    def population_loss(pop_u, terr, keys):
        s = fn(model, member_params(pop_u), jax.tree_util.tree_map(tile, terr), tile(keys))
        return per_env_objective(s, cfg.distance, cfg.objective).reshape(pop, batch).mean(1)

    program = program_digest(cfg, f"es{pop}")
    return cached(program + "/pop", lambda: jax.jit(population_loss), problem.static("es/pop", program))


def eval_schedule(pop: int, eval_every: int, eval_at: Optional[Sequence[float]] = None):
    """should_eval(generation, train_s, train_s_before) of `tune_es`: where the rollouts used cross a multiple of
    the gradient run's evaluation period (`eval_every` steps of the same batch: every eval_every / pop
    generations), or with `eval_at` at the generation whose own seconds pass one of those marks."""
    if eval_at is None:
        return lambda gen, *_: (gen * pop) // eval_every > ((gen - 1) * pop) // eval_every
    return lambda gen, now, before: any(before < m <= now for m in eval_at)


def tune_es(cfg: TuneConfig, out_dir: str, rollouts: Optional[int], resume: bool = True, progress: bool = True,
            time_limit: Optional[float] = None, eval_at: Optional[Sequence[float]] = None) -> Dict[str, Any]:
    """The evosax strategy of `strategy(cfg)` (CMA-ES, sep-CMA-ES or SNES) on the same unconstrained params and
    the same smooth training objective (or, with `es_objective: hard`, the hard form that evaluation uses: an ES
    needs no gradient; `es_rollouts`: where it runs, `population_objective`), with the same terrain stream:
    generation k evaluates every member of its population on the `train_batch` terrains of step k. It stops after
    `rollouts` rollouts (population x train_batch per generation), so it can be given exactly the gradient run's
    budget, or with None at `time_limit` alone. Its starting mean is the hand rules; its step size is
    `cfg.es_sigma` on the unconstrained scale. Held-out evaluations of the mean as for `tune`: where the rollouts
    used cross a multiple of the gradient run's evaluation period, or with `eval_at` (seconds of the method's own
    time: a wall-time race's marks) at the first generation past each mark."""
    if rollouts is None and time_limit is None:
        raise ValueError("tune_es: give a rollout budget or a time limit (it would never stop)")
    t_start = time.perf_counter()
    problem = Problem.build(cfg)
    u0 = problem.space.init(problem.params0)
    pop = cfg.es_population
    name = strategy(cfg, u0)
    es = STRATEGIES[name](population_size=pop, solution=u0)
    es_params = es.default_params.replace(std_init=jnp.float32(cfg.es_sigma))
    key = jax.random.PRNGKey(cfg.seed + 7)
    digest = config_digest(cfg, f"es{pop}")
    B = cfg.train_batch
    pop_loss = population_objective(problem, pop, B)

    def advance(state, gen):
        k_ask, k_tell = jax.random.split(jax.random.fold_in(key, gen))
        pop_u, state = es.ask(k_ask, state, es_params)
        terr, keys = problem.train_batch(gen)
        fit = pop_loss(pop_u, terr, keys)
        fit = jnp.where(jnp.isfinite(fit), fit, jnp.max(jnp.where(jnp.isfinite(fit), fit, 0.0)) + 1.0)
        state, _ = es.tell(k_tell, pop_u, fit, state, es_params)
        fields = {"train_objective": float(jnp.mean(fit)), "best_in_generation": float(jnp.min(fit))}
        limits = getattr(pop_loss, "limits", None)
        if limits and limits[-1]:  # MuJoCo Warp's: how many of the generation's walks hit its solver's limits
            fields["warp_limits"] = {k: limits[-1][k] for k in LIMIT_KEYS}
        return state, fields

    # evaluate whenever the rollouts used cross a multiple of the gradient run's evaluation period
    should_eval = eval_schedule(pop, cfg.eval_every, eval_at)
    label = f"{name.replace('_', '-')} (pop {pop})"
    res = drive(problem, out_dir, method=label, digest=digest, state=es.init(key, u0, es_params),
                params_of=es.get_mean, advance=advance,
                n_steps=None if rollouts is None else max(1, rollouts // (pop * B)),
                rollouts_per_step=pop * B, should_eval=should_eval, resume=resume, progress=progress,
                time_limit=time_limit, t_start=t_start)
    hit = [e["warp_limits"] for e in res["log"] if "warp_limits" in e]
    if hit:  # one line for the run instead of one a generation
        total = {k: sum(h[k] for h in hit) for k in LIMIT_KEYS}
        print(f"MuJoCo Warp over {len(hit)} generations: {total['line_search_limit']:,} of {total['envs']:,} walks "
              f"ended a line search at its limit, {total['iteration_limit']:,} a Newton solve at its limit"
              + (f", {total['other']:,} overflowed a pool" if total["other"] else "") + " (each generation's in "
              "log.json, warp_limits)")
    return res
