"""`hexjax bench`: throughput of the full rollout (controller + sensors + physics) at several batch sizes,
with MuJoCo C's single-thread speed on the same model as a reference ratio."""

from __future__ import annotations

import os
import platform
import time
from typing import Dict, Sequence

import jax
import mujoco
import numpy as np
from tqdm.auto import tqdm

from hexjax.control.registry import CONTROLLERS, OPEN_LOOP, make_controller
from hexjax.sim.config import PhysicsConfig, RolloutConfig
from hexjax.sim.physics import get_physics, timed_settings
from hexjax.sim.mjcf import compile_mjcf
from hexjax.sim.engines import sim_model
from hexjax.sim.model import batch_model
from hexjax.sim.engines import MESH, NAMES, get_engine, host_cores
from hexjax.sim.engines.warp import overflow_counts, overflow_line
from hexjax.sim.rollout import make_mesh, rollout
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import sample


def mujoco_c_steps_per_s(robot: str, terrain: str, physics: PhysicsConfig, seconds: float = 2.0) -> float:
    """Single-thread mj_step rate on the same MJCF, slots placed on a sampled terrain, gait running."""
    spec = get_robot(robot)
    sm = sim_model(spec, physics)
    m = compile_mjcf(sm.xml)  # its ground plane follows the terrain's ground_z
    mx, _ = batch_model(sm, sample(get_terrain(terrain), jax.random.PRNGKey(0), 1))
    m.geom_pos[:] = np.asarray(mx.geom_pos[0])
    m.geom_size[:] = np.asarray(mx.geom_size[0])
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    ctrl = make_controller("gait", spec)
    p = ctrl.default_params()
    step = jax.jit(lambda s: ctrl.step(p, s, None))
    st = ctrl.init(p, None)
    n_sub = int(round(ctrl.dt / physics.timestep))
    targets = []
    for _ in range(200):
        st, a = step(st)
        targets.append(np.asarray(a))
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        d.ctrl[:] = targets[(n // n_sub) % len(targets)]
        mujoco.mj_step(m, d)
        n += 1
    return n / (time.perf_counter() - t0)


def bench(robot: str = "luneckas2020", *, batches: Sequence[int] = (16, 64, 256), sim_seconds: float = 2.0,
          terrains: Sequence[str] = ("flat", "high-large"), gait: str = "tripod",
          physics: Sequence = ("validated",), repeats: int = 2, progress: bool = True,
          controller: str = "gait", engine: str = "mjx", nthread: int = 0, devices: int = 1,
          profile: str = "") -> Dict:
    """Times `rollout` at each batch size on each terrain and physics preset. env-steps = envs x physics steps.

    physics: physics presets (names, .yaml paths or `PhysicsPreset`s), each timed on every row; every row names
    its preset.

    engine: a comma list of engines ('mjx', 'warp', 'c'; `hexjax.sim.engines`), each
    timed on the same terrains, batches and controllers; nthread: MuJoCo C threads (0: all cores).
    devices: shard each batch over this many of the visible devices (an engine with a device mesh: mjx; the batch is the total,
    so 2 devices at B = 65,536 compare with 1 device at B = 32,768 for scaling).
    Each timed call is the whole rollout (model setup, controller, sensors, physics, summary); its first call
    (compile, and for 'c' the per-env model copies) is reported apart as compile_s / first_call_s.

    controller: a comma list of 'gait' (the Luneckas 2020 open-loop gait), 'cpg' (Yu 2019 CPG with reflexes and FSM),
    'tactile' (the Luneckas 2020 gait with the tactile overcoming switch), 'avoid' (the Luneckas 2020 gait steered by the
    Zhao 2018 planner, scoring its 37 candidates every control step), 'perceive' (the same, planning round what the
    kinect_v1 preset perceives: `hexjax.control.perceive_gait`); 'both' means 'gait,cpg'. With the open-loop
    gait listed too, every other controller's row gets `overhead_vs_gait` = gait rate / its rate - 1; a
    perceiving controller's rows get `rays_per_s_per_env`, and with its blind counterpart listed too (the
    registry's `blind`: avoid for perceive) `perception_overhead` = blind rate / its rate - 1 (the cost of
    perception in the control loop).

    profile: a folder; each row then runs one more call under JAX's profiler (a trace per row under it) and keeps
    its busiest kernels as `profile` (`hexjax.experiments.commands.profile`: where the time goes)."""
    names, engines, mesh = _checked(batches, controller, engine, devices, repeats, profile)
    presets = {p.name: p for p in (get_physics(x) for x in physics)}
    if len(presets) != len(physics):
        raise ValueError(f"physics={list(physics)!r}: each preset once")
    spec = get_robot(robot)
    ctrls = {}
    for n in names:
        ctrls[n] = make_controller(n, spec, gait=gait)
    cfg = RolloutConfig()
    steps = {n: int(round((sim_seconds + cfg.settle_time) / p.timestep)) for n, p in presets.items()}
    rows = []
    jobs = [(t, b, c, be, pn) for pn in presets for be in engines for t in terrains for b in batches for c in ctrls]
    for tname, b, cname, be, pname in tqdm(jobs, desc="bench", disable=not progress):
        rows.append(_time_row(spec, ctrls[cname], tname=tname, b=b, cname=cname, be=be, pname=pname,
                              preset=presets[pname], n_phys=steps[pname], sim_seconds=sim_seconds, cfg=cfg,
                              repeats=repeats, nthread=nthread, mesh=mesh, profile=profile, progress=progress))
        if progress:
            tqdm.write(f"{pname} {be} {tname} B={b} {cname}: compile {rows[-1]['compile_s']:.1f} s, "
                       f"{rows[-1]['env_steps_per_s']:.0f} env-steps/s, "
                       f"{rows[-1]['fell']} fell, {rows[-1]['nan']} nan, tactile events {rows[-1]['tactile_steps']}")
    ref = {(t, n): mujoco_c_steps_per_s(robot, t, p.config(get_terrain(t))) for t in terrains
           for n, p in presets.items()}
    for r in rows:
        r["mujoco_c_1thread_steps_per_s"] = round(ref[r["terrain"], r["physics"]], 1)
        r["ratio_vs_mujoco_c_1thread"] = round(r["env_steps_per_s"] / ref[r["terrain"], r["physics"]], 3)
    _relative_columns(rows, ctrls, sim_seconds)
    dev = jax.devices()[0]
    return dict(robot=robot, gait=gait, controller=controller, engines=engine, nthread=nthread or host_cores(),
                sim_seconds=sim_seconds, physics_steps_per_env=steps,
                physics=[timed_settings(p, e).record() for p in presets.values() for e in engines],
                backend=jax.default_backend(),
                device=f"{dev.platform}:{getattr(dev, 'device_kind', '')}", n_devices=len(jax.devices()),
                devices_used=devices,
                host=platform.node(), cpu_count=os.cpu_count(), jax=jax.__version__,
                mujoco=mujoco.__version__, date=time.strftime("%Y-%m-%d"), rows=rows)


def format_bench(res: Dict) -> str:
    head = (f"{'physics':<10} {'engine':<7} {'terrain':<11} {'ctrl':<7} {'pairs':>5} {'batch':>7} {'compile s':>9} "
            f"{'env-steps/s':>12} {'MuJoCo C 1thr':>13} {'ratio':>6} {'vs gait':>8} {'tactile':>8}")
    lines = [f"{res['device']} ({res['backend']}, {res['n_devices']} device(s), {res.get('devices_used', 1)} used), {res['sim_seconds']} s simulated, "
             f"robot {res['robot']}", head]
    for r in res["rows"]:
        extra = f"{100 * r['overhead_vs_gait']:+7.1f}%" if "overhead_vs_gait" in r else ""
        lines.append(f"{r.get('physics', ''):<10} {r.get('engine', r.get('backend', 'mjx')):<7} {r['terrain']:<11} "
                     f"{r.get('controller', 'gait'):<7} {r['pairs']:5d} {r['batch']:7d} "
                     f"{r['compile_s']:9.1f} {r['env_steps_per_s']:12.0f} "
                     f"{r['mujoco_c_1thread_steps_per_s']:13.0f} {r['ratio_vs_mujoco_c_1thread']:6.2f} {extra:>8} "
                     f"{r.get('tactile_steps', 0):8d}")
    lines.append("tactile: control steps with a tactile pad on, summed over envs and legs (the feet met obstacles)")
    for r in res["rows"]:
        if r.get("overflow"):
            lines.append(f"{r.get('engine')} B={r['batch']}: " + overflow_line(r["overflow"]))
    for r in res["rows"]:
        if "rays_per_s_per_env" in r:
            cost = f", perception costs {100 * r['perception_overhead']:+.1f} % against " \
                f"{CONTROLLERS[r['controller']].blind}" \
                if "perception_overhead" in r else ""
            lines.append(f"{r['controller']} {r['terrain']} B={r['batch']}: {r['rays_per_s_per_env']:,.0f} rays/s "
                         f"per env in the loop{cost}")
    return "\n".join(lines)


# The command (configs/commands/bench.yaml) ---------------------------------------------------------------------
FORWARD_ONLY = ("robot", "seconds", "terrains", "controller", "engine", "nthread", "devices", "physics", "profile")
GRAD_ONLY = ("tune", "solver_grad", "backward", "unroll_substeps", "walk")


def run(o, entry) -> Dict:
    for opt in entry.options:  # a flag of the other benchmark, changed from its default, would be ignored
        if opt.name in (FORWARD_ONLY if o.grad else GRAD_ONLY) and getattr(o, opt.name) != opt.default:
            raise ValueError(f"{opt.flag}: " + ("sets the forward benchmark, not --grad" if o.grad else
                                                "sets the gradient benchmark: add --grad"))
    if o.grad:
        from hexjax.experiments.commands.bench_grad import bench_grad
        return bench_grad(tune=o.tune, batches=o.batches, solver_grads=o.solver_grad, repeats=o.repeats,
                          unroll_substeps=o.unroll_substeps, backwards=o.backward,
                          walk=o.walk or None)
    return bench(robot=o.robot, batches=o.batches, sim_seconds=o.seconds, terrains=o.terrains,
                 controller=",".join(o.controller), engine=",".join(o.engine), nthread=o.nthread,
                 devices=o.devices, repeats=o.repeats, physics=tuple(o.physics), profile=o.profile)


def report(res: Dict) -> str:
    if res.get("kind") == "grad":
        from hexjax.experiments.commands.bench_grad import format_bench_grad
        return format_bench_grad(res)
    return format_bench(res)


def _checked(batches, controller: str, engine: str, devices: int, repeats, profile: str):
    """(controller names, engine names, device mesh or None) of `bench`'s arguments, each checked: one line."""
    if not isinstance(repeats, int) or repeats < 0:
        raise ValueError(f"repeats={repeats!r}: must be an integer >= 0")
    if profile and os.path.exists(profile) and not os.path.isdir(profile):
        raise ValueError(f"profile={profile!r}: a file is there; give a folder for the traces")
    for b in batches:
        if not isinstance(b, int) or b < 1:
            raise ValueError(f"batches entry {b!r}: must be an integer >= 1")
    names = ["gait", "cpg"] if controller == "both" else controller.split(",")
    bad = [n for n in names if n not in CONTROLLERS]
    if bad or not names:
        raise ValueError(f"controller={controller!r}: a comma list of {', '.join(map(repr, CONTROLLERS))} (or 'both')")
    engines = engine.split(",")
    bad = [x for x in engines if x not in NAMES]
    if bad or not engines:
        raise ValueError(f"engine={engine!r}: a comma list of {', '.join(NAMES)}")
    if not isinstance(devices, int) or not 1 <= devices <= len(jax.devices()):
        raise ValueError(f"devices={devices!r}: must be between 1 and the {len(jax.devices())} visible device(s)")
    lacking = [x for x in engines if get_engine(x).lacks({MESH})]
    if devices > 1 and lacking:
        raise ValueError(f"devices={devices}: sharding over devices needs an engine with a device mesh; {lacking[0]} "
                         "has none")
    for b in batches:
        if b % devices:
            raise ValueError(f"batches entry {b}: must be a multiple of devices={devices}")
    return names, engines, make_mesh(jax.devices()[:devices]) if devices > 1 else None


def _time_row(spec, ctrl, *, tname: str, b: int, cname: str, be: str, pname: str, preset, n_phys: int,
              sim_seconds: float, cfg, repeats: int, nthread: int, mesh, profile: str, progress: bool) -> Dict:
    """One row of `bench`: controller `cname` on terrain `tname` at batch b, engine be, physics preset `pname`."""
    params = ctrl.default_params()
    tspec = get_terrain(tname)
    terr = sample(tspec, jax.random.PRNGKey(0), b)
    timed = timed_settings(preset, be)
    phys = timed.config(tspec)
    kw = dict(physics=phys, config=cfg, engine=be, nthread=nthread or None, mesh=mesh)
    out, st = rollout(spec, terr, ctrl, params, sim_seconds, jax.random.PRNGKey(1), stats=True, **kw)
    first, compile_s, compiled = st.wall_s, st.compile_s, st.compiled
    best = first if repeats == 0 else np.inf  # repeats=0: the first call (with its compile) is the timing
    for r in range(repeats):
        t0 = time.perf_counter()
        out = rollout(spec, terr, ctrl, params, sim_seconds, jax.random.PRNGKey(2 + r), **kw)
        jax.block_until_ready(out.end_pose)
        best = min(best, time.perf_counter() - t0)
    prof = None
    if profile:
        from hexjax.experiments.commands.profile import format_profile, profile_call
        prof = profile_call(lambda: jax.block_until_ready(rollout(spec, terr, ctrl, params, sim_seconds,
                                                                  jax.random.PRNGKey(1), **kw).end_pose),
                            os.path.join(profile, f"{pname}_{be}_{tname}_{cname}_b{b}"))
        if progress:
            tqdm.write(format_profile(prof, f"{pname} {be} {tname} B={b} {cname}"))
    return dict(terrain=tname, batch=b, controller=cname, engine=be, physics=pname,
                settings=timed.settings_from, certified=timed.certified, iterations=phys.iterations,
                cone=phys.cone, pairs=sim_model(spec, phys).n_pairs,
                compile_s=round(compile_s, 2), compiled=compiled, first_call_s=round(first, 2), repeats=repeats,
                run_s=round(best, 4), env_steps_per_s=round(b * n_phys / best, 1),
                nan=int(np.asarray(out.nan).sum()), fell=int(np.asarray(out.fell).sum()),
                tactile_steps=int(np.asarray(out.tactile_steps).sum()),
                tactile_envs=int(np.count_nonzero(np.asarray(out.tactile_steps).sum(-1))),
                overflow=overflow_counts(out.overflow, phys),
                mean_travel_x=round(float(np.mean(np.asarray(out.travel)[:, 0])), 4),
                **({"profile": prof} if prof else {}))


def _relative_columns(rows, ctrls, sim_seconds: float) -> None:
    """Each row's cost against the open-loop gait's and, for a perceiving controller, its rays a second and its
    cost against the same walk blind (the registry's `blind`), where those rows were timed too."""
    rate = {(r["terrain"], r["batch"], r["controller"], r["engine"], r["physics"]): r["env_steps_per_s"] for r in rows}

    def rate_of(r, name):
        return rate[(r["terrain"], r["batch"], name, r["engine"], r["physics"])]

    for r in rows:
        c = ctrls[r["controller"]]
        if OPEN_LOOP in ctrls and r["controller"] != OPEN_LOOP:
            r["overhead_vs_gait"] = round(rate_of(r, OPEN_LOOP) / r["env_steps_per_s"] - 1.0, 3)
        if c.sensor is not None:  # a perceiving controller: its rays, and its cost over the same walk blind
            scans = int(np.ceil(sim_seconds / c.dt / c.perceive_every))
            r["rays_per_s_per_env"] = round(c.sensor.n_rays * scans / r["run_s"], 1)
            blind = CONTROLLERS[r["controller"]].blind
            if blind in ctrls:
                r["perception_overhead"] = round(rate_of(r, blind) / r["env_steps_per_s"] - 1.0, 3)
