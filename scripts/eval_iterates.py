"""Issue 19: the held-out objective, on this machine, of iterates of a finished `hexjax tune` run and of running
averages of them (`optimizer.average`), without training again.

    python scripts/eval_iterates.py docs/results/tune_cpg_st_sgd_clip10_h100_ho200_seed0_s15.json \
        --steps 0,3,13,14 --average 0.7 --json out/iterates.json

The run's config (held-out terrains, seed, controller) is read from its log. Each candidate is scored by the
held-out evaluation the tuner uses (hard rollout, `held_out_batch` terrains): the logged params of each step in
--steps, the final (validation-picked) iterate, and for each value in --average the exponential moving
average of the iterates of steps 1..last in the unconstrained params (`hexjax.tune.grad.average_iterate`, what
`optimizer.average` evaluates during a run). Prints one JSON line per candidate; --json writes them all.
Figures: docs/tuning.md, "Gradient against CMA-ES"."""

import argparse
import json
import time

from hexjax.tune.config import TuneConfig
from hexjax.tune.grad import average_iterate
from hexjax.tune.objective import Problem, evaluate_held_out
from hexjax.tune.space import with_values


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("log", help="a run's log.json (hexjax tune --out DIR writes DIR/<method>/log.json)")
    ap.add_argument("--steps", default="", help="comma list of logged steps to score")
    ap.add_argument("--average", default="", help="comma list of averaging fractions in (0, 1)")
    ap.add_argument("--json", default="", help="write the rows here")
    a = ap.parse_args()
    with open(a.log) as fh:
        run = json.load(fh)
    problem = Problem.build(TuneConfig(**run["config"]))
    logged = {e["step"]: e["params"] for e in run["log"]}
    u_of = lambda params: problem.space.init(with_values(problem.params0, params, a.log))
    cands = [(f"step {s}", logged[int(s)]) for s in a.steps.split(",") if s]
    cands.append((f"final (step {run['final']['step']}, as returned)", run["final"]["params"]))
    last = max(logged)
    for beta in (float(b) for b in a.average.split(",") if b):
        if not 0 < beta < 1:
            raise SystemExit(f"--average {beta}: must be in (0, 1)")
        avg = None  # step 1's average is its iterate
        for k in range(1, last + 1):
            avg = average_iterate(avg, u_of(logged[k]), k, beta)
        cands.append((f"average {beta} of steps 1-{last}", problem.space.physical(avg)))
    model, fn = problem.eval_rollout()
    rows = []
    for name, params in cands:
        t0 = time.perf_counter()
        r = evaluate_held_out(problem, u_of(params), fn, model)
        row = {"candidate": name, "held_out_objective": round(r["objective"], 4),
               "goal_error_cm": round(r["goal_error_cm"], 2), "fall_pct": r["fall_pct"],
               "seconds": round(time.perf_counter() - t0, 1)}
        print(json.dumps(row), flush=True)
        rows.append(row)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"log": a.log, "held_out_batch": problem.cfg.held_out_batch, "rows": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
