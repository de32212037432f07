"""The printed table and the figure of a `hexjax robustness` sweep (`hexjax.experiments.commands.robustness`)."""

from __future__ import annotations

from typing import Dict, List

import numpy as np

ENVELOPE_SUCCESS = 0.9  # a controller's envelope: the hardest level with at least this success at every easier one


def _devices(c) -> str:
    """Where a cell ran: on a CPU the sweep shards over one XLA device per core, so say cores there."""
    n, platform = c.get("devices", 1), c.get("backend", "")
    if platform == "cpu":
        return f"{n} CPU core{'s' if n > 1 else ''} (one XLA device each)"
    return f"{n} {platform.upper() or 'device'}{'s' if n > 1 else ''}"


def report(res: Dict) -> str:
    if "process" in res:
        return f"process {res['process']}: ran its shards of {res['cells_run']} cells; process 0 writes the results"
    c = res["config"]
    names = list(c["axes"])
    head = (f"{'controller':<10} " + " ".join(f"{n:>16}" for n in names)
            + f" {'succ %':>7} {'95 % CI':>13} {'goal err cm':>11} {'fall %':>7} {'energy J':>9} {'NaN':>4}")
    lines = [f"\nrobustness sweep: {c['batch']} envs per cell on {_devices(c)}, "
             f"{c['distance_m']:g} m on {c['terrain']}, "
             f"{res['physics']['name']} physics ({c.get('engine', c.get('physics_backend'))}), seed {c['seed']}", head,
             "-" * len(head)]
    for r in res["cells"]:
        lo, hi = r["success_ci95"]
        lines.append(f"{r['controller']:<10} " + " ".join(f"{r[n]:16g}" for n in names)
                     + f" {r['success_pct']:7.1f} {100 * lo:5.1f}-{100 * hi:5.1f} % {r['goal_error_cm']:11.1f} "
                     f"{r['fall_pct']:7.1f} {r['energy_J']:9.2f} {r['nan']:4d}")
    lines.append("succ: upright and within 10 cm of the goal; 95 % CI: Wilson interval of the success rate")
    lines.append(f"robustness envelope along {names[0]} (the hardest level reached with success >= 90 % at every "
                 "easier level; 'sure': its 95 % interval above 90 % too):")
    for label, e in res["envelope"].items():
        if e["level"] is None:
            lines.append(f"  {label}: below 90 % already at the easiest level")
        else:
            sure = "none" if e["sure_level"] is None else f"{e['sure_level']:g}"
            lines.append(f"  {label}: {names[0]} = {e['level']:g} (success {100 * e['success']:.0f} %, 95 % CI "
                         f"{100 * e['ci95'][0]:.0f}-{100 * e['ci95'][1]:.0f} %; sure: {sure})")
    lines.append("compile s per controller: " + ", ".join(f"{k} {v:.1f}" for k, v in res["compile_s"].items()))
    return "\n".join(lines)


METRICS = (("success_pct", "success %", "RdYlGn"), ("goal_error_cm", "goal error (cm)", "viridis_r"),
           ("fall_pct", "falls %", "Reds"), ("energy_J", "energy (J)", "magma_r"))


def plot(res: Dict, png: str) -> List[str]:
    """One panel per metric and controller: curves over a single axis, heat maps over two."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    c = res["config"]
    names = list(c["axes"])
    ctrls = c["controllers"]
    if len(names) == 1:
        fig, axs = plt.subplots(1, len(METRICS), figsize=(4.2 * len(METRICS), 3.6))
        for ax, (key, label, _) in zip(axs, METRICS):
            for cname in ctrls:
                sel = [r for r in res["cells"] if r["controller"] == cname]
                x = [r[names[0]] for r in sel]
                y = [r[key] for r in sel]
                ax.plot(x, y, "o-", label=cname)
                if key == "success_pct":
                    lo = [100 * r["success_ci95"][0] for r in sel]
                    hi = [100 * r["success_ci95"][1] for r in sel]
                    ax.fill_between(x, lo, hi, alpha=0.2)
            ax.set_xlabel(names[0])
            ax.set_title(label)
            ax.grid(alpha=0.3)
            if key.endswith("pct"):  # a share: 0-100 %, not autoscaled below zero when every cell reads 0
                ax.set_ylim(-2, 102)
            else:
                ax.set_ylim(bottom=0)
        axs[0].axhline(100 * ENVELOPE_SUCCESS, color="k", lw=0.8, ls="--")
        axs[0].legend()
    else:
        xs, ys = c["axes"][names[0]], c["axes"][names[1]]
        fig, axs = plt.subplots(len(ctrls), len(METRICS), figsize=(4.2 * len(METRICS), 3.4 * len(ctrls)), squeeze=False)
        for row, cname in enumerate(ctrls):
            for col, (key, label, cmap) in enumerate(METRICS):
                grid = np.full((len(ys), len(xs)), np.nan)
                for r in res["cells"]:
                    if r["controller"] == cname:
                        grid[ys.index(r[names[1]]), xs.index(r[names[0]])] = r[key]
                ax = axs[row, col]
                im = ax.imshow(grid, origin="lower", cmap=cmap, aspect="auto",
                               vmin=0 if key.endswith("pct") else None, vmax=100 if key.endswith("pct") else None)
                for (yi, xi), v in np.ndenumerate(grid):
                    ax.text(xi, yi, f"{v:.0f}" if abs(v) >= 10 else f"{v:.2g}", ha="center", va="center", fontsize=8)
                ax.set_xticks(range(len(xs)), [f"{v:g}" for v in xs])
                ax.set_yticks(range(len(ys)), [f"{v:g}" for v in ys])
                ax.set_xlabel(names[0])
                ax.set_ylabel(names[1])
                ax.set_title(f"{cname}: {label}")
                fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle(f"robustness: {c['batch']} envs per cell, {c['distance_m']:g} m on {c['terrain']}")
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return [png]
