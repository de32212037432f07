"""`hexjax tune`: tune a controller's params from the papers' hand rules by windowed gradients through MJX,
by CMA-ES on the same objective, or both (CMA-ES then gets the gradient run's rollouts, and with
`--equal-wall` also its wall time), with a comparison JSON and plot (docs/tuning.md)."""

from __future__ import annotations

import os
import time
from typing import Dict, List

from hexjax.experiments.runner import check_folder
from hexjax.tune.config import load_tune_config
from hexjax.world.files import resolve


def parse_sets(items) -> Dict:
    """['steps=5', 'optimizer.learning_rate=0.2'] -> nested overrides, values parsed as YAML."""
    import yaml
    out: Dict = {}
    for it in items or []:
        key, eq, val = it.partition("=")
        if not eq or not key:
            raise ValueError(f"--set {it!r}: use key=value (e.g. --set steps=5)")
        head, _, rest = key.partition(".")
        v = yaml.safe_load(val)
        if rest:
            out.setdefault(head, {})[rest] = v
        else:
            out[head] = v
    return out


def _row(r) -> Dict:
    last = r["log"][-1]
    return {"method": r["method"], "rollouts": last["rollouts"], "wall_s": last["wall_s"],
            "train_s": last.get("train_s", last["wall_s"]),
            "held_out_start": r["start"]["held_out"], "held_out_final": r["final"]["held_out"],
            "selected_step": r["final"]["step"], "selected_by": r["selected_by"],
            "held_out_last": r["last"]["held_out"],
            "improvement_pct": r["improvement_pct"], "params_start": r["start"]["params"],
            "params_final": r["final"]["params"],
            "skipped_steps": sum(1 for e in r["log"] if e.get("grad_finite") is False),
            "curve": [(e["rollouts"], e["held_out"]["objective"]) for e in r["log"] if "held_out" in e],
            # held-out J against the method's own seconds (evaluations left out), with its standard error
            "curve_s": [(e.get("train_s", e["wall_s"]), e["held_out"]["objective"], e["held_out"].get("objective_se"))
                        for e in r["log"] if "held_out" in e]}


def _paired(a, b) -> Dict:
    """Mean and standard error of the per-terrain difference a - b (the same held-out terrains and draws)."""
    import numpy as np
    d = np.asarray(a, float) - np.asarray(b, float)
    return {"mean": float(d.mean()), "se": float(d.std(ddof=1) / np.sqrt(d.size))}


def race(runs) -> Dict:
    """The equal-wall race of a gradient run (the first) against the evolution strategies after it: the gradient's
    held-out J less the start's and less each strategy's (paired over the held-out terrains), and the seconds the
    gradient took to first reach each strategy's picked J, as a fraction of that strategy's own seconds (None
    where it never did). Needs each evaluation's per-terrain J (logs written since they carry it)."""
    def per_env(r, which):
        return r[which]["held_out"].get("per_env_objective")

    g = runs[0]
    if per_env(g, "final") is None or per_env(g, "start") is None:
        return {}
    out = {"grad_less_start": _paired(per_env(g, "final"), per_env(g, "start")), "against": []}
    curve = [(e.get("train_s", e["wall_s"]), e["held_out"]["objective"]) for e in g["log"] if "held_out" in e]
    for r in runs[1:]:
        if per_env(r, "final") is None:
            continue
        target = r["final"]["held_out"]["objective"]
        own = r["log"][-1].get("train_s", r["log"][-1]["wall_s"])
        reach = next((t for t, j in curve if j <= target), None)
        out["against"].append({"method": r["method"], "es_train_s": own, "es_held_out": target,
                               "grad_less_es": _paired(per_env(g, "final"), per_env(r, "final")),
                               "grad_s_to_reach": reach, "ratio": None if reach is None else reach / own})
    return out


def run(o, entry) -> Dict:
    if o.equal_wall and o.method == "es":
        raise ValueError("--equal-wall with --method es: it gives the evolution strategy the gradient run's wall "
                         "time, so it needs --method grad or both")
    cfg = load_tune_config(o.config, parse_sets(o.set), merge=True)
    # the tuners (MJX, the rollout) load only once the config has passed its checks: a bad --set answers in
    # about a second
    out = o.out or os.path.join("out", "tune", resolve("tune", o.config).stem)
    check_folder("--out", out, os.path.abspath(out))  # checkpoints go there from the first step on
    from hexjax.tune.driver import compare_plot
    from hexjax.tune.es import tune_es
    from hexjax.tune.grad import tune
    limit = None if o.minutes is None else 60 * o.minutes
    print(f"tune {o.config} ({o.method}): {cfg.steps} steps of {cfg.train_batch} terrains ({cfg.distance:g} m "
          f"walks on {', '.join(cfg.terrains)}"
          f"{'' if o.method == 'es' else f'; estimator {cfg.estimator}'}), held-out evaluation on "
          f"{cfg.held_out_batch} terrains every {cfg.eval_every} steps on the {cfg.eval_physics} physics"
          f"{'' if limit is None else f', at most {o.minutes:g} min a method'}; a long run (the shipped configs "
          f"take about 15 min a method on 2 CPU cores); checkpoints in {out}/, rerun to resume", flush=True)
    t0 = time.perf_counter()
    runs: List[Dict] = []
    if o.method in ("grad", "both"):
        sub = "hybrid" if cfg.estimator == "hybrid" else "grad"  # the two write different checkpoints
        runs.append(tune(cfg, os.path.join(out, sub), resume=not o.restart, time_limit=limit))
    if o.method in ("es", "both"):
        budget = o.rollouts or (runs[0]["log"][-1]["rollouts"] if runs else cfg.steps * cfg.train_batch)
        runs.append(tune_es(cfg, os.path.join(out, "es"), rollouts=budget, resume=not o.restart, time_limit=limit))
    if o.equal_wall and runs and runs[0]["method"] in ("grad", "hybrid"):
        last = runs[0]["log"][-1]
        wall = last.get("train_s", last["wall_s"])  # the gradient run's own time, evaluations left out
        # evaluated where the gradient run was, in its own seconds, so that the two curves meet at each mark
        marks = [e.get("train_s", e["wall_s"]) for e in runs[0]["log"][1:] if "held_out" in e]
        runs.append(tune_es(cfg, os.path.join(out, "es_wall"), rollouts=None, resume=not o.restart, time_limit=wall,
                            eval_at=marks))
        runs[-1]["method"] += ", same wall time"
    import jax
    dev = jax.devices()[0]
    res = {"config": o.config, "out": out, "total_wall_s": time.perf_counter() - t0, "runs": [_row(r) for r in runs],
           "physics": cfg.judge().record(),  # the judge: MJX's kept program, or the host's certified engine
           "device": f"{dev.platform}:{getattr(dev, 'device_kind', '')}"}
    if len(runs) > 1 and runs[0]["method"] in ("grad", "hybrid"):
        res["race"] = race(runs)
    if len(runs) > 1:
        compare_plot(res["runs"], os.path.join(out, "compare.png"))
    return res


def _change(start, final) -> str:
    """A tuned field's start -> final; a pytree field (a reflex layer's weights) as its size and how far it moved."""
    if not isinstance(final, dict):
        return f"{start} -> {final}"
    import jax
    import numpy as np
    a = np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(start)])
    b = np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(final)])
    return f"{b.size:,} numbers, moved by {np.linalg.norm(b - a):.3g} (RMS {np.sqrt(np.mean((b - a) ** 2)):.2g})"


def report(res: Dict) -> str:
    lines = []
    for r in res["runs"]:
        s, f = r["held_out_start"], r["held_out_final"]
        pct = r["improvement_pct"]
        verdict = "better" if pct > 0 else ("worse" if pct < 0 else "unchanged")
        lines.append(f"{r['method']}: held-out objective {s['objective']:.4f} -> {f['objective']:.4f} m "
                     f"({-pct:+.1f} %, {verdict}), goal error {s['goal_error_cm']:.1f} -> {f['goal_error_cm']:.1f} cm (iterate "
                     f"{r['selected_step']}, {r['selected_by']}), {r['rollouts']} rollouts, {r['train_s']:.0f} s "
                     f"({r['wall_s']:.0f} s with evaluations)")
        if r.get("skipped_steps"):
            lines.append(f"  {r['skipped_steps']} step(s) skipped for a non-finite gradient (docs/tuning.md, "
                         f"\"Non-finite steps\")")
        for k, v in r["params_final"].items():
            lines.append(f"  {k}: " + _change(r["params_start"][k], v))
    rc = res.get("race") or {}
    if rc:
        d = rc["grad_less_start"]
        lines.append(f"race: the gradient's held-out J less the start's {d['mean']:+.4f} +- {d['se']:.4f} m "
                     "(paired SE)")
        for a in rc["against"]:
            d = a["grad_less_es"]
            reach = ("never reached in its run" if a["ratio"] is None else
                     f"reached in {a['grad_s_to_reach']:.0f} s, {a['ratio']:.2f}x of its {a['es_train_s']:.0f} s")
            lines.append(f"  against {a['method']}: {d['mean']:+.4f} +- {d['se']:.4f} m; its J {a['es_held_out']:.4f} "
                         f"{reach}")
    lines.append(f"logs, checkpoints and plots under {res['out']}/")
    return "\n".join(lines)
