"""The analytic positional-error model of Luneckas et al. 2020, Sect. 2.5 and 2.7, Eqs. 8-14.

One leg blocked by an obstacle loses a distance dL while the other side of the robot walks on; the robot
turns about the blocked leg by alpha_k (the isosceles triangle EFD of Fig. 9b, sides a, a and base dL) and
walks the remaining distance R at the accumulated heading error:

    dx      = sum_j sum_k dL                                   (Eq. 8: N obstacles, n/2 legs each)
    beta    = arccos(dL / (2 a))                               (Eq. 12)
    alpha_k = 180 deg - 2 beta  (= 2 (90 deg - beta))          (Eqs. 13-14)
    dalpha  = sum_j sum_k alpha_k                              (Eq. 11)
    R       = d - S l_i                                        (Eq. 10)
    dy      = (R - dx) sin(dalpha) / sin(90 deg - dalpha)      (Eq. 9, the law of sines in triangle ABC)

Angles are in radians here. Eq. 11 as printed sums every alpha_k with one sign; the text says a turn to
one side is +alpha and to the other -alpha, so `predict_from_obstacles` gives each obstacle the sign of its
side of the path (an obstacle on the left blocks left legs: the right side walks on and the robot turns
left, +alpha). The functions take arrays and broadcast, so a batch of terrains is one call.
"""

from __future__ import annotations

import math

import numpy as np


def dx_sum(dL, n_obstacles, n_legs: int = 6):
    """Eq. 8: longitudinal error, each of `n_obstacles` met by n/2 legs losing dL (m) each."""
    return np.asarray(n_obstacles) * (n_legs // 2) * np.asarray(dL, dtype=float)


def beta(dL, a):
    """Eq. 12: base angle of the isosceles triangle with legs a (robot width, m) and base dL (m), rad."""
    ratio = np.asarray(dL, dtype=float) / (2.0 * np.asarray(a, dtype=float))
    if np.any(np.abs(ratio) > 1):
        raise ValueError(f"dL / (2 a) = {np.max(np.abs(ratio))!r}: dL must be at most twice the width a")
    return np.arccos(ratio)


def alpha_k(dL, a):
    """Eqs. 13-14: rotation of the robot at one obstacle by one leg, alpha_1 + alpha_2 = pi - 2 beta, rad."""
    return math.pi - 2.0 * beta(dL, a)


def dalpha_sum(alphas, signs=None, axis=None):
    """Eq. 11: final heading error, the sum of the per-leg, per-obstacle rotations (signed by side), rad."""
    alphas = np.asarray(alphas, dtype=float)
    if signs is not None:
        alphas = alphas * np.asarray(signs, dtype=float)
    return alphas.sum(axis=axis)


def remaining_distance(d, steps, step_length):
    """Eq. 10: R = d - S l_i, m."""
    return np.asarray(d, dtype=float) - np.asarray(steps, dtype=float) * np.asarray(step_length, dtype=float)


def dy_from(R, dx, dalpha):
    """Eq. 9: transverse error (R - dx) sin(dalpha) / sin(90 deg - dalpha), m."""
    dalpha = np.asarray(dalpha, dtype=float)
    if np.any(np.abs(dalpha) >= math.pi / 2):
        raise ValueError("|dalpha| must be below 90 deg for Eq. 9 (the triangle ABC closes only then)")
    return (np.asarray(R, dtype=float) - np.asarray(dx, dtype=float)) * np.sin(dalpha) / np.sin(math.pi / 2 - dalpha)


def path_obstacles(box_pos, box_half, box_valid, distance: float, lane=(0.07, 0.21), start_x: float = 0.0):
    """Obstacles the legs of one side meet on a straight walk of `distance` m along +x from `start_x`:
    valid boxes whose footprint overlaps a leg lane (|y| in `lane`, m) and whose near face is before the
    front feet's last reach (distance + 0.15 m). Arrays (..., M, 3) -> (in_path (..., M) bool, side (..., M)
    +1 left / -1 right)."""
    pos, half, valid = np.asarray(box_pos), np.asarray(box_half), np.asarray(box_valid)
    y_lo, y_hi = np.abs(pos[..., 1]) - half[..., 1], np.abs(pos[..., 1]) + half[..., 1]
    # a box straddling y = 0 reaches both lanes; count it on the side of its centre
    in_lane = (y_hi >= lane[0]) & (np.maximum(y_lo, 0.0) <= lane[1])
    x_near = pos[..., 0] - half[..., 0]
    in_x = (x_near >= start_x - 0.05) & (x_near <= start_x + distance + 0.15)
    side = np.where(pos[..., 1] >= 0, 1.0, -1.0)
    return valid & in_lane & in_x, side


def obstacle_counts(box_pos, box_half, box_valid, distance: float, **lane_kw):
    """What the model needs of a terrain's obstacles (`path_obstacles`): their number N in the path, their
    signed count (left minus right), and the x (m) of the last one (0 when there is none). (...,) each."""
    in_path, side = path_obstacles(box_pos, box_half, box_valid, distance, **lane_kw)
    x_last = np.where(in_path, np.asarray(box_pos)[..., 0], -np.inf).max(-1)
    return in_path.sum(-1), np.where(in_path, side, 0.0).sum(-1), np.where(np.isfinite(x_last), x_last, 0.0)


def predict_from_counts(dL, a, n_obstacles, signed_obstacles, x_last, distance, n_legs: int = 6):
    """The model's (dx, dy, dalpha) from obstacle counts (`obstacle_counts`) and a per-interaction loss dL
    (m): Eq. 8 for dx, Eqs. 11-14 with each obstacle signed by its side for dalpha, and Eqs. 9-10 with R the
    distance left after the last obstacle (S l_i its position). Returns a dict of arrays (m, m, rad)."""
    dx = dx_sum(dL, n_obstacles, n_legs)
    da = np.asarray(signed_obstacles, dtype=float) * (n_legs // 2) * alpha_k(dL, a)
    R = np.asarray(distance, dtype=float) - np.clip(x_last, 0.0, distance)
    dy = dy_from(R, dx, np.clip(da, -math.radians(89.0), math.radians(89.0)))
    return {"dx": dx, "dy": dy, "dalpha": da, "n_obstacles": np.asarray(n_obstacles), "R": R}


def predict_from_obstacles(dL, a, box_pos, box_half, box_valid, distance: float, n_legs: int = 6, **lane_kw):
    """`predict_from_counts` for each terrain of a batch, from its boxes. (B,) arrays."""
    return predict_from_counts(dL, a, *obstacle_counts(box_pos, box_half, box_valid, distance, **lane_kw),
                               distance, n_legs)


def fit_dL(dx_excess, n_obstacles, n_legs: int = 6) -> float:
    """Least-squares dL (m) for dx_excess ~ N (n/2) dL over runs (Eq. 8 through the origin)."""
    x = np.asarray(n_obstacles, dtype=float) * (n_legs // 2)
    y = np.asarray(dx_excess, dtype=float)
    ok = np.isfinite(y)
    den = float(np.sum(x[ok] ** 2))
    return float(np.sum(x[ok] * y[ok]) / den) if den > 0 else 0.0
