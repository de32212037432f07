"""Issues 5 and 19: variance and sign of the windowed MJX gradient and of the hybrid estimate against batch
size, from one compiled call.

Every env gets its own copy of the unconstrained params, so one backward pass through N envs returns N
per-env windowed gradients g_e of the per-env objective J_e; with --pairs K > 0 every env also runs K
antithetic perturbations (forward), the whole walk's directional derivatives that the hybrid estimate
(`hexjax.tune.hybrid`) fits. A batch of B envs gives one estimate per estimator: the windowed gradient
(first_order: the mean of its g_e), the hybrid one, and the same fit without the windowed prior
(zeroth_order).

Printed and written, per parameter and for B in {1, 2, 4, 8, 16, 32} (2,000 random batches each):
- rel. std: ||sd of the B-env estimate|| / ||its mean||;
- sign agreement with the estimator's own N-env estimate;
- with --pairs: sign agreement with a reference computed on other envs: the envs are split in two halves,
  the reference is the zeroth-order fit to all of the first half's pairs, the B-env batches are drawn from
  the second half. A biased estimator (the windowed gradient of a delayed effect) agrees with
  its own mean but not with this reference.

    python scripts/grad_variance.py [--config tactile_tripod] [--n 32] [--window S] [--pairs K] [--sigma S]
        [--prior L] [--solver-grad implicit] [--json F]     (writes F and, with --pairs, F's .npz beside it)
    python scripts/grad_variance.py --from-npz F.npz [--prior L] [--json F2]   (the tables again, offline)"""

import argparse
import json
import os
import time

import jax
import numpy as np

from hexjax.tune.config import load_tune_config
from hexjax.tune.hybrid import combine, per_env_estimates, per_env_gradients
from hexjax.tune.objective import Problem

ap = argparse.ArgumentParser()
ap.add_argument("--config", default="tactile_tripod", help="tuning config name or .yaml path")
ap.add_argument("--n", type=int, default=32)
ap.add_argument("--seed", type=int, default=11, help="terrain stream step (not used by tuning's first steps)")
ap.add_argument("--window", type=float, default=None, help="s (default: the config's)")
ap.add_argument("--pairs", type=int, default=0, help="antithetic perturbations per env for the hybrid (0: none)")
ap.add_argument("--sigma", type=float, default=None, help="their scale, unconstrained (default: the config's zo_sigma)")
ap.add_argument("--prior", type=float, default=None, help="the hybrid's zo_prior (default: the config's)")
ap.add_argument("--solver-grad", default=None, help="unrolled or implicit (default: the config's)")
ap.add_argument("--from-npz", default=None, help="recompute the tables from a run's saved .npz (no rollouts)")
ap.add_argument("--json", default="docs/results/grad_variance.json")
a = ap.parse_args()

over = {k: v for k, v in (("window", a.window), ("zo_sigma", a.sigma), ("zo_prior", a.prior),
                          ("solver_grad", a.solver_grad)) if v}
cfg = load_tune_config(a.config, over)
problem = Problem.build(cfg)
u0 = problem.space.init(problem.params0)
t0 = time.perf_counter()
if a.from_npz:
    z = np.load(a.from_npz)
    j, G, EPS, D = z["j"], z["G"], z["EPS"], z["D"]
    a.n, a.pairs = len(G), EPS.shape[1]
elif a.pairs:
    terr, keys = problem.train_batch(10_000 + a.seed, n=a.n)
    grad_rollout = problem.train_rollout(grad=True, params_batched=True)
    est = per_env_estimates(problem, grad_rollout, problem.train_rollout(grad=False, params_batched=True), a.pairs,
                            cfg.zo_sigma)
    j, G, EPS, D = (np.asarray(x) for x in jax.jit(est)(u0, terr, keys, jax.random.PRNGKey(a.seed)))
else:
    terr, keys = problem.train_batch(10_000 + a.seed, n=a.n)
    grads = per_env_gradients(problem, problem.train_rollout(grad=True, params_batched=True))
    j, G = (np.asarray(x) for x in jax.jit(grads)(u0, terr, keys))
wall = time.perf_counter() - t0
# the flat order of ravel_pytree: the dict's sorted keys, each array flattened
labels = [f"{n}[{i}]" if np.size(u0[n]) > 1 else n for n in sorted(u0) for i in range(np.size(u0[n]))]
finite = np.all(np.isfinite(G), axis=1)
rng = np.random.default_rng(0)
estimators = {"first_order": lambda i: G[i].mean(0)}
if a.pairs:
    estimators["hybrid"] = lambda i: combine(G[i], EPS[i], D[i], cfg.zo_prior, np)
    estimators["zeroth_order"] = lambda i: combine(np.zeros_like(G[i]), EPS[i], D[i], 1e-6, np)


def table(estimate, pool, ref):
    """Rows over B of rel. std and sign agreement (with the estimate from all of `pool`, and with `ref`)."""
    own = estimate(pool)
    rows = []
    for b in (1, 2, 4, 8, 16, 32):
        if b > len(pool):
            break
        draws = np.stack([estimate(rng.choice(pool, b, replace=False)) for _ in range(2000)])
        row = {"batch": b, "rel_std": float(np.linalg.norm(draws.std(0)) / np.linalg.norm(draws.mean(0))),
               "sd": draws.std(0).tolist(),
               "sign_agreement_own_mean": (np.sign(draws) == np.sign(own)).mean(0).tolist()}
        if ref is not None:
            row["sign_agreement_reference"] = (np.sign(draws) == np.sign(ref)).mean(0).tolist()
        rows.append(row)
    return {"estimate_all": own.tolist(), "rows": rows}


idx = np.nonzero(finite)[0]
res = {}
if a.pairs:
    half = len(idx) // 2
    ref_pool, test_pool = idx[:half], idx[half:]
    reference = estimators["zeroth_order"](ref_pool)
    res["reference"] = {"estimate": reference.tolist(), "envs": int(half), "pairs": int(half * a.pairs)}
    print("reference (zeroth-order fit to the first half): "
          + ", ".join(f"{n}={m:+.3g}" for n, m in zip(labels, reference)))
else:
    test_pool, reference = idx, None
for name, fn_est in estimators.items():
    r = res[name] = table(fn_est, test_pool, reference)
    print(f"{name}: estimate from all {len(test_pool)} envs "
          + ", ".join(f"{n}={m:+.3g}" for n, m in zip(labels, r["estimate_all"])))
    for row in r["rows"]:
        line = f"  B={row['batch']:3d}: rel. std {row['rel_std']:6.2f}; sign = own " + " ".join(
            f"{n}={s:.2f}" for n, s in zip(labels, row["sign_agreement_own_mean"]))
        if "sign_agreement_reference" in row:
            line += "; sign = reference " + " ".join(
                f"{n}={s:.2f}" for n, s in zip(labels, row["sign_agreement_reference"]))
        print(line)
print(f"objective of the {a.n} envs: {float(np.mean(j)):.4f} m; {int((~finite).sum())} envs with a non-finite "
      f"estimate; {wall:.0f} s with compile on {jax.devices()[0]}")
os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
with open(a.json, "w") as f:
    json.dump({"config": a.config, "window_s": cfg.window, "solver_grad": cfg.solver_grad, "pairs": a.pairs,
               "sigma": cfg.zo_sigma, "prior": cfg.zo_prior, "device": str(jax.devices()[0]), "n": a.n, "names": labels,
               "nonfinite": int((~finite).sum()), "objective": float(np.mean(j)), "wall_s": wall,
               "from_npz": a.from_npz, **res}, f, indent=2)
if a.pairs and not a.from_npz:  # the raw per-env numbers, to recompute any estimator offline
    np.savez(os.path.splitext(a.json)[0] + ".npz", j=j, G=G, EPS=EPS, D=D, labels=np.array(labels))
print(f"wrote {a.json}")
