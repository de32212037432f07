"""`hexjax evaluate`: a gait over flat ground and the four seed-000 obstacle categories.

All categories share one physics configuration and are padded to one box count, so the whole
evaluation compiles the rollout once."""

from __future__ import annotations

import dataclasses
import time
from typing import Dict, Sequence

import jax
import jax.numpy as jnp
from tqdm.auto import tqdm

from hexjax.analysis.metrics import batch_stats, goal_errors
from hexjax.control.gait import GaitController
from hexjax.mjcf import PhysicsConfig
from hexjax.robot import get_robot
from hexjax.sim.model import sim_model
from hexjax.sim.rollout import RolloutConfig, rollout
from hexjax.terrain import SEED000_CATEGORIES, Terrain, get_terrain, sample

DEFAULT_CATEGORIES = ("flat",) + SEED000_CATEGORIES


def pad_terrain(t: Terrain, m: int) -> Terrain:
    """Pad a batched terrain to `m` boxes with invalid entries (so terrains share compiled shapes)."""
    cur = t.box_pos.shape[-2]
    if cur > m:
        raise ValueError(f"terrain has {cur} boxes, more than the pad size {m}")
    if cur == m:
        return t
    pad = [(0, 0)] * (t.box_pos.ndim - 2) + [(0, m - cur), (0, 0)]
    return Terrain(box_pos=jnp.pad(t.box_pos, pad, constant_values=-5.0),
                   box_half=jnp.pad(t.box_half, pad, constant_values=0.01),
                   box_valid=jnp.pad(t.box_valid, pad[:-1], constant_values=False), ground_z=t.ground_z)


def evaluate(robot: str = "luneckas2020", gait: str = "tripod", distance: float = 1.0, batch: int = 16,
             seed: int = 0, categories: Sequence[str] = DEFAULT_CATEGORIES, step_height: float = 0.03,
             physics: PhysicsConfig = PhysicsConfig(), progress: bool = True, mesh=None,
             backend: str = "mjx") -> Dict:
    """Walk `distance` m with the open-loop seed-000 gait on each category; returns
    {"config": ..., "categories": {name: batch_stats + env_steps_per_s}}. backend: the physics engine
    ('mjx', 'warp', 'c'; see `hexjax.sim.rollout.rollout`)."""
    if not (isinstance(distance, (int, float)) and 0 < distance <= 20):
        raise ValueError(f"distance={distance!r}: must be in (0, 20] m")
    if not isinstance(batch, int) or batch < 1:
        raise ValueError(f"batch={batch!r}: must be an integer >= 1")
    spec = get_robot(robot)
    specs = {name: get_terrain(name, length=distance + 0.3) for name in categories}
    ctrl = GaitController(spec, gait=gait, step_height=step_height)
    params = ctrl.default_params()
    n_cycles, duration = ctrl.duration_for(distance, params)
    ctrl = dataclasses.replace(ctrl, n_cycles=n_cycles)
    m = max(s.max_boxes for s in specs.values())
    from hexjax.sim.rollout import BACKENDS
    if backend not in BACKENDS:
        raise ValueError(f"backend={backend!r}: use one of {BACKENDS}")
    if backend != "c":  # build the MJX model up front so no category's timing includes it
        sim_model(spec, physics, "warp" if backend == "warp" else "jax")
    key = jax.random.PRNGKey(seed)
    results = {}
    bar = tqdm(list(specs.items()), desc=f"evaluate {gait} {distance:g} m", disable=not progress, unit="cat")
    for i, (name, tspec) in enumerate(bar):
        bar.set_postfix_str(name)
        k_t, k_r = jax.random.split(jax.random.fold_in(key, i))
        terr = pad_terrain(sample(tspec, k_t, batch), m)
        t0 = time.perf_counter()
        summ = rollout(spec, terr, ctrl, params, duration, k_r, physics=physics, config=RolloutConfig(), mesh=mesh,
                       backend=backend)
        jax.block_until_ready(summ.end_pose)
        wall = time.perf_counter() - t0 - rollout.last_compile_s
        stats = batch_stats(summ, goal_errors(summ, distance))
        n_steps = (duration + RolloutConfig().settle_time) / physics.timestep
        stats["wall_s"] = wall
        stats["compile_s"] = rollout.last_compile_s
        stats["env_steps_per_s"] = batch * n_steps / wall
        results[name] = stats
    return {"config": dict(robot=robot, gait=gait, distance_m=distance, batch=batch, seed=seed,
                           gait_cycles=n_cycles, duration_s=duration, step_height_m=step_height,
                           step_length_m=float(params.step_length), swing_time_s=float(params.swing_time),
                           slots_per_leg=physics.slots_per_leg, torso_slots=physics.torso_slots,
                           backend=jax.default_backend(), devices=len(jax.devices()), physics_backend=backend),
            "categories": results}


def format_table(result: Dict) -> str:
    head = f"{'category':<11} {'|dx| cm':>8} {'|dy| cm':>8} {'|da| deg':>9} {'fall %':>7} {'succ %':>7} {'NaN':>4} {'env-steps/s':>12}"
    lines = [head, "-" * len(head)]
    for name, s in result["categories"].items():
        lines.append(f"{name:<11} {s['abs_dx_cm']:8.1f} {s['abs_dy_cm']:8.1f} {s['abs_dalpha_deg']:9.1f} "
                     f"{s['fall_pct']:7.1f} {s['success_pct']:7.1f} {s['nan']:4d} {s['env_steps_per_s']:12.0f}")
    return "\n".join(lines)
