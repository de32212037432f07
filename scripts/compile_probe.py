"""The forward and gradient programs of `hexjax bench --grad` under sets of XLA compiler options.

Lowers each program once (the tactile_tripod objective, implicit backward, B = --batch) and compiles it once per
option set with `Lowered.compile(compiler_options=...)`, so every set sees the same HLO. Prints one JSON line per
(program, options): tracing and lowering s (`lower_s`, of which `trace_s` is the tracing to a jaxpr), XLA compile
s (`compile_s` wall, `compile_cpu_s` the process's CPU over all of XLA's threads), the size of the lowered
StableHLO text, the number of times MJX's `step` was traced for the program and, with --run, env-steps/s (best of
two calls after a warm-up); gradient rows add the loss and the gradient's norm, so options that change the numbers
show it. --kernels counts the optimised program's fusions (LLVM's kernels), instructions and while loops: a
measure of what XLA compiles that does not vary from run to run as the seconds do. --json writes the rows (and
each gradient as .npy beside it). Options are XLA DebugOptions fields, e.g. '{"xla_gpu_autotune_level": 0}'.
--gc python traces under Python's own garbage-collector thresholds instead of hexjax's
(`hexjax.cache.rare_collections`); --trace-only stops after lowering. What it found: docs/testing.md, "Time".

    python scripts/compile_probe.py --batch 4096 --duration 3 --run --options '{}' '{"xla_gpu_autotune_level": 0}'
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import dataclasses
import gc
import hashlib
import json
import re
import time

import jax
import numpy as np
from jax.flatten_util import ravel_pytree

from hexjax import cache
from hexjax.experiments.bench_grad import best_call, objective_program, physics_steps
from hexjax.sim.mjx_rules import mjx, swapped
from hexjax.tune.config import BACKWARDS, load_tune_config
from hexjax.tune.objective import Problem


@contextlib.contextmanager
def _counting(module, name):
    """Count the calls of `module.name` while the context is open (a one-element list); the function is restored
    after."""
    fn, n = getattr(module, name), [0]

    def counted(*args, **kw):
        n[0] += 1
        return fn(*args, **kw)

    with swapped(module, name, counted):
        yield n


def _table(lines, name, pattern):
    """{id: match groups} of one of the tables that close XLA's HLO text (FileNames, FileLocations, ...)."""
    if name not in lines:
        return {}
    out, i = {}, lines.index(name) + 1
    while i < len(lines) and (m := re.match(pattern, lines[i])):
        out[int(m.group(1))] = m.groups()[1:]
        i += 1
    return out


def _fusions_by_source(hlo: str) -> collections.Counter:
    """Fusions of an optimised HLO text counted by the source file of the operation each was made from (the
    innermost frame of its metadata's `stack_frame_id`; '?' where it has none)."""
    lines = hlo.split("\n")
    files = _table(lines, "FileNames", r'^(\d+) "(.*)"$')
    locs = _table(lines, "FileLocations", r"^(\d+) \{file_name_id=(\d+)")
    frames = _table(lines, "StackFrames", r"^(\d+) \{file_location_id=(\d+)")
    count = collections.Counter()
    for line in lines:
        if not re.match(r"^\s*(ROOT )?\S+ = \S+ fusion\(", line):
            continue
        m = re.search(r"stack_frame_id=(\d+)", line)
        frame = frames.get(int(m.group(1))) if m else None
        path = files[int(locs[int(frame[0])][0])][0] if frame else "?"
        if "site-packages/" in path:
            path = path.split("site-packages/")[-1]
        elif "/hexjax/" in path:
            path = path[path.rindex("/hexjax/") + 1:]
        count[path] += 1
    return count


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=4096, help="envs per call")
    ap.add_argument("--options", nargs="+", default=["{}"], help="JSON objects of XLA options, one per set")
    ap.add_argument("--modes", default="forward,grad", help="programs: comma list of forward, grad")
    ap.add_argument("--run", action="store_true", help="also time each compiled program")
    ap.add_argument("--unroll-substeps", action="store_true", help="the tuning key unroll_substeps")
    ap.add_argument("--backward", default="sequential", choices=BACKWARDS, help="the tuning key backward")
    ap.add_argument("--duration", type=float, default=None, help="walk s instead of the config's (9 s)")
    ap.add_argument("--json", default=None, help="write the rows here")
    ap.add_argument("--gc", choices=("hexjax", "python"), default="hexjax",
                    help="garbage-collector thresholds while tracing: hexjax's (rare_collections) or Python's")
    ap.add_argument("--trace-only", action="store_true", help="trace and lower only, no XLA compile")
    ap.add_argument("--kernels", action="store_true",
                    help="count the optimised program's fusions (each a kernel of its own for LLVM), instructions and "
                         "loops, and its fusions by source file")
    a = ap.parse_args()
    cfg = load_tune_config("tactile_tripod", {"unroll_substeps": True} if a.unroll_substeps else None)
    p = Problem.build(dataclasses.replace(cfg, solver_grad="implicit", backward=a.backward))
    n_phys = physics_steps(p, a.duration)
    u0 = p.space.init(p.params0)
    terr, keys = p.train_batch(0, a.batch)
    rows = []
    for mode in a.modes.split(","):
        t0, c0 = time.perf_counter(), time.process_time()
        f = objective_program(p, grad=mode != "forward", duration=a.duration)
        full = gc.get_stats()[2]["collections"]
        with _counting(mjx, "step") as traced, (cache.rare_collections() if a.gc == "hexjax" else
                                                 contextlib.nullcontext()):
            tr = f.trace(u0, terr, keys)
            trace_s = time.perf_counter() - t0
            low = tr.lower()
        lower_s, lower_cpu = time.perf_counter() - t0, time.process_time() - c0
        full = gc.get_stats()[2]["collections"] - full
        text = low.as_text()
        base = dict(mode=mode, gc=a.gc, trace_s=round(trace_s, 2), lower_s=round(lower_s, 2),
                    lower_cpu_s=round(lower_cpu, 2), full_collections=full, stablehlo_chars=len(text),
                    stablehlo_sha=hashlib.sha256(text.encode()).hexdigest()[:16], steps_traced=traced[0])
        if a.trace_only:
            print(json.dumps(base), flush=True)
            rows.append(base)
            continue
        for opt in a.options:
            o = json.loads(opt)
            t0, c0 = time.perf_counter(), time.process_time()
            c = low.compile(compiler_options=o or None)
            comp_s, comp_cpu = time.perf_counter() - t0, time.process_time() - c0
            row = dict(base, options=o, compile_s=round(comp_s, 2), compile_cpu_s=round(comp_cpu, 2))
            if a.kernels:
                hlo = c.as_text()
                by_file = _fusions_by_source(hlo)
                row.update(fusions=sum(by_file.values()), instructions=hlo.count(" = "),
                           whiles=hlo.count(" while("), fusions_by_source=dict(by_file.most_common(10)))
            if a.run:
                best, out = best_call(c, (u0, terr, keys), 2)
                row["env_steps_per_s"] = round(a.batch * n_phys / best, 1)
                if mode != "forward":
                    (loss, _), g = out
                    flat = np.asarray(ravel_pytree(g)[0])
                    row.update(loss=float(loss), grad_head=[float(v) for v in flat[:6]],
                               grad_norm=float(np.linalg.norm(flat)))
                    if a.json:
                        np.save(a.json.replace(".json", f"_g{len(rows)}.npy"), flat)
            print(json.dumps(row), flush=True)
            rows.append(row)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(dict(batch=a.batch, device=str(jax.devices()[0]), rows=rows), fh, indent=1)


if __name__ == "__main__":
    main()
