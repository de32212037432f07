"""Hexapod robot: the geometry spec (`RobotSpec`, presets in configs/robots/), frames and leg kinematics in JAX.

Frames. World and torso: x forward, y left, z up. Each leg has a *leg frame* at its coxa joint, rotated
about z by the leg's mount yaw so that its x axis points outward from the body. Joint angles:
  q1 coxa yaw about the leg z axis (positive turns the leg towards +y of the leg frame),
  q2 femur pitch (positive lifts the femur),
  q3 tibia pitch relative to the femur (0: tibia continues the femur; negative: knee bent down).
Leg order everywhere: LF, LM, LH, RF, RM, RH (indices 0..5), as in Luneckas 2020 Fig. 13.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Tuple

import jax.numpy as jnp
import numpy as np

LEG_NAMES = ("LF", "LM", "LH", "RF", "RM", "RH")
N_LEGS = 6


# (field, largest value, unit): checked by `RobotSpec.validate`
_UPPER_BOUNDS = tuple((f, 2.0, "m") for f in ("coxa_length", "femur_length", "tibia_length", "body_length",
                                            "body_width", "body_thickness", "hip_x", "hip_y", "stance_radial",
                                            "body_clearance")) + tuple(
    (f, 0.5, "m") for f in ("foot_radius", "pad_radius", "pad_offset")) + (
    ("total_mass", 1000.0, "kg"), ("kp", 1e5, "N*m/rad"), ("kv", 1e4, "N*m*s/rad"), ("max_torque", 1e5, "N*m"),
    ("joint_damping", 1e4, "N*m*s/rad"), ("armature", 100.0, "kg*m^2"), ("friction", 10.0, ""))


@dataclasses.dataclass(frozen=True)
class RobotSpec:
    """Every number that defines a hexapod. SI units (m, kg, rad, N*m)."""

    name: str
    coxa_length: float
    femur_length: float
    tibia_length: float
    total_mass: float
    body_length: float  # torso box, along x
    body_width: float  # along y
    body_thickness: float
    hip_x: float  # |x| of front/hind hips from the torso centre
    hip_y: float  # |y| of all hips
    leg_mass_fraction: float = 0.3  # share of total_mass carried by the six legs
    foot_radius: float = 0.01
    stance_radial: float = 0.13  # horizontal distance coxa joint -> foot in the neutral stance
    stance_splay: float = 0.5  # rad, front/hind legs rotated forward/backward in the neutral stance
    body_clearance: float = 0.08  # torso bottom above ground in the neutral stance
    coxa_range: Tuple[float, float] = (-1.2, 1.2)
    femur_range: Tuple[float, float] = (-1.4, 1.4)
    tibia_range: Tuple[float, float] = (-2.6, 0.2)
    kp: float = 20.0  # position-servo stiffness, N*m/rad (6 let stance legs sag and feet scuff: 10 % short per m)
    kv: float = 0.3  # servo velocity gain, N*m*s/rad
    max_torque: float = 1.5  # N*m (Dynamixel AX-12 stall torque is ~1.5 N*m)
    joint_damping: float = 0.05
    armature: float = 0.002
    friction: float = 1.0
    # Tactile pad on the front of each shin (Luneckas 2020 Sect. 2.3): a capsule parallel to the
    # tibia, offset towards the walking direction, covering the given fraction of the tibia length.
    pad_offset: float = 0.012
    pad_radius: float = 0.006
    pad_span: Tuple[float, float] = (0.3, 0.85)

    def validate(self) -> None:
        """Raise ValueError naming the first bad field; called before any model is built."""
        for f in ("coxa_length", "femur_length", "tibia_length", "total_mass", "body_length",
                  "body_width", "body_thickness", "foot_radius", "stance_radial", "kp",
                  "max_torque", "pad_radius", "friction"):
            v = getattr(self, f)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"robot.{f}={v!r}: must be a finite number > 0")
        for f in ("hip_x", "hip_y", "body_clearance", "kv", "joint_damping", "armature", "pad_offset"):
            v = getattr(self, f)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"robot.{f}={v!r}: must be a finite number >= 0")
        if not (isinstance(self.stance_splay, (int, float)) and math.isfinite(self.stance_splay)
                and abs(self.stance_splay) <= math.pi / 2):
            raise ValueError(f"robot.stance_splay={self.stance_splay!r}: must be in [-pi/2, pi/2] rad")
        for f, hi, unit in _UPPER_BOUNDS:  # what no walking hexapod exceeds: a slip of units, not a robot
            v = getattr(self, f)
            if v > hi:
                raise ValueError(f"robot.{f}={v!r}: must be at most {hi} {unit}")
        if not 0 < self.leg_mass_fraction < 1:
            raise ValueError(f"robot.leg_mass_fraction={self.leg_mass_fraction!r}: must be in (0, 1)")
        for f in ("coxa_range", "femur_range", "tibia_range", "pad_span"):
            lo, hi = getattr(self, f)
            if not lo < hi:
                raise ValueError(f"robot.{f}={(lo, hi)!r}: min must be < max")
        # The neutral stance must be reachable by every leg.
        feet = neutral_feet_leg_frame(self)
        for i in range(N_LEGS):
            q, ok = leg_ik_np(self, feet[i])
            if not ok:
                raise ValueError(
                    f"robot.stance_radial={self.stance_radial!r}, robot.body_clearance="
                    f"{self.body_clearance!r}: neutral stance of leg {LEG_NAMES[i]} is out of reach")

    # Derived quantities -------------------------------------------------------------------------
    @property
    def hip_height(self) -> float:
        """Height of the coxa joints (torso mid-plane) above flat ground in the neutral stance, m."""
        return self.body_clearance + 0.5 * self.body_thickness


# Mounting geometry ------------------------------------------------------------------------------
def hip_positions(spec: RobotSpec) -> np.ndarray:
    """(6, 3) coxa joint positions in the torso frame, m."""
    xs = (spec.hip_x, 0.0, -spec.hip_x)
    return np.array([(x, spec.hip_y, 0.0) for x in xs] + [(x, -spec.hip_y, 0.0) for x in xs])


def mount_yaws(spec: RobotSpec) -> np.ndarray:
    """(6,) yaw of each leg frame in the torso frame: left legs point to +y, right legs to -y."""
    del spec
    return np.array([math.pi / 2] * 3 + [-math.pi / 2] * 3)


def forward_sign() -> np.ndarray:
    """(6,) sign of the robot's +x direction along each leg frame's y axis (-1 left, +1 right)."""
    return np.array([-1.0] * 3 + [1.0] * 3)


def neutral_feet_leg_frame(spec: RobotSpec) -> np.ndarray:
    """(6, 3) neutral-stance foot positions in each leg frame, m (front legs splayed forward)."""
    splay = np.array([1.0, 0.0, -1.0, 1.0, 0.0, -1.0]) * spec.stance_splay
    # rotate towards the robot's front: +x of torso is forward_sign * y of the leg frame
    ang = splay * forward_sign()
    r, z = spec.stance_radial, -(spec.hip_height - spec.foot_radius)
    return np.stack([r * np.cos(ang), r * np.sin(ang), np.full(6, z)], axis=1)


def leg_to_body(spec: RobotSpec, p_leg, leg=None):
    """Leg-frame points (..., 6, 3) (or a single leg's (..., 3) with `leg`) to the torso frame."""
    yaw = jnp.asarray(mount_yaws(spec)); hip = jnp.asarray(hip_positions(spec))
    if leg is not None:
        yaw, hip = yaw[leg], hip[leg]
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    x, y, z = p_leg[..., 0], p_leg[..., 1], p_leg[..., 2]
    return jnp.stack([c * x - s * y, s * x + c * y, z], axis=-1) + hip


def body_to_leg(spec: RobotSpec, p_body, leg=None):
    """Inverse of `leg_to_body`."""
    yaw = jnp.asarray(mount_yaws(spec)); hip = jnp.asarray(hip_positions(spec))
    if leg is not None:
        yaw, hip = yaw[leg], hip[leg]
    d = p_body - hip
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1], d[..., 2]], axis=-1)


def neutral_feet_body(spec: RobotSpec) -> np.ndarray:
    """(6, 3) neutral-stance foot centres in the torso frame, m."""
    p, yaw = neutral_feet_leg_frame(spec), mount_yaws(spec)
    c, s = np.cos(yaw), np.sin(yaw)
    x = c * p[:, 0] - s * p[:, 1]
    y = s * p[:, 0] + c * p[:, 1]
    return np.stack([x, y, p[:, 2]], axis=1) + hip_positions(spec)


# Kinematics (JAX) -------------------------------------------------------------------------------
def quat_yaw(q):
    """Heading (rad) of a torso quaternion (w, x, y, z): the yaw of its z-y-x Euler angles."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def wrap_angle(a):
    """a wrapped to (-pi, pi]."""
    return jnp.arctan2(jnp.sin(a), jnp.cos(a))


def leg_fk(spec: RobotSpec, q):
    """Foot centre in the leg frame from joint angles. q: (..., 3) rad -> (..., 3) m."""
    q1, q2, q3 = q[..., 0], q[..., 1], q[..., 2]
    r = spec.coxa_length + spec.femur_length * jnp.cos(q2) + spec.tibia_length * jnp.cos(q2 + q3)
    z = spec.femur_length * jnp.sin(q2) + spec.tibia_length * jnp.sin(q2 + q3)
    return jnp.stack([r * jnp.cos(q1), r * jnp.sin(q1), z], axis=-1)


def leg_ik(spec: RobotSpec, p):
    """Joint angles (knee-up branch) reaching foot centre p (..., 3) m in the leg frame.

    Returns (q (..., 3) rad, reachable (...,) bool). Unreachable targets are clamped to the nearest
    reachable distance so q stays finite; `reachable` also checks the joint limits."""
    lf, lt = spec.femur_length, spec.tibia_length
    q1 = jnp.arctan2(p[..., 1], p[..., 0])
    r = jnp.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2) - spec.coxa_length
    z = p[..., 2]
    d2 = r ** 2 + z ** 2
    dmin, dmax = abs(lf - lt) * 1.001, (lf + lt) * 0.999
    in_reach = (d2 >= dmin ** 2) & (d2 <= dmax ** 2)
    d = jnp.clip(jnp.sqrt(d2), dmin, dmax)
    c3 = jnp.clip((d ** 2 - lf ** 2 - lt ** 2) / (2 * lf * lt), -1.0, 1.0)
    q3 = -jnp.arccos(c3)
    q2 = jnp.arctan2(z, r) - jnp.arctan2(lt * jnp.sin(q3), lf + lt * jnp.cos(q3))
    q = jnp.stack([q1, q2, q3], axis=-1)
    lo = jnp.array([spec.coxa_range[0], spec.femur_range[0], spec.tibia_range[0]])
    hi = jnp.array([spec.coxa_range[1], spec.femur_range[1], spec.tibia_range[1]])
    in_limits = jnp.all((q >= lo) & (q <= hi), axis=-1)
    return q, in_reach & in_limits


def leg_ik_np(spec: RobotSpec, p) -> Tuple[np.ndarray, bool]:
    q, ok = leg_ik(spec, jnp.asarray(p, dtype=jnp.float32))
    return np.asarray(q), bool(ok)


def neutral_joint_angles(spec: RobotSpec) -> np.ndarray:
    """(6, 3) joint angles of the neutral stance, rad."""
    q, _ = leg_ik(spec, jnp.asarray(neutral_feet_leg_frame(spec)))
    return np.asarray(q)
