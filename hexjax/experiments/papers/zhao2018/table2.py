"""Zhao 2018 experiment 1 (Sect. 5, Tables 1-2): the avoidance planner from (0, 0) to (0, 8) among Table 1's
four obstacles, each plan cycle beside the position Table 2 recorded."""

from __future__ import annotations

from typing import Dict

import jax
import numpy as np

from hexjax.plan.avoid import AvoidConfig, AvoidParams, check_inputs, octopus_params, plan

# Zhao 2018 Table 1 (x, y, radius, m) and Table 2 (robot position after each plan cycle, m).
TABLE1 = np.array([[0.463, 1.338, 0.268], [-1.027, 3.236, 0.198], [0.538, 4.769, 0.224], [-1.012, 6.366, 0.202]])
TABLE2 = np.array([[-0.371, 0.371], [-0.546, 1.023], [-0.489, 1.749], [-0.314, 2.401], [-0.014, 2.920],
                   [-0.012, 3.669], [-0.312, 4.189], [-0.487, 4.841], [-0.312, 5.493], [-0.012, 6.013],
                   [-0.008, 6.761], [-0.003, 7.509], [0.002, 8.057]])
START, TARGET = np.array([0.0, 0.0]), np.array([0.0, 8.0])  # Sect. 5, experiment 1


def zhao2018_experiment(params: AvoidParams | None = None, cfg: AvoidConfig = AvoidConfig()) -> Dict:
    """Experiment 1 (Sect. 5: start (0, 0), target (0, 8), Table 1's obstacles, d_min 0.05 m, d_max 0.2 m):
    the planned positions beside Table 2, and the checks of the acceptance (reached, no overlap)."""
    p = params or octopus_params()
    c, r, v = TABLE1[:, :2], TABLE1[:, 2], np.ones(len(TABLE1), bool)
    check_inputs(START, TARGET, c, r, v, p, cfg)
    out = jax.jit(lambda: plan(START, TARGET, c, r, v, p, cfg))()
    n = int(out.cycles)
    path = np.asarray(out.path)[1:n + 1]
    rows = []
    for i in range(max(n, len(TABLE2))):
        ours = path[i].tolist() if i < n else None
        paper = TABLE2[i].tolist() if i < len(TABLE2) else None
        dist = float(np.linalg.norm(path[i] - TABLE2[i])) if ours is not None and paper is not None else None
        k = int(np.asarray(out.chosen)[i]) if i < n else -1
        n_fan = int(np.asarray(p.angles).shape[-1])
        ang = None if k < 0 else ("target" if k == n_fan else float(np.degrees(np.asarray(p.angles)[k])))
        rows.append({"cycle": i + 1, "planned": ours, "table2": paper, "distance": dist, "direction_deg": ang})
    d = [row["distance"] for row in rows if row["distance"] is not None]
    return {"start": START.tolist(), "target": TARGET.tolist(), "obstacles": TABLE1.tolist(),
            "d_min": float(p.d_min), "d_max": float(p.d_max), "n_T": cfg.n_T,
            "robot_circles": {"offsets": np.asarray(p.robot_offsets).tolist(), "radii": np.asarray(p.robot_radii).tolist()},
            "reached": bool(out.reached), "cycles": n, "cycles_table2": len(TABLE2),
            "min_clearance": float(out.min_clearance), "overlap": bool(out.min_clearance <= 0),
            "path_length": float(out.length), "mean_distance_to_table2": float(np.mean(d)),
            "max_distance_to_table2": float(np.max(d)), "cycles_table": rows,
            "path": np.asarray(out.path)[: n + 1].tolist()}


def plot_zhao2018(result: Dict, png: str) -> None:
    """Fig. 18-like: obstacles (circles), the planned path with the robot's circles at each plan cycle,
    and Table 2's recorded positions."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5, 8))
    for i, (x, y, rad) in enumerate(result["obstacles"]):
        ax.add_patch(plt.Circle((x, y), rad, color="tab:red", alpha=0.5, label="obstacles" if i == 0 else None))
    path = np.asarray(result["path"])
    offs, radii = np.asarray(result["robot_circles"]["offsets"]), np.asarray(result["robot_circles"]["radii"])
    for j, q in enumerate(path):
        for k, (o, rr) in enumerate(zip(offs, radii)):
            ax.add_patch(plt.Circle(q + o, rr, fill=False, color="tab:blue", lw=0.4, alpha=0.5,
                                    label="robot circles at each plan cycle" if j == k == 0 else None))
    ax.plot(path[:, 0], path[:, 1], "-o", color="k", ms=3, label="hexjax plan cycles")
    t2 = np.vstack([[0.0, 0.0], TABLE2])
    ax.plot(t2[:, 0], t2[:, 1], "--s", color="tab:green", ms=3, label="Table 2 (recorded)")
    ax.plot(*result["target"], "*", color="tab:orange", ms=12, label="target")
    ax.set_aspect("equal")
    ax.set_xlim(-2.2, 1.8)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"Zhao 2018 experiment 1: {result['cycles']} cycles, min clearance "
                 f"{100 * result['min_clearance']:.1f} cm")
    ax.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=120)
    plt.close(fig)


# The experiment (configs/experiments/zhao2018.yaml) --------------------------------------------------------
def run(o, entry) -> Dict:
    return zhao2018_experiment()


def report(res: Dict) -> str:
    lines = [f"\nzhao2018 experiment 1: start {res['start']}, target {res['target']}, 4 obstacles (Table 1), "
             f"d_min {res['d_min']:g} m, d_max {res['d_max']:g} m, n_T {res['n_T']}",
             f"{'cycle':>5} {'direction':>9} {'planned (m)':>16} {'Table 2 (m)':>16} {'distance (m)':>12}"]
    for row in res["cycles_table"]:
        d = row["direction_deg"]
        d = "-" if d is None else (d if isinstance(d, str) else f"{d:.0f} deg")
        pl = "-" if row["planned"] is None else f"({row['planned'][0]:.3f}, {row['planned'][1]:.3f})"
        t2 = "-" if row["table2"] is None else f"({row['table2'][0]:.3f}, {row['table2'][1]:.3f})"
        dist = "-" if row["distance"] is None else f"{row['distance']:.3f}"
        lines.append(f"{row['cycle']:>5} {d:>9} {pl:>16} {t2:>16} {dist:>12}")
    lines.append(f"reached: {res['reached']} in {res['cycles']} cycles (Table 2: {res['cycles_table2']}); smallest "
                 f"robot-obstacle clearance {100 * res['min_clearance']:.1f} cm (overlap: {res['overlap']}); distance "
                 f"to Table 2 mean {100 * res['mean_distance_to_table2']:.1f} cm, max "
                 f"{100 * res['max_distance_to_table2']:.1f} cm")
    return "\n".join(lines)


plot = plot_zhao2018  # (result, png): the registry's plot
