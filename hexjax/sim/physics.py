"""Physics presets as data: configs/physics/<name>.yaml -> `PhysicsPreset` (`get_physics`).

A preset names everything that decides what the contact solve computes: the engine (`backend`: MJX's JAX
implementation, MJX with MuJoCo Warp kernels, or MuJoCo C in float64), the timestep, Newton iterations and
line-search steps with their tolerances, the friction cone and impratio, the integrator and hexjax's contact
culling (how many terrain boxes each leg and the torso collide with at a time in MJX; `hexjax.sim.model`).

    reference   MuJoCo C, float64, converged (iterations >= 100, tolerance <= 1e-10), elliptic cone, every
                terrain box a geom: the physics every other preset is measured against (`hexjax fidelity`)
    validated   a contract, not one engine: the engine/settings pairs whose every cell of the fidelity matrix is
                within the contract of `reference` (docs/physics.md), listed in its `engines`; the default of every
                command that reports results, which runs the fastest of them on the host (`pick_engine`)
    fast        two Newton iterations and the pyramidal cone, for throughput and RL; its deviations from
                `reference` are measured in docs/physics.md

A preset file is checked on load like every other preset (unknown key, wrong type, out-of-range value, an empty
file: one ValueError line naming the file, the key and the value), before anything is traced.

Engines by job. A preset's `engines` lists the engine/settings pairs certified to compute its physics: each a
backend, the preset whose settings that backend runs, and the `hexjax fidelity` JSONs whose every cell meets the
contract (or has a paired 95 % interval that meets the band) for that pair, a later JSON's cells replacing an
earlier one's (a cell re-run with more envs); the reference runs its own settings and needs no certificate. An
evaluation command runs the fastest certified pair on the host (`pick_engine`; `ENGINE_ORDER`: MuJoCo C first on a
CPU-only host, where it runs 19x MJX), prints which and writes it into its JSON; `--backend` picks another
certified one or the preset's own engine. A job only MJX can run (gradients, a device mesh) runs the preset's own
settings, recorded as uncertified where no certificate lists them.
"""

from __future__ import annotations

import dataclasses
import os
import types
from typing import Any, Dict, Optional, Tuple

from hexjax.sim.config import PhysicsConfig, physics_for
from hexjax.world.files import build, read_yaml, resolve

PHYSICS_BACKENDS = ("mjx", "warp", "c")
DEFAULT_PRESET = "validated"  # what every results command runs unless --physics says otherwise
# fastest first, as measured on the tactile gait over high-large (docs/benchmarks.md, "Engines by job")
ENGINE_ORDER = {"cpu": ("c", "mjx", "warp"), "gpu": ("warp", "mjx", "c")}
NOT_MJX = frozenset({"c", "warp"})  # `pick_engine(exclude=...)` for a job only MJX runs (gradients, a mesh)
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
    # (backend, preset whose settings it runs, the fidelity JSONs that certify it, relative to the repository; a
    # later one's cells replace an earlier one's: more envs deciding a cell; none for the reference itself): the
    # engines certified for this preset's physics (module docstring); empty: the preset's own engine only
    engines: Tuple[Tuple[str, str, Tuple[str, ...]], ...] = ()

    def validate(self) -> None:
        if self.backend not in PHYSICS_BACKENDS:
            raise ValueError(f"physics.backend={self.backend!r}: use one of {PHYSICS_BACKENDS}")
        seen = [e[0] for e in self.engines]
        for i, (be, settings, _) in enumerate(self.engines):
            if be not in PHYSICS_BACKENDS:
                raise ValueError(f"physics.engines[{i}][0]={be!r}: use one of {PHYSICS_BACKENDS}")
            if be in seen[:i]:
                raise ValueError(f"physics.engines[{i}][0]={be!r}: an engine listed twice")
            if not settings:
                raise ValueError(f"physics.engines[{i}][1]={settings!r}: name the preset whose settings it runs")
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
        out.pop("engines")
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


@dataclasses.dataclass(frozen=True)
class Engine:
    """What an evaluation runs for a physics preset (`pick_engine`): `preset` carries the settings the engine runs
    under the asked-for preset's name; `backend` the engine; `settings` the preset those settings come from;
    `certificates` the fidelity JSONs that certify the pair (none for the reference itself or an uncertified
    preset's own engine); `why` how it was chosen."""

    preset: PhysicsPreset
    backend: str
    settings: str
    certificates: Tuple[str, ...]
    why: str

    def record(self) -> Dict[str, Any]:
        """The run's physics for a result's JSON: the preset's record (its name, the settings run, the engine)
        with how the engine was chosen."""
        return self.preset.record(self.backend) | {"engine": dict(backend=self.backend, settings=self.settings,
                                                                   certificates=list(self.certificates),
                                                                   picked=self.why)}

    def header(self) -> str:
        """The physics header's lines: the settings run, then the engine and how it was chosen."""
        return (self.preset.header(self.backend)
                + f"\nengine: {self.backend} with {self.settings}'s settings ({self.why})")


def engine_available(backend: str) -> bool:
    """Whether this process can step physics with `backend` (MuJoCo Warp needs warp-lang; the others are always
    installed)."""
    if backend != "warp":
        return True
    import importlib.util
    return importlib.util.find_spec("warp") is not None


def pick_engine(preset, backend: Optional[str] = None, platform: Optional[str] = None, exclude=()) -> Engine:
    """The engine an evaluation of physics `preset` (name, path or `PhysicsPreset`) runs: `backend` where given
    (one of the preset's certified engines, or any engine for a preset that lists none: its own settings),
    else the fastest certified engine available on `platform` (default: JAX's default backend; `ENGINE_ORDER`)
    and not in `exclude` (engines that cannot run the job: MJX's alone for gradients); where none is left, the
    preset's own settings on its own engine, said so in `why`. One ValueError line for a backend that is neither
    certified nor the preset's own."""
    p = get_physics(preset)
    if not p.engines:
        be = backend or p.backend
        if be not in PHYSICS_BACKENDS:
            raise ValueError(f"backend={be!r}: use one of {PHYSICS_BACKENDS}")
        why = "asked for (--backend)" if backend else f"the {p.name} preset's own"
        return Engine(p, be, p.name, (), why)
    table = {e[0]: e for e in p.engines}
    own = (p.backend, p.name, ())  # the preset's own settings on its own engine: what gradients run
    if backend:
        if backend not in table and backend != p.backend:
            raise ValueError(f"backend={backend!r}: physics {p.name!r} is certified on {', '.join(table)} only "
                             f"(its engines), or runs its own settings on {p.backend} (docs/physics.md)")
        be, why = backend, "asked for (--backend)"
    else:
        if platform is None:
            import jax
            platform = jax.default_backend()
        kind = "cpu" if platform == "cpu" else "gpu"
        be = next((b for b in ENGINE_ORDER[kind] if b in table and engine_available(b) and b not in exclude),
                  p.backend)
        why = f"the fastest certified engine on this {'CPU-only host' if kind == 'cpu' else platform.upper()}"
        if be not in table:
            why = f"the preset's own settings: the job needs {be}, which no certificate covers (docs/physics.md)"
    if be not in table:
        if backend:
            why += f"; {be} at these settings is not certified (docs/physics.md)"
        table[be] = own
    _, settings, certs = table[be]
    run = p if settings == p.name else dataclasses.replace(get_physics(settings), name=p.name, summary=p.summary,
                                                           engines=())
    return Engine(dataclasses.replace(run, backend=be), be, settings, certs, why)


def timed_settings(preset: PhysicsPreset, backend: Optional[str]) -> Tuple[PhysicsPreset, str, bool]:
    """What `hexjax bench` times for `preset` on `backend`: (the preset carrying the settings run, the name of the
    preset they come from, whether `preset` certifies that engine). A certified engine runs its own settings
    (MuJoCo C the reference's for `validated`); any other engine is timed on the preset's own, uncertified."""
    if backend in {e[0] for e in preset.engines}:
        e = pick_engine(preset, backend)
        return e.preset, e.settings, True
    return preset, preset.name, False


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
        raw = read_yaml(path)
        if not raw:
            raise ValueError(f"{path}: an empty physics preset: give its settings (docs/configs.md lists the keys; "
                             "configs/physics/validated.yaml is a complete one)")
        base, source = build(PhysicsPreset, raw, str(path), "physics", defaults={"name": path.stem}), str(path)
    if not overrides:
        base.validate()
        return base
    own = {f.name: getattr(base, f.name) for f in dataclasses.fields(base)}
    return build(PhysicsPreset, overrides, source, "physics", defaults=own)
