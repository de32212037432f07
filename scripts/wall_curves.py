"""Held-out objective against wall seconds for several `hexjax tune` runs of one config (gradient,
hybrid, CMA-ES), and when each first reaches the final held-out objective of the one named by --target.

    python scripts/wall_curves.py out/a/log.json out/b/log.json ... [--labels a,b,...] [--target 2]
        [--png docs/results/x.png] [--json docs/results/x.json]

A run's points are its evaluated iterates (step 0 and every `eval_every` steps): (the method's wall seconds
since the run started, its compile included and the held-out evaluations left out; held-out objective of
that iterate). "final" is the iterate the
run returns (picked on the validation terrains)."""

import argparse
import json
import os

ap = argparse.ArgumentParser()
ap.add_argument("logs", nargs="+")
ap.add_argument("--labels", default="", help="comma-separated, one per log (default: each run's method)")
ap.add_argument("--target", type=int, default=-1, help="index of the run whose final held-out objective is the bar")
ap.add_argument("--title", default="")
ap.add_argument("--png", default="")
ap.add_argument("--json", default="")
a = ap.parse_args()

runs = []
for i, path in enumerate(a.logs):
    with open(path) as f:
        r = json.load(f)
    label = a.labels.split(",")[i] if a.labels else r["method"]
    # the method's own seconds (evaluations left out; older logs have only wall_s)
    secs = lambda e: e["train_s"] if "train_s" in e else e["wall_s"]
    pts = [(secs(e), e["held_out"]["objective"], e["step"]) for e in r["log"] if "held_out" in e]
    runs.append({"label": label, "log": path, "curve": pts, "final": r["final"]["held_out"]["objective"],
                 "final_step": r["final"]["step"], "start": r["start"]["held_out"]["objective"],
                 "wall_s": secs(r["log"][-1]), "steps": r["log"][-1]["step"],
                 "rollouts": r["log"][-1]["rollouts"], "nonfinite_grad_steps": sum(
                     1 for e in r["log"] if e.get("grad_finite") is False)})
bar = runs[a.target]
for r in runs:
    # the first evaluated iterate at or below the target run's final held-out objective
    hit = next(((w, j) for w, j, _ in r["curve"] if j <= bar["final"]), None)
    r["reaches_target_at_s"] = None if hit is None else hit[0]
    best = min(r["curve"], key=lambda p: p[1])
    print(f"{r['label']:28s} start {r['start']:.4f} -> final {r['final']:.4f} (best evaluated {best[1]:.4f} at "
          f"{best[0]:.0f} s), {r['steps']} steps, {r['rollouts']} rollouts, {r['wall_s']:.0f} s; reaches "
          f"{bar['label']}'s final {bar['final']:.4f}: "
          + ("never" if hit is None else f"at {hit[0]:.0f} s ({hit[0] / bar['wall_s']:.2f} of its wall time)"))
if a.png:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    for r in runs:
        w, j, _ = zip(*r["curve"])
        ax.plot(w, j, "o-", ms=3, label=r["label"])
    ax.axhline(bar["final"], color="0.5", ls=":", lw=1, label=f"{bar['label']}: final")
    ax.set_xlabel("wall seconds of the method (compile included, held-out evaluations left out)")
    ax.set_ylabel("held-out objective J (m, hard mode)")
    ax.set_title(a.title, fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(a.png)), exist_ok=True)
    fig.savefig(a.png, dpi=110)
    print(f"wrote {a.png}")
if a.json:
    os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
    with open(a.json, "w") as f:
        json.dump({"target": bar["label"], "runs": runs}, f, indent=2)
    print(f"wrote {a.json}")
