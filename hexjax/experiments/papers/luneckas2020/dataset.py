"""The error predictor's dataset (Luneckas 2020 Sect. 2.6): simulated walks as per-env sequences of the
path so far, sampled every `SAMPLE_M` of planned advance, with the goal error as the target.

Per step inputs (F = 8, `FEATURES`): actual advance x and lateral offset y in the start frame (m), sin and
1 - cos of the heading change, planned advance (m), planned distance left (m), and two flags known to the
robot: tripod (1) or wave (0), method on (1) or off (0). Targets: goal (dx, dy), m.
"""

from __future__ import annotations

import json
import os
import zipfile
from typing import Dict, Sequence

import numpy as np

from hexjax.experiments.papers.luneckas2020 import error_model as em
from hexjax.experiments.papers.luneckas2020.walks import errors_from, readout_index, robot_width, simulate_gait
from hexjax.sim.engines import TRACES
from hexjax.world.presets import get_robot

NEEDS = frozenset({TRACES})  # the walks' traces (the runner picks the engine once)

SAMPLE_M = 0.05
FEATURES = ("x", "y", "sin_dalpha", "one_minus_cos_dalpha", "planned_x", "planned_left", "tripod", "method")


# Dataset -----------------------------------------------------------------------------------------
def sequences_from_runs(ctrl, params, terrain, summary, groups, gait: str, distance: float, width: float,
                        sample_m: float = SAMPLE_M) -> Dict[str, np.ndarray]:
    """Turn one batched rollout (from `luneckas.simulate_gait`) into per-env sequences. Runs that fell or
    went non-finite are dropped (their goal error is not defined). Returns a dict of numpy arrays:
    X (S, K, F), Y (S, 2), plus per-sequence category, method, terrain index, and the analytic model's inputs."""
    trace = np.asarray(summary.trace)
    n_steps = trace.shape[1]
    p0 = np.asarray(summary.start_pose)
    k_pts = np.arange(1, int(round(distance / sample_m)) + 1) * sample_m
    idx = [readout_index(ctrl, params, float(x), n_steps) for x in k_pts[:-1]]
    poses = [trace[:, i][:, [0, 1, 3]] for i in idx] + [np.asarray(summary.end_pose)]
    ok = ~np.asarray(summary.fell) & ~np.asarray(summary.nan)
    cols = []
    for x_plan, pose in zip(k_pts, poses):
        dx, dy, da, adv = errors_from(p0, pose, float(x_plan))
        cols.append(np.stack([adv, dy, np.sin(da), 1 - np.cos(da), np.full_like(adv, x_plan),
                              np.full_like(adv, distance - x_plan)], -1))
    X = np.stack(cols, 1)  # (B, K, 6)
    enable = np.asarray(params.enable)
    B, K = X.shape[:2]
    flags = np.stack([np.full(B, 1.0 if gait == "tripod" else 0.0), enable], -1)
    X = np.concatenate([X, np.broadcast_to(flags[:, None], (B, K, 2))], -1).astype(np.float32)
    dx, dy, _, _ = errors_from(p0, np.asarray(summary.end_pose), distance)
    Y = np.stack([dx, dy], -1).astype(np.float32)
    n_obs, signed, x_last = em.obstacle_counts(terrain.box_pos, terrain.box_half, terrain.box_valid, distance)
    category = np.empty(B, dtype=object)
    terrain_id = np.zeros(B, dtype=np.int64)
    for cat, _, sl in groups:
        category[sl] = cat
        terrain_id[sl] = np.arange(sl.stop - sl.start)
    return {"X": X[ok], "Y": Y[ok], "category": category[ok].astype(str), "method": enable[ok],
            "gait": np.full(int(ok.sum()), gait), "terrain_id": terrain_id[ok],
            "n_obstacles": n_obs[ok], "signed_obstacles": signed[ok], "x_last": x_last[ok], "distance": np.full(int(ok.sum()), distance),
            "width": np.full(int(ok.sum()), width)}


def make_dataset(n: int = 16, seed: int = 1, gaits: Sequence[str] = ("wave", "tripod"), distance: float = 2.0,
                 progress: bool = True, physics="validated") -> Dict[str, np.ndarray]:
    """Simulate the luneckas2020 matrix (every category x with/without, plus flat) for each gait on `n`
    terrains per cell and return the concatenated sequences (see `sequences_from_runs`)."""
    width = robot_width(get_robot("luneckas2020"))
    parts = []
    for g in gaits:
        ctrl, params, terrain, s, groups, _ = simulate_gait(g, n, seed, distance, progress=progress, physics=physics)
        parts.append(sequences_from_runs(ctrl, params, terrain, s, groups, g, distance, width))
    return concat_datasets(parts)


def concat_datasets(parts):
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def save_dataset(path: str, data: Dict[str, np.ndarray], meta: Dict) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    np.savez_compressed(path, meta=json.dumps(meta), **data)


def dataset_meta(path: str) -> Dict:
    """What `save_dataset` recorded about how a dataset was made (its physics among it); {} if nothing."""
    with np.load(path, allow_pickle=False) as f:
        return json.loads(str(f["meta"])) if "meta" in f.files else {}


def load_dataset(path: str) -> Dict[str, np.ndarray]:
    if not os.path.isfile(path):
        raise ValueError(f"dataset {path!r} not found: make one with `hexjax experiment luneckas2020-dataset --out {path}`")
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files if k != "meta"}
    except (ValueError, OSError, zipfile.BadZipFile) as err:  # not an .npz: numpy takes it for a pickle
        raise ValueError(f"{path}: not an .npz archive numpy can read ({type(err).__name__}); make a dataset with "
                         "`hexjax experiment luneckas2020-dataset`") from None
    if "X" not in data or "Y" not in data or data["X"].ndim != 3:
        raise ValueError(f"{path}: not a hexjax error-predictor dataset (needs X (S, K, F) and Y (S, 2))")
    if data["X"].shape[-1] != len(FEATURES):
        raise ValueError(f"{path}: X has {data['X'].shape[-1]} features per step, expected {len(FEATURES)} {FEATURES}")
    return data


def split_by_terrain(data, held_out_frac: float = 0.2, seed: int = 0):
    """Boolean mask of held-out sequences: a fraction of the terrains (category, terrain index, dataset
    part) is held out whole, so no held-out terrain is seen in training by either gait or method."""
    if not 0 < held_out_frac < 1:
        raise ValueError(f"held_out_frac={held_out_frac!r}: must be in (0, 1)")
    keys = np.array([f"{c}/{t}/{p}" for c, t, p in zip(data["category"], data["terrain_id"],
                                                         data.get("part", np.zeros(len(data["Y"]), int)))])
    uniq = np.unique(keys)
    rng = np.random.default_rng(seed)
    held = set(rng.choice(uniq, size=max(1, int(round(held_out_frac * uniq.size))), replace=False).tolist())
    return np.array([k in held for k in keys])


# The experiment (configs/experiments/luneckas2020-dataset.yaml) ---------------------------------------------
def run(o, entry) -> Dict:
    from hexjax.sim.physics import pick
    data = make_dataset(n=o.n, seed=o.seed, gaits=o.gaits, distance=o.distance, physics=o.physics)
    save_dataset(o.out, data, {"source": "hexjax experiment luneckas2020-dataset", "n": o.n, "seed": o.seed,
                               "gaits": list(o.gaits), "distance_m": o.distance,
                               "physics": pick(o.physics, needs=NEEDS).record()})
    return {"sequences": int(len(data["Y"])), "steps": int(data["X"].shape[1]), "out": o.out}


def report(res: Dict) -> str:
    return f"{res['sequences']} sequences (the runs that stayed upright) of {res['steps']} steps; wrote {res['out']}"
