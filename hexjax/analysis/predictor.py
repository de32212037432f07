"""The positional-error predictor of Luneckas et al. 2020 (seed 000) Sect. 2.6, Fig. 8, trained on simulated walks.

Network (as in the paper): at each time step the robot's position and its planned position are the input;
a ReLU layer embeds them into 64 features, one LSTM cell with a hidden state of 64 carries the history,
and a linear read-out gives the prediction; Adam, learning rate 1e-3, 50 epochs.

What is predicted. The paper says "future positional errors" without a horizon; here it is the error at
the goal, (dx, dy) of the finished walk, predicted at every point along the way from the path so far.
Time steps are points of the *plan*: every `SAMPLE_M` (5 cm) of commanded advance, so wave and tripod
walks of the same distance give sequences of the same length.

Per step inputs (F = 7): actual advance x and lateral offset y in the start frame (m), sin and 1 - cos of
the heading change, planned advance (m), planned distance left (m), and two flags known to the robot:
tripod (1) or wave (0), method on (1) or off (0). Targets: goal (dx, dy), m.

Baselines reported beside it on held-out terrains: the last error carried forward (the error now is the
error at the goal), and the analytic model (Eqs. 8-14, `error_model`) with dL fitted on the training set
by least squares per gait and method; the analytic model knows the obstacles in the path, the network
does not.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from typing import Dict, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization
from tqdm.auto import tqdm

from hexjax.analysis import error_model as em

SAMPLE_M = 0.05
FEATURES = ("x", "y", "sin_dalpha", "one_minus_cos_dalpha", "planned_x", "planned_left", "tripod", "method")


# Dataset -----------------------------------------------------------------------------------------
def sequences_from_runs(ctrl, params, terrain, summary, groups, gait: str, distance: float, width: float,
                        sample_m: float = SAMPLE_M) -> Dict[str, np.ndarray]:
    """Turn one batched rollout (from `luneckas.simulate_gait`) into per-env sequences. Runs that fell or
    went non-finite are dropped (their goal error is not defined). Returns a dict of numpy arrays:
    X (S, K, F), Y (S, 2), plus per-sequence category, method, terrain index, and the analytic model's inputs."""
    from hexjax.analysis.luneckas import _readout_index, errors_from

    trace = np.asarray(summary.trace)
    n_steps = trace.shape[1]
    p0 = np.asarray(summary.start_pose)
    k_pts = np.arange(1, int(round(distance / sample_m)) + 1) * sample_m
    idx = [_readout_index(ctrl, params, float(x), n_steps) for x in k_pts[:-1]]
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
                 progress: bool = True) -> Dict[str, np.ndarray]:
    """Simulate the luneckas2020 matrix (every category x with/without, plus flat) for each gait on `n`
    terrains per cell and return the concatenated sequences (see `sequences_from_runs`)."""
    from hexjax.analysis.luneckas import robot_width, simulate_gait
    from hexjax.robot import get_robot

    width = robot_width(get_robot("luneckas2020"))
    parts = []
    for g in gaits:
        ctrl, params, terrain, s, groups = simulate_gait(g, n, seed, distance, progress=progress)
        parts.append(sequences_from_runs(ctrl, params, terrain, s, groups, g, distance, width))
    return concat_datasets(parts)


def concat_datasets(parts):
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _mkdir_for(path: str) -> None:
    import os
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)


def save_dataset(path: str, data: Dict[str, np.ndarray], meta: Dict) -> None:
    _mkdir_for(path)
    np.savez_compressed(path, meta=json.dumps(meta), **data)


def load_dataset(path: str) -> Dict[str, np.ndarray]:
    import os
    if not os.path.isfile(path):
        raise ValueError(f"dataset {path!r} not found: make one with `hexjax dataset luneckas2020 --out {path}`")
    with np.load(path, allow_pickle=False) as f:
        data = {k: f[k] for k in f.files if k != "meta"}
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


# Model -------------------------------------------------------------------------------------------
class ErrorPredictor(nn.Module):
    """ReLU embedding (64) -> LSTM (hidden 64) -> linear read-out, applied along the sequence (Fig. 8)."""

    hidden: int = 64
    embed: int = 64
    out: int = 2

    @nn.compact
    def __call__(self, x):  # (B, K, F) normalised inputs -> (B, K, out)
        h = nn.relu(nn.Dense(self.embed)(x))
        h = nn.RNN(nn.LSTMCell(self.hidden))(h)
        return nn.Dense(self.out)(h)


@dataclasses.dataclass
class TrainConfig:
    epochs: int = 50
    learning_rate: float = 1e-3
    batch_size: int = 32
    hidden: int = 64
    embed: int = 64
    seed: int = 0
    target_scale: float = 10.0  # targets are trained in decimetres (m x 10) so the loss is O(1)

    def validate(self):
        if not (isinstance(self.epochs, int) and self.epochs >= 1):
            raise ValueError(f"epochs={self.epochs!r}: must be an integer >= 1")
        if not (self.learning_rate > 0 and math.isfinite(self.learning_rate)):
            raise ValueError(f"learning_rate={self.learning_rate!r}: must be a finite number > 0")
        if not (isinstance(self.batch_size, int) and self.batch_size >= 1):
            raise ValueError(f"batch_size={self.batch_size!r}: must be an integer >= 1")
        if self.hidden < 1 or self.embed < 1:
            raise ValueError(f"hidden={self.hidden!r}, embed={self.embed!r}: must be >= 1")


def train_predictor(X, Y, cfg: TrainConfig = TrainConfig(), progress: bool = True):
    """Fit the network to predict goal errors Y (S, 2) at every step of X (S, K, F). Returns
    (params, norm, history) with norm the input/target scaling needed at prediction time."""
    cfg.validate()
    X = np.asarray(X, np.float32)
    Y = np.asarray(Y, np.float32)
    if X.ndim != 3 or Y.shape != (X.shape[0], 2) or X.shape[0] < 1:
        raise ValueError(f"X {X.shape}, Y {Y.shape}: expected X (S, K, F) and Y (S, 2) with S >= 1")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(Y))):
        raise ValueError("X and Y must be finite (drop runs that fell or went NaN)")
    mu, sd = X.reshape(-1, X.shape[-1]).mean(0), X.reshape(-1, X.shape[-1]).std(0) + 1e-6
    norm = {"mu": mu.tolist(), "sd": sd.tolist(), "target_scale": cfg.target_scale}
    model = ErrorPredictor(hidden=cfg.hidden, embed=cfg.embed)
    key = jax.random.PRNGKey(cfg.seed)
    params = model.init(key, jnp.zeros((1,) + X.shape[1:]))
    opt = optax.adam(cfg.learning_rate)
    opt_state = opt.init(params)
    Xn = (X - mu) / sd
    Yt = np.broadcast_to(Y[:, None, :] * cfg.target_scale, X.shape[:2] + (2,))

    @jax.jit
    def step(params, opt_state, xb, yb, wb):
        def loss_fn(p):
            err = model.apply(p, xb) - yb
            return jnp.sum(wb[:, None, None] * err ** 2) / (jnp.sum(wb) * err.shape[1] * err.shape[2])
        loss, g = jax.value_and_grad(loss_fn)(params)
        upd, opt_state = opt.update(g, opt_state, params)
        return optax.apply_updates(params, upd), opt_state, loss

    S = X.shape[0]
    bs = min(cfg.batch_size, S)
    n_batches = int(math.ceil(S / bs))
    rng = np.random.default_rng(cfg.seed)
    history = []
    bar = tqdm(range(cfg.epochs), desc="train error predictor", disable=not progress)
    for _ in bar:
        perm = rng.permutation(S)
        perm = np.concatenate([perm, perm[: n_batches * bs - S]])  # pad the last batch (weight 0)
        w = np.ones(n_batches * bs, np.float32)
        w[S:] = 0.0
        tot = 0.0
        for b in range(n_batches):
            ib = perm[b * bs:(b + 1) * bs]
            params, opt_state, loss = step(params, opt_state, Xn[ib], Yt[ib], w[b * bs:(b + 1) * bs])
            tot += float(loss)
        history.append(tot / n_batches)
        bar.set_postfix(loss=f"{history[-1]:.4f}")
    return params, norm, history


def predict(params, norm, X, hidden: int = 64, embed: int = 64):
    """Goal-error predictions (S, K, 2) m at every step of X (S, K, F)."""
    model = ErrorPredictor(hidden=hidden, embed=embed)
    Xn = (np.asarray(X, np.float32) - np.asarray(norm["mu"], np.float32)) / np.asarray(norm["sd"], np.float32)
    return np.asarray(jax.jit(model.apply)(params, Xn)) / norm["target_scale"]


def save_predictor(path: str, params, norm, cfg: TrainConfig) -> None:
    blob = {"params": serialization.to_state_dict(params), "norm": norm, "config": dataclasses.asdict(cfg),
            "features": list(FEATURES)}
    _mkdir_for(path)
    with open(path, "wb") as f:
        f.write(serialization.msgpack_serialize(blob))


def load_predictor(path: str):
    """(params, norm, TrainConfig) saved by `save_predictor`."""
    with open(path, "rb") as f:
        blob = serialization.msgpack_restore(f.read())
    if list(blob.get("features", [])) != list(FEATURES):
        raise ValueError(f"{path}: predictor was trained on features {blob.get('features')}, expected {FEATURES}")
    cfg = TrainConfig(**blob["config"])
    params = jax.tree_util.tree_map(jnp.asarray, blob["params"])
    norm = {"mu": list(blob["norm"]["mu"]), "sd": list(blob["norm"]["sd"]),
            "target_scale": float(blob["norm"]["target_scale"])}
    return params, norm, cfg


# Baselines and evaluation --------------------------------------------------------------------------
def last_error_baseline(X):
    """The error now, carried forward to the goal: (planned x - actual x, actual y), (S, K, 2) m."""
    X = np.asarray(X)
    return np.stack([X[..., 4] - X[..., 0], X[..., 1]], -1)


def fit_analytic(data, mask):
    """dL (m) per (gait, method) fitted on the sequences in `mask` (Eq. 8 on top of the flat runs' mean dx)."""
    fits = {}
    for g in np.unique(data["gait"]):
        flat = mask & (data["gait"] == g) & (data["category"] == "flat")
        calib = float(data["Y"][flat, 0].mean()) if flat.any() else 0.0
        for m in (0.0, 1.0):
            sel = mask & (data["gait"] == g) & (data["method"] == m) & (data["category"] != "flat")
            dL = max(em.fit_dL(data["Y"][sel, 0] - calib, data["n_obstacles"][sel]), 0.0) if sel.any() else 0.0
            fits[(str(g), m)] = (dL, calib)
    return fits


def analytic_prediction(data, fits):
    """(S, 2) goal (dx, dy) from Eqs. 8-14 with the fitted dL and the obstacles in each path."""
    out = np.zeros((len(data["Y"]), 2))
    for i in range(len(out)):
        dL, calib = fits.get((str(data["gait"][i]), float(data["method"][i])), (0.0, 0.0))
        flat = data["category"][i] == "flat"
        pred = em.predict_from_counts(dL, data["width"][i], 0 if flat else data["n_obstacles"][i],
                                      0 if flat else data["signed_obstacles"][i], data["x_last"][i],
                                      data["distance"][i])
        out[i] = (pred["dx"] + calib, pred["dy"])
    return out


def evaluate_predictor(params, norm, cfg: TrainConfig, data, mask, fits) -> Dict:
    """RMS error (cm) of the goal-error vector on the sequences in `mask`, over all steps and at 25/50/75 %
    of the path, for the network, the last-error baseline and the analytic model."""
    X, Y = data["X"][mask], data["Y"][mask]
    pred = predict(params, norm, X, cfg.hidden, cfg.embed)
    base = last_error_baseline(X)
    ana = np.broadcast_to(analytic_prediction({k: v[mask] for k, v in data.items()}, fits)[:, None], pred.shape)
    K = X.shape[1]

    def rms(p, ks=slice(None)):
        e = p[:, ks] - Y[:, None, :]
        return float(100 * np.sqrt(np.mean(np.sum(e ** 2, -1))))

    out = {"sequences": int(mask.sum()), "steps_per_sequence": K, "all_steps": {}, "by_progress": {}}
    for name, p in (("lstm", pred), ("last_error", base), ("analytic", ana)):
        out["all_steps"][name + "_rms_cm"] = rms(p)
        for frac in (0.25, 0.5, 0.75):
            k = max(0, int(round(frac * K)) - 1)
            out["by_progress"].setdefault(f"{int(frac * 100)}%", {})[name + "_rms_cm"] = rms(p, slice(k, k + 1))
    return out


def run_training(paths: Sequence[str], out: str, cfg: TrainConfig = TrainConfig(), held_out_frac: float = 0.2,
                 progress: bool = True) -> Dict:
    """Load datasets, hold out a fraction of terrains, train, save to `out`, reload and evaluate."""
    cfg.validate()
    if not 0 < held_out_frac < 1:
        raise ValueError(f"held_out_frac={held_out_frac!r}: must be in (0, 1)")
    parts = []
    for i, p in enumerate(paths):
        d = load_dataset(p)
        d["part"] = np.full(len(d["Y"]), i)
        parts.append(d)
    data = concat_datasets(parts)
    held = split_by_terrain(data, held_out_frac, cfg.seed)
    train = ~held
    t0 = time.perf_counter()
    params, norm, hist = train_predictor(data["X"][train], data["Y"][train], cfg, progress=progress)
    train_s = time.perf_counter() - t0
    save_predictor(out, params, norm, cfg)
    params2, norm2, cfg2 = load_predictor(out)
    fits = fit_analytic(data, train)
    res = {"datasets": list(paths), "train_sequences": int(train.sum()), "held_out_sequences": int(held.sum()),
           "train_s": round(train_s, 1), "config": dataclasses.asdict(cfg), "loss_history": hist,
           "analytic_dL_cm": {f"{g}/{'with' if m else 'without'}": round(100 * v[0], 3) for (g, m), v in fits.items()},
           "held_out": evaluate_predictor(params2, norm2, cfg2, data, held, fits),
           "train": evaluate_predictor(params2, norm2, cfg2, data, train, fits), "saved": out}
    return res
