"""Where does a control step of the batched rollout spend its time? (issue 7, throughput)

Two views, both at one batch size on obstacle terrain with the full (tactile) controller:

1. Stages. Each stage of `mjx.step` (and each piece hexjax adds per control step) is jitted on its own,
   vmapped over the batch and applied `--reps` times in a `lax.scan` to a settled state, so its time per
   call is measured apart from the others. The stage times need not add up to the fused step: XLA fuses
   across stage borders in the real program.
2. Variants. The whole rollout (`hexjax.sim.rollout.rollout`) with one setting changed at a time, so
   what each lever would buy is measured in the real program.

Prints a table and writes JSON (`--json`). Run it where the numbers matter (the GPU, through the device
tool); on a 2-core CPU use a small batch.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from hexjax.control.tactile import TactileGaitController
from hexjax.sim.config import PhysicsConfig, RolloutConfig, SensorConfig
from hexjax.sim.model import batch_model, mjx, read_obs, sim_model
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


def stage_profile(b: int, reps: int, terrain: str):
    from mujoco.mjx._src import collision_driver, constraint, forward, smooth, solver
    spec = get_robot("luneckas2020")
    physics = PhysicsConfig()
    sm = sim_model(spec, physics)
    terr = sample(get_terrain(terrain), jax.random.PRNGKey(0), b)
    m_b, in_axes = batch_model(sm, terr)
    ctrl = TactileGaitController(spec)
    params = ctrl.default_params()

    def init(_):
        return sm.init_data(jnp.zeros(3))

    d = jax.jit(jax.vmap(init))(jnp.arange(b))

    # settle 0.5 s in the stance so the feet carry the weight, as in a real step
    @jax.jit
    def settle(m, d):
        def one(m, d):
            return jax.lax.scan(lambda dd, _: (mjx.step(m, dd), None), d, None, length=100)[0]
        return jax.vmap(one, in_axes=(in_axes, 0))(m, d)

    d = settle(m_b, d)
    jax.block_until_ready(d)

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
        f = jax.jit(jax.vmap(lambda m, d: jax.lax.scan(lambda dd, _: (body(m, dd), None), d, None, length=reps)[0],
                             in_axes=(in_axes, 0)))
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
            lambda m, d, t: jax.lax.scan(lambda dd, _: (body_slots(m, dd, t), None), d, None,
                                         length=reps)[0], in_axes=(in_axes, 0, 0))), (m_b, d, terr)),
        ("read_obs", jax.jit(jax.vmap(
            lambda m, d: jax.lax.scan(lambda dd, _: (body_obs(m, dd), None), d, None, length=reps)[0],
            in_axes=(in_axes, 0))), (m_b, d)),
        ("controller.step (tactile)", jax.jit(jax.vmap(scan_ctrl)), (cs0, obs)),
    ]:
        s = _time(f, *args) / reps
        rows.append(dict(stage=name, ms_per_call=round(1e3 * s, 3), ns_per_env=round(1e9 * s / b, 1)))
        print(f"{name:<32} {1e3 * s:9.3f} ms/call {1e9 * s / b:9.1f} ns/env", flush=True)
    return rows


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
    ap.add_argument("--json", default="")
    a = ap.parse_args()
    dev = jax.devices()[0]
    res = dict(device=f"{dev.platform}:{getattr(dev, 'device_kind', '')}", jax=jax.__version__, batch=a.batch,
               terrain=a.terrain, date=time.strftime("%Y-%m-%d"))
    print(res, flush=True)
    if not a.skip_stages:
        res["stages"] = stage_profile(a.batch, a.reps, a.terrain)
    names = [n for n in a.variants.split(",") if n]
    res["variants"] = variant_profile(a.batch, a.seconds, a.terrain, names) if names else []
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
