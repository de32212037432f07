"""Where does a control step of the batched rollout spend its time?

Three views, each at one batch size on obstacle terrain (where a controller runs, the full tactile one):

1. Stages. Each stage of `mjx.step` (and each piece hexjax adds per control step) is jitted on its own,
   vmapped over the batch and applied `--reps` times in a `lax.scan` to a settled state, so its time per
   call is measured apart from the others. The stage times need not add up to the fused step: XLA fuses
   across stage borders in the real program.
   A stage that leaves the fields it reads unchanged computes the same values at each repetition; an
   optimisation barrier keeps XLA from hoisting it out of the loop (`_repeated`).
2. Variants. The whole rollout (`hexjax.sim.rollout.rollout`) with one setting changed at a time, so
   what each lever would buy is measured in the real program.
3. Kernels (`--kernels`, CPU only). The whole `mjx.step`, scanned `--reps` times, run once under
   `jax.profiler`; XLA:CPU's kernel events are summed by class (the name without its `.N` suffix). XLA:CPU
   writes those events only with `XLA_FLAGS=--xla_cpu_enable_xprof_traceme=true` set before the run.

Prints a table and writes JSON (`--json`). Run it where the numbers matter (the GPU, through the device
tool); on a 2-core CPU use a small batch.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import os
import re
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from hexjax.control.tactile import TactileGaitController
from hexjax.sim.config import PhysicsConfig, RolloutConfig, SensorConfig
from hexjax.sim.engines import sim_model
from hexjax.sim.model import batch_model, mjx, read_obs
from hexjax.sim.rollout import rollout
from hexjax.sim.step import env_view
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import sample


def _time(fn, *args, repeats=3):
    out = fn(*args)
    jax.block_until_ready(out)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def _repeated(step, carry, reps: int):
    """`step` applied `reps` times to its own output, in a `lax.scan`. Each application takes the carry through an
    optimisation barrier together with the step's index. A stage that leaves the fields it reads unchanged computes
    the same values every time, and without the barrier XLA hoists it out of the loop and runs it once: on the CPU
    the time per call of collision, kinematics and the solve fell 3-10x from 2 to 20 repetitions."""
    def body(c, i):
        c, _ = jax.lax.optimization_barrier((c, i))
        return step(c), None
    return jax.lax.scan(body, carry, jnp.arange(reps))[0]


def _stepped(in_axes, n: int):
    """`mjx.step` applied `n` times to each env's state in a `lax.scan`, vmapped over the batch (the model's
    batched fields along `in_axes`)."""
    return jax.vmap(lambda m, d: jax.lax.scan(lambda dd, _: (mjx.step(m, dd), None), d, None, length=n)[0],
                    in_axes=(in_axes, 0))


def _settled(b: int, terrain: str):
    """The Luneckas 2020 robot on `b` draws of `terrain`, settled 0.5 s in its stance so that the feet carry the
    weight, as in a real step: (spec, sim model, terrain batch, batched model, its vmap axes, data)."""
    spec = get_robot("luneckas2020")
    sm = sim_model(spec, PhysicsConfig())
    terr = sample(get_terrain(terrain), jax.random.PRNGKey(0), b)
    m_b, in_axes = batch_model(sm, terr)
    d = jax.jit(jax.vmap(lambda _: sm.init_data(jnp.zeros(3))))(jnp.arange(b))
    d = jax.block_until_ready(jax.jit(_stepped(in_axes, 100))(m_b, d))
    return spec, sm, terr, m_b, in_axes, d


def stage_profile(b: int, reps: int, terrain: str):
    from mujoco.mjx._src import collision_driver, constraint, forward, smooth, solver
    spec, sm, terr, m_b, in_axes, d = _settled(b, terrain)
    ctrl = TactileGaitController(spec)
    params = ctrl.default_params()

    def smooth_pos(m, d):
        d = smooth.kinematics(m, d)
        d = smooth.com_pos(m, d)
        d = smooth.crb(m, d)
        return smooth.factor_m(m, d)

    stages = {
        "mjx.step (whole)": mjx.step,
        "kinematics+com+crb+factor_m": smooth_pos,
        "collision": collision_driver.collision,
        "make_constraint": constraint.make_constraint,
        "fwd_velocity": forward.fwd_velocity,
        "fwd_actuation": forward.fwd_actuation,
        "fwd_acceleration": forward.fwd_acceleration,
        "solve (Newton)": solver.solve,
        "integrate (implicitfast)": forward.implicit,
    }
    rows = []

    def timed(name, body):
        f = jax.jit(jax.vmap(lambda m, d: _repeated(lambda dd: body(m, dd), d, reps), in_axes=(in_axes, 0)))
        s = _time(f, m_b, d) / reps
        rows.append(dict(stage=name, ms_per_call=round(1e3 * s, 3), ns_per_env=round(1e9 * s / b, 1)))
        print(f"{name:<32} {1e3 * s:9.3f} ms/call {1e9 * s / b:9.1f} ns/env", flush=True)

    for name, fn in stages.items():
        timed(name, fn)

    sensors = SensorConfig()

    def body_slots(m, d, t):
        me, _, _ = env_view(sm, sensors, t, d, base=m)  # the control step's slots and model
        return d.replace(qpos=d.qpos + 1e-9 * me.geom_pos[0, 0])

    def body_obs(m, d):
        o = read_obs(sm, sensors, m, d)
        return d.replace(qpos=d.qpos + 1e-9 * o.foot_force[0, 0])

    cs0 = jax.vmap(lambda k: ctrl.init(params, k))(jax.random.split(jax.random.PRNGKey(0), b))
    obs = jax.jit(jax.vmap(lambda m, d: read_obs(sm, sensors, m, d), in_axes=(in_axes, 0)))(m_b, d)

    def scan_ctrl(cs, o):
        def f(c, _):
            c2, a = ctrl.step(params, c, o)
            return c2, a
        return jax.lax.scan(f, cs, None, length=reps)

    for name, f, args in [
        ("slots+env_model+read_obs", jax.jit(jax.vmap(
            lambda m, d, t: _repeated(lambda dd: body_slots(m, dd, t), d, reps), in_axes=(in_axes, 0, 0))),
         (m_b, d, terr)),
        ("read_obs", jax.jit(jax.vmap(lambda m, d: _repeated(lambda dd: body_obs(m, dd), d, reps),
                                      in_axes=(in_axes, 0))), (m_b, d)),
        ("controller.step (tactile)", jax.jit(jax.vmap(scan_ctrl)), (cs0, obs)),
    ]:
        s = _time(f, *args) / reps
        rows.append(dict(stage=name, ms_per_call=round(1e3 * s, 3), ns_per_env=round(1e9 * s / b, 1)))
        print(f"{name:<32} {1e3 * s:9.3f} ms/call {1e9 * s / b:9.1f} ns/env", flush=True)
    return rows


def _kernels_unavailable() -> str:
    """Why `--kernels` cannot run here, or '' (checked before any work)."""
    if jax.devices()[0].platform != "cpu":
        return "--kernels reads XLA:CPU's kernel events; on a GPU use scripts/profile_grad.py's profile"
    if "xla_cpu_enable_xprof_traceme=true" not in os.environ.get("XLA_FLAGS", ""):
        return ("--kernels: XLA:CPU writes kernel events only with XLA_FLAGS=--xla_cpu_enable_xprof_traceme=true "
                "set before the run")
    return ""


def kernel_profile(b: int, reps: int, terrain: str, top: int = 15):
    from profile_grad import kernel_events  # the script beside this one: its reader of the profiler's trace
    _, _, _, m_b, in_axes, d = _settled(b, terrain)
    compiled = jax.jit(_stepped(in_axes, reps)).lower(m_b, d).compile()
    module = re.search(r"HloModule\s+([\w.\-]+)", compiled.as_text()).group(1)
    step_s = _time(compiled, m_b, d) / reps
    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            jax.block_until_ready(compiled(m_b, d))
        kernels = kernel_events(tmp, module)
    if not kernels:
        raise SystemExit("--kernels: the profile holds no kernel events (was XLA_FLAGS set before jax started?)")
    us, count = collections.Counter(), collections.Counter()
    for e in kernels:
        name = re.sub(r"\.\d+$", "", e["args"]["hlo_op"])
        us[name] += e["dur"]
        count[name] += 1
    total = sum(us.values())
    small = sum(e["dur"] for e in kernels if e["dur"] < 5)
    print(f"mjx.step {1e3 * step_s:.2f} ms for {b} envs; {len(kernels)} kernel events, {total / 1e3:.1f} ms of CPU "
          f"over {reps} steps ({small / 1e3:.1f} ms in events under 5 us)", flush=True)
    rows = []
    for name, t in us.most_common(top):
        rows.append(dict(kernel_class=name, ms_per_step=round(t / 1e3 / reps, 3), share=round(t / total, 4),
                         events=count[name]))
        print(f"{name:<36} {t / 1e3 / reps:9.3f} ms/step {100 * t / total:6.1f} % {count[name]:7d} events")
    return dict(step_ms=round(1e3 * step_s, 3), kernel_events=len(kernels), kernel_ms=round(total / 1e3, 1),
                under_5us_ms=round(small / 1e3, 1), reps=reps, classes=rows)


def variant_profile(b: int, seconds: float, terrain: str, names):
    spec = get_robot("luneckas2020")
    ctrl = TactileGaitController(spec)
    params = ctrl.default_params()
    terr = sample(get_terrain(terrain), jax.random.PRNGKey(0), b)
    base = PhysicsConfig()
    variants = {
        "default": (base, RolloutConfig()),
        "solver as fixed scan (no while_loop)": (base, RolloutConfig(solver_grad="unrolled")),
        "torso_slots=0": (dataclasses.replace(base, torso_slots=0), RolloutConfig()),
        "slots_per_leg=1": (dataclasses.replace(base, slots_per_leg=1), RolloutConfig()),
        "iterations=1": (dataclasses.replace(base, iterations=1), RolloutConfig()),
        "ls_iterations=2": (dataclasses.replace(base, ls_iterations=2), RolloutConfig()),
    }
    rows = []
    for name in names:
        phys, cfg = variants[name]
        out, st = rollout(spec, terr, ctrl, params, seconds, jax.random.PRNGKey(1), physics=phys, config=cfg,
                          stats=True)
        first = st.wall_s
        best = np.inf
        for r in range(2):
            t0 = time.perf_counter()
            out = rollout(spec, terr, ctrl, params, seconds, jax.random.PRNGKey(2 + r), physics=phys, config=cfg)
            jax.block_until_ready(out.end_pose)
            best = min(best, time.perf_counter() - t0)
        rate = st.env_steps / best
        rows.append(dict(variant=name, batch=b, first_call_s=round(first, 1), run_s=round(best, 3),
                         env_steps_per_s=round(rate), fell=int(np.asarray(out.fell).sum()),
                         nan=int(np.asarray(out.nan).sum())))
        print(f"{name:<40} {rate:12.0f} env-steps/s (first call {first:.1f} s)", flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=32768)
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--terrain", default="high-large")
    ap.add_argument("--variants", default="default,solver as fixed scan (no while_loop),torso_slots=0,"
                                          "slots_per_leg=1,iterations=1")
    ap.add_argument("--skip-stages", action="store_true")
    ap.add_argument("--kernels", action="store_true", help="also sum XLA:CPU's kernel events by class (module doc)")
    ap.add_argument("--json", default="")
    a = ap.parse_args()
    if a.kernels and (why := _kernels_unavailable()):
        ap.error(why)
    dev = jax.devices()[0]
    res = dict(device=f"{dev.platform}:{getattr(dev, 'device_kind', '')}", jax=jax.__version__, batch=a.batch,
               terrain=a.terrain, date=time.strftime("%Y-%m-%d"))
    print(res, flush=True)
    if not a.skip_stages:
        res["stages"] = stage_profile(a.batch, a.reps, a.terrain)
    if a.kernels:
        res["kernels"] = kernel_profile(a.batch, a.reps, a.terrain)
    names = [n for n in a.variants.split(",") if n]
    res["variants"] = variant_profile(a.batch, a.seconds, a.terrain, names) if names else []
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
