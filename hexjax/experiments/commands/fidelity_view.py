"""The printed table and the plot of `hexjax fidelity` (`hexjax.experiments.commands.fidelity`)."""

from __future__ import annotations

from typing import Dict, List

import numpy as np

# the fidelity contract, per cell (docs/physics.md): preset under test minus the reference
CONTRACT = {"success_pts": 5.0, "advance_cm": 1.5, "heading_deg": 1.5}


def _engine(record) -> str:
    """The engine a JSON's physics record names (older records call it `backend`)."""
    return record.get("engine", record.get("backend"))


def report(res: Dict) -> str:
    c, s = res["config"], res["summary"]
    pa, pb = res["physics"], res["against"]
    head = (f"{'controller':<11} {'cell':<26} {'succ % A/B':>12} {'d succ (95 % CI)':>22} {'d adv cm':>9} "
            f"{'d head deg':>10} {'d drift cm':>10} {'fall % A/B':>11} {'slip cm/m A/B':>14}  ok")
    lines = [f"\nfidelity: {pa['name']} ({_engine(pa)}) against {pb['name']} ({_engine(pb)}), {c['batch']} envs per "
             f"cell, {c['distance_m']:g} m, seed {c['seed']}",
             f"contract: |d success| <= {CONTRACT['success_pts']:g} points, |d mean advance| <= "
             f"{CONTRACT['advance_cm']:g} cm, |d heading| <= {CONTRACT['heading_deg']:g} deg (A - B)", head,
             "-" * len(head)]
    for r in res["cells"]:
        lo, hi = r["d_success_ci"]
        ok = "yes" if r["within"] else ("ci" if r["within_ci"] else "NO")
        lines.append(f"{r['controller']:<11} {r['cell']:<26} {r['success_pct'][0]:5.1f}/{r['success_pct'][1]:5.1f} "
                     f"{r['d_success_pts']:+6.1f} ({lo:+6.1f}, {hi:+6.1f}) {r['d_advance_cm']:+9.2f} "
                     f"{r['d_heading_deg']:+10.2f} {r['d_drift_cm']:+10.2f} {r['fall_pct'][0]:5.1f}/{r['fall_pct'][1]:5.1f} "
                     f"{r['slip_cm_per_m'][0]:6.1f}/{r['slip_cm_per_m'][1]:6.1f}  {ok}")
    lines.append(f"{s['within']} of {s['rows']} cells within the contract ({s['within_ci']} with the band inside "
                 f"their 95 % intervals); worst |d success| {s['worst_success_pts']:.1f} points, |d advance| "
                 f"{s['worst_advance_cm']:.2f} cm, |d heading| {s['worst_heading_deg']:.2f} deg")
    lines.append("ok: yes within the contract; ci: outside it, but the contract band meets the paired 95 % interval "
                 "(more envs decide); NO: outside it and its interval")
    if res["replay"]:
        lines.append("open-loop replay (the same joint targets): torso divergence A - B, mean (max) over envs, "
                     "position in mm, yaw in deg")
        for r in res["replay"]:
            cols = ", ".join(f"{t:g} s {10 * p:.3g} ({10 * pm:.3g}) mm {y:.3g} deg" for t, p, pm, y in
                             zip(r["times_s"], r["position_cm_mean"], r["position_cm_max"], r["yaw_deg_mean"]))
            lines.append(f"  {r['cell']:<20} {cols}")
    return "\n".join(lines)


def plot(res: Dict, png: str) -> List[str]:
    """Per cell and controller, the differences A - B with their paired 95 % intervals against the contract band."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = res["cells"]
    labels = [f"{r['controller']}: {r['cell']}" for r in rows]
    y = np.arange(len(rows))
    panels = (("d_success_pts", "d_success_ci", "success_pts", "d success (points)"),
              ("d_advance_cm", "d_advance_ci", "advance_cm", "d mean advance (cm)"),
              ("d_heading_deg", "d_heading_ci", "heading_deg", "d heading error (deg)"))
    fig, axs = plt.subplots(1, 3, figsize=(15, 0.22 * len(rows) + 1.6), sharey=True)
    for ax, (k, ci, band, title) in zip(axs, panels):
        v = np.array([r[k] for r in rows])
        lo = np.array([r[ci][0] for r in rows])
        hi = np.array([r[ci][1] for r in rows])
        ok = np.array([abs(x) <= CONTRACT[band] for x in v])
        ax.axvspan(-CONTRACT[band], CONTRACT[band], color="tab:green", alpha=0.15, lw=0)
        ax.errorbar(v, y, xerr=[np.clip(v - lo, 0, None), np.clip(hi - v, 0, None)], fmt="none", ecolor="0.6",
                    lw=0.8)
        ax.scatter(v[ok], y[ok], s=12, color="tab:green", zorder=3)
        ax.scatter(v[~ok], y[~ok], s=14, color="tab:red", zorder=3)
        ax.axvline(0, color="k", lw=0.6)
        ax.set_title(title)
        ax.grid(axis="x", alpha=0.3)
    axs[0].set_yticks(y, labels, fontsize=7)
    axs[0].set_ylim(len(rows) - 0.5, -0.5)  # the first cell on top, no margin rows
    pa, pb = res["physics"], res["against"]
    height = fig.get_size_inches()[1]
    fig.suptitle(f"fidelity: {pa['name']} ({_engine(pa)}) - {pb['name']} ({_engine(pb)}), "
                 f"{res['config']['batch']} envs per cell; green band: the contract", y=1 - 0.15 / height)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.45 / height))
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return [png]
