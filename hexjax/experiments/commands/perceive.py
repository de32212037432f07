"""`hexjax perceive`: one scan of a range sensor from the robot standing on a terrain, turned into what the
perceiving planner sees (2.5D grid map, RANSAC ground, obstacle circles) and drawn: the true boxes, the
returned points and the circles from above, and the map. Also times the scan batched over envs."""

from __future__ import annotations

import math
import time
from typing import Dict

import jax
import jax.numpy as jnp
import numpy as np

from hexjax.perceive.grid import GridMap, GridSpec, fuse
from hexjax.perceive.obstacles import map_obstacles
from hexjax.perceive.raycast import scan
from hexjax.perceive.sensors import get_sensor
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import Terrain, sample

FIELD = "zhao-field"  # --terrain value: a random field of zhao2018-mjx (0.25 m boxes), not a terrain preset


def _terrain(name: str, seed: int, robot) -> Terrain:
    if name == FIELD:
        from hexjax.control.registry import make_controller
        from hexjax.experiments.papers.zhao2018.closed_loop import field_setup, obstacle_boxes, seeded_fields
        f, k_box = seeded_fields(seed, 1, field_setup(make_controller("avoid", robot))[1])
        return jax.tree_util.tree_map(lambda x: x[0], obstacle_boxes(k_box, f))
    return jax.tree_util.tree_map(lambda x: x[0], sample(get_terrain(name), jax.random.PRNGKey(seed), 1))


def perceive_once(sensor: str = "kinect_v1", terrain: str = FIELD, seed: int = 0, robot: str = "luneckas2020",
                  pose=(0.0, 0.0, 0.0), cell: float = 0.04, threshold: float = 0.05, bench_envs: int = 256) -> Dict:
    """Scan once from the robot standing at pose (x m, y m, yaw deg), map, fit the ground, find circles; time
    the scan vmapped over `bench_envs` envs. Returns numbers and the arrays to draw (`_`-keys)."""
    rb = get_robot(robot)
    s = get_sensor(sensor)
    s.validate(rb)
    spec = GridSpec.covering((pose[0] - 0.5, pose[1] - 1.5), (pose[0] + 3.0, pose[1] + 1.5), cell)
    t = _terrain(terrain, seed, rb)
    z = float(t.ground_z) + rb.body_clearance + 0.5 * rb.body_thickness
    yaw = math.radians(pose[2])
    quat = jnp.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
    pos = jnp.array([pose[0], pose[1], z])
    one = jax.jit(lambda tt, k: scan(s, pos, quat, tt, k))
    sc = one(t, jax.random.PRNGKey(seed))
    g = fuse(spec, GridMap.empty(spec), sc)
    h, known = g.heights()
    plane, mask, circ = map_obstacles(spec, g, jax.random.PRNGKey(seed + 1), threshold, 32, near=sc.origin[:2])
    # throughput: the scan alone, vmapped over bench_envs copies of the terrain (compiled once, best of 5)
    tb = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (bench_envs,) + x.shape), t)
    many = jax.jit(jax.vmap(lambda tt, k: scan(s, pos, quat, tt, k)))
    keys = jax.random.split(jax.random.PRNGKey(0), bench_envs)
    jax.block_until_ready(many(tb, keys))
    walls = []
    for _ in range(5):
        t0 = time.perf_counter()
        jax.block_until_ready(many(tb, keys))
        walls.append(time.perf_counter() - t0)
    wall = min(walls)
    n_boxes = int(np.asarray(t.box_valid).sum())
    return {"sensor": sensor, "kind": s.kind, "terrain": terrain, "seed": seed, "pose": list(pose),
            "rays": s.n_rays, "returns": int(sc.valid.sum()), "boxes": n_boxes,
            "ground_height_m": float(plane.height(jnp.asarray(pose[:2], jnp.float32))),
            "ground_tilt_deg": math.degrees(float(plane.tilt())), "obstacle_cells": int(mask.sum()),
            "known_cells": int(known.sum()), "circles": int(circ.valid.sum()),
            "bench_envs": bench_envs, "scan_s": wall, "rays_per_s_per_env": s.n_rays / wall,
            "rays_per_s": s.n_rays * bench_envs / wall, "device": str(jax.devices()[0].platform),
            "_scan": sc, "_terrain": t, "_heights": (np.asarray(h), np.asarray(known)), "_mask": np.asarray(mask),
            "_circles": circ, "_grid": spec}


def draw(res: Dict, png: str):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    sc, t, spec, circ = res["_scan"], res["_terrain"], res["_grid"], res["_circles"]
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 5))
    for ax in (a, b):
        for p, hh, v in zip(np.asarray(t.box_pos), np.asarray(t.box_half), np.asarray(t.box_valid)):
            if v:
                ax.add_patch(plt.Rectangle(p[:2] - hh[:2], 2 * hh[0], 2 * hh[1], fill=False, ec="tab:red", lw=1))
        for c, r, v in zip(np.asarray(circ.centres), np.asarray(circ.radii), np.asarray(circ.valid)):
            if v:
                ax.add_patch(plt.Circle(c, r, fill=False, color="tab:blue", lw=1))
        ax.plot(*np.asarray(sc.origin[:2]), "k^", ms=8)
        ext = [spec.origin[0], spec.origin[0] + spec.nx * spec.cell, spec.origin[1], spec.origin[1] + spec.ny * spec.cell]
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
    p = np.asarray(sc.points)[np.asarray(sc.valid)]
    im = a.scatter(p[:, 0], p[:, 1], c=p[:, 2], s=3, cmap="viridis", vmin=min(0.0, p[:, 2].min(initial=0)),
                   vmax=max(0.05, p[:, 2].max(initial=0)))
    fig.colorbar(im, ax=a, label="point height (m)", shrink=0.8)
    a.set_title(f"{res['sensor']} ({res['kind']}): {res['returns']} of {res['rays']} rays returned", fontsize=10)
    h, known = res["_heights"]
    im = b.imshow(np.where(known, h, np.nan).T, origin="lower", extent=ext, cmap="viridis")
    fig.colorbar(im, ax=b, label="cell mean height (m)", shrink=0.8)
    m = res["_mask"]
    ij = np.argwhere(m)
    b.plot(spec.origin[0] + (ij[:, 0] + 0.5) * spec.cell, spec.origin[1] + (ij[:, 1] + 0.5) * spec.cell, "rs", ms=2)
    b.set_title(f"2.5D map: {res['known_cells']} cells known, {res['obstacle_cells']} obstacle cells (red), "
                f"{res['circles']} circles", fontsize=10)
    a.set_ylabel("y (m)")
    fig.suptitle("red outlines: true boxes; blue: perceived obstacle circles (Zhao 2018 Eq. 1); triangle: sensor",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return [png]


# The command (configs/commands/perceive.yaml) ----------------------------------------------------------------
def run(o, entry) -> Dict:
    return perceive_once(o.sensor, o.terrain, o.seed, o.robot, (o.x, o.y, o.yaw), o.cell, o.threshold, o.bench_envs)


def report(res: Dict) -> str:
    return "\n".join([
        f"{res['sensor']} ({res['kind']}) on {res['terrain']} seed {res['seed']} from {res['pose']}: {res['returns']} of "
        f"{res['rays']} rays returned; ground at {100 * res['ground_height_m']:.1f} cm, tilt {res['ground_tilt_deg']:.2f} "
        f"deg; {res['obstacle_cells']} obstacle cells -> {res['circles']} circles ({res['boxes']} boxes on the terrain)",
        f"scan throughput ({res['device']}, {res['bench_envs']} envs at once): {res['rays_per_s']:,.0f} rays/s, "
        f"{res['rays_per_s_per_env']:,.0f} rays/s per env ({1e3 * res['scan_s']:.2f} ms a batch of scans)"])


plot = draw
