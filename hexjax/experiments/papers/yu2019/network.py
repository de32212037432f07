"""`hexjax experiment yu2019-network`: Yu 2019's CPG network on its own and as a gait generator.

1. Phase locking (Eq. 5, Fig. 3): from random states, how long the two followers of the free network take to
   lock onto the leader (follower phase = twice the leader's, plus pi: x_i = 1 - 2 x_1^2 on the limit cycle),
   with Table 1's coupling k = 0.1 and with k = 1. The paper's Fig. 3 shows them locked "after roughly 2 s".
2. The gaits of Eq. 16 (Fig. 23): the controller walks flat ground on the `validated` physics with the gait
   indicator gamma = 2, 3, 6 (tripod, tetrapod, wave), one compiled program for the three (the gait is a traced
   param). Eq. 16 gives the leader a swing of T_g / gamma and a stance of (gamma - 1) T_g / gamma, so a leg's
   duty factor (the fraction of a cycle it stands) is (gamma - 1) / gamma and 6 / gamma legs swing at a time.
   Measured from the controller's own swing/stance modes, and the torso's advance.
"""

from __future__ import annotations

import math
import time
from typing import Dict

import jax
import jax.numpy as jnp
import numpy as np

from hexjax.control.cpg import CPG_GAITS, MODE_NAMES, gait_fields
from hexjax.control.registry import make_controller
from hexjax.control.vdp import NetworkParams, integrate, phase_amplitude
from hexjax.experiments.papers.yu2019.steps import paired_rows
from hexjax.sim.config import RolloutConfig
from hexjax.sim.engines import TRACES
from hexjax.sim.physics import pick
from hexjax.sim.rollout import rollout
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import sample

NEEDS = frozenset({TRACES})  # what it needs of its engine: the walks' traces (the runner picks the engine once)

STANCE_MODES = (MODE_NAMES.index("stance"), MODE_NAMES.index("stance-prolong"))


def lock_times(k: float, n: int, seed: int, t_max: float, dt: float, tol: float) -> np.ndarray:
    """(n,) s: for n random network states (every x, y uniform in [-1.5, 1.5]), the time after which both
    followers stay within `tol` rad of the locked phase (twice the leader's plus pi) up to t_max; inf where they
    are not locked by then. Table 1's network with every coupling weight k."""
    net = NetworkParams.table1()
    net = NetworkParams(eps=net.eps, b=net.b, omega=net.omega, k=jnp.full(4, k))
    z0 = jax.random.uniform(jax.random.PRNGKey(seed), (n, 3, 2), minval=-1.5, maxval=1.5)
    zs = jax.jit(integrate, static_argnums=(2, 3))(z0, net, dt, int(round(t_max / dt)))  # (T+1, n, 3, 2)
    phase, _ = phase_amplitude(zs, net.omega)  # (T+1, n, 3)
    off = jnp.angle(jnp.exp(1j * (phase[..., 1:] - 2 * phase[..., :1] - math.pi)))  # wrapped to (-pi, pi]
    bad = np.asarray(jnp.max(jnp.abs(off), -1) > tol)  # (T+1, n)
    last_bad = np.where(bad.any(0), bad.shape[0] - 1 - np.argmax(bad[::-1], 0), -1)
    t = (last_bad + 1) * dt
    return np.where(bad[-1], np.inf, t)


def _pct(x: np.ndarray) -> Dict:
    fin = x[np.isfinite(x)]
    q = lambda p: float(np.percentile(fin, p)) if fin.size else None
    return {"median_s": q(50), "p90_s": q(90), "max_s": q(100), "locked_rate": float(np.mean(np.isfinite(x)))}


def gait_walk(gaits, batch: int, seed: int, duration: float, physics) -> Dict:
    """Walks each Eq. 16 gait on flat ground (one batch of len(gaits) x batch envs); per gait the duty factor and
    legs in swing at once, after the first gait cycle, and the torso's speed."""
    robot = get_robot("yu2019")
    preset = pick(physics, needs=NEEDS)  # the legs' swing/stance modes are read from the controller's traces
    spec = get_terrain("flat")
    flat = sample(spec, jax.random.PRNGKey(seed), batch)
    ctrl = make_controller("cpg", robot)
    rows = [ctrl.default_params(**gait_fields(g)) for g in gaits]
    terrain, params, keys = paired_rows([flat] * len(gaits), rows, batch, seed)
    t0 = time.perf_counter()
    s, st = rollout(robot, terrain, ctrl, params, duration, keys, physics=preset.config(spec), engine=preset.engine.name,
                    config=RolloutConfig(record=True), params_batched=True, stats=True)
    mode = np.asarray(s.ctrl_trace["mode"])  # (B, T, 6)
    stance = np.isin(mode, STANCE_MODES)
    out = {"robot": robot.name, "duration_s": duration, "envs_per_gait": batch,
           "wall_s": round(time.perf_counter() - t0, 1), "compile_s": round(st.compile_s, 1), "gaits": {}}
    period = 2 * math.pi / float(rows[0].net.omega[0])  # T_g of Eq. 16: Table 1's 5 s
    skip = int(round(period / ctrl.dt))  # the first cycle: the legs leave their start phases
    for i, g in enumerate(gaits):
        sl = slice(i * batch, (i + 1) * batch)
        gamma = CPG_GAITS[g][0]
        st_g = stance[sl, skip:]
        adv = np.asarray(s.end_pose[sl, 0] - s.start_pose[sl, 0])
        # swing onsets per leg (stance -> swing), for the order in which the legs step
        onset = st_g[:, :-1] & ~st_g[:, 1:]
        first = np.where(onset.any(1), onset.argmax(1), -1)  # (b, 6) first onset step after the skipped cycle
        out["gaits"][g] = {
            "gamma": gamma, "duty_factor_eq16": (gamma - 1) / gamma, "legs_in_swing_eq16": 6 / gamma,
            "duty_factor": float(st_g.mean()), "duty_factor_per_leg": st_g.mean((0, 1)).round(3).tolist(),
            "legs_in_swing_mean": float((~st_g).sum(-1).mean()),
            "legs_in_swing_max": int((~st_g).sum(-1).max()),
            "speed_m_s": float(adv.mean() / duration), "fell": int(np.asarray(s.fell[sl]).sum()),
            "nan_envs": int(np.asarray(s.nan[sl]).sum()),
            "first_swing_order": np.argsort(first[0]).tolist(),
        }
    return out


# The experiment (configs/experiments/yu2019-network.yaml) --------------------------------------------------
def run(o, entry) -> Dict:
    pre = entry.preset
    t0 = time.perf_counter()
    lock = {}
    for k in pre["couplings"]:
        t = lock_times(float(k), o.states, o.seed, pre["lock_horizon_s"], pre["dt"], pre["lock_tol_rad"])
        lock[f"k={k:g}"] = _pct(t) | {"lock_s": [round(float(v), 2) if np.isfinite(v) else None for v in t]}
    res = {"config": {"experiment": "yu2019-network", "states": o.states, "seed": o.seed,
                      "lock_horizon_s": pre["lock_horizon_s"], "lock_tol_rad": pre["lock_tol_rad"], "dt": pre["dt"],
                      "paper_lock_s": 2.0},
           "phase_lock": lock, "lock_wall_s": round(time.perf_counter() - t0, 1)}
    res["gaits"] = gait_walk(pre["gaits"], o.batch, o.seed, o.duration, o.physics)
    return res


def report(res: Dict) -> str:
    c = res["config"]
    lines = [f"\nyu2019-network: phase locking of the free network (Eq. 5) from {c['states']} random states "
             f"(within {c['lock_tol_rad']:g} rad, {c['lock_horizon_s']:g} s horizon; Fig. 3: ~{c['paper_lock_s']:g} s)"]
    for k, d in res["phase_lock"].items():
        med = "-" if d["median_s"] is None else f"{d['median_s']:.1f} s"
        p90 = "-" if d["p90_s"] is None else f"{d['p90_s']:.1f} s"
        lines.append(f"  {k:7s} median {med:>8s}, 90 % by {p90:>8s}, locked {100 * d['locked_rate']:.0f} %")
    g = res["gaits"]
    lines.append(f"Eq. 16 gaits on flat ground ({g['envs_per_gait']} envs each, {g['duration_s']:g} s):")
    lines.append(f"  {'gait':9s} {'gamma':>5s} {'duty (Eq. 16)':>14s} {'swinging (Eq. 16)':>18s} {'speed':>10s} {'falls':>5s}")
    for name, d in g["gaits"].items():
        lines.append(f"  {name:9s} {d['gamma']:5d} {d['duty_factor']:6.3f} ({d['duty_factor_eq16']:.3f}) "
                     f"{d['legs_in_swing_mean']:9.2f} ({d['legs_in_swing_eq16']:.2f}) "
                     f"{1000 * d['speed_m_s']:7.1f} mm/s {d['fell']:5d}")
    return "\n".join(lines)
