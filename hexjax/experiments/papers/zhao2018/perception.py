"""Perception in the loop (Zhao 2018 Sect. 5, Fig. 15): the avoidance planner steering the MJX robot from the
obstacles its range sensor finds (`PerceivingAvoidGait`: scan -> 2.5D grid map -> RANSAC ground -> obstacle
circles), against the same planner handed the true circles (privileged) and told of none (blind), over the
same random fields (`hexjax.experiments.papers.zhao2018.closed_loop`, whose runner each mode goes through).
"""

from __future__ import annotations

import math
import time
from typing import Dict

import jax
import numpy as np
from tqdm.auto import tqdm

from hexjax.sim.engines import RANGE_SENSORS, TRACES
from hexjax.control.perceive_gait import PerceivingAvoidGait, map_bounds
from hexjax.control.registry import make_controller
from hexjax.experiments.papers.zhao2018.closed_loop import field_setup, run_closed_loop, seeded_fields
from hexjax.perceive.grid import GridMap, GridSpec
from hexjax.perceive.sensors import get_sensor
from hexjax.plan.avoid import AvoidConfig
from hexjax.world.presets import get_robot

NEEDS = frozenset({RANGE_SENSORS, TRACES})  # the walks' traces, the torso's range sensor (the runner picks once)

MODES = ("privileged", "perceived", "blind")


def perceiving_controller(robot: str, sensor: str, n_T: int, cell: float, fields, every: int,
                          threshold: float, **sensor_overrides) -> PerceivingAvoidGait:
    """The perceiving planner-gait for `fields`: its map covers the start, the targets and the obstacles'
    corridor, with 0.3 m round them (`map_bounds`)."""
    rb = get_robot(robot)
    lo, hi = map_bounds(fields, margin=0.3)
    return make_controller("perceive", rb, avoid=AvoidConfig(n_T=n_T, max_cycles=40), sensor=get_sensor(sensor, **sensor_overrides),
                               grid=GridSpec.covering(lo, hi, cell), perceive_every=every,
                               obstacle_threshold=threshold)


def _mode_numbers(res: Dict, dt: float, goal_tol: float) -> Dict:
    m = res["mjx"]
    ok, touched = res["_ok"], res["_touched"]
    tr, target = res["_traces"], np.asarray(res["_fields"].target)
    near = np.linalg.norm(tr[:, :, :2] - target[:, None], axis=-1) <= goal_tol
    t_goal = np.where(near.any(1), near.argmax(1) * dt, np.nan)
    length = np.sum(np.linalg.norm(np.diff(tr[:, :, :2], axis=1), axis=-1), axis=1)
    straight = np.linalg.norm(target, axis=-1)
    return {"success_rate": float(ok.mean()), "collision_rate": float(touched.mean()),
            "reached": m["reached"], "touched": m["touched"], "fell": m["fell"], "nan": m["nan"],
            "path_ratio_mean": float((length / straight)[ok].mean()) if ok.any() else None,
            "time_to_goal_s_mean": float(np.nanmean(t_goal[ok])) if ok.any() else None,
            "wall_s": res["wall_s"], "compile_s": res["compile_s"], "env_steps_per_s": res["env_steps_per_s"]}


def run_perception(n: int = 16, *, seed: int = 0, robot: str = "luneckas2020", sensor: str = "kinect_v1",
                   n_T: int = 2, cell: float = 0.04, every: int = 5, threshold: float = 0.05,
                   duration=None, chunk: int = 0, modes=MODES, physics="validated", progress: bool = False,
                   **sensor_overrides) -> Dict:
    """Every mode of `modes` over the same n fields (same seed, same obstacle boxes, same rollout keys), under the
    physics preset `physics` (on MJX)."""
    if not (isinstance(n, int) and n >= 1):
        raise ValueError(f"batch={n!r}: must be an integer >= 1")
    rb = get_robot(robot)
    GridSpec(cell=cell).validate()  # the sensor and grid checked before any JAX work
    get_sensor(sensor, **sensor_overrides).validate(rb)
    base = make_controller("avoid", rb, avoid=AvoidConfig(n_T=n_T, max_cycles=40))
    _, ap = field_setup(base)
    fields, _ = seeded_fields(seed, n, ap)
    ctrl = perceiving_controller(robot, sensor, n_T, cell, fields, every, threshold, **sensor_overrides)
    t0 = time.perf_counter()
    out, raw = {}, {}
    for mode in modes:
        res = run_closed_loop(n=n, seed=seed, robot=robot, n_T=n_T, duration=duration, chunk=chunk, fields=fields,
                              blind=mode == "blind", controller=ctrl if mode == "perceived" else None,
                              progress=progress, physics=physics, label=f"zhao2018-perception {mode}")
        raw[mode] = res
        out[mode] = _mode_numbers(res, base.dt, float(ap.goal_tol))
        duration = res["config"]["duration_s"]  # every mode walks as long as the first
    priv, perc = out.get("privileged"), out.get("perceived")
    ratio = {}
    if priv and perc:
        ratio = {"success_perceived_over_privileged": perc["success_rate"] / priv["success_rate"]
                 if priv["success_rate"] > 0 else None,
                 "collisions_perceived_over_privileged": perc["collision_rate"] / priv["collision_rate"]
                 if priv["collision_rate"] > 0 else (0.0 if perc["collision_rate"] == 0 else math.inf)}
    s = ctrl.sensor
    result = {"config": {"robot": robot, "fields": n, "seed": seed, "sensor": sensor, "sensor_kind": s.kind,
                         "fov_deg": [s.fov_h, s.fov_v], "rays": s.n_rays, "range_m": [s.range_min, s.range_max],
                         "noise_std": s.noise_std, "noise_quad": s.noise_quad, "dropout": s.dropout,
                         "grid_cell_m": cell, "grid_cells": [ctrl.grid.nx, ctrl.grid.ny], "scan_every_steps": every,
                         "scan_period_s": every * base.dt, "obstacle_threshold_m": threshold,
                         "duration_s": duration, "device": str(jax.devices()[0].platform)},
              "obstacles_per_field": raw[modes[0]]["obstacles_per_field"],
              "straight_line_blocked": raw[modes[0]]["straight_line_blocked"],
              "modes": out, **ratio, "wall_s": time.perf_counter() - t0}
    if "perceived" in raw:
        fin = raw["perceived"]["_final"]
        result["perceived_circles_mean"] = float(np.asarray(fin.circ.valid).sum(-1).mean())
        result["scans_per_env"] = int(np.asarray(fin.scans).max())
        result["_perceived"] = raw["perceived"]
    result["_raw"] = raw
    result["_perceived_grid"] = ctrl.grid
    return result


SWEEP_KEYS = {"noise_std": float, "noise_quad": float, "dropout": float, "range_max": float, "range_min": float,
              "n_h": int, "n_v": int, "fov_h": float, "fov_v": float}


def parse_sweep(text: str):
    """'key=v1,v2,...' -> (key, [values]) for a sensor key of SWEEP_KEYS; one-line errors."""
    if "=" not in text:
        raise ValueError(f"--sweep {text!r}: use key=v1,v2,... with key one of {sorted(SWEEP_KEYS)}")
    key, vals = text.split("=", 1)
    if key not in SWEEP_KEYS:
        raise ValueError(f"--sweep {key!r}: unknown sensor key; use one of {sorted(SWEEP_KEYS)}")
    try:
        values = [SWEEP_KEYS[key](v) for v in vals.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"--sweep {text!r}: values must be {SWEEP_KEYS[key].__name__}s") from None
    if not values:
        raise ValueError(f"--sweep {text!r}: give at least one value")
    return key, values


def run_sweeps(sweeps, n: int, seed: int, robot: str, sensor: str, **kw) -> Dict:
    """The privileged and blind runs once, then the perceived run once per value of every sweep axis (a sensor
    key set to that value, the rest from the preset), over the same fields. Each value's sensor is checked
    before anything runs."""
    axes = [parse_sweep(t) for t in sweeps]
    rb = get_robot(robot)
    for key, values in axes:
        for v in values:
            get_sensor(sensor, **{key: v}).validate(rb)
    base = run_perception(n=n, seed=seed, robot=robot, sensor=sensor, modes=("privileged", "blind"), **kw)
    kw = dict(kw, duration=base["config"]["duration_s"])
    out = []
    for key, values in axes:
        for v in tqdm(values, desc=f"sweep {key}", unit="value"):
            r = run_perception(n=n, seed=seed, robot=robot, sensor=sensor, modes=("perceived",), **kw, **{key: v})
            out.append({"key": key, "value": v, **r["modes"]["perceived"],
                        "circles_mean": r["perceived_circles_mean"]})
    base["sweep"] = out
    return base


# The experiment (configs/experiments/zhao2018-perception.yaml) ----------------------------------------------
def run(o, entry) -> Dict:
    pre = entry.preset
    kw = dict(n_T=pre["n_T"], cell=o.cell, every=o.every, threshold=pre["obstacle_threshold"], duration=o.duration,
              chunk=o.chunk, physics=o.physics, progress=True)
    if o.sweep:
        return run_sweeps(o.sweep, n=o.batch, seed=o.seed, robot=o.robot, sensor=o.sensor, **kw)
    return run_perception(n=o.batch, seed=o.seed, robot=o.robot, sensor=o.sensor, **kw)


def report(res: Dict) -> str:
    c = res["config"]
    lines = [f"\nzhao2018-perception: {c['fields']} random fields (seed {c['seed']}, "
             f"{res['obstacles_per_field']:.1f} boxes each, straight line blocked in {res['straight_line_blocked']}), "
             f"{c['duration_s']:g} s; sensor {c['sensor']} ({c['sensor_kind']}, {c['rays']} rays every "
             f"{c['scan_period_s']:g} s, {c['range_m'][0]:g}-{c['range_m'][1]:g} m), map {c['grid_cells'][0]} x "
             f"{c['grid_cells'][1]} cells of {100 * c['grid_cell_m']:g} cm",
             f"{'mode':<11} {'success %':>9} {'collide %':>9} {'reached':>7} {'fell':>4} {'path ratio':>10} "
             f"{'t goal s':>8} {'wall s':>7}"]
    for mode, m in res["modes"].items():
        pr = "-" if m["path_ratio_mean"] is None else f"{m['path_ratio_mean']:.3f}"
        tg = "-" if m["time_to_goal_s_mean"] is None else f"{m['time_to_goal_s_mean']:.1f}"
        lines.append(f"{mode:<11} {100 * m['success_rate']:>9.1f} {100 * m['collision_rate']:>9.1f} "
                     f"{m['reached']:>7d} {m['fell']:>4d} {pr:>10} {tg:>8} {m['wall_s']:>7.1f}")
    if "success_perceived_over_privileged" in res:
        r, k = res["success_perceived_over_privileged"], res["collisions_perceived_over_privileged"]
        lines.append(f"perceived / privileged: success {'n/a' if r is None else f'{100 * r:.0f} %'}, collisions "
                     f"{'n/a' if k is None else f'{k:.2f}x'}; {res.get('perceived_circles_mean', 0):.1f} circles "
                     f"perceived per field at the end")
    for r in res.get("sweep", []):
        lines.append(f"perceived, {r['key']}={r['value']:g}: success {100 * r['success_rate']:.1f} %, collide "
                     f"{100 * r['collision_rate']:.1f} %, {r['circles_mean']:.1f} circles, wall {r['wall_s']:.1f} s")
    lines.append("success: stopped within 10 cm of the target, no obstacle touched, no fall; collide: touched a box")
    return "\n".join(lines)


def plot(res: Dict, png: str, k: int = 6):
    """Without a sweep, k fields (`plot_fields`); with one, success and collisions against each swept key."""
    if res.get("sweep"):
        return plot_sweep(res, png)
    return plot_fields(res, png, k)


def plot_sweep(res: Dict, png: str):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    keys = list(dict.fromkeys(r["key"] for r in res["sweep"]))
    fig, axes = plt.subplots(1, len(keys), figsize=(4.6 * len(keys), 3.6), squeeze=False)
    for ax, key in zip(axes[0], keys):
        rows = [r for r in res["sweep"] if r["key"] == key]
        x = [r["value"] for r in rows]
        ax.plot(x, [100 * r["success_rate"] for r in rows], "o-", color="k", label="perceived: success")
        ax.plot(x, [100 * r["collision_rate"] for r in rows], "s--", color="tab:red", label="perceived: collisions")
        for mode, c in (("privileged", "tab:green"), ("blind", "tab:grey")):
            m = res["modes"].get(mode)
            if m:
                ax.axhline(100 * m["success_rate"], color=c, lw=1, label=f"{mode}: success")
        ax.set_xlabel(f"sensor {key}")
        ax.set_ylabel("% of fields")
        ax.set_ylim(-3, 103)
        ax.legend(fontsize=7)
    c = res["config"]
    fig.suptitle(f"zhao2018-perception sweep: {c['fields']} fields, sensor {c['sensor']}", fontsize=10)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return [png]


def plot_fields(res: Dict, png: str, k: int = 6):
    """k fields: true boxes, the perceived circles and map at the end, and the torso paths of each mode."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    raw = res["_raw"]
    first = raw[next(iter(raw))]
    f, tr = first["_fields"], first["_terrain"]
    order = np.concatenate([np.flatnonzero(first["_blocked"]), np.flatnonzero(~first["_blocked"])])[:k]
    cols = min(3, len(order))
    rows = int(math.ceil(len(order) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.4 * cols, 3.8 * rows), squeeze=False)
    colours = {"privileged": "tab:green", "perceived": "k", "blind": "tab:grey"}
    perc = raw.get("perceived")
    for slot, ax in enumerate(axes.ravel()):
        if slot >= len(order):
            ax.axis("off")
            continue
        i = int(order[slot])
        if perc is not None:
            fin = perc["_final"]
            h, known = GridMap(sum_z=fin.grid.sum_z[i], count=fin.grid.count[i]).heights()
            mean = np.where(np.asarray(known), np.asarray(h), np.nan)
            spec = res["_perceived_grid"]
            ext = [spec.origin[0], spec.origin[0] + spec.nx * spec.cell, spec.origin[1], spec.origin[1] + spec.ny * spec.cell]
            ax.imshow(mean.T, origin="lower", extent=ext, cmap="viridis", vmin=0, vmax=0.25, alpha=0.6)
            for c, r, v in zip(np.asarray(fin.circ.centres[i]), np.asarray(fin.circ.radii[i]), np.asarray(fin.circ.valid[i])):
                if v:
                    ax.add_patch(plt.Circle(c, r, fill=False, color="tab:blue", lw=0.8))
        for p, hh, v in zip(np.asarray(tr.box_pos[i]), np.asarray(tr.box_half[i]), np.asarray(tr.box_valid[i])):
            if v:
                ax.add_patch(plt.Rectangle(p[:2] - hh[:2], 2 * hh[0], 2 * hh[1], color="tab:red", alpha=0.5))
        for mode, r in raw.items():
            t = r["_traces"][i]
            ax.plot(t[:, 0], t[:, 1], "-", color=colours.get(mode, "k"), lw=1.1,
                    label=f"{mode} ({'ok' if r['_ok'][i] else 'failed'})")
        ax.plot(*np.asarray(f.target[i]), "*", color="tab:orange", ms=10)
        ax.set_aspect("equal")
        ax.set_xlim(-0.4, 2.4)
        ax.set_ylim(-1.0, 1.0)
        ax.set_title(f"field {i}", fontsize=9)
        ax.legend(fontsize=6, loc="lower right")
    fig.suptitle("red: true boxes; blue: perceived circles; colour: perceived map height (0-0.25 m)", fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return [png]
