"""Foot slip: how far the feet slide while they stand, from the joint angles and the torso pose alone, so MJX and
MuJoCo C measure it with the same arithmetic (`hexjax.sim.step.accumulate` sums it into `Summary.foot_slip`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from hexjax.world.robot import RobotSpec, leg_fk, leg_to_body, mount_yaws


def _quat_matrix(q):
    """Rotation matrix (3, 3) of a unit quaternion (w, x, y, z)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def feet_world(robot: RobotSpec, qpos):
    """(centres (6, 3), orientations (6, 3, 3)) of the feet in the world frame from one env's generalised
    positions (nq,): each leg's forward kinematics (`leg_fk`), its mount on the torso, the torso's pose. A foot
    turns with its tibia: the leg's yaw (mount + coxa) about z, then femur + tibia pitch about -y. Needs no
    engine, so MJX and MuJoCo C measure foot slip with the same arithmetic."""
    q = qpos[7:].reshape(6, 3)
    rt = _quat_matrix(qpos[3:7])
    centres = qpos[:3] + leg_to_body(robot, leg_fk(robot, q)) @ rt.T
    yaw = jnp.asarray(mount_yaws(robot)) + q[:, 0]
    pitch = -(q[:, 1] + q[:, 2])  # about +y
    cy, sy, cp, sp = jnp.cos(yaw), jnp.sin(yaw), jnp.cos(pitch), jnp.sin(pitch)
    zero, one = jnp.zeros_like(yaw), jnp.ones_like(yaw)
    rz = jnp.stack([jnp.stack([cy, -sy, zero], -1), jnp.stack([sy, cy, zero], -1), jnp.stack([zero, zero, one], -1)], -2)
    ry = jnp.stack([jnp.stack([cp, zero, sp], -1), jnp.stack([zero, one, zero], -1), jnp.stack([-sp, zero, cp], -1)], -2)
    return centres, rt @ rz @ ry


def slip(robot: RobotSpec, q_old, q_new, contact, rise: float = 1e-3):
    """Horizontal distance (m) the feet of one env slid in one control step: the displacement of each foot's
    material point that touched the ground at the step's start (its lowest point then: a foot that rolls with
    its tibia moves its centre but not that point), for the feet in `contact` (6,) at the start that rose less
    than `rise` m during it (a foot lifting into its swing does not count). No gradient."""
    c0, r0 = feet_world(robot, q_old)
    c1, r1 = feet_world(robot, q_new)
    bottom = jnp.array([0.0, 0.0, -robot.foot_radius])
    moved = (c1 - c0) + jnp.einsum("lij,lkj,k->li", r1, r0, bottom) - bottom
    stood = contact & (c1[:, 2] - c0[:, 2] < rise)
    d = jnp.sqrt(jnp.sum(moved[:, :2] ** 2, -1) + 1e-18)
    return jax.lax.stop_gradient(jnp.sum(jnp.where(stood, d, 0.0)))
