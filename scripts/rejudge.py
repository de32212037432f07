"""Judge the params of finished `hexjax tune` runs again on a larger held-out set: each log's start and
returned iterate (with --all, every evaluated iterate) on the config's held-out terrains at another batch, on
its eval physics. For a race judged on few terrains, whether a method's gain is larger than the set's noise.

    python scripts/rejudge.py --config cpg_legs --set held_out_batch=160 out/a/log.json out/b/log.json
        [--labels SGD,CMA-ES] [--all | --steps 8,12] [--training-physics] [--json docs/results/x.json]

The held-out terrains come from the config's seed as in a tuning run (`Problem.eval_batch`), so a batch of n
is the set a run with held_out_batch n would have been judged on. Prints a line per iterate with the standard
error of its per-terrain objective and of its paired difference from the start (the same terrains), and writes
the figures, per terrain too, as JSON. With --training-physics the iterates are judged on the solver the gradient
trained on (MJX) instead: what the tuner saw, against what it is judged on."""

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

ap = argparse.ArgumentParser()
ap.add_argument("logs", nargs="+")
ap.add_argument("--config", required=True, help="the tune config the runs used (name or path)")
ap.add_argument("--set", action="append", default=[], help="key=value overrides, e.g. held_out_batch=160")
ap.add_argument("--labels", default="")
ap.add_argument("--all", action="store_true", help="every evaluated iterate, not only the start and the pick")
ap.add_argument("--steps", default="", help="comma-separated iterates to judge as well (e.g. 8,12)")
ap.add_argument("--reuse", default="", help="an earlier --json of the same config and batch: its iterates are not "
                                            "rolled out again")
ap.add_argument("--training-physics", action="store_true",
                help="judge on the config's training solver (MJX) instead of its eval physics")
ap.add_argument("--json", default="")
a = ap.parse_args()

from hexjax.experiments.commands.tuning import parse_sets  # noqa: E402
from hexjax.tune.config import load_tune_config  # noqa: E402

cfg = load_tune_config(a.config, parse_sets(a.set), merge=True)
extra = [x.strip() for x in a.steps.split(",") if x.strip()]
if not all(x.isdigit() for x in extra):
    raise SystemExit(f"--steps {a.steps!r}: give iterate numbers, e.g. 8,12")
extra = {int(x) for x in extra}
if a.labels and len(a.labels.split(",")) != len(a.logs):
    raise SystemExit(f"--labels {a.labels!r}: {len(a.labels.split(','))} labels for {len(a.logs)} logs")
runs = []
for i, path in enumerate(a.logs):
    if not os.path.exists(path):
        raise SystemExit(f"logs: {path!r} does not exist")
    with open(path) as f:
        r = json.load(f)
    runs.append((a.labels.split(",")[i] if a.labels else r["method"], path, r))

import numpy as np  # noqa: E402

from hexjax.tune.objective import Problem, evaluate_held_out  # noqa: E402
from hexjax.tune.space import with_values  # noqa: E402

problem = Problem.build(cfg)
if a.training_physics:
    import dataclasses

    from hexjax.sim.rollout import rollout_function
    model, fn = rollout_function(problem.robot, problem.eval_ctrl, problem.duration, physics=problem.physics(),
                                 kept=True)
    judged_on = {"name": "the training solver", "engine": "mjx", **dataclasses.asdict(problem.physics())}
else:
    model, fn = problem.eval_rollout()
    judged_on = cfg.judge().record()


seen = {}  # params already judged (runs from one start judge it once), by their JSON
if a.reuse:
    with open(a.reuse) as f:
        prev = json.load(f)
    if (prev["config"], prev["held_out_batch"], prev["physics"]) != (a.config, cfg.held_out_batch, judged_on):
        raise SystemExit(f"--reuse {a.reuse}: judged {prev['config']} on {prev['held_out_batch']} terrains, not "
                         f"{a.config} on {cfg.held_out_batch}, or on other physics")
    for pr in prev["runs"]:
        with open(pr["log"]) as f:
            by_step = {e["step"]: e for e in json.load(f)["log"]}
        for row in pr["iterates"]:
            seen[json.dumps(by_step[row["step"]]["params"], sort_keys=True)] = {
                **{k: row[k] for k in ("objective", "stderr", "goal_error_cm", "fall_pct", "nan_envs")},
                "per_env": np.asarray(row["per_env"])}


def judge(params):
    k = json.dumps(params, sort_keys=True)
    if k not in seen:
        seen[k] = _judge(params)
    return seen[k]


def _judge(params):
    u = problem.space.init(with_values(problem.eval_params0, params))  # a log's physical numbers, as in a run
    res = evaluate_held_out(problem, u, fn, model, per_env=True)
    if res["nan_envs"]:
        print(f"  {res['nan_envs']} env(s) ended non-finite", flush=True)
    j = res["per_env"]
    return {**{k: res[k] for k in ("objective", "goal_error_cm", "fall_pct", "nan_envs")}, "per_env": j,
            "stderr": float(j.std(ddof=1) / np.sqrt(len(j)))}


print(f"{cfg.held_out_batch} held-out terrains of {a.config} on {judged_on['name']} ({judged_on['engine']})")
out = {"config": a.config, "sets": a.set, "held_out_batch": cfg.held_out_batch, "physics": judged_on, "runs": []}
for label, path, r in runs:
    steps = [e for e in r["log"] if "held_out" in e]
    if not a.all:
        steps = [steps[0]] + [e for e in steps if e["step"] != 0 and (e["step"] == r["final"]["step"]
                                                                       or e["step"] in extra)]
    rows = []
    for e in steps:
        t = time.perf_counter()
        res = judge(e["params"])
        rows.append({"step": e["step"], "rollouts": e["rollouts"], "logged": e["held_out"]["objective"],
                     "objective": res["objective"], "stderr": res["stderr"],
                     "goal_error_cm": res["goal_error_cm"], "fall_pct": res["fall_pct"], "nan_envs": res["nan_envs"],
                     "returned": e["step"] == r["final"]["step"], "per_env": res["per_env"].tolist()})
        d = res["per_env"] - judge(steps[0]["params"])["per_env"]  # the same terrains: a paired difference
        rows[-1].update(vs_start=float(d.mean()), vs_start_stderr=float(d.std(ddof=1) / np.sqrt(len(d))))
        print(f"{label:8s} iterate {e['step']:3d}{' (returned)' if rows[-1]['returned'] else '':11s} "
              f"J {res['objective']:.4f} +- {res['stderr']:.4f} (logged {e['held_out']['objective']:.4f} on "
              f"{r['config']['held_out_batch']}), goal error {rows[-1]['goal_error_cm']:.1f} cm, falls "
              f"{rows[-1]['fall_pct']:.1f} %; against the start {rows[-1]['vs_start']:+.4f} +- "
              f"{rows[-1]['vs_start_stderr']:.4f} [{time.perf_counter() - t:.0f} s]", flush=True)
    out["runs"].append({"label": label, "log": path, "iterates": rows})
if a.reuse:  # the earlier file's other runs stay in the figures
    labels = {r["label"] for r in out["runs"]}
    out["runs"] += [pr for pr in prev["runs"] if pr["label"] not in labels]
if a.json:
    with open(a.json, "w") as f:
        json.dump(out, f, indent=2)
    print(f"wrote {a.json}")
