"""The evolution-strategy baseline: CMA-ES (evosax) on the same unconstrained params, smooth objective and
terrain stream as the gradient tuner, given its rollout budget or its wall time (docs/tuning.md)."""

from __future__ import annotations

import time
from typing import Any, Dict, Optional

import jax
import jax.numpy as jnp
from evosax.algorithms import CMA_ES

from hexjax.tune.config import TuneConfig
from hexjax.tune.driver import cached, config_digest, drive, program_digest
from hexjax.tune.objective import Problem, per_env_objective


def tune_es(cfg: TuneConfig, out_dir: str, rollouts: int, resume: bool = True, progress: bool = True,
            time_limit: Optional[float] = None) -> Dict[str, Any]:
    """CMA-ES (evosax) on the same unconstrained params and the same smooth training objective (or, with
    `es_objective: hard`, the hard form that evaluation uses: CMA-ES needs no gradient), with the same
    terrain stream: generation k evaluates every member of its population on the `train_batch`
    terrains of step k. It stops after `rollouts` rollouts (population x train_batch per generation), so it
    can be given exactly the gradient run's budget. Its starting mean is the hand rules; its step size is
    `cfg.es_sigma` on the unconstrained scale. Held-out evaluations of the mean as for `tune`."""
    t_start = time.perf_counter()
    problem = Problem.build(cfg)
    u0 = problem.space.init(problem.params0)
    pop = cfg.es_population
    es = CMA_ES(population_size=pop, solution=u0)
    es_params = es.default_params.replace(std_init=jnp.float32(cfg.es_sigma))
    key = jax.random.PRNGKey(cfg.seed + 7)
    digest = config_digest(cfg, f"es{pop}")
    hard = cfg.es_objective == "hard"
    model, fn = (problem.hard_rollout(params_batched=True) if hard else
                 problem.train_rollout(grad=False, params_batched=True))
    start = problem.eval_params0 if hard else problem.params0
    B = cfg.train_batch

    # every member on the same terrains: params batched over pop x B envs
    def population_loss(pop_u, terr, keys):
        tile = lambda x: jnp.tile(x, (pop,) + (1,) * (x.ndim - 1))
        flat_p = jax.vmap(lambda uu: problem.space.apply(uu, start))(pop_u)
        params = jax.tree_util.tree_map(lambda x: jnp.repeat(x, B, axis=0), flat_p)
        s = fn(model, params, jax.tree_util.tree_map(tile, terr), tile(keys))
        j = per_env_objective(s, cfg.distance, cfg.objective)
        return j.reshape(pop, B).mean(1)

    program = program_digest(cfg, f"es{pop}")
    pop_loss = cached(program + "/pop", lambda: jax.jit(population_loss), problem.static("es/pop", program))

    def advance(state, gen):
        k_ask, k_tell = jax.random.split(jax.random.fold_in(key, gen))
        pop_u, state = es.ask(k_ask, state, es_params)
        terr, keys = problem.train_batch(gen)
        fit = pop_loss(pop_u, terr, keys)
        fit = jnp.where(jnp.isfinite(fit), fit, jnp.max(jnp.where(jnp.isfinite(fit), fit, 0.0)) + 1.0)
        state, _ = es.tell(k_tell, pop_u, fit, state, es_params)
        return state, {"train_objective": float(jnp.mean(fit)), "best_in_generation": float(jnp.min(fit))}

    # evaluate whenever the rollouts used cross a multiple of the gradient run's evaluation period
    should_eval = lambda gen: (gen * pop) // cfg.eval_every > ((gen - 1) * pop) // cfg.eval_every
    return drive(problem, out_dir, f"cma-es (pop {pop})", digest, es.init(key, u0, es_params), es.get_mean,
                  advance, max(1, rollouts // (pop * B)), pop * B, should_eval, resume, progress, time_limit, t_start)
