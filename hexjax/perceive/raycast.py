"""Ray casting against a terrain's own geometry: its axis-aligned boxes and its ground plane (`Terrain`), the
exact first hit of every ray, in pure JAX (vmap it over envs). `scan` turns one sensor pose into the point
cloud the sensor would return: range limits, noise and dropout as `RangeSensor` describes them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from hexjax.perceive.sensors import RangeSensor
from hexjax.world.terrain import Terrain

_TINY = 1e-12


@struct.dataclass
class Scan:
    """One scan of one env: points (R, 3) world frame, m; valid (R,) bool (a return inside the sensor's range,
    not dropped); origin (3,) the sensor's position, world frame."""

    points: jax.Array
    valid: jax.Array
    origin: jax.Array


def ray_box(origin, dirs, box_pos, box_half, box_valid):
    """(R,) distance along each ray (origin (3,), unit dirs (R, 3)) to its first hit on any valid box (box_pos,
    box_half (M, 3), box_valid (M,)); inf where it hits none. The slab method: a ray is inside a box between
    its largest entry and smallest exit over the three axes. A ray starting inside a box hits it at 0."""
    safe = jnp.where(jnp.abs(dirs) < _TINY, jnp.where(dirs < 0, -_TINY, _TINY), dirs)
    inv = 1.0 / safe  # (R, 3)
    lo = (box_pos - box_half - origin)[None] * inv[:, None]  # (R, M, 3)
    hi = (box_pos + box_half - origin)[None] * inv[:, None]
    t_in = jnp.max(jnp.minimum(lo, hi), -1)
    t_out = jnp.min(jnp.maximum(lo, hi), -1)
    hit = (t_out >= jnp.maximum(t_in, 0.0)) & box_valid[None]
    return jnp.min(jnp.where(hit, jnp.maximum(t_in, 0.0), jnp.inf), -1)


def ray_ground(origin, dirs, ground_z):
    """(R,) distance along each ray to the plane z = ground_z (from above); inf for rays not going down to it."""
    dz = dirs[:, 2]
    t = (ground_z - origin[2]) / jnp.where(dz < -_TINY, dz, -_TINY)
    return jnp.where((dz < -_TINY) & (t >= 0), t, jnp.inf)


def ray_terrain(origin, dirs, terrain: Terrain):
    """(R,) distance along each ray to the first thing it meets: a box or the ground; inf for none."""
    return jnp.minimum(ray_box(origin, dirs, terrain.box_pos, terrain.box_half, terrain.box_valid),
                       ray_ground(origin, dirs, terrain.ground_z))


def quat_to_mat(q):
    """(3, 3) rotation of a unit quaternion q = (w, x, y, z) (MuJoCo's order)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def sensor_pose(sensor: RangeSensor, torso_pos, torso_quat):
    """(origin (3,), rotation (3, 3) sensor -> world) of a sensor on a torso at torso_pos, torso_quat."""
    r_torso = quat_to_mat(torso_quat / jnp.linalg.norm(torso_quat))
    origin = torso_pos + r_torso @ jnp.asarray(sensor.mount_pos, jnp.float32)
    return origin, r_torso @ jnp.asarray(sensor.mount_rotation())


def scan(sensor: RangeSensor, torso_pos, torso_quat, terrain: Terrain, key) -> Scan:
    """The points `sensor` returns from a torso at (torso_pos (3,), torso_quat (4,)) over one env's terrain.
    Each ray's true distance is measured (camera: depth along the optical axis; LiDAR: along the ray), kept
    if inside [range_min, range_max], moved along the ray by Gaussian noise of std noise_std + noise_quad *
    range^2, and dropped with probability `dropout`."""
    dirs_s = jnp.asarray(sensor.directions())
    origin, rot = sensor_pose(sensor, torso_pos, torso_quat)
    dirs = dirs_s @ rot.T  # (R, 3) world
    dist = ray_terrain(origin, dirs, terrain)
    measure = dist * dirs_s[:, 0] if sensor.kind == "camera" else dist  # depth, or range
    valid = jnp.isfinite(dist) & (measure >= sensor.range_min) & (measure <= sensor.range_max)
    k_noise, k_drop = jax.random.split(key)
    if sensor.noise_std > 0 or sensor.noise_quad > 0:
        r = jnp.where(valid, measure, 0.0)
        std = sensor.noise_std + sensor.noise_quad * r * r
        # noise on the measure, moved onto the ray (a camera's depth error scales the whole ray)
        scale = jnp.where(sensor.kind == "camera", 1.0 / jnp.maximum(dirs_s[:, 0], 1e-3), 1.0)
        dist = dist + std * scale * jax.random.normal(k_noise, dist.shape)
    if sensor.dropout > 0:
        valid = valid & (jax.random.uniform(k_drop, dist.shape) >= sensor.dropout)
    pts = origin + jnp.where(valid, dist, 0.0)[:, None] * dirs
    return Scan(points=jnp.where(valid[:, None], pts, 0.0), valid=valid, origin=origin)

