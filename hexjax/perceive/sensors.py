"""Range sensors: a depth camera and a spinning LiDAR, as Zhao 2018 Sect. 5 equips Octopus-III with them.

Zhao 2018 gives the fields of view and ranges (Sect. 5): the Kinect V1 sees 57 deg x 43 deg from 0.8 m to
4.0 m (indoors), the Velodyne PUCK 360 deg x 30 deg up to 100 m (outdoors). The resolutions are the sensors'
data-sheet values, not the paper's: a 640 x 480 depth image, and 16 laser channels over the 30 deg. The
presets (`configs/sensors/*.yaml`) sample fewer rays than the hardware (a scan of every pixel would cost
more than the physics); `n_h`, `n_v` set the resolution.

Frames: the sensor frame has x along the optical axis (camera) or the spin axis' zero azimuth (LiDAR), y
left, z up. It sits in the torso frame at `mount_pos` (m), turned by `mount_rpy` (deg: roll about x, then
pitch about y, then yaw about z, R = Rz Ry Rx); a positive pitch tilts the axis down (x towards -z).

Range: a camera measures depth (distance along its optical axis), a LiDAR the distance along each ray;
`range_min` / `range_max` bound that measure, and a ray with nothing inside them returns no point. Noise
(`noise_std` + `noise_quad` * range^2, m, Gaussian along the ray; the Kinect's error grows with the square
of the depth) and `dropout` (each ray's probability of returning nothing) are drawn per ray and scan.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Tuple

import numpy as np

from hexjax.world.files import build, read_yaml, replaced, resolve
from hexjax.world.robot import RobotSpec

SENSOR_KINDS = ("camera", "lidar")


@dataclasses.dataclass(frozen=True)
class RangeSensor:
    """Static description of one range sensor (module docstring: frames, range, noise). Angles in deg."""

    kind: str = "camera"
    fov_h: float = 57.0  # horizontal field of view, deg (Zhao 2018 Sect. 5: Kinect V1 57 deg)
    fov_v: float = 43.0  # vertical, deg (Kinect V1 43 deg)
    n_h: int = 32  # rays across the horizontal field of view
    n_v: int = 24  # rays (camera rows, LiDAR channels) across the vertical one
    range_min: float = 0.8  # m (Kinect V1: 0.8 m)
    range_max: float = 4.0  # m (Kinect V1: 4.0 m)
    noise_std: float = 0.0  # m, range noise's constant part
    noise_quad: float = 0.0  # m per m^2, range noise's part growing with range^2
    dropout: float = 0.0  # probability that a ray returns no point
    mount_pos: Tuple[float, float, float] = (0.1, 0.0, 0.04)  # m, torso frame
    mount_rpy: Tuple[float, float, float] = (0.0, 0.0, 0.0)  # deg: roll, pitch (+ down), yaw

    @property
    def n_rays(self) -> int:
        return self.n_h * self.n_v

    def validate(self, robot: RobotSpec = None) -> None:
        """Host-side checks; every error one line naming the key and value. With `robot`, the mount must lie
        outside its torso box (a sensor inside the torso would see only the torso)."""
        if self.kind not in SENSOR_KINDS:
            raise ValueError(f"sensor.kind={self.kind!r}: use one of {SENSOR_KINDS}")
        top = 360.0 if self.kind == "lidar" else 170.0
        if not 0.0 < self.fov_h <= top:
            raise ValueError(f"sensor.fov_h={self.fov_h!r}: must be in (0, {top:g}] deg for a {self.kind}")
        if not 0.0 < self.fov_v <= 170.0:
            raise ValueError(f"sensor.fov_v={self.fov_v!r}: must be in (0, 170] deg")
        for f in ("n_h", "n_v"):
            v = getattr(self, f)
            if not 1 <= v <= 4096:
                raise ValueError(f"sensor.{f}={v!r}: must be in [1, 4096] rays")
        if not 0.0 <= self.range_min < self.range_max:
            raise ValueError(f"sensor.range_min={self.range_min!r}, range_max={self.range_max!r}: need "
                             "0 <= range_min < range_max")
        for f in ("noise_std", "noise_quad"):
            if getattr(self, f) < 0:
                raise ValueError(f"sensor.{f}={getattr(self, f)!r}: must be >= 0")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"sensor.dropout={self.dropout!r}: must be in [0, 1) (probability)")
        if robot is not None:
            half = np.array([robot.body_length, robot.body_width, robot.body_thickness]) / 2
            if np.all(np.abs(np.asarray(self.mount_pos)) < half):
                raise ValueError(f"sensor.mount_pos={list(self.mount_pos)!r}: inside the torso of {robot.name} "
                                 f"(half extents {[round(float(h), 4) for h in half]} m); mount it on the "
                                 "surface or outside")

    def directions(self) -> np.ndarray:
        """(n_v * n_h, 3) unit ray directions in the sensor frame, row by row from the top, each row from
        the left. Camera: through the pixel centres of a pinhole image; LiDAR: n_v channels evenly over the
        vertical field, n_h azimuths evenly over the horizontal one (a full turn does not repeat its start)."""
        if self.kind == "camera":
            th, tv = math.tan(math.radians(self.fov_h) / 2), math.tan(math.radians(self.fov_v) / 2)
            u = (np.arange(self.n_h) + 0.5) / self.n_h * 2 - 1  # -1 .. 1, left to right
            v = 1 - (np.arange(self.n_v) + 0.5) / self.n_v * 2  # 1 .. -1, top to bottom
            uu, vv = np.meshgrid(u, v)
            d = np.stack([np.ones_like(uu), -uu * th, vv * tv], -1).reshape(-1, 3)
        else:
            full = self.fov_h >= 360.0
            az = (np.arange(self.n_h) / self.n_h - 0.5) * 360.0 if full else \
                np.linspace(-self.fov_h / 2, self.fov_h / 2, self.n_h) if self.n_h > 1 else np.zeros(1)
            el = np.linspace(self.fov_v / 2, -self.fov_v / 2, self.n_v) if self.n_v > 1 else np.zeros(1)
            a, e = np.meshgrid(-np.radians(az), np.radians(el))  # azimuth grows to the right: -y
            d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
        return (d / np.linalg.norm(d, axis=-1, keepdims=True)).astype(np.float32)

    def mount_rotation(self) -> np.ndarray:
        """(3, 3) rotation from the sensor frame to the torso frame, R = Rz(yaw) Ry(pitch) Rx(roll)."""
        r, p, y = np.radians(self.mount_rpy)
        rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
        ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
        rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
        return (rz @ ry @ rx).astype(np.float32)


def validate_perceiver(ctrl) -> None:
    """Host-side checks of a perceiving controller's static perception fields (its `sensor` on its `robot`,
    its map `grid`, `perceive_every`); each error one line naming the field and value."""
    ctrl.sensor.validate(ctrl.robot)
    ctrl.grid.validate()
    if not (isinstance(ctrl.perceive_every, int) and ctrl.perceive_every >= 1):
        raise ValueError(f"perceive_every={ctrl.perceive_every!r}: must be a whole number of control steps >= 1")


def get_sensor(name: str, **overrides) -> RangeSensor:
    """`RangeSensor` of preset `name` (configs/sensors/<name>.yaml) or of a YAML file path, with keys replaced
    by `overrides` (checked like the file's own, after the file is checked on its own)."""
    path = resolve("sensors", name)
    return replaced(build(RangeSensor, read_yaml(path), str(path), "sensor"), overrides, str(path), "sensor")
