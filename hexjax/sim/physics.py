"""Physics presets as data (configs/physics/<name>.yaml -> `PhysicsPreset`), and the one physics value a
command runs (`Physics`: the settings and the engine, chosen once by `pick`).

A preset names everything that decides what the contact solve computes: its settings (one `PhysicsConfig`: the
timestep, Newton iterations and line-search steps with their tolerances, the friction cone and impratio, the
integrator and hexjax's terrain-box slots) and the engine they are written for (`hexjax.sim.engines`).

    reference   MuJoCo C, float64, converged (iterations >= 100, tolerance <= 1e-10), elliptic cone, every
                terrain box a geom: the physics every other preset is measured against (`hexjax fidelity`)
    validated   a contract, not one engine: the engine/settings pairs whose every cell of the fidelity matrix is
                within the contract of `reference` (docs/physics.md), listed in its `engines`; the default of every
                command that reports results, which runs the fastest of them on the host (`pick`)
    fast        two Newton iterations and the pyramidal cone, for throughput and RL; its deviations from
                `reference` are measured in docs/physics.md

A preset file is checked on load like every other preset (unknown key, wrong type, out-of-range value, an empty
file: one ValueError line naming the file, the key and the value), before anything is traced.

Engines by job. A preset's `engines` lists the engine/settings pairs certified to compute its physics: each an
engine, the preset whose settings that engine runs, and the `hexjax fidelity` JSONs whose every cell meets the
contract (or has a paired 95 % interval that meets the band) for that pair, a later JSON's cells replacing an
earlier one's (a cell re-run with more envs); the reference runs its own settings and needs no certificate. A
command picks once, where it starts (`pick`): the fastest certified engine on the host that can do what the job
needs (gradients, traces, a device mesh, range sensors: `hexjax.sim.engines.base.CAPABILITIES`), or the one
`--engine` names; a job no certified engine can do runs the preset's own settings on an engine that can,
recorded as uncertified. The result prints one header line (`Physics.header`) and records the same in its JSON
(`Physics.record`).
"""

from __future__ import annotations

import dataclasses
import difflib
import os
import types
from typing import Any, Dict, Optional, Tuple

from hexjax.sim.config import PhysicsConfig, physics_for
from hexjax.world.files import build, read_yaml, resolve

DEFAULT_PRESET = "validated"  # what every results command runs unless --physics says otherwise
SETTINGS = tuple(f.name for f in dataclasses.fields(PhysicsConfig))
# a preset's settings where its file leaves a key out: `PhysicsConfig`'s, the slot counts the terrain's own
DEFAULT_SETTINGS = PhysicsConfig(slots_per_leg=None)


@dataclasses.dataclass(frozen=True)
class _Head:
    """The keys of a preset file besides its settings (checked by `hexjax.world.files.build`)."""

    name: str = "custom"
    summary: str = ""
    engine: str = "mjx"
    # (engine, the preset whose settings it runs, the fidelity JSONs that certify it, relative to the repository;
    # a later one's cells replace an earlier one's: more envs deciding a cell; none for the reference itself)
    engines: Tuple[Tuple[str, str, Tuple[str, ...]], ...] = ()

    def validate(self) -> None:
        from hexjax.sim.engines import get_engine
        try:
            get_engine(self.engine)
        except ValueError as err:
            raise ValueError(f"physics.{err}") from None
        seen = [e[0] for e in self.engines]
        for i, (name, settings, _) in enumerate(self.engines):
            try:
                get_engine(name)
            except ValueError as err:
                raise ValueError(f"physics.engines[{i}][0]: {err}") from None
            if name in seen[:i]:
                raise ValueError(f"physics.engines[{i}][0]={name!r}: an engine listed twice")
            if not settings:
                raise ValueError(f"physics.engines[{i}][1]={settings!r}: name the preset whose settings it runs")


@dataclasses.dataclass(frozen=True)
class PhysicsPreset:
    """One physics preset (see the module docstring): its `settings` (a slot count of None: the terrain preset's
    own), the `engine` they are written for, and the `engines` certified for its physics. Its settings read as
    its own attributes (`preset.iterations`)."""

    name: str = "custom"
    summary: str = ""
    engine: str = "mjx"
    settings: PhysicsConfig = DEFAULT_SETTINGS
    engines: Tuple[Tuple[str, str, Tuple[str, ...]], ...] = ()

    def __getattr__(self, key):
        if key in SETTINGS:
            return getattr(self.settings, key)
        raise AttributeError(f"PhysicsPreset has no attribute {key!r}")

    def validate(self) -> None:
        _Head(self.name, self.summary, self.engine, self.engines).validate()
        self.settings.validate()

    def config(self, terrain=None, kind: Optional[str] = None) -> PhysicsConfig:
        """The `PhysicsConfig` of this preset for a terrain (a `TerrainSpec`, for its kind and slot counts; or
        `kind` alone): flat ground gets no slots (`physics_for`), other terrains the preset's slot counts or,
        where it leaves them None, the terrain's own (2 and 2 without a terrain)."""
        slots, torso = self.settings.slots_per_leg, self.settings.torso_slots
        if slots is None:
            slots = int(getattr(terrain, "slots_per_leg", 2))
        if torso is None:
            torso = int(getattr(terrain, "torso_slots", 2))
        cfg = dataclasses.replace(self.settings, slots_per_leg=slots, torso_slots=torso)
        kind = kind or getattr(terrain, "kind", None)
        return physics_for(kind, cfg) if kind else cfg


def shared_config(preset, specs) -> PhysicsConfig:
    """One `PhysicsConfig` for a batch that mixes terrains (`TerrainSpec`s): where the preset (a `PhysicsPreset`
    or a `Physics`) leaves the slot counts to the terrain, the most any of them takes (per leg and for the
    torso); flat ground's none where every terrain is flat."""
    rough = [s for s in specs if s.kind != "flat"]
    if not rough:
        return preset.config(kind="flat")
    most = types.SimpleNamespace(slots_per_leg=max(s.slots_per_leg for s in rough),
                                 torso_slots=max(s.torso_slots for s in rough))
    return preset.config(most, kind="mixed")


@dataclasses.dataclass(frozen=True)
class Physics:
    """The physics a command runs, chosen once (`pick`): `preset` the asked-for preset (its name names the
    physics), `engine` the engine that steps it, `settings` the settings it runs (the preset's own or, for a
    certified pair, those of the preset `settings_from` names), `certificates` the fidelity JSONs that certify
    the pair (none for the reference itself or an uncertified run) and `why` how it was chosen."""

    preset: PhysicsPreset
    engine: Any  # hexjax.sim.engines.base.Engine
    settings: PhysicsConfig
    settings_from: str
    certificates: Tuple[str, ...] = ()
    why: str = ""

    @property
    def name(self) -> str:
        return self.preset.name

    @property
    def certified(self) -> bool:
        """Whether `validated`-style certification covers this engine and these settings (or they are the
        preset's reference: a preset run on its own engine whose `engines` list it with no certificate)."""
        from hexjax.sim.engines import get_engine
        return any(get_engine(e[0]) is self.engine and e[1] == self.settings_from for e in self.preset.engines)

    def config(self, terrain=None, kind: Optional[str] = None) -> PhysicsConfig:
        """The settings run for a terrain (`PhysicsPreset.config`)."""
        return dataclasses.replace(self.preset, settings=self.settings).config(terrain, kind)

    def record(self) -> Dict[str, Any]:
        """What a result's JSON keeps of the physics it ran: the preset's name, the engine (its name, full name
        and precision), every setting, where they come from, the certificates and how the engine was chosen."""
        return dict(name=self.name, engine=self.engine.name, engine_title=self.engine.title,
                    precision=self.engine.precision, settings_from=self.settings_from,
                    **dataclasses.asdict(self.settings), certified=self.certified,
                    certificates=list(self.certificates), picked=self.why)

    def header(self) -> str:
        """One line for a command's printed header: the contract, the engine by its full name, the settings."""
        cert = "certified" if self.certified else "not certified"
        src = "" if self.settings_from == self.name else f"{self.settings_from}'s settings: "
        return (f"physics: {self.name} on engine: {self.engine.name} ({self.engine.title}, {cert}; {self.why}); "
                f"{src}{self.engine.settings(self.settings)}")


def _ordered(kind: str):
    from hexjax.sim.engines import ORDER
    return ORDER[kind]


def pick(preset=None, engine: Optional[str] = None, needs=(), platform: Optional[str] = None) -> Physics:
    """The physics to run for `preset` (name, path, `PhysicsPreset`, or a `Physics`, given back where it can do
    `needs`): `engine` where given (one of the preset's certified engines, or the preset's own engine; for a
    preset that certifies none, any engine: its own settings), else the fastest certified engine available on
    `platform` (default: JAX's default backend; `hexjax.sim.engines.ORDER`) that can do what the job `needs`
    (capabilities); where none is left, the preset's own settings on the fastest engine that can, said so in
    `why`. One ValueError line for an engine that is neither certified nor the preset's own, one that cannot do
    what the job needs, or one whose package is missing (with how to install it)."""
    from hexjax.sim.engines import ENGINES, get_engine, host_kind
    if isinstance(preset, Physics):
        lacks = preset.engine.lacks(needs)
        if (engine is None or get_engine(engine) is preset.engine) and not lacks:
            return preset
        preset = preset.preset
    p = get_physics(preset)
    table = {e[0]: e for e in p.engines}  # certified engines by the names the preset file gives them
    if engine:
        e = get_engine(engine)
        if p.engines and e.name not in table and e is not get_engine(p.engine):
            raise ValueError(f"engine={e.name!r}: physics {p.name!r} is certified on {', '.join(table)} only "
                             f"(its engines), or runs its own settings on {p.engine} (docs/physics.md)")
        lacks = e.lacks(needs)
        if lacks:
            raise ValueError(f"engine={e.name!r}: this job needs {' and '.join(lacks)}, which {e.title} does not "
                             f"give; engines that do: {', '.join(n for n, x in ENGINES.items() if not x.lacks(needs))}")
        why = "asked for (--engine)"
    else:
        kind = host_kind(platform)
        fits = [ENGINES[n] for n in _ordered(kind) if ENGINES[n].available() and not ENGINES[n].lacks(needs)]
        e = next((x for x in fits if x.name in table), None)
        if e is not None:
            why = f"the fastest certified engine on this {'CPU-only host' if kind == 'cpu' else 'GPU host'}"
            hint = _install_hint(table, kind, needs)
            if hint:
                why += f"; {hint}"
        else:
            e = get_engine(p.engine) if not get_engine(p.engine).lacks(needs) else fits[0]
            why = (f"the job needs {' and '.join(sorted(needs))}, which no certified engine gives" if needs and
                   p.engines else f"the {p.name} preset's own engine")
    if not e.available():
        raise ValueError(f"engine={e.name!r}: {e.title} is not installed here: {e.install}")
    _, settings_from, certs = table.get(e.name, (e.name, p.name, ()))
    settings = p.settings if settings_from == p.name else get_physics(settings_from).settings
    return Physics(p, e, settings, settings_from, tuple(certs), why)


def _install_hint(table, kind: str, needs) -> str:
    """On a GPU host, a faster certified engine that is not installed, and how to install it; else ''."""
    from hexjax.sim.engines import ENGINES
    for n in _ordered(kind):
        x = ENGINES[n]
        if n in table and not x.lacks(needs):
            return "" if x.available() else f"{x.title} would be faster here: {x.install}"
    return ""


def get_physics(name=None, /, **overrides) -> PhysicsPreset:
    """The `PhysicsPreset` of preset `name` (configs/physics/<name>.yaml; default `validated`) or of a YAML file
    path, with keys replaced by `overrides` (settings or preset keys, checked as the file's own). A
    `PhysicsPreset` is checked and given back (with `overrides`, which may rename it: `name=`). A file without
    `name` takes its file name."""
    if name is None:
        name = DEFAULT_PRESET
    if isinstance(name, Physics):
        name = name.preset
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
        base, source = _build(raw, str(path), _Head(name=path.stem), DEFAULT_SETTINGS), str(path)
    if not overrides:
        base.validate()
        return base
    head = _Head(base.name, base.summary, base.engine, base.engines)
    return _build(overrides, source, head, base.settings)


def _build(raw: Dict[str, Any], source: str, head: _Head, settings: PhysicsConfig) -> PhysicsPreset:
    """A `PhysicsPreset` from a file's (or overrides') flat keys: the settings' keys into one `PhysicsConfig`
    (on top of `settings`), the rest into the preset's own (on top of `head`); one ValueError line for an
    unknown key."""
    own = [f.name for f in dataclasses.fields(_Head)]
    unknown = [k for k in raw if k not in own and k not in SETTINGS]
    if unknown:
        k = unknown[0]
        near = {"backend": "engine"}.get(k) or next(iter(difflib.get_close_matches(str(k), own + list(SETTINGS),
                                                                                 n=1)), None)
        hint = f" (did you mean {near!r}?)" if near else ""
        raise ValueError(f"{source}: physics.{k}: unknown key{hint}; known keys: {', '.join(own + list(SETTINGS))}")
    cfg = build(PhysicsConfig, {k: v for k, v in raw.items() if k in SETTINGS}, source, "physics",
                defaults=dataclasses.asdict(settings))
    h = build(_Head, {k: v for k, v in raw.items() if k in own}, source, "physics", defaults=dataclasses.asdict(head))
    return PhysicsPreset(name=h.name, summary=h.summary, engine=h.engine, settings=cfg, engines=h.engines)


def timed_settings(preset: PhysicsPreset, engine: Optional[str]) -> Physics:
    """What `hexjax bench` times for `preset` on `engine`: a certified engine runs its certified settings (MuJoCo C
    the reference's for `validated`); any other engine the preset's own, said uncertified."""
    p = get_physics(preset)
    if engine in {e[0] for e in p.engines}:
        return pick(p, engine)
    from hexjax.sim.engines import get_engine
    e = get_engine(engine or p.engine)
    return Physics(p, e, p.settings, p.name, (), "timed on its own settings" if p.engines else
                   f"the {p.name} preset's own")
