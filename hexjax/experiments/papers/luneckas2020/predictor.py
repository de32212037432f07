"""The positional-error predictor of Luneckas et al. 2020 Sect. 2.6, Fig. 8, trained on simulated walks.

Network (as in the paper): at each time step the robot's position and its planned position are the input;
a ReLU layer embeds them into 64 features, one LSTM cell with a hidden state of 64 carries the history,
and a linear read-out gives the prediction; Adam, learning rate 1e-3, 50 epochs.

What is predicted. The paper says "future positional errors" without a horizon; here it is the error at
the goal, (dx, dy) of the finished walk, predicted at every point along the way from the path so far.
Time steps are points of the *plan*: every `SAMPLE_M` (5 cm) of commanded advance, so wave and tripod
walks of the same distance give sequences of the same length (the inputs: `dataset.FEATURES`).

Baselines reported beside it on held-out terrains: the last error carried forward (the error now is the
error at the goal), and the analytic model (Eqs. 8-14, `error_model`) with dL fitted on the training set
by least squares per gait and method; the analytic model knows the obstacles in the path, the network
does not.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from typing import Dict, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization
from tqdm.auto import tqdm

from hexjax.experiments.papers.luneckas2020 import error_model as em
from hexjax.experiments.papers.luneckas2020.dataset import (FEATURES, concat_datasets, dataset_meta, load_dataset,
                                                     split_by_terrain)


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
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
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
    # each dataset's physics (older datasets recorded none): the walks the figures below come from
    res = {"datasets": list(paths),
           "physics": {p: dataset_meta(p).get("physics", "not recorded") for p in paths},
           "train_sequences": int(train.sum()), "held_out_sequences": int(held.sum()),
           "train_s": round(train_s, 1), "config": dataclasses.asdict(cfg), "loss_history": hist,
           "analytic_dL_cm": {f"{g}/{'with' if m else 'without'}": round(100 * v[0], 3) for (g, m), v in fits.items()},
           "held_out": evaluate_predictor(params2, norm2, cfg2, data, held, fits),
           "train": evaluate_predictor(params2, norm2, cfg2, data, train, fits), "saved": out}
    return res


# The experiment (configs/experiments/luneckas2020-predictor.yaml) -------------------------------------------
def run(o, entry) -> Dict:
    cfg = TrainConfig(epochs=o.epochs, learning_rate=o.lr, seed=o.seed)
    return run_training(o.data, o.out, cfg, held_out_frac=o.held_out)


def report(res: Dict) -> str:
    h = res["held_out"]
    lines = [f"\ntrained on {res['train_sequences']} sequences in {res['train_s']:.0f} s; held-out terrains: "
             f"{res['held_out_sequences']} sequences; saved {res['saved']}",
             f"{'goal-error RMS (cm)':24s} {'all steps':>10s} " + " ".join(f"{k:>8s}" for k in h["by_progress"])]
    for name in ("lstm", "last_error", "analytic"):
        lines.append(f"{name:24s} {h['all_steps'][name + '_rms_cm']:10.2f} "
                     + " ".join(f"{v[name + '_rms_cm']:8.2f}" for v in h["by_progress"].values()))
    return "\n".join(lines)
