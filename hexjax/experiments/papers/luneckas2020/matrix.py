"""`hexjax experiment luneckas2020`: the experiment matrix of Luneckas et al. 2020 Sect. 3.3.

Gaits {wave 0.013 m/s, 20 steps/m; tripod 0.036 m/s, 13 steps/m} x density {low, high} x height {small,
large} x distance {1 m, 2 m}, each with and without the tactile method, plus the obstacle-free
calibration (Table 1), each cell over `n` randomised terrains.

How the runs are laid out (one compiled rollout per gait):
- the batch holds every category x {without, with} x n terrains and n flat calibration terrains;
  with and without the method walk the *same* terrains (paired), and both gaits get the same terrains;
- every run walks the longest distance (2 m). The 1 m figures are read from the same runs at the moment
  the gait has commanded 1 m of advance (the paper ran separate trials; the first metre of a 2 m run
  over a field populated for 2 m is the same experiment, and it saves a third of the compute). The 2 m
  figures are taken after the stop ramp and 0.5 s of standing, as in the paper.
- H of Eq. 7 is the category's maximum obstacle height (5 cm small, 8 cm large): the one thing the method
  assumes known.

Per cell: mean and spread of (dx, dy) cm, |dalpha| deg, relative error |(dx, dy)| / d (%), fall and stuck
rates, and the analytic model (Eqs. 8-14) beside the simulation."""

from __future__ import annotations

import json
import math
import time
from typing import Dict, Sequence

import jax
import numpy as np

from hexjax.experiments.papers.luneckas2020 import error_model as em
from hexjax.experiments.papers.luneckas2020.dataset import concat_datasets, save_dataset, sequences_from_runs
from hexjax.experiments.papers.luneckas2020.walks import (DISTANCES, GAITS, METHODS, STRIKE_GAP, STUCK_RATIO,
                                                          STUCK_WINDOW, errors_from, readout_index, robot_width,
                                                          simulate_gait, torso_strikes)
from hexjax.experiments.runner import read_partial, write_partial
from hexjax.sim.metrics import error_stats
from hexjax.sim.engines import TRACES
from hexjax.sim.physics import pick
from hexjax.world.presets import get_robot
from hexjax.world.terrain import LUNECKAS2020_CATEGORIES

NEEDS = frozenset({TRACES})  # the walks' traces (the runner picks the engine once)


def _cell(dx, dy, da, fell, stuck, nan, d):
    """A cell's rates and its goal errors over the robots that stayed upright (`error_stats`' schema)."""
    ok = ~fell & ~nan
    out = {"n": int(dx.size), "n_upright": int(ok.sum()), "fall_rate": float(fell.mean()),
           "stuck_rate": float((stuck & ok).mean()), "nan_envs": int(nan.sum())}
    out.update(error_stats(dx, dy, da, d, keep=ok))
    return out


def run_luneckas2020(n: int = 16, seed: int = 0, gaits: Sequence[str] = GAITS,
                     distances: Sequence[float] = DISTANCES, progress: bool = True, keep_sequences: bool = False,
                     physics="validated", partial: str = "") -> Dict:
    """Runs the whole matrix; returns a JSON-ready dict (see module doc) and, with keep_sequences,
    `_sequences`: the runs as an error-predictor dataset (`predictor`). `partial`: a file where each finished
    gait is kept (a gait's rollout is minutes on a GPU at n = 512); a rerun with the same settings takes the
    gaits kept there instead of running them again (not with keep_sequences, whose runs are not kept)."""
    if not isinstance(n, int) or n < 1:
        raise ValueError(f"n={n!r}: must be an integer >= 1")
    for g in gaits:
        if g not in GAITS:
            raise ValueError(f"gait={g!r}: choose from {GAITS}")
    distances = sorted(float(d) for d in distances)
    if not distances or distances[0] <= 0 or distances[-1] > 10:
        raise ValueError(f"distances={distances!r}: each must be in (0, 10] m")
    robot = get_robot("luneckas2020")
    d_max = distances[-1]
    width = robot_width(robot)
    res = {"config": {"experiment": "luneckas2020", "robot": robot.name, "n": n, "seed": seed,
                      "gaits": list(gaits), "distances_m": distances, "categories": list(LUNECKAS2020_CATEGORIES),
                      "robot_width_a_m": width, "stuck": f"advanced < {STUCK_RATIO:.0%} of the commanded advance "
                      f"over the last {STUCK_WINDOW:.0%} of the path", "backend": jax.default_backend(),
                      "paper_relative_error_pct": {"without": 24.0, "with": 12.0}},
           "calibration": {}, "cells": {}, "model": {}, "timing": {}}
    # the walks' physics (`walks.py`): a resumed run keeps only gaits made on the same physics
    res["physics"] = pick(physics, needs=NEEDS).record()
    # what a kept gait depends on; "readouts" names the per-run figures a kept gait carries (a gait kept before
    # the torso-strike and slip readouts were added is run again)
    key = json.dumps({k: res["config"][k] for k in ("n", "seed", "distances_m")} | {"physics": res["physics"],
                     "readouts": "causes, torso strikes, foot slip"}, sort_keys=True)
    kept = {} if keep_sequences else read_partial(partial, key, "gaits", "luneckas2020", "gaits", len(gaits), gaits)
    for gait in gaits:
        if gait in kept:
            for part in ("calibration", "cells", "model", "timing"):
                res[part][gait] = kept[gait][part]
            continue
        fits = {}  # dL per method, fitted at the shortest distance (`_model_vs_sim`)
        t0 = time.perf_counter()
        ctrl, params, terrain, s, groups, st = simulate_gait(gait, n, seed, d_max, progress=progress, physics=physics)
        wall = time.perf_counter() - t0
        trace = np.asarray(s.trace)  # (B, T, 4): x, y, z, yaw
        n_steps = trace.shape[1]
        strikes = torso_strikes(get_robot("luneckas2020"), trace, terrain)  # (B, T)
        slip = np.asarray(s.foot_slip)  # (B,) m over the whole walk
        fell_t = np.asarray(s.fall_time)
        nan = np.asarray(s.nan)
        p0 = np.asarray(s.start_pose)
        res["timing"][gait] = {"wall_s": round(wall, 1), "compile_s": round(st.compile_s, 1),
                               "envs": int(p0.shape[0]), "simulated_s": float(n_steps * ctrl.dt),
                               "cycles": ctrl.n_cycles, "swing_time_s": float(ctrl.pattern.swing_time),
                               "step_length_m": float(ctrl.pattern.step_length)}
        for d in distances:
            if d == d_max:
                pose, t_read, k = np.asarray(s.end_pose), math.inf, n_steps - 1
            else:
                k = readout_index(ctrl, params, d, n_steps)
                pose, t_read = trace[:, k][:, [0, 1, 3]], (k + 1) * ctrl.dt
            dx, dy, da, adv = errors_from(p0, pose, d)
            fell = np.asarray(s.fell) if d == d_max else fell_t <= t_read
            # stuck: little progress over the last STUCK_WINDOW of the commanded path before the readout
            k0 = readout_index(ctrl, params, (1 - STUCK_WINDOW) * d, n_steps)
            _, _, _, adv0 = errors_from(p0, trace[:, k0][:, [0, 1, 3]], d)
            stuck = (adv - adv0) < STUCK_RATIO * STUCK_WINDOW * d
            dkey = f"{d:g}m"
            struck = strikes[:, :k + 1].mean(1)  # share of the walk so far with the torso on or against a box
            for cat, meth, sl in groups:
                cell = _cell(dx[sl], dy[sl], da[sl], fell[sl], stuck[sl], nan[sl], d)
                cell["causes"] = _causes(dx[sl], dy[sl], fell[sl] | nan[sl], stuck[sl], struck[sl] > 0, d)
                cell["per_env"] = {"dx_cm": (100 * dx[sl]).round(2).tolist(), "dy_cm": (100 * dy[sl]).round(2).tolist(),
                                   "dalpha_deg": np.degrees(da[sl]).round(2).tolist(), "fell": fell[sl].tolist(),
                                   "stuck": stuck[sl].tolist(),
                                   "overcoming_steps": np.asarray(s.final_state.n_overcome[sl]).sum(-1).round(1).tolist(),
                                   "tactile_steps": np.asarray(s.tactile_steps[sl]).sum(-1).tolist(),
                                   "torso_strike_share": struck[sl].round(4).tolist(),
                                   "foot_slip_cm_whole_walk": (100 * slip[sl]).round(2).tolist()}
                if cat == "flat":
                    res["calibration"].setdefault(gait, {})[dkey] = cell
                else:
                    res["cells"].setdefault(gait, {}).setdefault(cat, {}).setdefault(dkey, {})[meth] = cell
            res["model"].setdefault(gait, {})[dkey] = _model_vs_sim(res, gait, dkey, d, terrain, groups, dx, dy, da,
                                                                     fell | nan, width, fits)
        if keep_sequences:
            res.setdefault("_sequences", []).append(
                sequences_from_runs(ctrl, params, terrain, s, groups, gait, d_max, width))
        elif partial:
            kept[gait] = {part: res[part][gait] for part in ("calibration", "cells", "model", "timing")}
            write_partial(partial, {"digest": key, "gaits": kept}, f"{len(kept)} of {len(gaits)} gaits kept in "
                          f"{partial}; the same command resumes after them")
    res["summary"] = _summary(res)
    return res  # the runner removes the partial file once the JSON holds the whole matrix


def _causes(dx, dy, bad, stuck, struck, d) -> Dict:
    """Where a cell's mean relative error (over its upright runs) comes from: the upright runs split into those
    that got stuck (little progress at the end), those whose torso struck a box but went on, and the clean rest;
    per class its share of the upright runs, its mean relative error, and its part of the cell's mean (share x
    mean; the parts add up to the cell's figure)."""
    ok = ~bad
    rel = 100 * np.hypot(dx, dy) / d
    classes = {"stuck": ok & stuck, "torso_struck": ok & ~stuck & struck, "clean": ok & ~stuck & ~struck}
    n_ok = max(int(ok.sum()), 1)
    out = {}
    for name, m in classes.items():
        share = float(m.sum()) / n_ok
        mean = float(rel[m].mean()) if m.any() else 0.0
        out[name] = {"share": share, "rel_error_pct": mean if m.any() else None, "part_pct": share * mean}
    return out


def _model_vs_sim(res, gait, dkey, d, terrain, groups, dx, dy, da, bad, width, fits):
    """Eqs. 8-14 beside the simulation. dL is fitted per method on the first readout of this gait (the
    shortest distance: `fits` is empty then and is filled here), with the calibration's mean dx removed,
    and then predicts every cell; the longer distances test the fit."""
    calib = res["calibration"][gait][dkey]["dx_cm"] / 100
    out = {}
    pos, half, valid = (np.asarray(a) for a in (terrain.box_pos, terrain.box_half, terrain.box_valid))
    for meth in METHODS:
        sel = [(c, sl) for c, m_, sl in groups if m_ == meth and c != "flat"]
        if not sel:
            continue
        counts = {c: em.obstacle_counts(pos[sl], half[sl], valid[sl], d) for c, sl in sel}
        if meth not in fits:
            n_all = np.concatenate([counts[c][0] for c, _ in sel])
            ex_all = np.concatenate([np.where(bad[sl], np.nan, dx[sl] - calib) for _, sl in sel])
            fits[meth] = max(em.fit_dL(ex_all, n_all), 0.0)
        dL = fits[meth]
        rows = {}
        for c, sl in sel:
            pred = em.predict_from_counts(dL, width, *counts[c], d)
            ok = ~bad[sl]
            nz = pred["dalpha"] != 0
            sim_dx = dx[sl][ok]
            mdx = pred["dx"][ok] + calib
            corr = float(np.corrcoef(sim_dx, mdx)[0, 1]) if ok.sum() > 2 and np.std(mdx) > 0 and np.std(sim_dx) > 0 else None
            rows[c] = {"obstacles_in_path_mean": float(pred["n_obstacles"].mean()),
                       "model_abs_dx_cm": float(100 * np.abs(mdx).mean()) if ok.any() else None,
                       "sim_abs_dx_cm": float(100 * np.abs(sim_dx).mean()) if ok.any() else None,
                       "model_abs_dy_cm": float(100 * np.abs(pred["dy"][ok]).mean()) if ok.any() else None,
                       "sim_abs_dy_cm": float(100 * np.abs(dy[sl][ok]).mean()) if ok.any() else None,
                       "model_abs_dalpha_deg": float(np.degrees(np.abs(pred["dalpha"][ok])).mean()) if ok.any() else None,
                       "sim_abs_dalpha_deg": float(np.degrees(np.abs(da[sl][ok])).mean()) if ok.any() else None,
                       "dx_corr_per_env": corr,
                       # share of runs turning to the side the model says (a predicted 0 counts as a miss)
                       "dalpha_sign_agreement": float(np.mean(np.sign(pred["dalpha"][ok]) == np.sign(da[sl][ok])))
                       if ok.any() else None,
                       "dalpha_sign_agreement_nonzero": float(np.mean(
                           np.sign(pred["dalpha"][ok & nz]) == np.sign(da[sl][ok & nz]))) if (ok & nz).any() else None}
        out[meth] = {"dL": dL, "dL_cm": 100 * dL, "alpha_k_deg": math.degrees(em.alpha_k(dL, width)), "cells": rows}
    return out


def _summary(res) -> Dict:
    """Per-cell relative errors with and without, the cells where the method wins, and overall ratios."""
    rows, wins, total = [], 0, 0
    for gait, cats in res["cells"].items():
        for cat, dists in cats.items():
            for dkey, meths in dists.items():
                w, o = meths.get("with"), meths.get("without")
                if not (w and o):
                    continue
                # "where the robot does not fall": compared on the upright runs; a cell where every run of
                # either method fell has no comparison
                comparable = w["n_upright"] > 0 and o["n_upright"] > 0
                win = comparable and w["rel_error_pct"] < o["rel_error_pct"]
                total += comparable
                wins += bool(win)
                rows.append({"gait": gait, "category": cat, "distance": dkey,
                             "rel_error_without_pct": o["rel_error_pct"], "rel_error_with_pct": w["rel_error_pct"],
                             "fall_without": o["fall_rate"], "fall_with": w["fall_rate"],
                             "stuck_without": o["stuck_rate"], "stuck_with": w["stuck_rate"], "with_lower": bool(win)})
    mean = lambda key, pred=lambda r: True: float(np.mean([r[key] for r in rows if pred(r)])) if rows else math.nan
    low1 = lambda r: r["category"].startswith("low") and r["distance"] == "1m"
    wave_better = 0
    n_pairs = 0
    if "wave" in res["cells"] and "tripod" in res["cells"]:
        for cat, dists in res["cells"]["wave"].items():
            for dkey in dists:
                n_pairs += 1
                wave_better += (res["cells"]["wave"][cat][dkey]["with"]["goal_error_cm"]
                                < res["cells"]["tripod"][cat][dkey]["with"]["goal_error_cm"])
    # the overall relative error of each method as the sum of its causes' parts (means over the cells)
    breakdown = {}
    for meth in METHODS:
        cells = [dists[dk][meth] for cats in res["cells"].values() for dists in cats.values() for dk in dists
                 if meth in dists[dk] and "causes" in dists[dk][meth]]
        if cells:
            breakdown[meth] = {c: float(np.mean([x["causes"][c]["part_pct"] for x in cells]))
                               for c in ("stuck", "torso_struck", "clean")}
            breakdown[meth]["share_stuck"] = float(np.mean([x["causes"]["stuck"]["share"] for x in cells]))
            breakdown[meth]["share_torso_struck"] = float(np.mean([x["causes"]["torso_struck"]["share"] for x in cells]))
    return {"rows": rows, "cells_with_lower": wins, "cells_compared": total, "error_breakdown_pct": breakdown,
            "torso_strike": f"an obstacle top within {100 * STRIKE_GAP:g} cm of the torso's underside at some step",
            "overall_rel_error_without_pct": mean("rel_error_without_pct"),
            "overall_rel_error_with_pct": mean("rel_error_with_pct"),
            "low_density_1m_rel_error_without_pct": mean("rel_error_without_pct", low1),
            "low_density_1m_rel_error_with_pct": mean("rel_error_with_pct", low1),
            "wave_better_than_tripod_cells": f"{wave_better} of {n_pairs}",
            "paper": "relative error ~24 % without the method (low density, 1 m), ~12 % with it; wave better 6 of 8"}


def format_luneckas(res: Dict) -> str:
    lines = []
    for gait, cal in res["calibration"].items():
        lines.append(f"calibration (no obstacles), {gait}: " + ", ".join(
            f"{k}: (dx, dy) = ({c['dx_cm']:.1f}, {c['dy_cm']:.1f}) cm, |da| {c['abs_dalpha_deg']:.1f} deg" for k, c in cal.items()))
    head = (f"{'gait':6s} {'terrain':10s} {'d':>3s} {'method':7s} {'dx cm':>12s} {'dy cm':>12s} {'|da| deg':>8s} "
            f"{'rel %':>6s} {'fall':>5s} {'stuck':>5s}")
    lines += ["", head, "-" * len(head)]
    for gait, cats in res["cells"].items():
        for cat, dists in cats.items():
            for dkey, meths in dists.items():
                for meth, c in meths.items():
                    lines.append(f"{gait:6s} {cat:10s} {dkey:>3s} {meth:7s} {c['dx_cm']:5.1f}±{c['dx_std_cm']:<5.1f} "
                                 f"{c['dy_cm']:5.1f}±{c['dy_std_cm']:<5.1f} {c['abs_dalpha_deg']:8.1f} {c['rel_error_pct']:6.1f} "
                                 f"{100 * c['fall_rate']:4.0f}% {100 * c['stuck_rate']:4.0f}%")
    s = res["summary"]
    lines += ["", f"method lowers the relative error in {s['cells_with_lower']} of {s['cells_compared']} cells",
              f"overall relative error: {s['overall_rel_error_without_pct']:.1f} % without -> "
              f"{s['overall_rel_error_with_pct']:.1f} % with (paper: ~24 % -> ~12 %)",
              f"low density, 1 m: {s['low_density_1m_rel_error_without_pct']:.1f} % -> {s['low_density_1m_rel_error_with_pct']:.1f} %",
              f"wave better than tripod (with the method): {s['wave_better_than_tripod_cells']} cells (paper: 6 of 8)"]
    for meth, b in s.get("error_breakdown_pct", {}).items():
        lines.append(f"where the error comes from, {meth}: stuck runs {b['stuck']:.1f} pts ({100 * b['share_stuck']:.0f} % of "
                     f"runs), torso struck a box {b['torso_struck']:.1f} pts ({100 * b['share_torso_struck']:.0f} %), "
                     f"clean walks {b['clean']:.1f} pts")
    for gait, dd in res["model"].items():
        for dkey, mm in dd.items():
            for meth, m in mm.items():
                cells = "; ".join(f"{c}: |dx| {r['model_abs_dx_cm']:.1f}/{r['sim_abs_dx_cm']:.1f}, |da| "
                                  f"{r['model_abs_dalpha_deg']:.1f}/{r['sim_abs_dalpha_deg']:.1f}"
                                  for c, r in m["cells"].items() if r["sim_abs_dx_cm"] is not None)
                lines.append(f"model {gait} {dkey} {meth}: dL {m['dL_cm']:.2f} cm, alpha_k {m['alpha_k_deg']:.2f} deg "
                             f"(model/sim) {cells}")
    return "\n".join(lines)


def plot_luneckas(res: Dict, stem: str) -> list:
    """Writes `<stem>_bars.png` (cf. the paper's Fig. 20) and `<stem>_field.png` (end poses as a vector
    field, cf. Figs. 16-18). Returns the paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    cats = res["config"]["categories"]
    dkeys = [f"{d:g}m" for d in res["config"]["distances_m"]]
    gaits = list(res["cells"])
    labels = [f"{c.split('-')[0]}\n{c.split('-')[1]}\n{dk}" for dk in dkeys for c in cats]
    x = np.arange(len(labels))
    fig, ax = plt.subplots(figsize=(13, 5))
    w = 0.8 / (2 * len(gaits))
    colours = {"wave": "#1f77b4", "tripod": "#d62728"}
    for gi, gait in enumerate(gaits):
        for mi, meth in enumerate(METHODS):
            vals = [res["cells"][gait][c][dk][meth]["goal_error_cm"] for dk in dkeys for c in cats]
            errs = [res["cells"][gait][c][dk][meth]["goal_error_std_cm"] for dk in dkeys for c in cats]
            off = (2 * gi + mi - len(gaits) + 0.5) * w
            ax.bar(x + off, vals, w, yerr=errs, capsize=2, color=colours.get(gait, None),
                   alpha=1.0 if meth == "with" else 0.35, hatch="" if meth == "with" else "//",
                   label=f"{gait}, {meth} method", error_kw={"lw": 0.6})
    ax.set_xticks(x, labels, fontsize=8)
    ax.set_ylabel("distance from the goal |(dx, dy)| (cm), mean ± sd of upright runs")
    ax.set_title(f"Luneckas 2020 matrix in simulation, n = {res['config']['n']} terrains per cell (cf. Fig. 20)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    p = f"{stem}_bars.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)

    fig, axes = plt.subplots(len(gaits), 2 * len(dkeys), figsize=(4.2 * 2 * len(dkeys), 4.0 * len(gaits)),
                             squeeze=False)
    style = {"small": "#2ca02c", "large": "#9467bd"}
    for gi, gait in enumerate(gaits):
        for di, dk in enumerate(dkeys):
            d = float(dk[:-1])
            for ci, dens in enumerate(("low", "high")):
                ax = axes[gi, 2 * di + ci]
                for cat in cats:
                    if not cat.startswith(dens):
                        continue
                    for meth in METHODS:
                        r = res["cells"][gait][cat][dk][meth]["per_env"]
                        h = cat.split("-")[1]
                        ex, ey = d - np.asarray(r["dx_cm"]) / 100, np.asarray(r["dy_cm"]) / 100
                        da = np.radians(np.asarray(r["dalpha_deg"]))
                        ok = ~np.asarray(r["fell"], bool) & np.isfinite(ex)
                        ax.quiver(ex[ok], ey[ok], np.cos(da[ok]), np.sin(da[ok]), color=style[h],
                                  alpha=1.0 if meth == "with" else 0.35, width=0.006, scale=18,
                                  label=f"{h}, {meth}")
                        if (~ok).any():
                            ax.scatter(ex[~ok], ey[~ok], marker="x", color=style[h], s=20)
                ax.plot([d], [0], "k*", ms=12)
                ax.plot([0, d], [0, 0], "k:", lw=0.8)
                ax.set_xlim(-0.1, d + 0.25)
                ax.set_ylim(-0.25 - 0.3 * d, 0.25 + 0.3 * d)
                ax.set_aspect("equal")
                ax.set_title(f"{gait}, {dens} density, {dk}", fontsize=9)
                ax.set_xlabel("x along the start heading (m)")
                if ci == 0 and di == 0:
                    ax.set_ylabel("y (m)")
                ax.legend(fontsize=6, loc="lower left")
    fig.suptitle("End poses: arrows at the end position along the end heading, x = fell, star = goal (cf. Figs. 16-18)")
    fig.tight_layout()
    p = f"{stem}_field.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    paths.append(p)
    return paths


# The experiment (configs/experiments/luneckas2020.yaml) -----------------------------------------------------
def run(o, entry) -> Dict:
    res = run_luneckas2020(n=o.n, seed=o.seed, gaits=o.gaits, distances=o.distances, keep_sequences=bool(o.dataset),
                           physics=o.physics, partial=(o.json + ".partial.json") if o.json else "")
    if o.dataset:
        save_dataset(o.dataset, concat_datasets(res.pop("_sequences")),
                     {"source": "experiment luneckas2020", "n": o.n, "seed": o.seed})
        print(f"wrote {o.dataset}")
    return res


def report(res: Dict) -> str:
    c = res["config"]
    return f"\nluneckas2020: robot {c['robot']}, {c['n']} randomised terrains per cell, seed {c['seed']}\n" + \
        format_luneckas(res)


def plot(res: Dict, png: str):
    return plot_luneckas(res, png[:-4] if png.endswith(".png") else png)
