"""Ground segmentation by RANSAC (Zhao 2018 Sect. 5: "The RANSAC algorithm is used to segment the ground, and
the ground height is calculated at the same time"), batched: a fixed number of hypotheses drawn at once, so
the fit is one vmappable, jittable function with no data-dependent loop.

Each hypothesis is the plane through three points drawn from the valid ones; planes tilted more than
`max_tilt_deg` from horizontal are refused (a box's side is a plane too, and the ground under a walking robot
is not a wall). The hypothesis with the most points within `threshold` of it, counted on a random subset of
the valid points, wins, and a least-squares fit z = a x + b y + c to all its inliers refines it.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class Plane:
    """n . p + d = 0 with n (3,) a unit normal pointing up; inliers (N,) bool; count () inliers."""

    normal: jax.Array
    offset: jax.Array
    inliers: jax.Array
    count: jax.Array

    def height(self, xy):
        """Height (...) of the plane above points xy (..., 2)."""
        n = self.normal
        return -(self.offset + n[0] * xy[..., 0] + n[1] * xy[..., 1]) / jnp.maximum(n[2], 1e-6)

    def tilt(self):
        """Angle between the normal and world z, rad."""
        return jnp.arccos(jnp.clip(self.normal[2], -1.0, 1.0))


def fit_plane(points, valid, key, n_hyp: int = 128, threshold: float = 0.01, max_tilt_deg: float = 30.0,
              n_score: int = 512) -> Plane:
    """RANSAC plane of points (N, 3) among those `valid` (N,) (module docstring); each hypothesis is scored on
    `n_score` valid points drawn at random. With fewer than 3 valid points the plane is z = 0 with no inliers."""
    n = points.shape[0]
    # (H, 3) indices of valid points, uniformly: the k-th valid point for k uniform below their count (a
    # categorical draw over all N points would cost N random numbers per index)
    rank = jnp.cumsum(valid.astype(jnp.int32))
    k_hyp, k_score = jax.random.split(key)

    def draw(k, shape):
        u = jnp.floor(jax.random.uniform(k, shape) * rank[-1]).astype(jnp.int32)
        return jnp.clip(jnp.searchsorted(rank, u + 1, side="left", method="scan_unrolled"), 0, n - 1)

    idx = draw(k_hyp, (n_hyp, 3))
    p = points[idx]  # (H, 3, 3)
    normal = jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    norm = jnp.linalg.norm(normal, axis=-1, keepdims=True)
    normal = normal / jnp.maximum(norm, 1e-12) * jnp.where(normal[:, 2:] < 0, -1.0, 1.0)
    offset = -jnp.sum(normal * p[:, 0], -1)
    ok = (norm[:, 0] > 1e-9) & (normal[:, 2] >= math.cos(math.radians(max_tilt_deg)))
    # each hypothesis scored on the same `n_score` valid points drawn at random (with replacement): the count
    # over all N points would cost N x H distances, most of the fit's time on a CPU
    q = points[draw(k_score, (min(n_score, n),))]  # (S, 3)
    dist = jnp.abs(q[:, :1] * normal[:, 0] + q[:, 1:2] * normal[:, 1] + q[:, 2:] * normal[:, 2] + offset)  # (S, H)
    count = jnp.sum(dist < threshold, 0) * (rank[-1] > 0)
    best = jnp.argmax(jnp.where(ok, count, -1))
    inl = (jnp.abs(points @ normal[best] + offset[best]) < threshold) & valid & ok[best]
    # least squares z = a x + b y + c over the inliers (3 x 3 normal equations, centred for conditioning)
    w = inl.astype(points.dtype)
    m = jnp.maximum(jnp.sum(w), 1.0)
    mu = jnp.sum(points * w[:, None], 0) / m
    q = points - mu
    a = jnp.stack([q[:, 0], q[:, 1], jnp.ones(n)], -1) * w[:, None]
    ata = a.T @ a + 1e-9 * jnp.eye(3)
    coef = jnp.linalg.solve(ata, a.T @ (q[:, 2] * w))
    refined = jnp.array([-coef[0], -coef[1], 1.0]) / jnp.sqrt(coef[0] ** 2 + coef[1] ** 2 + 1.0)
    use = jnp.sum(inl) >= 3
    nrm = jnp.where(use, refined, jnp.array([0.0, 0.0, 1.0]))
    off = jnp.where(use, -jnp.dot(refined, mu + jnp.array([0.0, 0.0, coef[2]])), 0.0)
    inl = jnp.abs(points @ nrm + off) < threshold
    inl = inl & valid & use
    return Plane(normal=nrm, offset=off, inliers=inl, count=jnp.sum(inl))
