"""Presets as data: every robot, terrain, experiment and tuning preset is a YAML file under `configs/`.

    configs/robots/<name>.yaml       -> `RobotSpec`    (`get_robot`)
    configs/terrains/<name>.yaml     -> `TerrainSpec`  (`get_terrain`)
    configs/experiments/<name>.yaml  -> an experiment's options and fixed numbers (`hexjax.experiments`)
    configs/tune/<name>.yaml         -> `TuneConfig`   (`hexjax.tune.config`)

Wherever a preset name is taken, a path to a YAML file of one's own is taken too (`--robot my.yaml`).
The folder is found from the package itself (`hexjax/configs` links to the repository's `configs/`, and a
wheel carries a copy), so presets load from any working directory.

Every file is checked on load, before anything is traced: an unknown (misspelt) key, a value of the wrong
type, a non-finite number, or a value the spec's own `validate()` refuses raises one ValueError line that
names the file, the key and the value.
"""

from __future__ import annotations

import os

from hexjax.world.files import build, read_yaml, replaced, resolve
from hexjax.world.robot import RobotSpec
from hexjax.world.terrain import TerrainSpec


def _named(kind: str, name, spec_type) -> None:
    if not isinstance(name, (str, os.PathLike)):
        raise ValueError(f"{kind}={name!r}: give a preset name, a .yaml path or a {spec_type.__name__}")


def get_robot(name) -> RobotSpec:
    """`RobotSpec` of preset `name` (configs/robots/<name>.yaml) or of a YAML file path. A file without
    `name` takes its file name. A `RobotSpec` is checked and given back."""
    if isinstance(name, RobotSpec):
        name.validate()
        return name
    _named("robot", name, RobotSpec)
    path = resolve("robots", name)
    return build(RobotSpec, read_yaml(path), str(path), "robot", defaults={"name": path.stem})


def get_terrain(name: str | TerrainSpec, **overrides) -> TerrainSpec:
    """`TerrainSpec` of preset `name` (configs/terrains/<name>.yaml) or of a YAML file path, with keys
    replaced by `overrides` (checked like the file's own). A `difficulty` key sets the keys its family scales
    (`hexjax.world.terrain.DIFFICULTY`; lengths for the Luneckas 2020 robot), over any the file writes.
    A `TerrainSpec` is taken as it is (its difficulty already applied), with `overrides` replaced.
    A file is checked on its own first, so a bad value in it is refused even where an override (such as the
    `length` that `hexjax evaluate` sets) would have replaced it."""
    if isinstance(name, TerrainSpec):
        base, source, scale = name, "TerrainSpec", "difficulty" in overrides
    else:
        _named("terrain", name, TerrainSpec)
        path = resolve("terrains", name)
        base, source, scale = build(TerrainSpec, read_yaml(path), str(path), "terrain"), str(path), True
    spec = replaced(base, overrides, source, "terrain")
    if scale and spec.difficulty is not None:  # the family's scaled keys set from it (`TerrainSpec.at_difficulty`)
        spec = spec.at_difficulty(spec.difficulty)
    return spec


def luneckas2020() -> RobotSpec:
    """The 18-DOF hexapod of Luneckas 2020 Sect. 2.1 (configs/robots/luneckas2020.yaml)."""
    return get_robot("luneckas2020")


def yu2019() -> RobotSpec:
    """The virtual hexapod of Yu 2019 Table 3 (configs/robots/yu2019.yaml)."""
    return get_robot("yu2019")


def chen2019() -> RobotSpec:
    """A hexapod sized for the rugged patch of Chen 2019 Sect. 3.1 (configs/robots/chen2019.yaml)."""
    return get_robot("chen2019")
