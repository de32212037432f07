"""Engines by job (`hexjax.sim.physics.pick_engine`): `validated` is a contract that several engine/settings pairs
meet; an evaluation runs the fastest certified one on its host, `--backend` picks another certified one, gradients
run MJX, and every certificate a preset names is a fidelity run that shows its pair within the contract."""

import dataclasses
import json
from pathlib import Path

import jax
import numpy as np
import pytest

from hexjax.control.registry import make_controller
from hexjax.sim.config import PhysicsConfig, RolloutConfig
from hexjax.sim.physics import engine_available, get_physics, pick_engine
from hexjax.sim.rollout import make_mesh, resolve_physics
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import sample

ROOT = Path(__file__).resolve().parents[1]


def test_validated_runs_its_fastest_certified_engine_and_its_own_settings_where_the_job_needs_them():
    """On a CPU-only host `validated` evaluates on MuJoCo C at the reference's settings. On a GPU host it takes the
    first certified engine of Warp, MJX, MuJoCo C (Warp only where installed). A job that only MJX can run
    (gradients, `exclude`), or a --backend of the preset's own engine, runs the preset's own MJX settings and its
    record says they are not certified where no certificate lists them."""
    cpu = pick_engine("validated", platform="cpu")
    ref = get_physics("reference")
    assert (cpu.backend, cpu.settings, cpu.preset.name) == ("c", "reference", "validated")
    assert all(getattr(cpu.preset, k) == getattr(ref, k) for k in ("iterations", "ls_iterations", "tolerance", "cone"))
    assert cpu.record()["engine"]["picked"].startswith("the fastest certified engine on this CPU-only host")
    listed = [e[0] for e in get_physics("validated").engines]
    gpu = pick_engine("validated", platform="gpu")
    assert gpu.backend == next(b for b in ("warp", "mjx", "c") if b in listed and (b != "warp" or engine_available(b)))
    for job in (dict(backend="mjx"), dict(exclude={"c", "warp"})):
        mjx = pick_engine("validated", platform="cpu", **job)
        assert (mjx.backend, mjx.settings, mjx.preset.iterations, mjx.preset.cone) == ("mjx", "validated", 8,
                                                                                     "elliptic")
        assert ("not certified" in mjx.why or "no certificate" in mjx.why) == ("mjx" not in listed), mjx.why
    # a preset that lists no engines runs its own settings on whatever engine is asked for
    fast_c = pick_engine("fast", "c")
    assert (fast_c.backend, fast_c.preset.iterations, fast_c.preset.cone) == ("c", 2, "pyramidal")


def test_an_uncertified_engine_and_an_empty_preset_are_refused_in_one_line(tmp_path):
    uncertified = next((b for b in ("warp", "c") if b not in {e[0] for e in get_physics("validated").engines}), None)
    if uncertified is not None:
        with pytest.raises(ValueError, match=f"backend='{uncertified}': physics 'validated' is certified on"):
            pick_engine("validated", uncertified)
    empty = tmp_path / "empty.yaml"
    empty.write_text("# nothing but a comment\n")
    with pytest.raises(ValueError, match="empty physics preset"):
        get_physics(str(empty))
    twice = tmp_path / "twice.yaml"
    twice.write_text("backend: mjx\nengines: [[mjx, validated, []], [mjx, fast, []]]\n")
    with pytest.raises(ValueError, match="engines\\[1\\]\\[0\\]='mjx': an engine listed twice"):
        get_physics(str(twice))


def test_a_rollout_without_physics_runs_validated_on_an_engine_that_can_run_the_call():
    """`hexjax.rollout`'s default physics is `validated` (the fastest certified engine here: MuJoCo C on a CPU),
    a `PhysicsConfig` runs MJX as given, and a call that needs MJX (gradients, a mesh) or its traces gets it."""
    robot = get_robot("luneckas2020")
    ctrl = make_controller("gait", robot)
    flat = sample(get_terrain("flat"), jax.random.PRNGKey(0), 2)
    boxes = sample(get_terrain("high-large"), jax.random.PRNGKey(0), 2)
    here = pick_engine("validated")
    phys, be = resolve_physics(None, None, boxes, ctrl, RolloutConfig(), None)
    assert be == here.backend and phys.iterations == here.preset.iterations and phys.cone == "elliptic"
    assert (phys.slots_per_leg, phys.torso_slots) == (2, 2)
    phys, _ = resolve_physics(None, None, flat, ctrl, RolloutConfig(), None)
    assert (phys.slots_per_leg, phys.torso_slots) == (0, 0)  # flat ground: no boxes to collide with
    for cfg, mesh in ((RolloutConfig(solver_grad="implicit"), None), (RolloutConfig(), make_mesh()),
                      (RolloutConfig(record=True), None)):
        phys, be = resolve_physics("validated", None, boxes, ctrl, cfg, mesh)
        assert be in (("mjx", "warp") if cfg.record else ("mjx",)) and phys.iterations == 8, (cfg, be)
    raw = PhysicsConfig()
    assert resolve_physics(raw, None, boxes, ctrl, RolloutConfig(), None) == (raw, "mjx")
    with pytest.raises(ValueError, match="physics=3"):
        resolve_physics(3, None, boxes, ctrl, RolloutConfig(), None)


@pytest.mark.parametrize("name", ["validated"])
def test_every_certificate_shows_its_engine_within_the_contract(name):
    """Each engine a preset certifies with fidelity JSONs: each run tested the same engine and settings against
    `reference`, the first covers the whole matrix, and every cell (as the last run that has it found it: a cell
    re-run with more envs) is within the contract or has a paired 95 % interval that meets the band
    (docs/physics.md). The reference itself needs none."""
    preset = get_physics(name)
    assert preset.engines
    keys = ("backend", "timestep", "iterations", "ls_iterations", "tolerance", "cone", "impratio", "integrator")
    for backend, settings, certs in preset.engines:
        if not certs:
            assert settings == "reference", (backend, settings)
            continue
        cells = {}
        for i, cert in enumerate(certs):
            res = json.loads((ROOT / cert).read_text())
            ran = get_physics(settings).record(backend)
            assert {k: res["physics"][k] for k in keys} == {k: ran[k] for k in keys}, cert
            assert res["against"]["name"] == "reference" and res["against"]["backend"] == "c", cert
            if i == 0:
                assert res["summary"]["rows"] == len(res["cells"]) >= 100, cert  # the whole matrix
            cells |= {(c["controller"], c["cell"]): c | {"from": cert} for c in res["cells"]}
        missed = [(k, c["from"]) for k, c in cells.items() if not (c["within"] or c["within_ci"])]
        assert not missed, missed
