"""The loop both tuners share (`hexjax.tune.grad`, `hexjax.tune.es`): resume from a checkpoint, evaluate the
start, step, evaluate on the held-out and validation terrains, checkpoint after every step, and write the
log and its plot."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import time
from typing import Any, Dict, Optional

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from hexjax.interrupt import keep
from hexjax.sim.compiled import Compiled
from hexjax.tune.config import TuneConfig
from hexjax.tune.objective import Problem, evaluate_held_out
from hexjax.tune.space import load_values


def nonfinite_note(step: int, loss, grad, cfg: TuneConfig) -> Optional[str]:
    """None where the step's objective and every gradient entry are finite; else the line the tuner prints as it
    skips the step: how many entries are not finite, and what bounds the backward flow in this config (an
    unbounded windowed gradient can explode: docs/tuning.md, "Non-finite steps")."""
    flat = np.concatenate([np.ravel(x) for x in _flat(grad)] or [np.zeros(0)])
    bad = int(np.count_nonzero(~np.isfinite(flat)))
    if bad == 0 and math.isfinite(float(loss)):
        return None
    what = f"{bad} of {flat.size} gradient entries are not finite" if bad else f"the objective is {float(loss)}"
    if cfg.backward == "forward":
        hint = "backward: forward has no bound on the gradient's flow; a reverse backward with grad_clip has one"
    elif cfg.grad_clip is None:
        hint = "grad_clip: null leaves the backward flow unbounded; set grad_clip (per env, e.g. 1 or 10)"
    else:
        hint = f"the flow is bounded at grad_clip={cfg.grad_clip:g} per env"
    return f"step {step + 1}: {what}; the step is skipped ({hint})"


def _flat(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


def config_digest(cfg: TuneConfig, method: str, also_drop: tuple = ()) -> str:
    """Identifies what a checkpoint continues: the config less the step count and evaluation period (a run
    may be extended) and less the other method's settings; less `also_drop` too (`program_digest`)."""
    d = dataclasses.asdict(cfg)
    drop = ["steps", "eval_every"] + (["optimizer", "window", "grad_clip"] if method != "grad" else
                                      ["es_population", "es_sigma"])
    if method != "grad" or cfg.estimator == "first_order":  # digests of configs older than the estimator hold
        drop += ["estimator", "zo_pairs", "zo_sigma", "zo_prior"]
    if not cfg.terrain_overrides:
        drop.append("terrain_overrides")
    if method == "grad" or cfg.es_objective == "smooth":
        drop.append("es_objective")
    if method != "grad" or not cfg.unroll_substeps:  # digests from before the key hold
        drop.append("unroll_substeps")
    if cfg.gates == "smooth":  # likewise
        drop.append("gates")
    if method != "grad" or cfg.backward == "sequential":  # likewise
        drop.append("backward")
    # checkpoints from before the key evaluated on the training physics, `fast` for the default solver: they
    # continue under eval_physics 'fast'; under 'validated' the digest differs, so an old held-out history is
    # never extended with evaluations on other physics
    if cfg.eval_physics == "fast":
        drop.append("eval_physics")
    if cfg.train_physics is None:  # digests from before the key hold
        drop.append("train_physics")
    if cfg.start is None:  # likewise; a start names its numbers too, so an edited preset starts afresh
        drop.append("start")
    else:
        d["start"] = [cfg.start, load_values(cfg.start)]
    if method == "grad" or cfg.es_strategy == "auto":  # auto was CMA-ES for every config before the key
        drop.append("es_strategy")
    if method == "grad" or cfg.es_rollouts == "training":  # likewise
        drop.append("es_rollouts")
    if cfg.eval_engine == "mjx":  # likewise
        drop.append("eval_engine")
    for k in drop:
        d.pop(k)
    for k in also_drop:
        d.pop(k, None)
    return hashlib.sha256(json.dumps([method, d], sort_keys=True, default=str).encode()).hexdigest()[:16]


# settings that never reach a tuner's compiled program: the run's length and evaluation period, the seed (it draws
# the terrains and keys, which the program takes as arguments), the held-out and validation batches (the
# evaluation rollout, on `eval_physics`, is a program of its own) and the optimiser and CMA-ES's step size
# (applied outside it)
_OUTSIDE_PROGRAM = ("seed", "held_out_batch", "validation_batch", "eval_physics", "eval_engine", "optimizer",
                    "es_sigma")


def program_digest(cfg: TuneConfig, method: str) -> str:
    """Identifies a tuner's compiled program (`Problem.static`): `config_digest` less the settings the program
    does not depend on, so that runs that differ only in those (another seed, learning rate or held-out
    batch) share one kept program instead of tracing and lowering it again (a first step of 70-76 s against
    41 s on an H100 for the `cpg_step_ditch` gradient)."""
    return config_digest(cfg, method, also_drop=_OUTSIDE_PROGRAM)


_COMPILED: Dict[str, Any] = {}


def cached(key: str, make, static: Optional[tuple] = None):
    """One compiled function per (config digest, role) in this process (jit caches by function identity,
    and every `tune` call builds new closures). With `static` (`Problem.static`) it is also kept on disk
    (`hexjax.sim.compiled`), so that a resumed or repeated run skips tracing it again (20-40 s on 2 cores)."""
    if key not in _COMPILED:
        _COMPILED[key] = make() if static is None else Compiled(make(), static=static)
    return _COMPILED[key]


def save_checkpoint(path: str, state, step: int, log: list, digest: str) -> None:
    """Params, optimiser state (any pytree), step and log, written atomically."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    leaves = _flat(state)
    tmp = path + ".tmp.npz"
    np.savez(tmp, *leaves, meta=np.frombuffer(json.dumps({"step": step, "log": log, "digest": digest}).encode(), np.uint8))
    os.replace(tmp, path)


def load_checkpoint(path: str, like, digest: str):
    """(state, step, log) from `path`, shaped like the pytree `like`; refuses a checkpoint of another config."""
    with np.load(path) as z:
        meta = json.loads(bytes(z["meta"]).decode())
        if meta["digest"] != digest:
            raise ValueError(f"{path}: checkpoint was written by a different config or method; "
                             "use another --out directory or delete it")
        n = len(jax.tree_util.tree_leaves(like))
        leaves = [jnp.asarray(z[f"arr_{i}"]) for i in range(n)]
    return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(like), leaves), meta["step"], meta["log"]


def drive(problem: Problem, out_dir: str, *, method: str, digest: str, state, params_of, advance,
          n_steps: Optional[int], rollouts_per_step: int, should_eval, resume: bool, progress: bool, time_limit,
          t_start: float):
    """The loop both methods share: resume from out_dir/checkpoint.npz, evaluate the start, then `advance`
    (state, step) -> (state, log fields) up to `n_steps` times (None: until `time_limit` alone) or until
    `time_limit`, evaluating where `should_eval(step, train_s, train_s_before)` (the method's own seconds now and
    at the step before) and at the end, checkpointing after every step. `params_of(state)` gives the
    unconstrained params to evaluate."""
    ckpt = os.path.join(out_dir, "checkpoint.npz")
    step, log = 0, []
    if resume and os.path.exists(ckpt):
        state, step, log = load_checkpoint(ckpt, state, digest)
        print(f"resumed from {ckpt} at step {step}")
    # clocks: wall_s counts everything since the run began (a resumed run goes on from its log), eval_s the
    # held-out and validation evaluations in it (their compile included); train_s = wall_s - eval_s is the
    # method's own time, what `time_limit` bounds and what wall-time comparisons use
    clock = {"t0": t_start - (log[-1]["wall_s"] if log else 0.0), "eval": log[-1].get("eval_s", 0.0) if log else 0.0}

    def evaluate(u):
        t = time.perf_counter()
        out = _evaluate(problem, u, efn, em)
        clock["eval"] += time.perf_counter() - t
        return out

    def times():
        wall = time.perf_counter() - clock["t0"]
        return {"wall_s": wall, "eval_s": clock["eval"], "train_s": wall - clock["eval"]}

    em, efn = problem.eval_rollout()
    bar = tqdm(total=n_steps, initial=step, desc=f"tune ({method})", unit="step", disable=not progress)
    if step == 0:
        u = params_of(state)
        ev = evaluate(u)
        log.append({"step": 0, "rollouts": 0, **times(), **ev, "params": _jsonable(problem.space.physical(u))})
    while n_steps is None or step < n_steps:
        if time_limit is not None and times()["train_s"] > time_limit:
            print(f"time limit {time_limit:.0f} s reached at step {step}")
            break
        state, fields = advance(state, step)
        step += 1
        u = params_of(state)
        entry = {"step": step, "rollouts": step * rollouts_per_step, **fields,
                 "params": _jsonable(problem.space.physical(u))}
        if should_eval(step, times()["train_s"], log[-1].get("train_s", log[-1]["wall_s"])) or step == n_steps:
            entry.update(evaluate(u))
        entry.update(times())
        log.append(entry)
        save_checkpoint(ckpt, state, step, log, digest)
        keep(f"{method} step {step}{'' if n_steps is None else f' of {n_steps}'} kept in {ckpt}; the same command "
             "resumes from it")
        bar.set_postfix(train=f"{fields['train_objective']:.3f}", held=f"{_last_held(log):.3f}",
                        s=f"{entry['train_s']:.0f}")
        bar.update(1)
    bar.close()
    if "held_out" not in log[-1]:
        log[-1].update(evaluate(params_of(state)))
        log[-1].update(times())
        save_checkpoint(ckpt, state, step, log, digest)
    return _finish(problem, log, out_dir, method)


def _evaluate(problem: Problem, u, fn, model) -> Dict[str, Any]:
    out = {"held_out": evaluate_held_out(problem, u, fn, model)}
    if problem.cfg.validation_batch:
        out["validation"] = evaluate_held_out(problem, u, fn, model, "validation")
    return out


def _last_held(log) -> float:
    for e in reversed(log):
        if "held_out" in e:
            return e["held_out"]["objective"]
    return math.nan


def _listed(v):
    """An array as nested lists; a pytree field (a mapping of arrays: the reflex layer's weights) leaf by leaf."""
    return {k: _listed(x) for k, x in v.items()} if isinstance(v, dict) else np.asarray(v).tolist()


def _jsonable(d):
    return {k: _listed(v) for k, v in d.items()}


def _finish(problem: Problem, log, out_dir: str, method: str) -> Dict[str, Any]:
    """The run's result: `final` is the evaluated iterate with the lowest validation objective (the last
    one without a validation set), reported on the held-out set; `last` is the last iterate."""
    evaluated = [e for e in log if "held_out" in e]
    key = "validation" if problem.cfg.validation_batch else None
    pick = min(evaluated, key=lambda e: e[key]["objective"]) if key else evaluated[-1]
    start = log[0]["held_out"]
    res = {"method": method, "config": dataclasses.asdict(problem.cfg), "log": log,
           "start": {"held_out": start, "params": log[0]["params"]},
           "final": {"step": pick["step"], "rollouts": pick["rollouts"], "held_out": pick["held_out"],
                     "validation": pick.get("validation"), "params": pick["params"]},
           "last": {"step": log[-1]["step"], "held_out": log[-1]["held_out"], "params": log[-1]["params"]},
           "improvement_pct": 100 * (start["objective"] - pick["held_out"]["objective"]) / start["objective"],
           "selected_by": "picked on the validation terrains" if key else "the last iterate (no validation set)"}
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "log.json"), "w") as f:
        json.dump(res, f, indent=2, default=float)
    write_params_preset(res, os.path.join(out_dir, "params.yaml"))
    plot_log(res, os.path.join(out_dir, "tune.png"))
    return res


def write_params_preset(res: Dict[str, Any], path: str) -> None:
    """The picked params as a params preset (`values`, with what made them): copied into configs/params/ it
    loads by name wherever params are taken (`hexjax experiment yu2019-ditch --params <name>`)."""
    import yaml

    cfg = res["config"]
    doc = {"controller": cfg["controller"], "gait": cfg["gait"],
           "made_by": {"method": res["method"], "terrain": cfg["terrain"], "train_physics": cfg.get("train_physics"),
                       "eval_physics": cfg.get("eval_physics"), "held_out_batch": cfg["held_out_batch"],
                       "step": res["final"]["step"], "rollouts": res["final"]["rollouts"],
                       "held_out_objective": float(res["final"]["held_out"]["objective"]),
                       "start_held_out_objective": float(res["start"]["held_out"]["objective"])},
           "values": {k: _listed(v) for k, v in res["final"]["params"].items()}}
    with open(path, "w") as f:
        f.write("# Params picked by `hexjax tune` (its log.json beside this file); a params preset: docs/configs.md.\n")
        yaml.safe_dump(doc, f, sort_keys=False, default_flow_style=None)


def _training_label(res: Dict[str, Any]) -> str:
    """What the training curve is: CMA-ES logs its population's mean objective, the gradient its batch's, on
    the smooth rollout or the hard one (`es_objective`, `gates`)."""
    cfg = res["config"]
    if "(pop " in res["method"]:  # an evolution strategy's label names its population
        return f"training batch ({cfg.get('es_objective', 'smooth')}, population mean)"
    return "training batch (hard forward)" if cfg.get("gates") == "straight_through" else "training batch (smooth)"


def plot_log(res: Dict[str, Any], path: str) -> None:
    """Training objective per step and held-out objective at each evaluation, against rollouts used."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    log = res["log"]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    tr = [(e["rollouts"], e["train_objective"]) for e in log if "train_objective" in e]
    if tr:
        ax.plot(*zip(*tr), ".-", alpha=0.5, label=_training_label(res))
    he = [(e["rollouts"], e["held_out"]["objective"]) for e in log if "held_out" in e]
    ax.plot(*zip(*he), "o-", label="held-out (hard)")
    ax.set_xlabel("rollouts used")
    ax.set_ylabel("objective J (m)")
    terrain = res["config"]["terrain"]
    terrain = ", ".join(terrain) if isinstance(terrain, list) else terrain
    ax.set_title(f"{res['method']}: {res['config']['controller']} {res['config']['gait']}\non {terrain}", fontsize=10)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def compare_plot(rows, path: str) -> None:
    """Held-out objective against rollouts used and against the method's own seconds (evaluations left out, with
    one standard error where the log has it), one line per method (rows: `hexjax.experiments.commands.tuning`)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for r in rows:
        line, = ax.plot(*zip(*r["curve"]), "o-", label=r["method"])
        t, j, se = zip(*r["curve_s"])
        bx.errorbar(t, j, yerr=[np.nan if e is None else e for e in se], fmt="o-", color=line.get_color(), capsize=2)
    ax.set_xscale("symlog", linthresh=10)  # 0 (the start) on the axis, decades from 10 on
    ax.set_xlabel("rollouts used")
    ax.set_ylabel("held-out objective J (m, hard mode)")
    bx.set_xlabel("seconds of the method's own time (compile included)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
