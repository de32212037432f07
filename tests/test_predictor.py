"""The LSTM goal-error predictor (Luneckas 2020 Sect. 2.6) on a small synthetic dataset: it learns, beats the
last-error baseline on held-out sequences, and saves/loads exactly."""

import numpy as np
import pytest

from hexjax.experiments.papers.luneckas2020 import dataset as ds
from hexjax.experiments.papers.luneckas2020 import predictor as pr


def _synthetic(n_seq=96, K=20, seed=0):
    """Walks whose goal error is decided early: a hidden 'terrain' factor slows the walk from step 5 on;
    the final shortfall is 3x what is visible at step 8, so carrying the current error forward undershoots."""
    rng = np.random.default_rng(seed)
    f = rng.uniform(0, 0.3, n_seq)
    k = np.arange(1, K + 1) * 0.05
    loss = np.clip(k[None] - 0.25, 0, None) * f[:, None]  # lost distance grows after 25 cm
    adv = k[None] - loss
    y = rng.normal(0, 0.002, (n_seq, K)) + 0.1 * loss
    X = np.stack([adv, y, np.zeros_like(adv), np.zeros_like(adv), np.broadcast_to(k, adv.shape),
                  np.broadcast_to(k[-1] - k, adv.shape), np.zeros_like(adv), np.ones_like(adv)], -1).astype(np.float32)
    Y = np.stack([loss[:, -1], y[:, -1]], -1).astype(np.float32)
    cats = np.array(["low-small"] * n_seq)
    return {"X": X, "Y": Y, "category": cats, "terrain_id": np.arange(n_seq), "method": np.ones(n_seq),
            "gait": np.array(["tripod"] * n_seq), "n_obstacles": np.zeros(n_seq, int),
            "signed_obstacles": np.zeros(n_seq), "x_last": np.zeros(n_seq), "distance": np.full(n_seq, k[-1]),
            "width": np.full(n_seq, 0.33)}


def test_lstm_learns_beats_baseline_and_round_trips(tmp_path):
    data = _synthetic()
    held = ds.split_by_terrain(data, 0.25, seed=0)
    assert 0 < held.sum() < len(held)
    cfg = pr.TrainConfig(epochs=40, seed=0)
    params, norm, hist = pr.train_predictor(data["X"][~held], data["Y"][~held], cfg, progress=False)
    assert hist[-1] < 0.3 * hist[0]
    fits = pr.fit_analytic(data, ~held)
    res = pr.evaluate_predictor(params, norm, cfg, data, held, fits)
    a = res["all_steps"]
    assert a["lstm_rms_cm"] < 0.6 * a["last_error_rms_cm"]
    # halfway along, the network already knows more than the error so far
    assert res["by_progress"]["50%"]["lstm_rms_cm"] < res["by_progress"]["50%"]["last_error_rms_cm"]
    path = tmp_path / "m.msgpack"
    pr.save_predictor(str(path), params, norm, cfg)
    p2, n2, c2 = pr.load_predictor(str(path))
    assert c2 == cfg
    np.testing.assert_allclose(pr.predict(p2, n2, data["X"][held]), pr.predict(params, norm, data["X"][held]),
                               atol=1e-6)
    # dataset file round trip
    dpath = tmp_path / "d.npz"
    ds.save_dataset(str(dpath), data, {"source": "test", "physics": {"name": "validated"}})
    assert ds.dataset_meta(str(dpath))["physics"] == {"name": "validated"}
    back = ds.load_dataset(str(dpath))
    np.testing.assert_array_equal(back["X"], data["X"])
    assert list(back["category"][:2]) == ["low-small", "low-small"]


def test_bad_config_and_data():
    with pytest.raises(ValueError, match="learning_rate"):
        pr.train_predictor(np.zeros((2, 3, 8)), np.zeros((2, 2)), pr.TrainConfig(learning_rate=0.0), progress=False)
    with pytest.raises(ValueError, match="epochs"):
        pr.TrainConfig(epochs=0).validate()
    with pytest.raises(ValueError, match="finite"):
        pr.train_predictor(np.full((2, 3, 8), np.nan), np.zeros((2, 2)), pr.TrainConfig(epochs=1), progress=False)
    with pytest.raises(ValueError, match="held_out_frac"):
        ds.split_by_terrain(_synthetic(8), 1.5)
