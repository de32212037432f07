"""Obstacle fields for the avoidance planner (Zhao 2018): random fields in batch, each with a collision-free
lane by construction. `random_fields` draws N fields from one PRNG key (`small_fields`: scaled to the
Luneckas 2020 robot); `plan_batch` plans them all in one jitted, vmapped call and summarises.
"""

from __future__ import annotations

import time
from typing import Dict

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hexjax.plan.avoid import AvoidConfig, AvoidParams, check_inputs, octopus_params, plan


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


def small_fields(key, n: int, robot_radius: float, d_max: float, n_obstacles: int = 40, length: float = 2.0,
                 width: float = 1.6) -> Fields:
    """`random_fields` scaled to the Luneckas 2020 robot and turned to face +x: start (0, 0), target (2, U(-0.3,
    0.3)); `n_obstacles` circles of radius 0.05-0.12 m drawn in a 1.6 m wide corridor, of which those within
    robot radius + d_max + 2 cm of a lane swaying up to 0.6 m are dropped (~10.6 stay; the straight line is
    blocked in ~35 % of fields), so a collision-free path exists by construction."""
    f = random_fields(key, n, n_obstacles=n_obstacles, length=length, width=width, radius_range=(0.05, 0.12),
                      lane_points=3, lane_sway=0.6, lane_half_width=robot_radius + d_max + 0.02,
                      target_sway=0.3)
    turn = lambda xy: jnp.stack([xy[..., 1], -xy[..., 0]], -1)  # (x, y) -> (y, -x): +y ahead becomes +x
    return Fields(start=turn(f.start), target=turn(f.target), centres=turn(f.centres), radii=f.radii,
                  valid=f.valid, lane=turn(f.lane))


def straight_line_blocked(fields: Fields, robot_radius: float) -> np.ndarray:
    """(N,) bool: a robot circle walking the straight line from start to target would overlap an obstacle."""
    line = jnp.stack([fields.start, fields.target], 1)
    d = dist_to_polyline(fields.centres, line)
    return np.asarray(jnp.any((d < fields.radii + robot_radius) & fields.valid, -1))


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
