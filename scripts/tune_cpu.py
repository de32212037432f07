"""Issue 5's CPU entry point: tune the tactile method from the papers' hand rules for at most 15 min of wall
time on this machine (compile and held-out evaluations included), then give CMA-ES (evosax) the same number
of rollouts, and then the same wall time, on the same objective. Writes out/tune/<config>/{grad,es,es_wall}/
(log.json, tune.png, checkpoint.npz) and a comparison JSON + plot.

    python scripts/tune_cpu.py [--config configs/tune/tactile_tripod.yaml] [--minutes 15] [--json F]

Rerunning resumes from the checkpoints (delete out/tune/<config> or pass --restart to start over); the
equal-wall-time run restarts its clock on resume, so rebuild the table with --report instead."""

import argparse
import json
import os
import time

from hexjax.analysis.tune import compare_plot, tune, tune_es
from hexjax.analysis.tune_config import load_tune_config

ap = argparse.ArgumentParser()
ap.add_argument("--config", default="configs/tune/tactile_tripod.yaml")
ap.add_argument("--minutes", type=float, default=15.0, help="wall-time limit per method")
ap.add_argument("--steps", type=int, default=None, help="gradient steps (default: the config's)")
ap.add_argument("--restart", action="store_true")
ap.add_argument("--skip-wall", action="store_true", help="skip the equal-wall-time CMA-ES run")
ap.add_argument("--report", action="store_true", help="only rebuild the JSON and plot from finished runs' logs")
ap.add_argument("--json", default="docs/results/tune_cpu.json")
a = ap.parse_args()

cfg = load_tune_config(a.config, {"steps": a.steps} if a.steps else None)
out = os.path.join("out", "tune", os.path.splitext(os.path.basename(a.config))[0])
limit = 60 * a.minutes - 60  # the last step and the final held-out evaluation must fit in the limit
t0 = time.perf_counter()
if a.report:  # rebuild the comparison from finished runs' logs, running nothing
    runs = []
    for m in ("grad", "es", "es_wall"):
        path = os.path.join(out, m, "log.json")
        if os.path.exists(path):
            with open(path) as f:
                runs.append(json.load(f))
            if m == "es_wall":
                runs[-1]["method"] += ", same wall time"
else:
    g = tune(cfg, os.path.join(out, "grad"), resume=not a.restart, time_limit=limit)
    runs = [g, tune_es(cfg, os.path.join(out, "es"), rollouts=g["log"][-1]["rollouts"], resume=not a.restart)]
    if not a.skip_wall:
        runs.append(tune_es(cfg, os.path.join(out, "es_wall"), rollouts=10 ** 6, resume=not a.restart,
                            time_limit=limit))
        runs[-1]["method"] += ", same wall time"
g = runs[0]

rows = []
for r in runs:
    last = r["log"][-1]
    rows.append({"method": r["method"], "rollouts": last["rollouts"], "wall_s": last["wall_s"],
                 "held_out_start": r["start"]["held_out"], "held_out_final": r["final"]["held_out"],
                 "selected_step": r["final"]["step"], "held_out_last": r["last"]["held_out"],
                 "improvement_pct": r["improvement_pct"], "params_final": r["final"]["params"],
                 "curve": [(e["rollouts"], e["held_out"]["objective"]) for e in r["log"] if "held_out" in e]})
    print(f"{r['method']:32s} {last['rollouts']:5d} rollouts {last['wall_s']:6.0f} s  held-out J "
          f"{r['start']['held_out']['objective']:.4f} -> {r['final']['held_out']['objective']:.4f} m "
          f"({r['improvement_pct']:+.1f} %, iterate {r['final']['step']} picked by validation; last iterate "
          f"{r['last']['held_out']['objective']:.4f} m)")
res = {"config": a.config, "minutes": a.minutes, "total_wall_s": None if a.report else time.perf_counter() - t0, "runs": rows,
       "start_params": g["start"]["params"]}
os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
with open(a.json, "w") as f:
    json.dump(res, f, indent=2, default=float)
png = a.json[:-5] + ".png"
compare_plot(rows, png)
print(f"wrote {a.json} and {png}")
