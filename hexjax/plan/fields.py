"""Obstacle fields for the avoidance planner: Zhao 2018's experiment 1 (Tables 1-2) and random fields in
batch, each with a collision-free lane by construction.

`zhao2018_experiment` plans experiment 1 and compares each plan cycle with Table 2; `random_fields` draws
N fields from one PRNG key; `plan_batch` plans them all in one jitted, vmapped call and summarises.
"""

from __future__ import annotations

import time
from typing import Dict

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

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
    for x, y, rad in result["obstacles"]:
        ax.add_patch(plt.Circle((x, y), rad, color="tab:red", alpha=0.5))
    path = np.asarray(result["path"])
    offs, radii = np.asarray(result["robot_circles"]["offsets"]), np.asarray(result["robot_circles"]["radii"])
    for q in path:
        for o, rr in zip(offs, radii):
            ax.add_patch(plt.Circle(q + o, rr, fill=False, color="tab:blue", lw=0.4, alpha=0.5))
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


@struct.dataclass
class Fields:
    """A batch of N fields: start, target (N, 2); obstacle centres (N, Q, 2), radii (N, Q), valid (N, Q);
    lane (N, K, 2): the polyline kept free by construction."""

    start: jax.Array
    target: jax.Array
    centres: jax.Array
    radii: jax.Array
    valid: jax.Array
    lane: jax.Array


def dist_to_polyline(pts, line):
    """(..., M) distance of points (..., M, 2) to a polyline (..., K, 2)."""
    a, b = line[..., :-1, :], line[..., 1:, :]  # (..., K - 1, 2)
    ab = b - a
    ap = pts[..., :, None, :] - a[..., None, :, :]  # (..., M, K - 1, 2)
    t = jnp.clip(jnp.sum(ap * ab[..., None, :, :], -1) / jnp.maximum(jnp.sum(ab * ab, -1)[..., None, :], 1e-12), 0, 1)
    proj = a[..., None, :, :] + t[..., None] * ab[..., None, :, :]
    return jnp.min(jnp.linalg.norm(pts[..., :, None, :] - proj, axis=-1), axis=-1)


def random_fields(key, n: int, n_obstacles: int = 16, length: float = 8.0, width: float = 6.0,
                  radius_range=(0.15, 0.35), lane_points: int = 4, lane_sway: float = 1.2,
                  lane_half_width: float = 1.0, target_sway: float = 1.0) -> Fields:
    """N fields like experiment 1: start (0, 0), target (U(-target_sway, target_sway), length); obstacle circles uniform in a
    `width` x `length` corridor. Each field has a polyline lane from start to target through
    `lane_points` waypoints swaying up to `lane_sway` m sideways, always ahead (y increasing, so the
    forward fan can follow it); obstacles closer than `lane_half_width` + their radius to it are dropped,
    so a robot no wider than the lane has a collision-free path by construction. The default half-width is
    the Octopus-III circles' reach (0.7 m) + d_max (0.2 m) + 0.1 m."""
    ks = jax.random.split(key, 5)
    tx = jax.random.uniform(ks[0], (n,), minval=-target_sway, maxval=target_sway)
    start = jnp.zeros((n, 2))
    target = jnp.stack([tx, jnp.full((n,), length)], -1)
    ys = jnp.linspace(0.0, length, lane_points + 2)[1:-1]
    sway = jax.random.uniform(ks[1], (n, lane_points), minval=-lane_sway, maxval=lane_sway)
    mid = jnp.stack([sway, jnp.broadcast_to(ys, (n, lane_points))], -1)
    lane = jnp.concatenate([start[:, None], mid, target[:, None]], 1)
    cx = jax.random.uniform(ks[2], (n, n_obstacles), minval=-0.5 * width, maxval=0.5 * width)
    cy = jax.random.uniform(ks[3], (n, n_obstacles), minval=0.8, maxval=length - 0.8)
    centres = jnp.stack([cx, cy], -1)
    radii = jax.random.uniform(ks[4], (n, n_obstacles), minval=radius_range[0], maxval=radius_range[1])
    valid = dist_to_polyline(centres, lane) > lane_half_width + radii
    return Fields(start=start, target=target, centres=centres, radii=radii, valid=valid, lane=lane)


def plan_batch(fields: Fields, params: AvoidParams | None = None, cfg: AvoidConfig = AvoidConfig(),
               repeats: int = 3) -> Dict:
    """Plan every field in one jitted, vmapped call; returns batch statistics (JSON-ready) and the per-field
    arrays. Time per plan cycle per field = best wall time of `repeats` calls / (N x max_cycles)."""
    p = params or octopus_params()
    check_inputs(fields.start, fields.target, fields.centres, fields.radii, fields.valid, p, cfg)
    fn = jax.jit(jax.vmap(lambda s, t, c, r, v: plan(s, t, c, r, v, p, cfg)))
    args = (fields.start, fields.target, fields.centres, fields.radii, fields.valid)
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        walls.append(time.perf_counter() - t0)
    n = int(fields.start.shape[0])
    reached = np.asarray(out.reached)
    clear = np.asarray(out.min_clearance)
    straight = np.linalg.norm(np.asarray(fields.target - fields.start), axis=-1)
    ratio = np.asarray(out.length) / straight
    wall = min(walls)
    return {
        "fields": n, "obstacles_per_field": float(np.asarray(fields.valid).sum(-1).mean()),
        "success_rate": float(reached.mean()), "collisions": int((clear <= 0).sum()),
        "fields_with_a_free_lane": n,
        "stuck_fields": int((np.asarray(out.stuck) > 0).sum()),
        "min_clearance": {"min": float(clear.min()), "p5": float(np.percentile(clear, 5)),
                          "median": float(np.median(clear))},
        "path_ratio": {"mean": float(ratio[reached].mean()) if reached.any() else None,
                       "p95": float(np.percentile(ratio[reached], 95)) if reached.any() else None},
        "cycles_mean": float(np.asarray(out.cycles).mean()),
        "wall_s": wall, "compile_s": compile_s, "max_cycles": cfg.max_cycles,
        "us_per_cycle_per_field": 1e6 * wall / (n * cfg.max_cycles),
        "device": str(jax.devices()[0].platform),
    }, out
