"""Issue 19: judge CPG params on the Yu 2019 experiments' own terrains (yu2019-step: step40, step50;
yu2019-ditch: ditch18, ditch40, ditch80), hard mode, the reflexes variant only, with the paper's numbers
or with tuned ones (a `hexjax tune` log.json: its picked iterate).

    python scripts/judge_cpg.py --json docs/results/paper.json [--params out/tune/.../log.json]
        [--batch 16] [--physics validated]

The experiments' terrain seeds (seed 0) are not among the tuning's training, held-out or validation draws.
With --params the same is `hexjax experiment yu2019-step --params F` (all variants)."""

import argparse
import json
import os
import time

from hexjax.experiments.registry import experiment
from hexjax.experiments.yu2019 import format_experiment, run_experiment
from hexjax.tune.space import load_values

ap = argparse.ArgumentParser()
ap.add_argument("--params", default=None, help="tuned params (log.json or a mapping); default: the paper's")
ap.add_argument("--batch", type=int, default=16)
ap.add_argument("--physics", default="validated", help="physics preset or .yaml path (docs/physics.md)")
ap.add_argument("--json", required=True)
a = ap.parse_args()

params = load_values(a.params) if a.params else None
out = {}
for name in ("yu2019-step", "yu2019-ditch"):
    preset = dict(experiment(name).preset)
    preset["variants"] = {"reflexes": {}}
    t = time.time()
    res = run_experiment(name, batch=a.batch, seed=0, record=False, progress=False, preset=preset, params=params,
                         physics=a.physics)
    res.pop("_records")
    print(format_experiment(res), f"({time.time() - t:.0f} s)", flush=True)
    out[name] = res
os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
with open(a.json, "w") as f:
    json.dump(out, f, indent=1)
print(f"wrote {a.json}")
