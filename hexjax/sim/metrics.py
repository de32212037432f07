"""Positional errors at the goal (Luneckas 2020 Sect. 2.5) and their statistics: the one schema of goal errors
every command, experiment and the tuner report (`error_stats`'s keys)."""

from __future__ import annotations

import math
from typing import Dict

import jax.numpy as jnp
import numpy as np
from flax import struct

from hexjax.sim.step import Summary


@struct.dataclass
class GoalErrors:
    """Per-env errors for a straight walk of planned distance d along the initial heading.

    dx (B,) m    longitudinal error: d minus the advance along the initial heading (> 0: fell short)
    dy (B,) m    transverse error: displacement across the initial heading (> 0: to the left)
    dalpha (B,) rad heading change, wrapped to (-pi, pi]
    advance (B,) m  displacement along the initial heading
    success (B,) bool  no fall, no NaN, and hypot(dx, dy) <= success_radius
    """

    dx: jnp.ndarray
    dy: jnp.ndarray
    dalpha: jnp.ndarray
    advance: jnp.ndarray
    success: jnp.ndarray


def pose_errors(start_pose, pose, distance: float, xp=jnp):
    """(dx, dy, dalpha, advance) of poses (..., 3) (x m, y m, yaw rad) against a straight walk of `distance`
    m along the start heading, in the start frame (Luneckas 2020 Sect. 2.5, Fig. 15): dx = distance -
    advance (> 0: short), dy lateral (> 0: left), dalpha wrapped to (-pi, pi]. xp: jax.numpy or numpy."""
    p0, p1 = start_pose, pose
    yaw0 = p0[..., 2]
    disp = p1[..., :2] - p0[..., :2]
    c, s = xp.cos(yaw0), xp.sin(yaw0)
    advance = c * disp[..., 0] + s * disp[..., 1]
    lateral = -s * disp[..., 0] + c * disp[..., 1]
    dalpha = xp.angle(xp.exp(1j * (p1[..., 2] - yaw0)))
    return distance - advance, lateral, dalpha, advance


def goal_errors(summary: Summary, distance: float, success_radius: float = 0.1) -> GoalErrors:
    """dx, dy, d-alpha at the goal (Luneckas 2020 Sect. 2.5, Fig. 15), in the robot's start frame."""
    dx, lateral, dalpha, advance = pose_errors(summary.start_pose, summary.end_pose, distance)
    ok = ~summary.fell & ~summary.nan & (jnp.hypot(dx, lateral) <= success_radius)
    return GoalErrors(dx=dx, dy=lateral, dalpha=dalpha, advance=advance, success=ok)


def travel_errors(summary: Summary, distance: float):
    """(dx, dy, dalpha) per env from `Summary.travel` (differentiable, truncated at gradient-window boundaries)
    in each env's start frame, the same convention as `pose_errors`: what the tuner's objective reads."""
    yaw0 = summary.start_pose[:, 2]
    c, s = jnp.cos(yaw0), jnp.sin(yaw0)
    tx, ty, tyaw = summary.travel[:, 0], summary.travel[:, 1], summary.travel[:, 2]
    return distance - (c * tx + s * ty), -s * tx + c * ty, tyaw


def error_stats(dx, dy, dalpha, distance: float, keep=None) -> Dict[str, float]:
    """Means and standard deviations of the goal errors over the envs of `keep` (default: the finite ones), in
    one schema: `dx_cm`, `dy_cm` (signed), `abs_dx_cm`, `abs_dy_cm`, `abs_dalpha_deg`, `goal_error_cm`
    (hypot(dx, dy)) and `rel_error_pct` (the goal error over the planned `distance`, Luneckas 2020's relative
    error), each with a `<name>_std` twin whose unit stays last (`dx_std_cm`). NaN where no env is kept."""
    dx, dy, da = (np.asarray(v, dtype=np.float64) for v in (dx, dy, dalpha))
    if keep is None:
        keep = np.isfinite(dx) & np.isfinite(dy)
    keep = np.asarray(keep, bool)
    err = np.hypot(dx, dy)
    out: Dict[str, float] = {}
    for name, unit, v in (("dx", "cm", 100 * dx), ("dy", "cm", 100 * dy), ("abs_dx", "cm", 100 * np.abs(dx)),
                          ("abs_dy", "cm", 100 * np.abs(dy)), ("abs_dalpha", "deg", np.degrees(np.abs(da))),
                          ("goal_error", "cm", 100 * err), ("rel_error", "pct", 100 * err / distance)):
        x = v[keep]
        out[f"{name}_{unit}"] = float(x.mean()) if x.size else math.nan
        out[f"{name}_std_{unit}"] = float(x.std()) if x.size else math.nan
    return out


def batch_stats(summary: Summary, errors: GoalErrors, distance: float) -> Dict[str, float]:
    """`error_stats` over the envs that stayed finite (NaN envs are counted, never averaged), with the rates,
    the advance, energy and path. Units: cm, deg, %, J."""
    nan = np.asarray(summary.nan)
    good = ~nan
    n_good = max(int(good.sum()), 1)

    def mean(x):
        x = np.asarray(x)[good]
        return float(x.mean()) if x.size else math.nan

    return {
        "n": int(nan.size),
        "nan": int(nan.sum()),
        **error_stats(errors.dx, errors.dy, errors.dalpha, distance, keep=good),
        "advance_m": mean(errors.advance),
        "fall_pct": 100 * float(np.asarray(summary.fell)[good].sum()) / n_good,
        "success_pct": 100 * float(np.asarray(errors.success).mean()),
        "energy_J": mean(summary.energy),
        "path_length_m": mean(summary.path_length),
        "tactile_steps": mean(np.asarray(summary.tactile_steps).sum(-1)),
    }


def paired(a, b):
    """(mean of a - b, 95 % interval (lo, hi)) of paired samples, normal approximation;
    (nan, (nan, nan)) where no pair is finite. For 0/1 outcomes (success, fall) this is the paired difference of
    two rates, the same envs under both conditions."""
    d = np.asarray(a, float) - np.asarray(b, float)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return math.nan, (math.nan, math.nan)
    m = float(d.mean())
    half = 1.96 * float(d.std(ddof=1)) / math.sqrt(d.size) if d.size > 1 else math.inf
    return m, (m - half, m + half)
