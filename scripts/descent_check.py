"""Is a tuning config's training gradient a descent direction of the objective it is judged by?

At the config's start params u0: the mean of the training gradient over `--batches` training batches (the
windowed first-order gradient, through the config's gates), then the hard objective (the held-out kind of
rollout) on the held-out and the validation terrains at u0 - a g / max|g| for each step a of `--steps`
(negative a: up the gradient). A descent direction lowers both as a grows; docs/tuning.md ("Straight-through
gates") has the measurements that chose the CPG preset's window with it.

    python scripts/descent_check.py --config cpg_step_ditch_grad --json docs/results/descent_cpg_st_w2.json

(cpg_step_ditch_grad: straight-through gates, 2 s windows, the 4-iteration solver its gradient needs.)
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from hexjax.experiments.commands.tuning import parse_sets
from hexjax.tune.config import load_tune_config
from hexjax.tune.objective import Problem, evaluate_held_out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="cpg_step_ditch_grad", help="tuning config (configs/tune/) or .yaml path")
    ap.add_argument("--set", action="append", default=[], help="override a config key, e.g. window=2.0 or optimizer.name=sgd")
    ap.add_argument("--batches", type=int, default=3, help="training batches whose gradients are averaged")
    ap.add_argument("--steps", default="0,0.05,0.1,0.2,-0.1", help="steps a along -g / max|g| (comma list)")
    ap.add_argument("--json", help="write the result here")
    o = ap.parse_args(argv)
    try:  # as `hexjax tune --set` reads them (dotted keys update a dict key)
        overrides = parse_sets(o.set)
    except ValueError as err:
        raise SystemExit(str(err)) from None
    if o.batches < 1:
        raise SystemExit(f"--batches={o.batches}: must be >= 1")
    steps = [float(a) for a in o.steps.split(",")]
    cfg = load_tune_config(o.config, overrides, merge=True)
    pb = Problem.build(cfg)
    u0 = pb.space.init(pb.params0)
    flat, unravel = ravel_pytree(u0)
    model, fn = pb.train_rollout(grad=True)
    vg = jax.jit(pb.value_and_grad(fn, model))
    grads, losses = [], []
    for b in range(o.batches):
        terr, keys = pb.train_batch(100 + b)  # batches the tuner's first steps do not draw
        t0 = time.perf_counter()
        (loss, _), g = vg(u0, terr, keys)
        grads.append(np.asarray(ravel_pytree(g)[0]))
        losses.append(float(loss))
        print(f"gradient {b}: training J {float(loss):.4f}, {time.perf_counter() - t0:.1f} s", flush=True)
    g = np.mean(grads, 0)
    cos = [float(grads[i] @ grads[j] / (np.linalg.norm(grads[i]) * np.linalg.norm(grads[j]) + 1e-30))
           for i in range(len(grads)) for j in range(i + 1, len(grads))]
    model_h, fn_h = pb.eval_rollout()  # the tuner's own evaluation program (kept across processes)
    d = jnp.asarray(g / max(np.abs(g).max(), 1e-30))
    names = sorted(pb.space.names)
    res = {"config": o.config, "overrides": overrides, "fields_in_ravel_order": names, "gradient": g.tolist(),
           "training_J": losses, "cosines_between_batches": cos, "hard_J": {}}
    print("cosines between the batches' gradients:", np.round(cos, 3).tolist())
    for a in steps:
        u = unravel(flat - a * d)
        js = {w: evaluate_held_out(pb, u, fn_h, model_h, w)["objective"] for w in ("held_out", "validation")}
        res["hard_J"][f"{a:g}"] = js
        print(f"a = {a:+.2f}: hard J held-out {js['held_out']:.4f}, validation {js['validation']:.4f}", flush=True)
    if o.json:
        with open(o.json, "w") as fh:
            json.dump(res, fh, indent=1)
    return res


if __name__ == "__main__":
    main()
