"""Chen 2019 Sect. 2.2, Steps 1-5: how close the paper's iterative incenter comes to the exact one
(`hexjax.plan.support`), over random convex polygons of 3-6 sides."""

from __future__ import annotations

import time
from typing import Dict

import jax
import jax.numpy as jnp
import numpy as np

from hexjax.plan.support import incenter_exact, incenter_iterative, random_polygons


def incenter_study(key, n: int = 100_000, sides=(3, 4, 5, 6), iterations: int = 60) -> dict:
    """The iterative incenter's error against the exact one over n random polygons per side count:
    relative radius shortfall (r_exact - r_iter) / r_exact and centre offset / r_exact, as percentiles."""
    out = {"n_per_sides": n, "iterations": iterations, "by_sides": {}}
    k_max = max(sides)
    it = jax.jit(jax.vmap(lambda p, v: incenter_iterative(p, v, iterations)))
    ex = jax.jit(jax.vmap(incenter_exact))
    for j, k in enumerate(sides):
        poly, valid = random_polygons(jax.random.fold_in(key, j), n, k, k_max)
        ci, ri = it(poly, valid)
        ce, re = ex(poly, valid)
        rel = np.asarray((re - ri) / re)
        off = np.asarray(jnp.linalg.norm(ci - ce, axis=-1) / re)
        q = [50, 90, 99, 99.9, 100]
        out["by_sides"][str(k)] = {
            "radius_shortfall": {f"p{x:g}": float(np.percentile(rel, x)) for x in q},
            "centre_offset": {f"p{x:g}": float(np.percentile(off, x)) for x in q},
            "iterative_exceeds_exact": int(np.sum(rel < -1e-4)),
            "within_1e-3": float(np.mean(rel <= 1e-3)),
        }
    return out


# The experiment (configs/experiments/chen2019-incenter.yaml) -----------------------------------------------
def run(o, entry) -> Dict:
    if o.polygons < 1:
        raise ValueError(f"--polygons={o.polygons!r}: study at least 1 polygon per side count")
    t0 = time.perf_counter()
    res = incenter_study(jax.random.PRNGKey(o.seed), o.polygons, iterations=entry.preset["iterations"])
    res["seed"], res["wall_s"] = o.seed, time.perf_counter() - t0
    return res


def report(res: Dict) -> str:
    lines = [f"Chen 2019 iterative incenter (Steps 1-5, {res['iterations']} iterations) against the exact one, "
             f"{res['n_per_sides']} random convex polygons per side count (seed {res['seed']}):",
             f"{'sides':>5} {'radius shortfall p50':>21} {'p99':>9} {'p99.9':>9} {'max':>9} {'within 1e-3':>12} "
             f"{'centre offset p99 / r':>22}"]
    for k, d in res["by_sides"].items():
        r, c = d["radius_shortfall"], d["centre_offset"]
        lines.append(f"{k:>5} {r['p50']:>21.2e} {r['p99']:>9.2e} {r['p99.9']:>9.2e} {r['p100']:>9.2e} "
                     f"{100 * d['within_1e-3']:>11.2f}% {c['p99']:>22.2e}")
    return "\n".join(lines)
