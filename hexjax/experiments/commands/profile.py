"""Where a rollout's time goes: one call under JAX's profiler, its trace read back as a table of the busiest
kernels (`hexjax bench --profile DIR`).

`jax.profiler.trace(..., create_perfetto_trace=True)` writes, beside TensorBoard's files, a Perfetto trace
(`perfetto_trace.json.gz`, Chrome's trace-event format): one process per device ("/device:GPU:0", its streams
as threads) and one for the host ("/host:CPU"). On a GPU the device's complete events are the kernels that ran,
MuJoCo Warp's among them (named after their Warp functions), so their summed durations say which stage of the
step costs what; the wall time of the call against the kernels' sum says how long the device sat idle (launches,
the controller between steps, transfers). On a host without a device the table reads XLA's own CPU threads
instead (the compiled programs' work; MuJoCo C's threads and Python's are not in it)."""

from __future__ import annotations

import collections
import glob
import gzip
import json
import os
import time
from typing import Callable, Dict


def kernel_table(trace_dir: str, top: int = 15) -> Dict:
    """The busiest event names of the newest Perfetto trace under `trace_dir`: {'where': the process read,
    'events_ms': summed durations of every event read, 'rows': [{'name', 'ms', 'calls', 'share'}] busiest first,
    `top` of them}."""
    found = sorted(glob.glob(os.path.join(trace_dir, "**", "perfetto_trace.json.gz"), recursive=True),
                   key=os.path.getmtime)
    if not found:
        raise FileNotFoundError(f"{trace_dir}: no perfetto_trace.json.gz (was it written by jax.profiler.trace?)")
    with gzip.open(found[-1], "rt", encoding="utf-8") as f:
        data = json.load(f)
    events = data["traceEvents"] if isinstance(data, dict) else data
    meta = lambda kind: {(e["pid"], e.get("tid")) if kind == "thread_name" else e["pid"]: e["args"]["name"]
                         for e in events if e.get("ph") == "M" and e.get("name") == kind}
    procs, threads = meta("process_name"), meta("thread_name")
    devices = {p for p, n in procs.items() if n.startswith("/device:")}

    def wanted(e):
        if devices:
            return e["pid"] in devices
        return threads.get((e["pid"], e.get("tid")), "").startswith("tf_XLA")

    ms, calls = collections.Counter(), collections.Counter()
    for e in events:
        if e.get("ph") == "X" and wanted(e):
            ms[e["name"]] += e.get("dur", 0.0) / 1e3
            calls[e["name"]] += 1
    total = sum(ms.values())
    rows = [dict(name=n, ms=round(v, 3), calls=calls[n], share=round(v / total, 4) if total else 0.0)
            for n, v in ms.most_common(top)]
    where = ", ".join(sorted(procs[p] for p in devices)) if devices else "the host's XLA threads"
    return dict(where=where, events_ms=round(total, 3), rows=rows)


def profile_call(fn: Callable[[], object], trace_dir: str, top: int = 15) -> Dict:
    """Run `fn` (which blocks until its result is ready) once under the profiler, writing the trace to
    `trace_dir`; `kernel_table` of it with the call's wall time ('wall_ms') and the trace's folder."""
    import jax
    os.makedirs(trace_dir, exist_ok=True)
    t0 = time.perf_counter()
    with jax.profiler.trace(trace_dir, create_perfetto_trace=True):
        fn()
    wall = time.perf_counter() - t0
    return dict(kernel_table(trace_dir, top), wall_ms=round(1e3 * wall, 3), trace=trace_dir)


def format_profile(p: Dict, label: str) -> str:
    lines = [f"{label}: {p['wall_ms']:,.0f} ms wall, {p['events_ms']:,.0f} ms of events on {p['where']} "
             f"(trace: {p['trace']})"]
    for r in p["rows"]:
        lines.append(f"  {100 * r['share']:5.1f} %  {r['ms']:10.1f} ms  {r['calls']:7d} x  {r['name'][:90]}")
    return "\n".join(lines)
