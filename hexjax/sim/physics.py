"""Physics presets as data: configs/physics/<name>.yaml -> `PhysicsPreset` (`get_physics`).

A preset names everything that decides what the contact solve computes: the engine (`backend`: MJX's JAX
implementation, MJX with MuJoCo Warp kernels, or MuJoCo C in float64), the timestep, Newton iterations and
line-search steps with their tolerances, the friction cone and impratio, the integrator and hexjax's contact
culling (how many terrain boxes each leg and the torso collide with at a time in MJX; `hexjax.sim.model`).

    reference   MuJoCo C, float64, converged (iterations >= 100, tolerance <= 1e-10), elliptic cone, every
                terrain box a geom: the physics every other preset is measured against (`hexjax fidelity`)
    validated   the cheapest MJX settings whose every cell of the fidelity matrix is within the contract of
                `reference` (docs/physics.md): the default of every command that reports results
    fast        two Newton iterations and the pyramidal cone, for throughput and RL; its deviations from
                `reference` are measured in docs/physics.md

A preset file is checked on load like every other preset (unknown key, wrong type, out-of-range value: one
ValueError line naming the file, the key and the value), before anything is traced.
"""

from __future__ import annotations

import dataclasses
import os
import types
from typing import Any, Dict, Optional

from hexjax.sim.config import PhysicsConfig, physics_for
from hexjax.world.files import build, read_yaml, resolve

PHYSICS_BACKENDS = ("mjx", "warp", "c")
DEFAULT_PRESET = "validated"  # what every results command runs unless --physics says otherwise
SETTINGS = ("timestep", "iterations", "ls_iterations", "tolerance", "ls_tolerance", "cone", "impratio",
            "integrator")


@dataclasses.dataclass(frozen=True)
class PhysicsPreset:
    """One physics preset (see the module docstring). `slots_per_leg`: terrain boxes each leg collides with at a
    time in MJX, `torso_slots`: the torso's (None: the terrain preset's own `slots_per_leg`, `torso_slots`).
    MuJoCo C has a broadphase and takes every box whatever these say."""

    name: str = "custom"
    summary: str = ""
    backend: str = "mjx"
    timestep: float = 0.005
    iterations: int = 2
    ls_iterations: int = 4
    tolerance: float = 1e-8
    ls_tolerance: float = 0.01
    cone: str = "pyramidal"
    impratio: float = 1.0
    integrator: str = "implicitfast"
    slots_per_leg: Optional[int] = None
    torso_slots: Optional[int] = 2

    def validate(self) -> None:
        if self.backend not in PHYSICS_BACKENDS:
            raise ValueError(f"physics.backend={self.backend!r}: use one of {PHYSICS_BACKENDS}")
        self.config().validate()

    def config(self, terrain=None, kind: Optional[str] = None) -> PhysicsConfig:
        """The `PhysicsConfig` of this preset for a terrain (a `TerrainSpec`, for its kind and slot counts; or
        `kind` alone): flat ground gets no slots (`physics_for`), other terrains `slots_per_leg` and
        `torso_slots` or, where the preset leaves them None, the terrain's own (2 and 2 without a terrain)."""
        slots, torso = self.slots_per_leg, self.torso_slots
        if slots is None:
            slots = int(getattr(terrain, "slots_per_leg", 2))
        if torso is None:
            torso = int(getattr(terrain, "torso_slots", 2))
        cfg = PhysicsConfig(slots_per_leg=slots, torso_slots=torso, **{k: getattr(self, k) for k in SETTINGS})
        kind = kind or getattr(terrain, "kind", None)
        return physics_for(kind, cfg) if kind else cfg

    def record(self, backend: Optional[str] = None) -> Dict[str, Any]:
        """What a result's JSON keeps of the physics it ran: the preset's name, every setting and the engine
        (`backend` where a command's --backend chose another than the preset's)."""
        out = dataclasses.asdict(self)
        out.pop("summary")
        out["backend"] = backend or self.backend
        out["precision"] = "float64" if out["backend"] == "c" else "float32"
        return out

    def header(self, backend: Optional[str] = None) -> str:
        """One line for a command's printed header."""
        be = backend or self.backend
        own = lambda v: "terrain default" if v is None else v
        slots = "every box a geom" if be == "c" else (
            f"{own(self.slots_per_leg)} slots per leg, {own(self.torso_slots)} torso")
        return (f"physics: {self.name} ({be}, {'float64' if be == 'c' else 'float32'}; {self.iterations} Newton "
                f"iterations, tolerance {self.tolerance:g}, {self.ls_iterations} line-search steps, {self.cone} cone, "
                f"impratio {self.impratio:g}, timestep {1e3 * self.timestep:g} ms; {slots})")


def shared_config(preset: PhysicsPreset, specs) -> PhysicsConfig:
    """One `PhysicsConfig` for a batch that mixes terrains (`TerrainSpec`s): where the preset leaves the slot
    counts to the terrain, the most any of them takes (per leg and for the torso); flat ground's none where every
    terrain is flat."""
    rough = [s for s in specs if s.kind != "flat"]
    if not rough:
        return preset.config(kind="flat")
    most = types.SimpleNamespace(slots_per_leg=max(s.slots_per_leg for s in rough),
                                 torso_slots=max(s.torso_slots for s in rough))
    return preset.config(most, kind="mixed")


def traced_backend(preset: PhysicsPreset, why: str) -> str:
    """The preset's engine where it is MJX's (JAX or Warp), for a run that reads what only MJX records (`why`);
    one ValueError line for a MuJoCo C preset."""
    if preset.backend == "c":
        raise ValueError(f"physics={preset.name!r} runs MuJoCo C, which keeps no {why}: give a preset on mjx or warp "
                         "(validated, fast, or a .yaml of one's own)")
    return preset.backend


def get_physics(name=None, /, **overrides) -> PhysicsPreset:
    """The `PhysicsPreset` of preset `name` (configs/physics/<name>.yaml; default `validated`) or of a YAML file
    path, with keys replaced by `overrides` (checked as the file's own). A `PhysicsPreset` is checked and given
    back (with `overrides`, which may rename it: `name=`). A file without `name` takes its file name."""
    if name is None:
        name = DEFAULT_PRESET
    if isinstance(name, PhysicsPreset):
        base, source = name, "PhysicsPreset"
    else:
        if not isinstance(name, (str, os.PathLike)) or not str(name):
            raise ValueError(f"physics={name!r}: give a preset name (reference, validated, fast) or a .yaml path")
        path = resolve("physics", name)
        base, source = build(PhysicsPreset, read_yaml(path), str(path), "physics", defaults={"name": path.stem}), str(path)
    if not overrides:
        base.validate()
        return base
    own = {f.name: getattr(base, f.name) for f in dataclasses.fields(base)}
    return build(PhysicsPreset, overrides, source, "physics", defaults=own)
