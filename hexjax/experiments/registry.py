"""The registry of what `hexjax` runs: paper experiments (configs/experiments/*.yaml) and commands
(configs/commands/*.yaml), each a YAML file of data. Reading it imports no JAX, so `hexjax --help` and
`hexjax experiment --list` answer at once.

A file holds:
    summary: one line for `--list` and `--help`
    paper:   the paper it reproduces ("Luneckas 2020"), experiments only
    entry:   the module that runs it; it defines run(opts, entry) -> result dict, report(result) -> str and,
             where it draws, plot(result, png_path) -> [written paths]
    options: the command-line flags, each {default, help} and optionally choices, a preset kind (robots,
             terrains, tune, sensors: a preset name or a .yaml path), the suffixes of an output file or of an input
             file that must exist, or `repeat` (the
             flag may be given several times), and for a number the bounds `min`, `max` (inclusive), `above`,
             `below` (exclusive), checked as the arguments parse; the type is the default's or `type`'s (a list
             default takes a comma list, each item checked; a false default is a switch)
    preset:  the experiment's fixed numbers (terrains, variants, durations): a copy with other numbers is a
             new experiment, `hexjax experiment path/to/my.yaml`
    physics_by: where it has a `physics` option, who turns the preset into an engine and settings: `runner` (the
             runner picks the fastest certified engine on this host, or --engine's, prints it and hands the command
             the chosen preset) or `command` (the command reads its presets itself: bench times each one it lists,
             fidelity holds one against another)
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

from hexjax.world.files import preset_names, read_yaml, resolve

BOUND_KEYS = ("min", "max", "above", "below")
OPTION_KEYS = {"default", "help", "choices", "preset", "output", "input", "type", "repeat", *BOUND_KEYS}
TYPES = {"int": int, "float": float, "str": str}


@dataclasses.dataclass(frozen=True)
class Option:
    """One command-line flag: `--name` (dashes for underscores) with its default and help; `preset`: the
    preset kind its value names; `output`: the file suffixes it may end in; `input`: those of a file that must
    exist (each checked before any work)."""

    name: str
    default: Any
    help: str = ""
    choices: Optional[Tuple[Any, ...]] = None
    preset: Optional[str] = None
    output: Optional[Tuple[str, ...]] = None
    input: Optional[Tuple[str, ...]] = None
    type: Optional[str] = None
    repeat: bool = False
    min: Optional[float] = None
    max: Optional[float] = None
    above: Optional[float] = None
    below: Optional[float] = None

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    @property
    def value_type(self):
        """The type of one value (a list option's items): the `type` key, else the default's."""
        if self.type:
            return TYPES[self.type]
        d = self.default[0] if isinstance(self.default, list) and self.default else self.default
        return type(d) if isinstance(d, (int, float, str)) and not isinstance(d, bool) else str

    def bounds_text(self) -> str:
        """The option's range in words ('>= 1', '> 0', 'in (0, 20]'), or '' when it has none."""
        lo = hi = None  # (bound, inclusive)
        if self.min is not None or self.above is not None:
            lo = (self.min, True) if self.min is not None else (self.above, False)
        if self.max is not None or self.below is not None:
            hi = (self.max, True) if self.max is not None else (self.below, False)
        if lo and hi:
            return f"in {'[' if lo[1] else '('}{_num(lo[0])}, {_num(hi[0])}{']' if hi[1] else ')'}"
        if lo:
            return f"{'>=' if lo[1] else '>'} {_num(lo[0])}"
        if hi:
            return f"{'<=' if hi[1] else '<'} {_num(hi[0])}"
        return ""

    def check_value(self, v):
        """`v` (one parsed value of a number option), or one ValueError line saying why not: a float must be
        finite, and every value must lie within the option's bounds."""
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"{v}: must be a finite number")
        if isinstance(v, (int, float)):
            low_bad = (self.min is not None and v < self.min) or (self.above is not None and v <= self.above)
            high_bad = (self.max is not None and v > self.max) or (self.below is not None and v >= self.below)
            if low_bad or high_bad:
                raise ValueError(f"{_num(v)}: must be {self.bounds_text()}")
        return v


def _num(x) -> str:
    """A bound or value as written: 1 rather than 1.0."""
    return str(int(x)) if isinstance(x, float) and x.is_integer() and abs(x) < 1e15 else str(x)


@dataclasses.dataclass(frozen=True)
class Entry:
    """A registered experiment or command (see the module docstring)."""

    name: str
    summary: str
    entry: str
    options: Tuple[Option, ...]
    preset: Dict[str, Any]
    paper: str = ""
    path: str = ""
    physics_by: str = ""  # "runner", "command", or "" (no physics option)


def _option(source: str, name: str, spec) -> Option:
    if not isinstance(spec, dict):
        spec = {"default": spec}
    unknown = set(spec) - OPTION_KEYS
    if unknown:
        raise ValueError(f"{source}: options.{name}: unknown keys {sorted(unknown)}; known: {sorted(OPTION_KEYS)}")
    if "default" not in spec:
        raise ValueError(f"{source}: options.{name}: needs a default")
    if spec.get("type") not in (None, *TYPES):
        raise ValueError(f"{source}: options.{name}.type={spec['type']!r}: use one of {sorted(TYPES)}")
    pk = spec.get("preset")
    if pk is not None and pk not in ("robots", "terrains", "tune", "sensors", "physics", "params"):
        raise ValueError(f"{source}: options.{name}.preset={pk!r}: use robots, terrains, tune, sensors, physics or "
                         "params")
    out, inp = spec.get("output"), spec.get("input")
    bounds = {k: spec[k] for k in BOUND_KEYS if spec.get(k) is not None}
    for k, b in bounds.items():
        if isinstance(b, bool) or not isinstance(b, (int, float)) or not math.isfinite(b):
            raise ValueError(f"{source}: options.{name}.{k}={b!r}: a bound must be a finite number")
    opt = Option(name=name, default=spec["default"], help=str(spec.get("help", "")),
                 choices=tuple(spec["choices"]) if spec.get("choices") is not None else None, preset=pk,
                 output=tuple(out) if out else None, input=tuple(inp) if inp else None, type=spec.get("type"),
                 repeat=bool(spec.get("repeat", False)), **bounds)
    if bounds and opt.value_type not in (int, float):
        raise ValueError(f"{source}: options.{name}: bounds {sorted(bounds)} need a number option (its default or "
                         "`type` int or float)")
    if ("min" in bounds and "above" in bounds) or ("max" in bounds and "below" in bounds):
        raise ValueError(f"{source}: options.{name}: give min or above, and max or below, not both")
    defaults = opt.default if isinstance(opt.default, list) else [opt.default]
    for d in defaults:
        if d is not None:
            try:
                opt.check_value(d)
            except ValueError as err:
                raise ValueError(f"{source}: options.{name}.default={d!r} is outside its own bounds ({err})") from None
    return opt


def load_entry(path: Path, kind: str) -> Entry:
    """The entry of one registry file; `kind` is 'experiments' or 'commands' (commands carry no paper)."""
    raw = read_yaml(path)
    source = str(path)
    known = {"summary", "paper", "entry", "options", "preset", "physics_by"}
    unknown = set(raw) - known
    if unknown:
        raise ValueError(f"{source}: unknown keys {sorted(unknown)}; known: {sorted(known)}")
    for k in ("summary", "entry"):
        if not isinstance(raw.get(k), str) or not raw[k]:
            raise ValueError(f"{source}: {k}: a non-empty string is required")
    if kind == "experiments" and not raw.get("paper"):
        raise ValueError(f"{source}: paper: name the paper the experiment reproduces (e.g. 'Yu 2019')")
    opts = raw.get("options") or {}
    preset = raw.get("preset") or {}
    if not isinstance(opts, dict) or not isinstance(preset, dict):
        raise ValueError(f"{source}: options and preset must be mappings")
    by = raw.get("physics_by", "")
    if "physics" in opts and by not in ("runner", "command"):
        raise ValueError(f"{source}: physics_by={by!r}: an entry with a physics option says who picks its engine: "
                         "runner or command")
    if "physics" not in opts and by:
        raise ValueError(f"{source}: physics_by={by!r}: the entry has no physics option")
    return Entry(name=path.stem, summary=raw["summary"], entry=raw["entry"], paper=str(raw.get("paper", "")),
                 options=tuple(_option(source, k, v) for k, v in opts.items()), preset=preset, path=source,
                 physics_by=by)


def experiments() -> Dict[str, Entry]:
    """Every registered paper experiment, by name (configs/experiments/*.yaml)."""
    return {n: load_entry(resolve("experiments", n), "experiments") for n in preset_names("experiments")}


def experiment(name: str) -> Entry:
    """One experiment: a registered name or a path to a YAML file of the same form."""
    return load_entry(resolve("experiments", name), "experiments")


def commands() -> Dict[str, Entry]:
    """The commands besides `experiment` (configs/commands/*.yaml), by name."""
    return {n: load_entry(resolve("commands", n), "commands") for n in preset_names("commands")}
