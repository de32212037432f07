"""`hexjax bench --grad`: the cost of a gradient against the forward rollout it differentiates.

For one tuning config (configs/tune/*.yaml) and each batch size, times in one process
- `forward`: the smooth training rollout and its objective, jitted (what a zeroth-order method like CMA-ES
  pays per batch), and
- `grad-<solver_grad>`: the tuner's value and gradient of the same objective (`Problem.value_and_grad`)
  through the gradient rollout (truncated windows, per-env per-step bound, remat;
  `hexjax.tune.objective.Problem.train_rollout`) with each way through MJX's
  constraint solve (`RolloutConfig.solver_grad`: 'unrolled' Newton iterations or 'implicit' differentiation),
  and with each way to run its backward pass (`TuneConfig.backward`: 'sequential' reverse mode through the
  rollout's scan, 'parallel' the windows side by side, `hexjax.sim.windows`; rows `grad-<solver>-parallel`;
  'forward' no backward pass, forward mode, `hexjax.sim.internals.forward_mode`: rows `grad-implicit-forward`, taken
  without the config's grad_clip, which bounds reverse mode's cotangents only: each row records its bound),
and reports env-steps/s, the gradient's rate as a share of the forward's, both compile times and each program's
memory (XLA's analysis, also per env and control step) with the device's peak (on a GPU).
Both programs are kept on disk (`hexjax.sim.compiled`), the gradient under the tuner's own key, so a second run,
or a run after `hexjax tune` with the same config and `train_batch`, loads them instead of tracing them again:
its compile times are loads (rows say where each program came from; set HEXJAX_CACHE_DIR=off to measure
compiles).
"""

from __future__ import annotations

import dataclasses
import os
import platform
import time
from collections.abc import Sequence

import jax
import numpy as np
from jax.flatten_util import ravel_pytree
from tqdm.auto import tqdm

from hexjax import cache
from hexjax.sim.compiled import Compiled
from hexjax.sim.config import GRAD_SOLVERS, RolloutConfig, control_steps, total_physics_steps
from hexjax.tune.config import BACKWARDS, load_tune_config
from hexjax.tune.driver import program_digest
from hexjax.tune.objective import Problem


def _time(fn, args, repeats: int):
    """(compile s, best call s, output) of jitted fn: lower + compile timed apart from the calls, traced as a
    tuning run's `Compiled` programs are (`hexjax.cache.rare_collections`)."""
    t0 = time.perf_counter()
    with cache.rare_collections():
        compiled = fn.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    return (compile_s,) + best_call(compiled, args, repeats)


def _time_kept(program: Compiled, args, repeats: int):
    """(compile s, where the program came from, best call s, output) of a kept program: its first call compiles
    or loads it (timed before the call runs, `Compiled.call`) and is the warm-up; with `repeats` 0 that first
    call, less its compile, is the one timed (a long walk at a large batch, timed once)."""
    t0 = time.perf_counter()
    out, stats = program.call(*args)
    jax.block_until_ready(out)
    if repeats == 0:
        return stats.compile_s, stats.source, time.perf_counter() - t0 - stats.compile_s, out
    return (stats.compile_s, stats.source) + best_call(program, args, repeats, warm=True)


def best_call(compiled, args, repeats: int, warm: bool = False):
    """(best call s, output) of a compiled program: one warm-up call (none if `warm`), then the fastest of
    `repeats` timed ones."""
    out = None if warm else jax.block_until_ready(compiled(*args))
    best = np.inf
    for _ in range(max(repeats, 1)):
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(*args))
        best = min(best, time.perf_counter() - t0)
    return best, out


def device_peak_bytes():
    """The device's peak memory in use so far in this process (GPU), or None where it keeps no count (CPU)."""
    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use")


def physics_steps(problem: Problem, duration: float | None = None) -> int:
    """Physics steps of one env in `problem`'s training rollout (settling included); `duration`: instead of the
    config's walk."""
    ctrl_dt = problem.train_ctrl.dt
    walk = problem.duration if duration is None else duration
    return total_physics_steps(RolloutConfig(), problem.physics(), ctrl_dt, control_steps(walk, ctrl_dt))


def objective_program(problem: Problem, grad: bool, duration: float | None = None,
                      settle_time: float | None = None):
    """The jitted program timed: the smooth training objective (u, terrain, keys) -> (mean J, per-env J), or with
    `grad` its value and gradient through the gradient rollout (`Problem.gradient_program`; both read `duration`
    and `settle_time`). Also what scripts/profile_grad.py compiles."""
    if grad:
        return jax.jit(problem.gradient_program(duration, settle_time))
    model, fn = problem.train_rollout(grad=False, duration=duration, settle_time=settle_time)
    return jax.jit(problem.loss_fn(fn, model))


def bench_grad(tune: str = "tactile_tripod", batches: Sequence[int] = (64,),
               solver_grads: Sequence[str] = GRAD_SOLVERS, repeats: int = 2, progress: bool = True,
               unroll_substeps: bool = False, backwards: Sequence[str] = ("sequential",),
               walk: float | None = None) -> dict:
    """Rows per batch: forward, then value_and_grad for each of `solver_grads` and `backwards` (see the module
    docstring); `unroll_substeps`: the gradient rollouts' `RolloutConfig.unroll_substeps`; `walk` (s): the
    objective's walk instead of the config's. A batch whose gradient cannot fit is refused before anything
    compiles (`Problem.check_gradient_fits`)."""
    bad = [s for s in solver_grads if s not in GRAD_SOLVERS]
    if bad or not solver_grads:
        raise ValueError(f"solver_grad={list(solver_grads)!r}: a comma list of {GRAD_SOLVERS}")
    for b in batches:
        if not isinstance(b, int) or b < 1:
            raise ValueError(f"batches entry {b!r}: must be an integer >= 1")
    bad = [b for b in backwards if b not in BACKWARDS]
    if bad or not backwards:
        raise ValueError(f"backward={list(backwards)!r}: a comma list of {BACKWARDS}")
    if "forward" in backwards and "unrolled" in solver_grads:
        raise ValueError("backward 'forward' goes through the solve by implicit differentiation: pass "
                         "solver_grad=implicit only with it")
    cfg = load_tune_config(tune, {"unroll_substeps": unroll_substeps} if unroll_substeps else None)
    problems = {s + ("" if b == "sequential" else "-" + b):
                Problem.build(dataclasses.replace(cfg, solver_grad=s, backward=b,
                                                  grad_clip=None if b == "forward" else cfg.grad_clip))
                for s in solver_grads for b in backwards}
    base = next(iter(problems.values()))
    if walk is not None and not walk > 0:
        raise ValueError(f"walk={walk!r}: seconds walked must be > 0")
    for b in batches:
        base.check_gradient_fits(b, "--batches", walk)
    n_phys = physics_steps(base, walk)
    n_ctrl = control_steps(base.duration if walk is None else walk, base.train_ctrl.dt)
    u0 = base.space.init(base.params0)
    data = {b: base.train_batch(0, b) for b in batches}  # the same terrains and headings for every mode
    rows = []
    jobs = [(b, m) for b in batches for m in ("forward",) + tuple(problems)]
    for b, mode in tqdm(jobs, desc="bench --grad", disable=not progress):
        terr, keys = data[b]
        problem = base if mode == "forward" else problems[mode]
        # the gradient's key is the tuner's (`hexjax.tune.grad`) with train_batch = b: `hexjax tune` with this
        # config and batch shares one kept program with it
        role = "bench/forward" if mode == "forward" else "grad/vg"
        digest = program_digest(dataclasses.replace(problem.cfg, train_batch=b), "grad")
        if walk is not None:  # another walk is another program
            role, digest = role + f"/walk{walk:g}", digest + f"/walk{walk:g}"
        program = Compiled(objective_program(problem, grad=mode != "forward", duration=walk),
                           static=problem.static(role, digest))
        compile_s, source, run_s, out = _time_kept(program, (u0, terr, keys), repeats)
        row = dict(batch=b, mode=mode if mode == "forward" else f"grad-{mode}", compile_s=round(compile_s, 2),
                   compiled=source, run_s=round(run_s, 4), env_steps_per_s=round(b * n_phys / run_s, 1))
        # memory: the program's own (XLA's analysis), per env and control step, and the device's peak so far
        held, peak = program.memory_bytes(), device_peak_bytes()
        row.update(program_bytes=held, device_peak_bytes=peak,
                   bytes_per_env_step=None if held is None else round(held / (b * n_ctrl), 1))
        if mode == "forward":
            row["loss"] = float(out[0])
        else:
            (loss, _), g = out
            flat = np.asarray(ravel_pytree(g)[0])
            row.update(loss=float(loss), grad_norm=float(np.linalg.norm(flat)),
                       grad_nonfinite=int(np.sum(~np.isfinite(flat))), grad_clip=problems[mode].cfg.grad_clip)
            fwd = next(r for r in rows if r["batch"] == b and r["mode"] == "forward")
            row["rate_vs_forward"] = round(row["env_steps_per_s"] / fwd["env_steps_per_s"], 4)
            row["compile_vs_forward"] = round(compile_s / max(fwd["compile_s"], 1e-9), 2)
        rows.append(row)
        if progress:
            tqdm.write(f"B={b} {row['mode']}: {'load' if source == 'disk' else 'compile'} {compile_s:.1f} s, "
                       f"{row['env_steps_per_s']:.0f} env-steps/s"
                       + (f", {100 * row['rate_vs_forward']:.1f} % of forward" if "rate_vs_forward" in row else "")
                       + ("" if held is None else f", program {held / 2**20:,.1f} MiB"
                          f" ({row['bytes_per_env_step']:,.0f} bytes an env and control step)")
                       + ("" if peak is None else f", device peak so far {peak / 2**30:.2f} GiB"))
    dev = jax.devices()[0]
    return dict(kind="grad", tune=tune, controller=cfg.controller, terrain=cfg.terrain, window_s=cfg.window,
                unroll_substeps=cfg.unroll_substeps,
                duration_s=base.duration if walk is None else walk, physics_steps_per_env=n_phys,
                control_steps_per_env=n_ctrl,
                solver_iterations=base.physics().iterations, backend=jax.default_backend(),
                device=f"{dev.platform}:{getattr(dev, 'device_kind', '')}", host=platform.node(),
                cpu_count=os.cpu_count(), jax=jax.__version__, date=time.strftime("%Y-%m-%d"), rows=rows)


def format_bench_grad(res: dict) -> str:
    lines = [f"{res['device']} ({res['backend']}): value_and_grad of the {res['tune']} objective against its forward "
             f"({res['duration_s']:.2f} s walk, {res['physics_steps_per_env']} physics steps per env, "
             f"{res['window_s']} s windows, {res['solver_iterations']} Newton iterations"
             + (", physics steps unrolled)" if res.get("unroll_substeps") else ")"),
             f"{'batch':>6} {'mode':<21} {'compile s':>9} {'x fwd':>6} {'env-steps/s':>12} {'% of fwd':>8} "
             f"{'loss':>9} {'|grad|':>9} {'nonfinite':>9} {'MiB':>9}"]
    for r in res["rows"]:
        pct = f"{100 * r['rate_vs_forward']:7.1f}%" if "rate_vs_forward" in r else ""
        cx = f"{r['compile_vs_forward']:6.2f}" if "compile_vs_forward" in r else ""
        gn = f"{r['grad_norm']:9.3g} {r['grad_nonfinite']:9d}" if "grad_norm" in r else ""
        mib = "" if r.get("program_bytes") is None else f"{r['program_bytes'] / 2**20:9.1f}"
        lines.append(f"{r['batch']:6d} {r['mode']:<21} {r['compile_s']:9.1f} {cx:>6} {r['env_steps_per_s']:12.0f} "
                     f"{pct:>8} {r['loss']:9.4f} {gn if gn else ' ' * 19} {mib:>9}")
    lines.append("MiB: the program's memory while it runs (XLA's analysis: arguments, outputs, temporaries); "
                 "the JSON also has it per env and control step and the device's peak")
    if any(r.get("compiled") == "disk" for r in res["rows"]):
        lines.append("compile s: loads of programs kept by an earlier run, not compiles (HEXJAX_CACHE_DIR=off "
                     "measures compiles)")
    return "\n".join(lines)
