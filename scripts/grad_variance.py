"""Issue 5: variance of the windowed MJX gradient against batch size, from one rollout.

Every env gets its own copy of the unconstrained params (params_batched), so one backward pass through N
envs returns N per-env gradients g_e of the per-env objective J_e. A batch of B envs averages B of them:
its covariance is the per-env covariance / B. Printed and written per parameter: the per-env mean and
std, and for B in {1, 2, 4, 8, 16, 32} the relative error ||std of the batch mean|| / ||mean|| and the
sign agreement P(sign of the batch mean = sign of the N-env mean), the latter measured by resampling.

    python scripts/grad_variance.py [--config tactile_tripod] [--n 32] [--window S] [--json F]"""

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from hexjax.tune.config import load_tune_config
from hexjax.tune.objective import Problem, per_env_objective

ap = argparse.ArgumentParser()
ap.add_argument("--config", default="tactile_tripod", help="tuning config name or .yaml path")
ap.add_argument("--n", type=int, default=32)
ap.add_argument("--seed", type=int, default=11, help="terrain stream step (not used by tuning's first steps)")
ap.add_argument("--window", type=float, default=None, help="s (default: the config's)")
ap.add_argument("--json", default="docs/results/grad_variance.json")
a = ap.parse_args()

cfg = load_tune_config(a.config, {"window": a.window} if a.window else None)
problem = Problem.build(cfg)
u0 = problem.space.init(problem.params0)
model, fn = problem.train_rollout(grad=True, params_batched=True)
terr, keys = problem.train_batch(10_000 + a.seed, n=a.n)


def total(ub):
    params = jax.vmap(lambda u: problem.space.apply(u, problem.params0))(ub)
    j = per_env_objective(fn(model, params, terr, keys), cfg.distance, cfg.objective)
    return jnp.sum(j), j


ub = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (a.n,) + x.shape), u0)
t0 = time.perf_counter()
(_, j), g = jax.jit(jax.value_and_grad(total, has_aux=True))(ub)
wall = time.perf_counter() - t0
names = problem.space.names
G = np.concatenate([np.asarray(g[k]).reshape(a.n, -1) for k in names], axis=1)  # (N, P) per-env gradients
finite = np.all(np.isfinite(G), axis=1)
G = G[finite]
mean, std = G.mean(0), G.std(0, ddof=1)
rng = np.random.default_rng(0)
rows = []
for b in (1, 2, 4, 8, 16, 32):
    if b > len(G):
        break
    draws = np.stack([G[rng.choice(len(G), b, replace=False)].mean(0) for _ in range(2000)])
    rel = float(np.linalg.norm(std / np.sqrt(b)) / np.linalg.norm(mean))
    sign = (np.sign(draws) == np.sign(mean)).mean(0)
    cos = (draws @ mean) / (np.linalg.norm(draws, axis=1) * np.linalg.norm(mean) + 1e-30)
    rows.append({"batch": b, "rel_std": rel, "sign_agreement": sign.tolist(), "cos_to_mean": float(np.mean(cos))})
    print(f"B={b:3d}: ||std|| / ||mean|| = {rel:6.2f}, mean cosine to the {len(G)}-env gradient {np.mean(cos):5.2f}, "
          "sign agreement " + " ".join(f"{n}={s:.2f}" for n, s in zip(names, sign)))
print("per-env mean gradient: " + ", ".join(f"{n}={m:+.3g} (sd {s:.3g})" for n, m, s in zip(names, mean, std)))
print(f"objective of the {a.n} envs: {float(np.mean(j)):.4f} m; {int((~finite).sum())} non-finite gradients; "
      f"{wall:.0f} s with compile")
os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
with open(a.json, "w") as f:
    json.dump({"config": a.config, "window_s": cfg.window, "device": str(jax.devices()[0]), "n": a.n, "names": list(names), "mean": mean.tolist(), "std": std.tolist(),
               "nonfinite": int((~finite).sum()), "objective": float(np.mean(j)), "rows": rows, "wall_s": wall}, f,
              indent=2)
print(f"wrote {a.json}")
