"""Engines by job (`hexjax.sim.physics.pick`): `validated` is a contract that several engine/settings pairs meet;
a command runs the fastest certified one on its host that can do what the job needs, `--engine` picks another
certified one, gradients run MJX, every engine declares what it can do (`hexjax.sim.engines`), and every
certificate a preset names is a fidelity run that shows its pair within the contract."""

import json
from pathlib import Path

import jax
import pytest

from hexjax.control.registry import make_controller
from hexjax.sim.config import PhysicsConfig, RolloutConfig
from hexjax.sim.engines import ENGINES, GRADIENTS, MESH, RANGE_SENSORS, TRACES, get_engine
from hexjax.sim.physics import get_physics, pick
from hexjax.sim.rollout import make_mesh, resolve_physics
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import sample

ROOT = Path(__file__).resolve().parents[1]


def test_validated_runs_its_fastest_certified_engine_and_its_own_settings_where_the_job_needs_them():
    """On a CPU-only host `validated` runs MuJoCo C at the reference's settings, traces included. On a GPU host
    it takes the first certified engine of Warp, MJX, MuJoCo C (Warp only where installed). A job that needs
    gradients or a device mesh, or an --engine of the preset's own, runs the preset's own MJX settings and its
    record says they are not certified."""
    cpu = pick("validated", platform="cpu")
    ref = get_physics("reference")
    assert (cpu.engine.name, cpu.settings_from, cpu.name) == ("c", "reference", "validated") and cpu.certified
    assert cpu.settings == ref.settings
    assert cpu.record()["picked"].startswith("the fastest certified engine on this CPU-only host")
    assert pick("validated", needs={TRACES}, platform="cpu").engine.name == "c"  # the paper experiments' pick
    listed = [e[0] for e in get_physics("validated").engines]
    gpu = pick("validated", platform="gpu")
    assert gpu.engine.name == next(b for b in ("warp", "mjx", "c") if b in listed and ENGINES[b].available())
    for job in (dict(engine="mjx"), dict(needs={GRADIENTS}), dict(needs={MESH})):
        mjx = pick("validated", platform="cpu", **job)
        assert (mjx.engine.name, mjx.settings_from, mjx.settings.iterations, mjx.settings.cone) == (
            "mjx", "validated", 8, "elliptic")
        assert not mjx.certified and "not certified" in mjx.header(), mjx.header()
    # a range sensor is cast in the MJX family's control step: a certified one where one is
    sensed = pick("validated", needs={RANGE_SENSORS}, platform="cpu")
    assert sensed.engine.name == ("warp" if "warp" in listed and ENGINES["warp"].available() else "mjx")
    # a preset that lists no engines runs its own settings on whatever engine is asked for
    fast_c = pick("fast", "c")
    assert (fast_c.engine.name, fast_c.settings.iterations, fast_c.settings.cone) == ("c", 2, "pyramidal")


def test_engines_declare_what_they_can_do_and_a_job_is_refused_an_engine_that_cannot():
    """Each engine's capabilities as hexjax uses them; a job that needs one its engine lacks is one line."""
    assert get_engine("mjx").can == {GRADIENTS, MESH, RANGE_SENSORS, TRACES}
    assert get_engine("warp").can == {RANGE_SENSORS, TRACES} and get_engine("c").can == {TRACES}
    assert (get_engine("c").precision, get_engine("warp").precision) == ("float64", "float32")
    with pytest.raises(ValueError, match="engine='c': this job needs gradients, which MuJoCo C does not give"):
        pick("validated", "c", needs={GRADIENTS})
    with pytest.raises(ValueError, match="engine='tpu': use one of mjx, warp, c"):
        get_engine("tpu")


def test_the_header_names_the_contract_the_engine_and_the_settings_it_runs():
    line = pick("validated", platform="cpu").header()
    assert "\n" not in line and line.startswith("physics: validated on engine: c (MuJoCo C, certified;")
    assert "reference's settings: float64, 100 Newton iterations" in line and "every terrain box a geom" in line
    own = pick("validated", "mjx").header()
    assert "engine: mjx (MJX (JAX), not certified;" in own and "float32, 8 Newton iterations" in own
    assert "8 line-search steps" in own and "the terrain's own box slots a leg" in own


def test_an_uncertified_engine_and_an_empty_preset_are_refused_in_one_line(tmp_path):
    strict = tmp_path / "strict.yaml"
    strict.write_text("engine: mjx\nengines: [[c, reference, []]]\n")
    with pytest.raises(ValueError, match="engine='warp': physics 'strict' is certified on c only"):
        pick(str(strict), "warp")
    empty = tmp_path / "empty.yaml"
    empty.write_text("# nothing but a comment\n")
    with pytest.raises(ValueError, match="empty physics preset"):
        get_physics(str(empty))
    twice = tmp_path / "twice.yaml"
    twice.write_text("engine: mjx\nengines: [[mjx, validated, []], [mjx, fast, []]]\n")
    with pytest.raises(ValueError, match="engines\\[1\\]\\[0\\]='mjx': an engine listed twice"):
        get_physics(str(twice))
    old = tmp_path / "old.yaml"
    old.write_text("backend: mjx\n")
    with pytest.raises(ValueError, match="physics.backend: unknown key \\(did you mean 'engine'\\?\\)"):
        get_physics(str(old))


def test_a_rollout_without_physics_runs_validated_on_an_engine_that_can_run_the_call():
    """`hexjax.rollout`'s default physics is `validated` (the fastest certified engine here: MuJoCo C on a CPU),
    a `PhysicsConfig` runs MJX as given, and a call that needs gradients or a mesh gets MJX."""
    robot = get_robot("luneckas2020")
    ctrl = make_controller("gait", robot)
    flat = sample(get_terrain("flat"), jax.random.PRNGKey(0), 2)
    boxes = sample(get_terrain("high-large"), jax.random.PRNGKey(0), 2)
    here = pick("validated")
    phys, e = resolve_physics(None, None, boxes, ctrl, RolloutConfig(), None)
    assert e is here.engine and phys.iterations == here.settings.iterations and phys.cone == "elliptic"
    assert (phys.slots_per_leg, phys.torso_slots) == (2, 2)
    phys, _ = resolve_physics(None, None, flat, ctrl, RolloutConfig(), None)
    assert (phys.slots_per_leg, phys.torso_slots) == (0, 0)  # flat ground: no boxes to collide with
    for cfg, mesh in ((RolloutConfig(solver_grad="implicit"), None), (RolloutConfig(), make_mesh())):
        phys, e = resolve_physics("validated", None, boxes, ctrl, cfg, mesh)
        assert e.name == "mjx" and phys.iterations == 8, (cfg, e)
    raw = PhysicsConfig()
    assert resolve_physics(raw, None, boxes, ctrl, RolloutConfig(), None) == (raw, get_engine("mjx"))
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
    keys = ("timestep", "iterations", "ls_iterations", "tolerance", "cone", "impratio", "integrator")
    engine_of = lambda rec: rec.get("engine", rec.get("backend"))  # older records call it backend
    for name, settings, certs in preset.engines:
        if not certs:
            assert settings == "reference", (name, settings)
            continue
        cells = {}
        for i, cert in enumerate(certs):
            res = json.loads((ROOT / cert).read_text())
            ran = get_physics(settings).settings
            assert {k: res["physics"][k] for k in keys} == {k: getattr(ran, k) for k in keys}, cert
            assert engine_of(res["physics"]) == name, cert
            assert res["against"]["name"] == "reference" and engine_of(res["against"]) == "c", cert
            if i == 0:
                assert res["summary"]["rows"] == len(res["cells"]) >= 100, cert  # the whole matrix
            cells |= {(c["controller"], c["cell"]): c | {"from": cert} for c in res["cells"]}
        missed = [(k, c["from"]) for k, c in cells.items() if not (c["within"] or c["within_ci"])]
        assert not missed, missed
