"""Yu 2019 Sect. 6.1 experiments as batched presets: the step obstacle (elevator reflex, `yu2019-step`) and
the ditches (searching reflex, `yu2019-ditch`), each run with and without the reflex on randomised
placements. The presets (terrains, variants, durations) are configs/experiments/yu2019-*.yaml.

`run_experiment(name)` returns a JSON-ready dict; `plot_experiment` draws foot paths in the sagittal
plane (cf. the paper's Figs. 8, 14, 15) and the CPG outputs of one leg (cf. Figs. 3, 7, 10).
"""

from __future__ import annotations

import math
from typing import Dict, Mapping, Optional

import jax
import jax.numpy as jnp
import numpy as np

from hexjax.control.cpg import MODE_NAMES, TRIPOD_GROUP, CPGController
from hexjax.control.reflex import ReflexController
from hexjax.control.registry import make_controller
from hexjax.sim.metrics import paired
from hexjax.experiments.registry import experiment
from hexjax.experiments.runner import step_bar
from hexjax.sim.config import RolloutConfig
from hexjax.sim.engines import TRACES
from hexjax.sim.physics import pick, shared_config
from hexjax.sim.rollout import rollout
from hexjax.tune.space import load_values, summed_up, with_values
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.robot import LEG_NAMES, leg_fk
from hexjax.world.terrain import sample

NEEDS = frozenset({TRACES})  # what it needs of its engine: the walks' traces (the runner picks the engine once)


def _obstacle_end(terrain, kind: str) -> np.ndarray:
    """(B,) x (m) the hind hips must pass: the step's face, or the far side of the (first) ditch."""
    pos, half = np.asarray(terrain.box_pos), np.asarray(terrain.box_half)
    if kind == "step":
        return pos[:, 0, 0] - half[:, 0, 0]
    return pos[:, 1, 0] - half[:, 1, 0]  # the slab after the ditch starts where the ditch ends


def _climb_time(s, terrain, robot, dt: float) -> np.ndarray:
    """(B, 6) s: first time each foot stood on top of the step (inside its footprint, at its height);
    inf if never."""
    feet = np.asarray(s.foot_trace)  # (B, T, 6, 3)
    pos, half = np.asarray(terrain.box_pos)[:, None, None, 0], np.asarray(terrain.box_half)[:, None, None, 0]
    inside = np.all(np.abs(feet[..., :2] - pos[..., :2]) < half[..., :2], axis=-1)
    up = inside & (feet[..., 2] > pos[..., 2] + half[..., 2] + robot.foot_radius - 0.005)
    return np.where(up.any(1), up.argmax(1) * dt, np.inf)


def _floor_gap(s, terrain, robot) -> np.ndarray:
    """(B,) m: how far above the (first) ditch's floor the lowest sole came while its foot was wholly over the
    ditch (its centre at least a foot radius inside both walls); inf where no foot was. A foot that found the
    floor reads ~0 (contact penetration), whatever the controller's own kinematic estimate of the depth."""
    feet = np.asarray(s.foot_trace)  # (B, T, 6, 3)
    pos, half = np.asarray(terrain.box_pos), np.asarray(terrain.box_half)
    lo = (pos[:, 0, 0] + half[:, 0, 0] + robot.foot_radius)[:, None, None]
    hi = (pos[:, 1, 0] - half[:, 1, 0] - robot.foot_radius)[:, None, None]
    inside = (feet[..., 0] > lo) & (feet[..., 0] < hi)
    sole = feet[..., 2] - robot.foot_radius - np.asarray(terrain.ground_z)[:, None, None]
    return np.where(inside, sole, np.inf).min((1, 2))


def _obstacle_start(terrain, kind: str) -> np.ndarray:
    """(B,) x (m) where the feature begins: the step's face, or the near edge of the (first) ditch."""
    pos, half = np.asarray(terrain.box_pos), np.asarray(terrain.box_half)
    return pos[:, 0, 0] + (-1 if kind == "step" else 1) * half[:, 0, 0]


FLOOR_TOL = 0.003  # m: a sole this close to the ditch floor stands on it (Yu 2019's 18 / 40 mm footholds)


def _summarise(ctrl: CPGController, robot, s, terrain, kind: str, stumble_tilt: float) -> Dict:
    fs = jax.tree_util.tree_map(np.asarray, s.final_state)
    end_x = np.asarray(s.end_pose[:, 0])
    far = _obstacle_end(terrain, kind)
    # the front feet got as far as the feature (their farthest reach ahead of the torso centre)
    reached = end_x + robot.hip_x + robot.stance_radial >= _obstacle_start(terrain, kind)
    # crossed: the hind hips are past the ditch, or past the step's face with every right foot having
    # stood on top of the step (a robot that veered along the face does not count)
    crossed = end_x - robot.hip_x > far
    climb = None
    if kind == "step":
        if s.foot_trace is None:
            raise ValueError("the step experiment needs foot traces: run with record=True")
        # all three right feet up: the time the last of them first stood on the step
        climb = _climb_time(s, terrain, robot, ctrl.dt)[:, [LEG_NAMES.index(n) for n in ("RF", "RM", "RH")]].max(-1)
        crossed = crossed & np.isfinite(climb)
    fell = np.asarray(s.fell)
    modes = np.asarray(ctrl.mode(s.final_state))
    n_found = fs.n_found.sum(-1)
    failed = fs.failed > 0.5  # legs waiting after a give-up at the end of the run
    gave_up = fs.n_fail.sum(-1) > 0  # runs where some search gave up (with walk_on the leg walks on after)
    # for a leg that gave up: distance of the measured foot from its AEP posture (q_ref)
    err = np.linalg.norm(np.asarray(leg_fk(robot, jnp.asarray(fs.q_meas)) - leg_fk(robot, jnp.asarray(fs.q_ref))), axis=-1)
    aep_err = np.where(failed, err, np.nan)
    # the FSM at a give-up: the failed leg's alien group in stance-prolong, its own group in swing-prolong
    alien_prolong = []
    for b in np.nonzero(failed.any(-1))[0]:
        leg = int(np.nonzero(failed[b])[0][0])
        alien = TRIPOD_GROUP != TRIPOD_GROUP[leg]
        alien_prolong.append(bool(np.all(modes[b][alien] == MODE_NAMES.index("stance-prolong"))))
    depth = fs.depth.max(-1)
    yaw = np.degrees(np.asarray(s.end_pose[:, 2] - s.start_pose[:, 2]))
    out = {
        "envs": int(end_x.shape[0]),
        "success_rate": float(np.mean(crossed & ~fell)),
        "fall_rate": float(np.mean(fell)),
        "stumble_rate": float(np.mean(np.asarray(s.max_tilt) > stumble_tilt)),
        "nan_envs": int(np.sum(np.asarray(s.nan))),
        "advance_m_mean": float(np.mean(end_x - np.asarray(s.start_pose[:, 0]))),
        "elevator_triggers_mean": float(fs.n_elev.sum(-1).mean()),
        "search_triggers_mean": float(fs.n_search.sum(-1).mean()),
        "footholds_found_mean": float(n_found.mean()),
        "envs_with_found_foothold": float(np.mean(n_found > 0)),
        "search_depth_mm_max": float(1000 * depth.max()) if depth.size else 0.0,
        "search_depth_mm_mean_of_found": float(1000 * depth[n_found > 0].mean()) if np.any(n_found > 0) else None,
        "out_of_range_envs": float(np.mean(gave_up)),
        "failed_leg_aep_error_mm_max": float(1000 * np.nanmax(aep_err)) if np.any(failed) else None,
        "failed_with_alien_group_in_stance_prolong": float(np.mean(alien_prolong)) if alien_prolong else None,
        "stance_prolong_steps_during_search_mean": float(fs.wait_steps.sum(-1).mean()),
        "per_env": {"advance_m": (end_x - np.asarray(s.start_pose[:, 0])).round(4).tolist(),
                    "crossed": crossed.tolist(), "fell": fell.tolist(),
                    "max_tilt_deg": np.degrees(np.asarray(s.max_tilt)).round(1).tolist(),
                    "elevator_triggers": fs.n_elev.sum(-1).tolist(), "search_triggers": fs.n_search.sum(-1).tolist(),
                    "search_depth_mm": (1000 * depth).round(1).tolist(), "gave_up": gave_up.tolist(),
                    "heading_change_deg": yaw.round(1).tolist()},
        "heading_change_deg_mean_abs": float(np.mean(np.abs(yaw))),
        "reached_feature_rate": float(np.mean(reached)),
    }
    if kind == "ditch" and s.foot_trace is not None:
        gap = _floor_gap(s, terrain, robot)
        over = np.isfinite(gap)
        out["foot_over_ditch_rate"] = float(np.mean(over))
        out["floor_reached_rate"] = float(np.mean(gap <= FLOOR_TOL))
        out["floor_reached_rate_of_feet_over_ditch"] = float(np.mean(gap[over] <= FLOOR_TOL)) if over.any() else None
        out["per_env"]["floor_gap_mm"] = [round(1000 * float(g), 1) if np.isfinite(g) else None for g in gap]
    if climb is not None:
        up = np.isfinite(climb)
        out["right_feet_up_rate"] = float(np.mean(up))
        out["right_feet_up_s_median"] = float(np.median(climb[up])) if up.any() else None
        out["per_env"]["right_feet_up_s"] = [round(float(c), 2) if np.isfinite(c) else None for c in climb]
    return out


def paired_rows(terrains, params_rows, batch: int, seed: int):
    """(terrain, params, keys) of rows run in one batch: row r is envs [r * batch, (r + 1) * batch), on
    terrains[r] (a batch of `batch`) with params_rows[r]; env i of every row gets the same key (heading draw and
    controller key, from `seed` + 1), so rows on the same terrains are paired env for env."""
    terrain = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), *terrains)
    params = jax.tree_util.tree_map(lambda *xs: jnp.repeat(jnp.stack([jnp.asarray(x) for x in xs]), batch, 0),
                                    *params_rows)
    keys = jnp.tile(jax.random.split(jax.random.PRNGKey(seed + 1), batch), (len(params_rows), 1))
    return terrain, params, keys


def run_experiment(name: str, batch: int = 32, seed: int = 0, duration: Optional[float] = None,
                   record: bool = True, progress: bool = True, preset: Optional[Mapping] = None,
                   params: Optional[Mapping] = None, physics="validated") -> Dict:
    """Runs every (terrain, variant) of experiment `name` (its preset: configs/experiments/<name>.yaml, or
    `preset`) on `batch` randomised terrains (the same terrains for every variant). `params` ({field: value},
    e.g. a tuned result) replaces the paper's numbers in every variant; `physics`: the physics preset (name,
    .yaml path or `PhysicsPreset`; on MJX: a step's success reads the foot traces). Returns {"config",
    "results": {terrain: {variant: metrics}}, "comparisons", "_records"}; `comparisons` holds, per terrain,
    each variant less each later one on the same envs (paired 95 % intervals); `_records` (with `record`) holds
    numpy traces of one env per row for plotting and is not JSON."""
    ex = dict(preset if preset is not None else experiment(name).preset)
    if not isinstance(batch, int) or batch < 1:
        raise ValueError(f"batch={batch!r}: must be an integer >= 1")
    dur = float(duration if duration is not None else ex["duration"])
    if not (math.isfinite(dur) and dur > 0):
        raise ValueError(f"duration={duration!r}: must be a finite number of seconds > 0")
    robot = get_robot(ex["robot"])
    preset = pick(physics, needs=NEEDS)  # a step's success reads the foot traces
    # a tuned reflex layer's preset (its weights, `net`) runs the CPG under that layer (`hexjax.control.reflex`)
    ctrl = make_controller("cpg-reflex" if params and "net" in params else "cpg", robot)
    cpg = ctrl.base if isinstance(ctrl, ReflexController) else ctrl
    if params:
        with_values(ctrl.default_params(), params)  # a wrong name or shape fails here
    variants = list(ex["variants"].items())
    stumble_tilt = math.radians(ex["stumble_tilt_deg"])
    out = {"config": {"experiment": name, "robot": robot.name, "batch": batch, "seed": seed, "duration_s": dur,
                      "terrains": list(ex["terrains"]), "variants": [v for v, _ in variants],
                      "stumble_tilt_deg": math.degrees(stumble_tilt),
                      "solver_iterations": preset.settings.iterations,
                      "params": {k: summed_up(v) for k, v in (params or {}).items()} or "the paper's"},
           "results": {}, "_records": {}, "timing": [], "physics": preset.record()}
    rows = [(t, v, o or {}) for t in ex["terrains"] for v, o in variants]
    specs = {t: get_terrain(t, **ex.get("terrain_overrides", {})) for t in ex["terrains"]}
    sampled = {t: sample(spec, jax.random.PRNGKey(seed), batch) for t, spec in specs.items()}
    # every row in one batch (the variants are params, the terrains share a shape): the GPU steps the rows
    # together instead of one small batch after another. Row r holds envs [r * batch, (r + 1) * batch); an
    # env's terrain and its heading noise and controller key are the same in every variant (paired rows).
    groups = {}  # terrain shapes -> row indices (presets of one kind share one)
    for i, (t, _, _) in enumerate(rows):
        shapes = tuple(np.shape(a) for a in jax.tree_util.tree_leaves(sampled[t]))
        groups.setdefault(shapes, []).append(i)
    summaries = {}
    for idx in groups.values():
        params_rows = [with_values(ctrl.default_params(**{k: float(v) for k, v in rows[i][2].items()}), params or {})
                       for i in idx]
        terrain, p, keys = paired_rows([sampled[rows[i][0]] for i in idx], params_rows, batch, seed)
        # a bar over the walk's control steps: one rollout holds every row of the group (minutes on a CPU)
        with step_bar(f"{name}: {len(idx)} rows x {batch} envs, {dur:g} s", ctrl.dt, dur,
                      RolloutConfig(record=True), enabled=progress) as cfg:  # the foot traces: step, ditch floor
            s, st = rollout(robot, terrain, ctrl, p, dur, keys,
                            physics=shared_config(preset, [specs[rows[i][0]] for i in idx]),
                            engine=preset.engine.name, config=cfg, params_batched=True, stats=True)
        if isinstance(ctrl, ReflexController):  # the CPG's own state under its learned reflex layer
            s = s.replace(final_state=s.final_state.base)
        out["timing"].append({"rows": [f"{rows[i][0]} / {rows[i][1]}" for i in idx], "envs": batch * len(idx),
                              "wall_s": round(st.wall_s, 1), "compile_s": round(st.compile_s, 1)})
        for j, i in enumerate(idx):
            part = slice(j * batch, (j + 1) * batch)
            summaries[i] = (jax.tree_util.tree_map(lambda a: a[part], s), sampled[rows[i][0]])
    for i, (terrain_name, label, _) in enumerate(rows):
        s, terrain = summaries[i]
        spec = specs[terrain_name]
        out["results"].setdefault(terrain_name, {})[label] = _summarise(cpg, robot, s, terrain, spec.kind,
                                                                        stumble_tilt)
        if record:
            env = int(np.argmax(np.asarray(s.final_state.n_elev.sum(-1) + s.final_state.n_search.sum(-1))))
            out["_records"][(terrain_name, label)] = dict(
                env=env, dt=ctrl.dt, feet=np.asarray(s.foot_trace[env]), x=np.asarray(s.ctrl_trace["x"][env]),
                mode=np.asarray(s.ctrl_trace["mode"][env]), box_pos=np.asarray(terrain.box_pos[env]),
                box_half=np.asarray(terrain.box_half[env]), ground_z=float(terrain.ground_z[env]), kind=spec.kind)
    out["comparisons"] = _comparisons(out["results"])
    return out


def _comparisons(results: Dict) -> Dict:
    """Per terrain, {"<a> - <b>": {metric: [mean, lo, hi]}} for every pair of variants (a listed before b): the
    paired differences in percentage points of success and falls (the same terrains and draws)."""
    out = {}
    for t, vs in results.items():
        pts = {}  # variant -> {metric: per-env 0 / 100}
        for v, r in vs.items():
            crossed, fell = np.asarray(r["per_env"]["crossed"], bool), np.asarray(r["per_env"]["fell"], bool)
            pts[v] = {"success_pts": 100.0 * (crossed & ~fell), "fall_pts": 100.0 * fell}
        names = list(vs)
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                row = {}
                for key in ("success_pts", "fall_pts"):
                    m, (lo, hi) = paired(pts[a][key], pts[b][key])
                    row[key] = [round(m, 2), round(lo, 2), round(hi, 2)]
                out.setdefault(t, {})[f"{a} - {b}"] = row
    return out


def format_experiment(res: Dict) -> str:
    rows = [f"{'terrain':9s} {'variant':12s} {'success':>8s} {'falls':>6s} {'stumble':>8s} {'advance':>8s} "
            f"{'elev':>6s} {'search':>7s} {'found':>6s} {'depth':>7s} {'gave up':>8s} {'|yaw|':>6s} {'up at':>6s}"]
    for t, vs in res["results"].items():
        for v, m in vs.items():
            rows.append(f"{t:9s} {v:12s} {100 * m['success_rate']:7.0f}% {100 * m['fall_rate']:5.0f}% "
                        f"{100 * m['stumble_rate']:7.0f}% {m['advance_m_mean']:7.2f}m {m['elevator_triggers_mean']:6.1f} "
                        f"{m['search_triggers_mean']:7.1f} {m['footholds_found_mean']:6.1f} "
                        f"{m['search_depth_mm_max']:5.1f}mm {100 * m['out_of_range_envs']:7.0f}% "
                        f"{m['heading_change_deg_mean_abs']:5.0f}d "
                        + (f"{m['right_feet_up_s_median']:5.0f}s" if m.get("right_feet_up_s_median") is not None else "     -"))
    return "\n".join(rows)


def plot_experiment(res: Dict, path: str) -> None:
    """One row per (terrain, variant): foot paths of the right legs in the sagittal plane (world x-z) with
    the obstacle, and the three neuron outputs of the leg with the most reflex activity, modes shaded."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recs = res["_records"]
    if not recs:
        raise ValueError("no records to plot: run with record=True")
    fig, axes = plt.subplots(len(recs), 2, figsize=(14, 3.2 * len(recs)), squeeze=False)
    colours = {"swing": "#cfe8ff", "stance-prolong": "#ffe0b3", "swing-prolong": "#ffd1dc", "search": "#d9f2d0",
               "search-failed": "#dddddd"}
    for row, ((terrain, label), r) in enumerate(recs.items()):
        ax = axes[row, 0]
        for i, leg in enumerate(LEG_NAMES):
            if leg.startswith("R") or r["kind"] == "ditch":
                ax.plot(r["feet"][:, i, 0], 1000 * r["feet"][:, i, 2], lw=0.8, label=leg)
        for pos, half in zip(r["box_pos"], r["box_half"]):
            ax.add_patch(plt.Rectangle((pos[0] - half[0], 1000 * (pos[2] - half[2])), 2 * half[0], 2000 * half[2],
                                       color="0.6", alpha=0.4, lw=0))
        ax.axhline(1000 * r["ground_z"], color="0.4", lw=0.8)
        ax.set_xlabel("x (m)"); ax.set_ylabel("foot centre z (mm)")
        ax.set_title(f"{terrain} / {label}: foot paths (env {r['env']})")
        ax.legend(fontsize=7, ncol=3)
        ax = axes[row, 1]
        mode = r["mode"]
        activity = ((mode == 4) | (mode == 5)).sum(0) + (np.diff(r["x"][:, :, 0], axis=0) < -0.05).sum(0)
        leg = int(np.argmax(activity))
        t = np.arange(len(mode)) * r["dt"]
        for k, name in enumerate(MODE_NAMES):
            if name in colours:
                on = mode[:, leg] == k
                ax.fill_between(t, -1.6, 1.6, where=on, color=colours[name], step="mid", lw=0, label=name)
        for j, lab in enumerate(("x1 (alpha)", "x2 (beta)", "x3 (gamma)")):
            ax.plot(t, r["x"][:, leg, j], lw=0.9, label=lab)
        ax.set_ylim(-1.6, 1.6); ax.set_xlabel("t (s)"); ax.set_ylabel("neuron output")
        ax.set_title(f"CPG outputs, leg {LEG_NAMES[leg]}")
        ax.legend(fontsize=7, ncol=4, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# The experiments (configs/experiments/yu2019-step.yaml, yu2019-ditch.yaml) --------------------------------
def run(o, entry) -> Dict:
    return run_experiment(entry.name, batch=o.batch, seed=o.seed, duration=o.duration, record=bool(o.png),
                          preset=entry.preset, params=load_values(o.params) if o.params else None,
                          physics=o.physics)


def report(res: Dict) -> str:
    c = res["config"]
    lines = [f"\n{c['experiment']}: robot {c['robot']}, {c['batch']} randomised terrains per row, "
             f"{c['duration_s']:g} s, seed {c['seed']}", format_experiment(res)]
    for t, pairs in res.get("comparisons", {}).items():
        for name, d in pairs.items():
            lines.append(f"{t:9s} {name}: success {d['success_pts'][0]:+.1f} pts (95 % {d['success_pts'][1]:+.1f} .. "
                         f"{d['success_pts'][2]:+.1f}), falls {d['fall_pts'][0]:+.1f} pts (95 % {d['fall_pts'][1]:+.1f} "
                         f".. {d['fall_pts'][2]:+.1f})")
    for t, vs in res["results"].items():
        for v, m in vs.items():
            if m.get("foot_over_ditch_rate"):
                lines.append(f"{t:9s} {v}: a foot wholly over the ditch in {100 * m['foot_over_ditch_rate']:.0f} % of runs, "
                             f"its sole on the floor (within {1000 * FLOOR_TOL:g} mm) in {100 * m['floor_reached_rate']:.0f} %")
    for t, vs in res["results"].items():
        if all(m["reached_feature_rate"] == 0 for m in vs.values()):
            lines.append(f"warning: on {t} no robot reached the obstacle in {c['duration_s']:g} s, so the rates above "
                         f"say nothing of the reflex; run longer (--duration)")
    return "\n".join(lines)


plot = plot_experiment  # (result, png): the registry's plot
