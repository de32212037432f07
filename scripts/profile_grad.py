"""Where does a gradient of the tuning objective spend its device time?

Profiles one call of the smooth forward objective and one of its `jax.value_and_grad` (the programs
`hexjax bench --grad` times) with the JAX profiler, and attributes every kernel's time to
- a phase: `forward`, `recompute` (with remat, each control step's forward run again inside the backward
  pass: `rematted_computation` in the op name) or `transpose` (the rest of the backward pass), read from the
  JAX op name XLA keeps in each instruction's metadata, or for an instruction without one (copies, layout
  transposes, stacking) from the loop or fusion that runs it, and
- a stage: the named scopes in the op's name: MJX's (`fwd_position`: kinematics, collision, constraints;
  `fwd_velocity`, `fwd_actuation`, `fwd_acceleration`, `solve`, `euler`) and hexjax's (`hx.*`: the controller,
  the implicit backward's pieces, ...).

`--only jvp` profiles the gradient in forward mode instead (`scripts/forward_grad_probe.py`'s program; each
kernel's phase then reads `forward`, tangents included). Prints a table per program and writes JSON
(`--json`). Shorten the walk with `--set distance=0.2` (compile time does not depend on it), or to a few control
steps with `--duration 0.2 --settle 0.1`: the profiler drops events past a few million. Run it where the numbers
matter: the GPU, through the device tool. There XLA groups kernels into command buffers (CUDA graphs), which the
profile shows as one op each; set `XLA_FLAGS=--xla_gpu_enable_command_buffer=` to see every kernel (wall times
then include launch gaps).

    python scripts/profile_grad.py --config tactile_tripod --batch 4096 --set distance=0.2 --json prof.json
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import os
import re
import tempfile
import time

import jax
import numpy as np

from hexjax.experiments.commands.bench_grad import objective_program
from hexjax.tune.config import load_tune_config
from hexjax.tune.objective import Problem

_META = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=.*?metadata=\{([^}]*)\}")
# named scopes that mark a stage in an op's name: MJX's (`mujoco.mjx._src.forward`) and hexjax's own (`hx.*`)
_SCOPES = {"fwd_position", "fwd_velocity", "fwd_actuation", "fwd_acceleration", "solve", "euler", "_advance",
           "_integrate_pos", "implicit", "rungekutta4"}
_CONTAINERS = ("while", "conditional", "call")  # CPU thunks that contain other thunks: counted through those


def _metadata(hlo_text: str) -> dict:
    """instruction name -> JAX op name (the named-scope path) from an optimised HLO module's text. An instruction
    XLA made without one (layout copies, the stacking of a loop's outputs) takes the op name of the nearest
    instruction that calls its computation (a while loop, a fusion), so it is counted in that loop's phase."""
    own, comp_of, caller = {}, {}, {}
    comp = None
    for line in hlo_text.splitlines():
        if line and not line[0].isspace() and line.rstrip().endswith("{"):
            head = re.match(r"^(?:ENTRY\s+)?%?([\w.\-]+)", line)
            comp = head.group(1) if head else None
            continue
        m = _META.match(line)
        if m:
            name = m.group(1)
            op = re.search(r'op_name="([^"]*)"', m.group(2))
            own[name], comp_of[name] = (op.group(1) if op else ""), comp
        ins = re.match(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=", line)
        if ins and comp:
            comp_of.setdefault(ins.group(1), comp)
            for callee in re.findall(r"(?:body|condition|calls|to_apply|true_computation|false_computation|"
                                     r"branch_computations)=\{?(%[\w.\-]+(?:,\s*%[\w.\-]+)*)", line):
                for c in callee.split(","):
                    caller.setdefault(c.strip().lstrip("%"), ins.group(1))

    def resolve(name, depth=0):
        if own.get(name) or depth > 32:
            return own.get(name, "")
        up = caller.get(comp_of.get(name))
        return resolve(up, depth + 1) if up else ""

    return {name: resolve(name) for name in comp_of}


def _stage(op_name: str) -> str:
    """The innermost two stage scopes in an op name, e.g. 'fwd_position' or 'solve/hx.implicit_hessian'."""
    parts = [p for p in op_name.split("/") if p in _SCOPES or p.startswith("hx.")]
    return "/".join(parts[-2:]) if parts else "other"


def _phase(op_name: str) -> str:
    """Of a gradient program: 'recompute' for a rematerialised control step's forward inside the backward
    pass, 'transpose' for the rest of the backward pass, 'forward' for the forward pass (and all of a forward
    program)."""
    if "transpose(" not in op_name:
        return "forward"
    return "recompute" if "rematted_computation" in op_name else "transpose"


def kernel_events(trace_dir: str, module: str) -> list[dict]:
    """The kernel events of `module` in the profiler's Perfetto trace: those that name an HLO instruction
    (`args["hlo_op"]`), on the device lanes (the GPU's; all lanes on a CPU), the containers left out."""
    (path,) = glob.glob(os.path.join(trace_dir, "**", "*perfetto_trace.json.gz"), recursive=True)
    with gzip.open(path) as f:
        data = json.load(f)
    events = data["traceEvents"] if isinstance(data, dict) else data
    pnames = {e["pid"]: e["args"]["name"] for e in events
              if e.get("ph") == "M" and e.get("name") == "process_name" and "args" in e}
    gpu_pids = {p for p, n in pnames.items() if "GPU" in n or "gpu" in n}
    kept = []
    for e in events:
        a = e.get("args") or {}
        if e.get("ph") != "X" or "hlo_op" not in a or module not in str(a.get("hlo_module", "")):
            continue
        if gpu_pids and e["pid"] not in gpu_pids:
            continue
        if a["hlo_op"].split(".")[0] in _CONTAINERS:
            continue
        kept.append(e)
    return kept


def _kernel_times(trace_dir: str, module: str) -> tuple[dict, float]:
    """(hlo op -> summed device microseconds, span of the events in s) from `kernel_events`."""
    times, t_lo, t_hi = collections.Counter(), np.inf, -np.inf
    for e in kernel_events(trace_dir, module):
        times[e["args"]["hlo_op"]] += float(e.get("dur", 0.0))
        t_lo, t_hi = min(t_lo, e["ts"]), max(t_hi, e["ts"] + e.get("dur", 0.0))
    return times, (t_hi - t_lo) * 1e-6 if times else 0.0


def profile(fn, args, label: str, top_n: int = 40, hlo_dir: str = None) -> dict:
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(*args))
    t0 = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    wall = time.perf_counter() - t0
    text = compiled.as_text()
    if hlo_dir:  # the optimised HLO, to read unscoped ops (copies, transposes) in their computations
        os.makedirs(hlo_dir, exist_ok=True)
        with gzip.open(os.path.join(hlo_dir, f"{label}.hlo.txt.gz"), "wt") as f:
            f.write(text)
    meta = _metadata(text)
    module = re.search(r"HloModule\s+([\w.\-]+)", text).group(1)
    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            jax.block_until_ready(compiled(*args))
        times, span = _kernel_times(tmp, module)
    by = collections.Counter()
    by_phase = collections.Counter()
    top = []
    for op, us in times.items():
        op_name = meta.get(op, "")
        ph = _phase(op_name)
        by[(ph, _stage(op_name))] += us
        by_phase[ph] += us
        top.append((us, op, ph, _stage(op_name), op_name[-120:]))
    total = sum(times.values())
    top.sort(reverse=True)
    return dict(label=label, compile_s=round(compile_s, 2), wall_s=round(wall, 4), profiled_span_s=round(span, 4),
                kernel_s=round(total * 1e-6, 4), kernels=len(times),
                phases={k: round(v * 1e-6, 4) for k, v in by_phase.most_common()},
                stages=[dict(phase=k[0], stage=k[1], s=round(v * 1e-6, 4), share=round(v / max(total, 1e-9), 4))
                        for k, v in by.most_common()],
                top_ops=[dict(s=round(u * 1e-6, 5), op=o, phase=p, stage=s, op_name=n)
                         for u, o, p, s, n in top[:top_n]])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="tactile_tripod", help="tuning config (configs/tune/) or YAML path")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--solver-grad", default=None, help="override the config's solver_grad (unrolled|implicit)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a top-level config key (YAML value), e.g. distance=0.2")
    ap.add_argument("--only", choices=("forward", "grad", "both", "jvp", "forward+jvp", "jvpm", "forward+jvpm", "jvpf",
                                       "forward+jvpf"),
                    default="both",
                    help="programs: both = forward and value_and_grad; jvp = the gradient in forward mode "
                         "(scripts/forward_grad_probe.py's program, its walk only: no --settle); jvpm = the same "
                         "with the probe's jvpm rule (the solver's factor, the update's derivative written out); "
                         "jvpf = the package's forward-mode rule (hexjax.sim.internals.forward_mode)")
    ap.add_argument("--duration", type=float, default=None,
                    help="s walked, instead of the config's (a short one keeps the trace small)")
    ap.add_argument("--settle", type=float, default=None, help="s of settling, instead of RolloutConfig's")
    ap.add_argument("--json", default=None)
    ap.add_argument("--top", type=int, default=40, help="ops listed per program in the JSON")
    ap.add_argument("--hlo-dir", default=None, help="write each program's optimised HLO text here (gzip)")
    a = ap.parse_args()
    import yaml
    overrides = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in a.set)}
    if a.solver_grad:
        overrides["solver_grad"] = a.solver_grad
    cfg = load_tune_config(a.config, overrides)
    prob = Problem.build(cfg)
    u0 = prob.space.init(prob.params0)
    terr, keys = prob.train_batch(0, a.batch)
    res = dict(config=a.config, batch=a.batch, overrides=overrides, solver_grad=cfg.solver_grad,
               device=str(jax.devices()[0].device_kind), jax=jax.__version__, date=time.strftime("%Y-%m-%d"),
               programs=[])
    labels = {"both": ("forward", "value_and_grad"), "grad": ("value_and_grad",), "forward+jvp": ("forward", "jvp"),
              "forward+jvpm": ("forward", "jvpm"), "forward+jvpf": ("forward", "jvpf")}
    for label in labels.get(a.only, (a.only,)):
        if label in ("jvp", "jvpm", "jvpf"):
            import forward_grad_probe as fgp  # the script beside this one
            with fgp.forward_rule(label):  # traced when `profile` lowers it
                res["programs"].append(profile(fgp.jvp_program(prob, one=False, duration=a.duration), (u0, terr, keys),
                                               label, a.top, a.hlo_dir))
        else:
            fn = objective_program(prob, label == "value_and_grad", duration=a.duration, settle_time=a.settle)
            res["programs"].append(profile(fn, (u0, terr, keys), label, a.top, a.hlo_dir))
    for p in res["programs"]:
        print(f"\n== {p['label']}: wall {p['wall_s']:.3f} s, kernels {p['kernel_s']:.3f} s over {p['kernels']} ops, "
              f"compile {p['compile_s']:.1f} s; phases " + ", ".join(f"{k} {v:.3f} s" for k, v in p["phases"].items()))
        for s in p["stages"][:25]:
            print(f"  {s['phase']:<10} {s['stage']:<34} {s['s']:8.4f} s {100 * s['share']:5.1f} %")
        print("  top ops:")
        for t in p["top_ops"][:15]:
            print(f"   {t['s']:8.5f} s {t['phase']:<9} {t['stage']:<24} {t['op']:<32} {t['op_name'][-70:]}")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
