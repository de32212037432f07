"""Chen 2019 Sect. 3.1 in simulation: whole-body support planning (`hexjax.control.support_gait`) against a
fixed gait over randomised rugged wave patches, counting capsizes; Fig. 6-like torso traces."""

from __future__ import annotations

import dataclasses
import time
from typing import Dict

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from hexjax.control.gait import GaitParams
from hexjax.control.registry import make_controller
from hexjax.experiments.runner import step_bar
from hexjax.perceive.grid import dem_grid
from hexjax.sim.config import RolloutConfig
from hexjax.sim.engines import RANGE_SENSORS, TRACES
from hexjax.sim.physics import pick
from hexjax.sim.rollout import rollout
from hexjax.world.dem import dem_for, dem_layout
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import heightmap, sample

NEEDS = frozenset({TRACES})  # what it needs of its engine: the walks' traces (the runner picks the engine once)


def patch_spec(width: float = 0.8, taper: float = 0.1):
    """The `waves` preset (Chen Sect. 3.1: 800 mm long, peaks 150-178 mm) at `width` m across, its heights
    fading to the floor over `taper` m inside its edges. The paper's "400 x 800 mm" does not say which side
    lies along the path; its physical patch is 850 wide x 800 long, and a 0.4 m wide patch would leave the
    chen2019 robot's feet (0.56 m apart) on flat ground either side, so the patch is 0.8 m square by default.
    Without the taper the patch starts with a cliff of up to 178 mm that the fixed gait cannot step onto
    (it stalls in front of it); with it both controllers walk onto the waves."""
    return get_terrain("waves", width=width, taper=taper)


CHEN_SLOTS = 4
"""Terrain slots per leg on the rugged patch: a 12 mm foot on 20 mm columns touches up to 4 (the waves preset's
own count). Under the `fast` preset's 2 Newton iterations the 4 kg chen2019 robot's stance feet sometimes sank
3 cm into the columns and popped out (1 of 8 planned walks capsized that way); with 4 none did."""


def _summarise(parts, far: float) -> Dict:
    cat = lambda f: np.concatenate([np.asarray(f(p)) for p in parts])
    fell, nan = cat(lambda s: s.fell), cat(lambda s: s.nan)
    end_x = cat(lambda s: s.end_pose[:, 0])
    tilt = np.degrees(cat(lambda s: s.max_tilt))
    crossed = (end_x > far) & ~fell & ~nan
    return {"capsized": int(fell.sum()), "capsize_rate": float(fell.mean()), "nan": int(nan.sum()),
            "crossed": int(crossed.sum()), "cross_rate": float(crossed.mean()),
            "stalled": int((~crossed & ~fell & ~nan).sum()),
            "max_tilt_deg": {"median": float(np.median(tilt)), "p95": float(np.percentile(tilt, 95)),
                             "max": float(np.max(tilt))},
            "tilted_over_30deg": int((tilt > 30).sum()), "end_x_median": float(np.median(end_x))}


def run_chen2019(n: int = 16, *, seed: int = 0, robot: str = "chen2019", duration: float = 16.0, stride: float = 0.05,
                 phase_time: float = 0.5, fixed_step_heights=(0.08, 0.13), chunk: int = 0, mesh=None,
                 sensor=None, perceive_every: int = 5, progress: bool = False, physics="validated") -> Dict:
    """Planned (SupportPlanController on the true DEM) vs fixed (the Luneckas 2020 tripod at the same stride
    and period and the robot's standard posture, at each swing height of `fixed_step_heights`) over n
    randomised wave patches (`patch_spec`), under the physics preset `physics` (on MJX, `CHEN_SLOTS` slots per
    leg where the preset leaves the count to the terrain). With a `sensor`
    (`hexjax.perceive.sensors.RangeSensor`) also "perceived": the same planner on the DEM it maps with that
    sensor, a scan every `perceive_every` control steps (`PerceivingSupportPlan`). Per controller: capsizes
    (the rollout's fall test: torso tilt > 60 deg or centre < 3 cm above the ground), crossings (torso past
    the patch's far edge, upright), stalls (neither), tilt statistics; for the planned ones also the smallest
    stability margin at a transition and control steps with a leg target out of reach; for the perceived one
    the final map's error against the true DEM over the patch. `_records` keeps traces for plots. progress: a bar
    per walk over its control steps (a program with a host callback, compiled afresh), or per chunk."""
    if not (isinstance(n, int) and n >= 1):
        raise ValueError(f"batch n={n!r}: must be an integer >= 1")
    if not (isinstance(duration, (int, float)) and duration > 0):
        raise ValueError(f"duration={duration!r}: must be > 0 s")
    # the plots and the support planner's records read the walks' traces
    preset = pick(physics, needs=NEEDS | ({RANGE_SENSORS} if sensor is not None else set()))
    phys = preset.config(kind="waves") if preset.settings.slots_per_leg is not None else \
        dataclasses.replace(preset.config(kind="waves"), slots_per_leg=CHEN_SLOTS)
    rb = get_robot(robot)
    spec = patch_spec()
    k_t, k_r = jax.random.split(jax.random.PRNGKey(seed))
    terrain = sample(spec, k_t, n)
    cfg = RolloutConfig(record=True)
    planned = make_controller("support", rb)
    pp = planned.default_params(stride=stride, phase_time=phase_time)
    tile = lambda x: jnp.broadcast_to(x, (n,) + jnp.shape(x))
    true_dem = dem_for(spec, terrain)
    pp = jax.tree_util.tree_map(tile, pp.replace(dem=None)).replace(dem=true_dem)
    variants = [("planned", planned, pp, True)]
    if sensor is not None:
        variants.append(("perceived", make_controller("perceive-support", rb, sensor=sensor, grid=dem_grid(spec),
                                                      perceive_every=perceive_every), pp, True))
    for h in fixed_step_heights:
        # the Luneckas 2020 tripod moves the torso l per swing slot: the same advance per phase as `stride`
        fp = GaitParams(step_length=jnp.float32(stride), step_height=jnp.float32(h),
                        swing_time=jnp.float32(phase_time), direction=jnp.float32(0.0),
                        body_height_offset=jnp.float32(0.0))
        variants.append((f"fixed_h{round(100 * h)}cm", make_controller("gait", rb, dt=0.02), fp, False))
    chunk = chunk or n
    far = spec.start_x + spec.length
    res = {"config": {"robot": robot, "patches": n, "seed": seed, "duration_s": duration, "stride": stride,
                      "phase_time": phase_time, "speed": stride / phase_time,
                      "fixed_step_heights": list(fixed_step_heights),
                      "patch": {"length": spec.length, "width": spec.width, "start_x": spec.start_x,
                                "taper": spec.taper, "peak_range": list(spec.height_range), "cell": spec.cell},
                      "torso_height": float(pp.height[0]), "physics_iterations": phys.iterations,
                      "slots_per_leg": phys.slots_per_leg, "device": str(jax.devices()[0].platform)},
           "physics": preset.record(),
           "_records": {}, "_terrain": terrain}
    if sensor is not None:
        res["config"].update(sensor=dataclasses.asdict(sensor), perceive_every=perceive_every)
    for name, ctrl, params, batched in variants:
        parts = []
        t0 = time.perf_counter()
        comp = 0.0
        with step_bar(f"chen2019 {name}: {n} patches, {duration:g} s", ctrl.dt, duration, cfg,
                      enabled=progress and n <= chunk) as run_cfg:
            for i in tqdm(range(0, n, chunk), desc=f"chen2019 {name}", unit="chunk",
                          disable=n <= chunk or not progress):
                sl = lambda x: x[i:i + chunk]
                prm = jax.tree_util.tree_map(sl, params) if batched else params
                s, st = rollout(rb, jax.tree_util.tree_map(sl, terrain), ctrl, prm, duration,
                                jax.random.fold_in(k_r, i), physics=phys, config=run_cfg, params_batched=batched,
                                mesh=mesh, stats=True, engine=preset.engine.name)
                comp += st.compile_s
                parts.append(jax.device_get(s))
        row = _summarise(parts, far)
        row["wall_s"], row["compile_s"] = time.perf_counter() - t0, comp
        cat = lambda f: np.concatenate([np.asarray(f(p)) for p in parts])
        if name in ("planned", "perceived"):
            sup = lambda s: getattr(s.final_state, "support", s.final_state)
            row["min_stability_margin_m"] = {"median": float(np.median(cat(lambda s: sup(s).min_margin))),
                                             "min": float(np.min(cat(lambda s: sup(s).min_margin)))}
            row["steps_with_a_leg_out_of_reach"] = int(cat(lambda s: sup(s).unreachable).sum())
        if name == "perceived":
            row["map"] = map_error(spec, true_dem, cat(lambda s: s.final_state.heights),
                                   cat(lambda s: s.final_state.grid.count) > 0)
            row["scans_per_walk"] = float(np.mean(cat(lambda s: s.final_state.scans)))
            res["_perceived_dem"] = cat(lambda s: s.final_state.heights)
            res["_true_dem"] = np.asarray(true_dem.heights)
        res[name] = row
        res["_records"][name] = {"trace": cat(lambda s: s.trace), "ctrl": cat(lambda s: s.ctrl_trace),
                                 "fell": cat(lambda s: s.fell)}
    return res


def map_error(spec, true_dem, heights, known) -> Dict:
    """How the perceived DEMs (heights (B, nx, ny) m, known (B, nx, ny): cells that got a return) differ from the
    true ones over the patch's cells (the taper included): the share of them seen, and the height error
    (perceived - true, m) over the seen cells and over all of them (unseen ones as the planner reads them,
    filled)."""
    origin, _, cell = dem_layout(spec)
    pad = int(round((spec.start_x - float(origin[0])) / cell))
    nx, ny = spec._grid_shape()
    win = (slice(None), slice(pad, pad + nx), slice(pad, pad + ny))
    err = (np.asarray(heights) - np.asarray(true_dem.heights))[win]
    seen = np.asarray(known)[win]
    q = lambda e: {"mean_abs": float(np.mean(np.abs(e))), "bias": float(np.mean(e)),
                   "p95_abs": float(np.percentile(np.abs(e), 95))}
    return {"seen_share": float(seen.mean()), "seen_cells": q(err[seen]) if seen.any() else None, "all_cells": q(err)}


def plot_chen2019(res: Dict, png: str, env: int = 0) -> None:
    """Fig. 6-like: torso pitch, roll and height over time for one patch, planned (measured and Eq. 3
    target) and the last fixed variant; plus the patch's height map with both torso paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fixed = [k for k in res["_records"] if k.startswith("fixed")]
    fname = fixed[-1]
    rp, rf = res["_records"]["planned"], res["_records"][fname]
    dt = 0.02
    t = np.arange(rp["trace"].shape[1]) * dt
    fig, ax = plt.subplots(2, 2, figsize=(10, 6))
    ax[0, 0].plot(t, np.degrees(rp["ctrl"][env, :, 0]), label="planned, measured")
    ax[0, 0].plot(t, np.degrees(rp["ctrl"][env, :, 2]), "--", lw=0.8, label="planned, Eq. 3 target")
    ax[0, 0].plot(t, np.degrees(rf["ctrl"][env, :, 0]), label=fname)
    ax[0, 0].set_ylabel("pitch (deg)")
    ax[0, 0].legend(fontsize=7)
    ax[0, 1].plot(t, np.degrees(rp["ctrl"][env, :, 1]), label="planned, measured")
    ax[0, 1].plot(t, np.degrees(rp["ctrl"][env, :, 3]), "--", lw=0.8, label="planned, Eq. 3 target")
    ax[0, 1].plot(t, np.degrees(rf["ctrl"][env, :, 1]), label=fname)
    ax[0, 1].set_ylabel("roll (deg)")
    ax[1, 0].plot(t, rp["trace"][env, :, 2], label="planned")
    ax[1, 0].plot(t, rf["trace"][env, :, 2], label=fname)
    ax[1, 0].set_ylabel("torso height (m)")
    for a in (ax[0, 0], ax[0, 1], ax[1, 0]):
        a.set_xlabel("time (s)")
    terr = jax.tree_util.tree_map(lambda x: x[env], res["_terrain"])
    c = res["config"]["patch"]
    xr, yr = (-0.2, c["start_x"] + c["length"] + 0.4), (-0.5, 0.5)
    hm = heightmap(terr, xr, yr, 0.01)
    im = ax[1, 1].imshow(hm.T, origin="lower", extent=(*xr, *yr), cmap="terrain")
    ax[1, 1].plot(rp["trace"][env, :, 0], rp["trace"][env, :, 1], "k-", label="planned")
    ax[1, 1].plot(rf["trace"][env, :, 0], rf["trace"][env, :, 1], "r-", label=fname)
    ax[1, 1].legend(fontsize=7)
    fig.colorbar(im, ax=ax[1, 1], label="height (m)")
    ok = lambda name: "capsized" if res["_records"][name]["fell"][env] else "upright"
    counts = ", ".join(f"{k} {res[k]['capsized']}" for k in ["planned"] + fixed)
    fig.suptitle(f"chen2019 patch {env}: planned {ok('planned')}, {fname} {ok(fname)}; capsized of "
                 f"{res['config']['patches']}: {counts}", fontsize=10)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


# The experiment (configs/experiments/chen2019.yaml) --------------------------------------------------------
def run(o, entry) -> Dict:
    p = entry.preset
    return run_chen2019(n=o.batch, seed=o.seed, robot=o.robot, duration=o.duration, stride=p["stride"],
                        phase_time=p["phase_time"], fixed_step_heights=tuple(p["fixed_step_heights"]), chunk=o.chunk,
                        physics=o.physics, progress=True)


def report(res: Dict) -> str:
    c = res["config"]
    lines = [f"\nchen2019: {c['robot']} robot over {c['patches']} rugged wave patches (seed {c['seed']}, peaks "
             f"{1000 * c['patch']['peak_range'][0]:.0f}-{1000 * c['patch']['peak_range'][1]:.0f} mm), "
             f"{c['speed']:.2f} m/s, {c['duration_s']:g} s",
             f"{'controller':>16} {'capsized':>9} {'crossed':>8} {'stalled':>8} {'tilt>30deg':>10} {'max tilt p95':>13}"]
    for k in [k for k in res if k in ("planned", "perceived") or k.startswith("fixed")]:
        r = res[k]
        lines.append(f"{k:>16} {r['capsized']:>9} {r['crossed']:>8} {r['stalled']:>8} {r['tilted_over_30deg']:>10} "
                     f"{r['max_tilt_deg']['p95']:>12.1f}d")
    for k in [k for k in ("planned", "perceived") if k in res]:
        p = res[k]
        lines.append(f"{k}: smallest stability margin at a transition {100 * p['min_stability_margin_m']['min']:.1f} "
                     f"cm (median {100 * p['min_stability_margin_m']['median']:.1f} cm); control steps with a leg "
                     f"target out of reach {p['steps_with_a_leg_out_of_reach']}")
    return "\n".join(lines)


plot = plot_chen2019  # (result, png): the registry's plot
