"""Finding and checking YAML files: the presets folder (configs/), preset names, and a type-checked build
of a frozen dataclass from a mapping, every error one line naming the file, the key and the value.
Imports no JAX, so the command line can list and check presets at once (`hexjax.world.presets` builds the
robot and terrain specs from them)."""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import typing
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional

KINDS = {"robots": "robot preset", "terrains": "terrain preset", "experiments": "experiment",
         "commands": "command", "tune": "tune config", "sensors": "sensor preset",
         "physics": "physics preset", "params": "params preset"}


def config_dir() -> Path:
    """The presets folder: `HEXJAX_CONFIG_DIR` if set, else the one shipped with the package."""
    env = os.environ.get("HEXJAX_CONFIG_DIR")
    return Path(env) if env else Path(__file__).resolve().parent.parent / "configs"


def preset_names(kind: str) -> List[str]:
    """Sorted names of the presets of one kind (one of `KINDS`)."""
    if kind not in KINDS:
        raise ValueError(f"preset kind={kind!r}: choose one of {sorted(KINDS)}")
    return sorted(p.stem for p in (config_dir() / kind).glob("*.yaml"))


def is_path(name: str) -> bool:
    """A preset argument that names a file rather than a preset: it ends in .yaml / .yml or holds a '/'."""
    return str(name).endswith((".yaml", ".yml")) or os.sep in str(name)


def resolve(kind: str, name: str) -> Path:
    """The YAML file of preset `name` of `kind`, or `name` itself when it is a path."""
    if kind not in KINDS:
        raise ValueError(f"preset kind={kind!r}: choose one of {sorted(KINDS)}")
    if is_path(name):
        p = Path(name).expanduser()
        if not p.is_file():
            raise ValueError(f"{name}: no such file")
        return p
    p = config_dir() / kind / f"{name}.yaml"
    if not p.is_file():
        names = preset_names(kind)
        near = difflib.get_close_matches(str(name), names, n=1)
        hint = f" (did you mean {near[0]!r}?)" if near else ""
        raise ValueError(f"{KINDS[kind]} {name!r} unknown{hint}; choose one of {names} or give a .yaml path")
    return p


def read_yaml(path) -> Dict[str, Any]:
    """The mapping at the top of a YAML file; a missing file, a syntax error or another top level is one line."""
    import yaml
    try:
        with open(path) as f:
            raw = yaml.safe_load(f)
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise ValueError(f"{path}: a folder, not a YAML file") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text file (YAML is UTF-8 text)") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        raise ValueError(f"{path}: not valid YAML{where}: {getattr(err, 'problem', err)}") from None
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: expected a mapping of keys at the top level, got {type(raw).__name__}")
    return raw


def _type_name(t) -> str:
    return getattr(t, "__name__", str(t).replace("typing.", ""))


def check_value(where: str, value: Any, t) -> Any:
    """`value` checked against the annotation `t` (float, int, str, bool, Tuple[float, ...], Optional[...],
    Dict, Any) and converted (an int for a float, a list for a tuple). `where` ("file: key") heads the error."""
    origin, args = typing.get_origin(t), typing.get_args(t)
    if origin is typing.Union:  # Optional[X]
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return check_value(where, value, inner[0])
    if t is Any or t is object:
        return value
    if t is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{where}={value!r}: must be true or false")
        return value
    if t is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{where}={value!r}: must be a number")
        if not math.isfinite(value):
            raise ValueError(f"{where}={value!r}: must be a finite number")
        return float(value)
    if t is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{where}={value!r}: must be a whole number")
        return value
    if t is str:
        if not isinstance(value, str):
            raise ValueError(f"{where}={value!r}: must be a string")
        return value
    if origin in (tuple, typing.Tuple):
        n = None if (len(args) == 2 and args[1] is Ellipsis) else len(args)
        if not isinstance(value, (list, tuple)) or (n is not None and len(value) != n):
            raise ValueError(f"{where}={value!r}: must be a list of {n or 'some'} values")
        kinds = [args[0]] * len(value) if n is None else list(args)
        return tuple(check_value(f"{where}[{i}]", v, k) for i, (v, k) in enumerate(zip(value, kinds)))
    if origin in (dict, typing.Dict, Mapping):
        if not isinstance(value, dict):
            raise ValueError(f"{where}={value!r}: must be a mapping")
        return value
    raise TypeError(f"{where}: no check for type {_type_name(t)}")


def build(cls, raw: Mapping[str, Any], source: str, prefix: str, defaults: Optional[Mapping[str, Any]] = None):
    """An instance of the frozen dataclass `cls` from the mapping `raw` read from `source` (a file name, for
    errors): unknown keys are refused (with the nearest known key), every value is type-checked, absent keys
    take `defaults` then the dataclass's own defaults, and the result's `validate()` runs. Every error is
    one ValueError line "source: prefix.key=value: why"."""
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = [k for k in raw if k not in fields]
    if unknown:
        k = unknown[0]
        near = difflib.get_close_matches(str(k), list(fields), n=1)
        hint = f" (did you mean {near[0]!r}?)" if near else ""
        raise ValueError(f"{source}: {prefix}.{k}: unknown key{hint}; known keys: {', '.join(fields)}")
    values = dict(defaults or {})
    for k, v in raw.items():
        values[k] = check_value(f"{source}: {prefix}.{k}", v, hints[k])
    missing = [k for k, f in fields.items() if k not in values and f.default is dataclasses.MISSING
               and f.default_factory is dataclasses.MISSING]
    if missing:
        raise ValueError(f"{source}: {prefix}.{missing[0]}: required key missing")
    obj = cls(**values)
    try:
        obj.validate()
    except ValueError as err:
        raise ValueError(f"{source}: {err}") from None
    return obj


def replaced(obj, overrides: Mapping[str, Any], source: str, prefix: str):
    """The frozen dataclass instance `obj` with the keys of `overrides` replaced, each checked as a file's keys
    are (`build`: unknown keys, types, the result's `validate()`). A loader builds the file on its own first and
    then calls this, so a bad value in the file is refused even where an override would have replaced it."""
    own = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
    return build(type(obj), overrides, source, prefix, defaults=own)
