"""Terrain data and specs: `Terrain` (a sampled terrain's boxes), `TerrainSpec` (a family, checked) and the
difficulty table every family is scaled by. The generators, sampling and views are in `hexjax.world.terrain`,
whose docstring describes the families."""

from __future__ import annotations

import dataclasses
import math
from typing import Optional, Tuple

import jax
from flax import struct

KINDS = ("flat", "obstacles", "step", "ditch", "waves", "rough", "slope", "stairs", "stones", "boxes")
MAX_EXTENT = 50.0  # m: no terrain dimension beyond this
MAX_BOXES = 20_000  # boxes per terrain: a batch holds this many per env


@struct.dataclass
class Terrain:
    """One terrain (or a batch, with a leading axis on every field). SI units, world frame.

    box_pos:   (M, 3) box centres, m
    box_half:  (M, 3) box half extents, m
    box_valid: (M,) bool, False for padding entries
    ground_z:  () height of the ground plane, m
    """

    box_pos: jax.Array
    box_half: jax.Array
    box_valid: jax.Array
    ground_z: jax.Array


@dataclasses.dataclass(frozen=True)
class TerrainSpec:
    """Static description of a terrain family; sampling draws one member per PRNG key. Lengths in m."""

    kind: str = "flat"
    length: float = 1.3  # extent of the populated corridor along x, m
    width: float = 0.7  # corridor width along y, m
    start_x: float = 0.25  # obstacles begin here (robot starts at x = 0)
    # obstacle fields
    spacing_range: Tuple[float, float] = (0.12, 0.13)  # hex-lattice spacing
    jitter: float = 0.009  # each centre moved within this radius
    drop_max: float = 0.0  # fraction of lattice sites dropped at most (thins low-density fields)
    height_range: Tuple[float, float] = (0.03, 0.05)
    length_range: Tuple[float, float] = (0.02, 0.03)  # along x
    width_range: Tuple[float, float] = (0.03, 0.08)  # along y
    # step / ditch
    step_length_range: Tuple[float, float] = (0.15, 0.3)
    step_side: str = "right"  # 'right', 'left' or 'full'
    ditch_count: int = 3
    ditch_width_range: Tuple[float, float] = (0.06, 0.09)
    ditch_gap_range: Tuple[float, float] = (0.25, 0.35)  # solid ground between ditches
    # grids (waves, rough); slope: the slices' length along x
    cell: float = 0.02
    taper: float = 0.0  # waves: heights fade to 0 over this many m inside the patch's edges (0: cut off)
    # slope / stairs
    direction: str = "up"  # 'up' or 'down' (down: the robot starts on a platform, the ground plane is below)
    slope_range: Tuple[float, float] = (0.2, 0.2)  # ramp angle, rad
    stair_count: int = 6
    tread_range: Tuple[float, float] = (0.1, 0.12)  # stairs: tread along x (height_range: the riser)
    # stepping stones: square stones on a grid of this pitch, tops at z = 0, over a pit height_range deep
    stone_pitch: float = 0.08
    gap_range: Tuple[float, float] = (0.02, 0.02)  # space between neighbouring stones
    # random boxes: this many, sized length_range x width_range x height_range, anywhere in the corridor
    box_count: int = 40
    difficulty: Optional[float] = None  # set by `at_difficulty` (None: the ranges as written)
    slots_per_leg: int = 2  # terrain boxes each leg collides with at a time (see sim.model)
    torso_slots: int = 2  # and the torso, where a physics preset leaves it to the terrain

    def validate(self) -> None:
        """Raise one ValueError line naming the first bad field and its value; also refuses families whose
        terrains would not fit a batch (more than `MAX_BOXES` boxes each)."""
        if self.kind not in KINDS:
            raise ValueError(f"terrain.kind={self.kind!r}: choose one of {KINDS}")
        for f, hi in (("length", MAX_EXTENT), ("width", MAX_EXTENT), ("cell", 1.0), ("jitter", 1.0)):
            v = getattr(self, f)
            if not (math.isfinite(v) and v >= 0) or (f != "jitter" and v == 0):
                raise ValueError(f"terrain.{f}={v!r}: must be a finite number > 0")
            if v > hi:
                raise ValueError(f"terrain.{f}={v!r}: must be at most {hi} m")
        if not (math.isfinite(self.start_x) and abs(self.start_x) <= MAX_EXTENT):
            raise ValueError(f"terrain.start_x={self.start_x!r}: must be a finite number within {MAX_EXTENT} m of 0")
        if not (math.isfinite(self.taper) and 0 <= self.taper <= 0.5 * min(self.length, self.width)):
            raise ValueError(f"terrain.taper={self.taper!r}: must be in [0, half the patch's shorter side]")
        for f in ("spacing_range", "height_range", "length_range", "width_range", "step_length_range",
                  "ditch_width_range", "ditch_gap_range", "tread_range", "gap_range"):
            lo, hi = getattr(self, f)
            if not (math.isfinite(lo) and math.isfinite(hi)):
                raise ValueError(f"terrain.{f}={(lo, hi)!r}: must be finite")
            if lo > hi:
                raise ValueError(f"terrain.{f}={(lo, hi)!r}: min must be <= max")
            if lo < 0:
                raise ValueError(f"terrain.{f}={(lo, hi)!r}: must be >= 0")
            if hi > MAX_EXTENT:
                raise ValueError(f"terrain.{f}={(lo, hi)!r}: must be at most {MAX_EXTENT} m")
        if self.kind == "obstacles" and self.spacing_range[0] <= 2 * self.jitter:
            raise ValueError(f"terrain.spacing_range={self.spacing_range!r}: must exceed 2 * jitter")
        if not 0 <= self.drop_max < 1:
            raise ValueError(f"terrain.drop_max={self.drop_max!r}: must be in [0, 1)")
        if self.step_side not in ("right", "left", "full"):
            raise ValueError(f"terrain.step_side={self.step_side!r}: use 'right', 'left' or 'full'")
        if not 1 <= self.ditch_count <= 100:
            raise ValueError(f"terrain.ditch_count={self.ditch_count!r}: must be in [1, 100]")
        if self.direction not in ("up", "down"):
            raise ValueError(f"terrain.direction={self.direction!r}: use 'up' or 'down'")
        lo, hi = self.slope_range
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi <= 0.8):
            raise ValueError(f"terrain.slope_range={(lo, hi)!r}: must be finite with 0 <= min <= max <= 0.8 rad")
        if not 1 <= self.stair_count <= 100:
            raise ValueError(f"terrain.stair_count={self.stair_count!r}: must be in [1, 100]")
        if not 1 <= self.box_count <= 5000:
            raise ValueError(f"terrain.box_count={self.box_count!r}: must be in [1, 5000]")
        if self.kind == "stairs" and self.tread_range[0] <= 0:
            raise ValueError(f"terrain.tread_range={self.tread_range!r}: must be > 0")
        if not (math.isfinite(self.stone_pitch) and 0.01 <= self.stone_pitch <= 1.0):
            raise ValueError(f"terrain.stone_pitch={self.stone_pitch!r}: must be in [0.01, 1] m")
        if self.gap_range[1] >= self.stone_pitch:
            raise ValueError(f"terrain.gap_range={self.gap_range!r}: must stay below stone_pitch={self.stone_pitch!r}")
        if self.difficulty is not None and not (math.isfinite(self.difficulty) and 0 <= self.difficulty <= 1):
            raise ValueError(f"terrain.difficulty={self.difficulty!r}: must be in [0, 1]")
        if not 1 <= self.slots_per_leg <= 8:
            raise ValueError(f"terrain.slots_per_leg={self.slots_per_leg!r}: must be in [1, 8]")
        if not (isinstance(self.torso_slots, int) and 0 <= self.torso_slots <= 16):
            raise ValueError(f"terrain.torso_slots={self.torso_slots!r}: must be a whole number in [0, 16]")
        if self.max_boxes > MAX_BOXES:
            raise ValueError(f"terrain: {self.max_boxes} boxes per terrain (length={self.length!r}, width="
                             f"{self.width!r}, cell / spacing); at most {MAX_BOXES}")

    def at_difficulty(self, difficulty: float, scale: float = 1.0) -> "TerrainSpec":
        """This family with the keys of `DIFFICULTY[kind]` set for `difficulty` in [0, 1] (linear between the
        table's easy and hard ends; lengths times `scale`, e.g. `leg_scale(robot)`), the rest kept."""
        d = float(difficulty)
        if not (math.isfinite(d) and 0 <= d <= 1):
            raise ValueError(f"terrain.difficulty={difficulty!r}: must be in [0, 1]")
        if not (math.isfinite(scale) and 0.1 <= scale <= 10):
            raise ValueError(f"terrain difficulty scale={scale!r}: must be in [0.1, 10]")
        new = {}
        for key, (easy, hard) in DIFFICULTY.get(self.kind, {}).items():
            s = 1.0 if key in UNSCALED else scale
            if isinstance(easy, tuple):
                new[key] = tuple(round(s * (e + d * (h - e)), 6) for e, h in zip(easy, hard))
            else:
                new[key] = round(s * (easy + d * (hard - easy)), 6)
        out = dataclasses.replace(self, difficulty=d, **new)
        out.validate()
        return out

    # Static sizes -------------------------------------------------------------------------------
    def _lattice_n(self) -> int:
        radius = 0.5 * math.hypot(self.length, self.width) + self.spacing_range[1]
        return int(math.ceil(radius / (0.5 * math.sqrt(3) * self.spacing_range[0]))) + 1

    def _grid_shape(self) -> Tuple[int, int]:
        return max(1, int(round(self.length / self.cell))), max(1, int(round(self.width / self.cell)))

    def _stone_grid(self) -> Tuple[int, int]:
        return max(1, int(round(self.length / self.stone_pitch))), max(1, int(round(self.width / self.stone_pitch)))

    @property
    def max_boxes(self) -> int:
        """Static number of box entries per terrain (padding included)."""
        if self.kind == "flat":
            return 1
        if self.kind == "obstacles":
            a = self.spacing_range[0] - 2 * self.jitter
            area = (self.length + a) * (self.width + a)
            return int(math.ceil(area / (0.5 * math.sqrt(3) * a * a) * 1.15)) + 4
        if self.kind == "step":
            return 1
        if self.kind == "ditch":
            return self.ditch_count + 1
        if self.kind == "slope":
            return self._grid_shape()[0] + 1
        if self.kind == "stairs":
            return self.stair_count + 1
        if self.kind == "stones":
            nx, ny = self._stone_grid()
            return nx * ny + 2
        if self.kind == "boxes":
            return self.box_count
        nx, ny = self._grid_shape()
        return nx * ny


# The keys each family's difficulty sets: (value at difficulty 0, value at 1). Lengths are for the Luneckas 2020
# robot (femur + tibia 0.202 m; `leg_scale` scales them to another robot); angles (UNSCALED) are not scaled.
# At 0 every family is nearly flat ground; at 1 it is past what the open-loop gait's 3 cm swing can take.
DIFFICULTY = {
    "obstacles": {"height_range": ((0.005, 0.01), (0.07, 0.08))},  # Luneckas 2020 fields: 3-5 cm small, 6-8 large
    "step": {"height_range": ((0.005, 0.005), (0.08, 0.08))},  # Yu 2019 steps: 40, 50 mm
    "ditch": {"height_range": ((0.005, 0.005), (0.1, 0.1))},  # Yu 2019 ditches: 18, 40, 80 mm deep
    "waves": {"height_range": ((0.005, 0.01), (0.15, 0.178))},  # Chen 2019 patch: peaks to ~178 mm
    "rough": {"height_range": ((0.0, 0.005), (0.0, 0.04))},
    "slope": {"slope_range": ((0.0, 0.0), (0.6, 0.6))},  # 0-34 deg
    "stairs": {"height_range": ((0.01, 0.01), (0.08, 0.08))},  # risers 1-8 cm (2 cm at 1/7)
    # stones 8 cm square at 0, 3 cm with 5 cm gaps at 1 (the pitch scales with the robot, so the gaps stay below it)
    "stones": {"gap_range": ((0.0, 0.0), (0.05, 0.05)), "stone_pitch": (0.08, 0.08)},
    "boxes": {"height_range": ((0.0, 0.005), (0.04, 0.08))},
}
UNSCALED = ("slope_range",)
LUNECKAS2020_LEG = 0.082 + 0.12  # femur + tibia, m (Luneckas 2020 Sect. 2.1)


def leg_scale(robot) -> float:
    """How much longer `robot`'s leg (femur + tibia) is than the Luneckas 2020 robot's: the factor the lengths
    of the difficulty table are multiplied by."""
    return (robot.femur_length + robot.tibia_length) / LUNECKAS2020_LEG
