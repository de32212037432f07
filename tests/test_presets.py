"""Presets as data (configs/): every robot, terrain, experiment and command loads from YAML, from any working
directory; a file of one's own works wherever a preset name does; a bad file fails in one line that names the
file, the key and the value."""

import json
import os
import subprocess
import sys

import pytest
import yaml

from hexjax.cli import main
from hexjax.experiments.registry import commands, experiments
from hexjax.world.files import config_dir, preset_names, read_yaml, resolve
from hexjax.world.presets import get_robot, get_terrain


def test_shipped_presets_load_with_the_papers_numbers():
    assert preset_names("robots") == ["chen2019", "luneckas2020", "yu2019"]
    assert len(preset_names("terrains")) == 18 and len(preset_names("tune")) >= 2
    # the benchmark families load at their shipped difficulty (0.5): a 4.5 cm riser, 2.5 cm gaps, 0.3 rad ramps
    assert get_terrain("stairs-up").height_range == pytest.approx((0.045, 0.045))
    assert get_terrain("stones").gap_range == pytest.approx((0.025, 0.025))
    assert get_terrain("slope-down").slope_range == pytest.approx((0.3, 0.3)) and get_terrain("slope-down").direction == "down"
    lun, yu = get_robot("luneckas2020"), get_robot("yu2019")
    # Luneckas 2020 Sect. 2.1: coxa 5 cm, femur 8.2 cm, tibia 12 cm, 1.5 kg; Yu 2019 Table 3: 50/120/150 mm
    assert (lun.coxa_length, lun.femur_length, lun.tibia_length, lun.total_mass) == (0.05, 0.082, 0.12, 1.5)
    assert (yu.coxa_length, yu.femur_length, yu.tibia_length, yu.body_length) == (0.05, 0.12, 0.15, 0.25)
    assert get_terrain("ditch40").height_range == (0.04, 0.04) and get_terrain("waves").height_range[1] == 0.178
    assert get_terrain("high-large", length=2.3).length == 2.3  # overrides are checked like the file's keys
    for name in preset_names("robots"):
        get_robot(name).validate()
    assert set(experiments()) >= {"luneckas2020", "yu2019-step", "yu2019-ditch", "zhao2018", "zhao2018-mjx",
                                  "zhao2018-perception", "chen2019", "chen2019-incenter", "chen2019-perception"}
    assert set(commands()) == {"evaluate", "bench", "tune", "render", "ppo", "terrain", "robustness", "perceive", "fidelity",
                              "families"}
    # Zhao 2018 Sect. 5: Kinect V1 57 x 43 deg, 0.8-4.0 m; Velodyne PUCK 360 x 30 deg, up to 100 m
    from hexjax.perceive.sensors import get_sensor
    kin, puck = get_sensor("kinect_v1"), get_sensor("velodyne_puck")
    assert (kin.kind, kin.fov_h, kin.fov_v, kin.range_min, kin.range_max) == ("camera", 57.0, 43.0, 0.8, 4.0)
    assert (puck.kind, puck.fov_h, puck.fov_v, puck.range_max) == ("lidar", 360.0, 30.0, 100.0)
    for name in preset_names("sensors"):
        get_sensor(name).validate(lun)


def test_presets_are_found_from_any_working_directory(tmp_path):
    code = ("from hexjax.world.presets import get_robot, get_terrain\n"
            "from hexjax.experiments.registry import experiments\n"
            "print(get_robot('yu2019').kp, get_terrain('step40').kind, len(experiments()))")
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                       env={**os.environ, "HEXJAX_CACHE_DIR": "off"})
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == ["60.0", "step", str(len(experiments()))]
    assert config_dir().is_dir() and (config_dir() / "robots" / "yu2019.yaml").is_file()


def _write(tmp_path, name, doc):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(doc))
    return str(p)


@pytest.mark.parametrize("change,match", [
    ({"coxa_lenght": 0.05}, r"robot.coxa_lenght: unknown key \(did you mean 'coxa_length'\?\)"),
    ({"femur_length": -0.082}, r"robot.femur_length=-0.082: must be a finite number > 0"),
    ({"tibia_length": "long"}, r"robot.tibia_length='long': must be a number"),
    ({"tibia_length": 120.0}, r"robot.tibia_length=120.0: must be at most 2.0 m"),
    ({"coxa_range": [1.2, -1.2]}, r"robot.coxa_range=\(1.2, -1.2\): min must be < max"),
    ({"kp": float("nan")}, r"robot.kp=nan: must be a finite number"),
    ({"femur_range": [0.1, 0.2, 0.3]}, r"robot.femur_range=\[0.1, 0.2, 0.3\]: must be a list of 2 values"),
])
def test_a_bad_robot_file_fails_in_one_line_naming_file_key_and_value(tmp_path, change, match):
    doc = {**read_yaml(resolve("robots", "luneckas2020")), **change}
    path = _write(tmp_path, "my_robot.yaml", doc)
    with pytest.raises(ValueError, match=match) as e:
        get_robot(path)
    msg = str(e.value)
    assert msg.startswith(path + ": ") and "\n" not in msg


def test_a_bad_terrain_file_and_bad_names(tmp_path):
    doc = {**read_yaml(resolve("terrains", "high-small")), "height_range": [0.05, 0.03]}
    path = _write(tmp_path, "t.yaml", doc)
    with pytest.raises(ValueError, match=r"t.yaml: terrain.height_range=\(0.05, 0.03\): min must be <= max"):
        get_terrain(path)
    bad_length = _write(tmp_path, "t.yaml", {**doc, "height_range": [0.03, 0.05], "length": -1.0})
    with pytest.raises(ValueError, match=r"t.yaml: terrain.length=-1.0: must be a finite number > 0"):
        get_terrain(bad_length)
    # also where the command replaces the key (`evaluate --categories t.yaml` ran, its length set from --distance)
    with pytest.raises(ValueError, match=r"t.yaml: terrain.length=-1.0: must be a finite number > 0"):
        get_terrain(bad_length, length=1.3)
    with pytest.raises(ValueError, match=r"terrain preset 'hihg-small' unknown \(did you mean 'high-small'\?\)"):
        get_terrain("hihg-small")
    with pytest.raises(ValueError, match="nowhere.yaml: no such file"):
        get_robot(str(tmp_path / "nowhere.yaml"))
    (tmp_path / "broken.yaml").write_text("kind: [flat\n")
    with pytest.raises(ValueError, match=r"broken.yaml: not valid YAML \(line"):
        get_terrain(str(tmp_path / "broken.yaml"))


def test_specs_built_in_python_are_taken_where_names_are():
    """`HexapodGoalEnv(robot=RobotSpec(...))` had looked for a file named after the spec's repr."""
    import dataclasses
    robot, stairs = get_robot("luneckas2020"), get_terrain("stairs-up")
    assert get_robot(robot) is robot and get_terrain(stairs) == stairs
    assert get_terrain(stairs, difficulty=0.5) == get_terrain("stairs-up", difficulty=0.5)
    for call, match in ((lambda: get_robot(3), r"^robot=3: give a preset name, a .yaml path or a RobotSpec$"),
                        (lambda: get_terrain(None), r"^terrain=None: give a preset name"),
                        (lambda: get_terrain(stairs, lenght=1.0),
                         r"^TerrainSpec: terrain.lenght: unknown key \(did you mean 'length'\?\)"),
                        (lambda: get_terrain(stairs, length=-1.0),
                         r"^TerrainSpec: terrain.length=-1.0: must be a finite number"),
                        (lambda: get_terrain(stairs, length="long"), r"^TerrainSpec: terrain.length='long': must be"),
                        (lambda: get_robot(dataclasses.replace(robot, total_mass=-1.0)), r"^robot.total_mass=-1.0")):
        with pytest.raises(ValueError, match=match):
            call()


def test_own_robot_and_terrain_files_work_in_the_cli(tmp_path, capsys):
    """`--robot my.yaml` and a terrain file of one's own in `--categories`: a longer-legged Luneckas robot on
    a denser field, evaluated (MuJoCo C physics, so no MJX program is compiled for the new robot)."""
    robot = {**read_yaml(resolve("robots", "luneckas2020")), "name": "long_legs", "tibia_length": 0.13}
    terrain = {**read_yaml(resolve("terrains", "high-small")), "height_range": [0.01, 0.02]}
    rp, tp = _write(tmp_path, "long_legs.yaml", robot), _write(tmp_path, "low_bumps.yaml", terrain)
    out = tmp_path / "ev.json"
    assert main(["evaluate", "--robot", rp, "--categories", f"flat,{tp}", "--batch", "2", "--distance", "0.3",
                 "--engine", "c", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["config"]["robot"] == "long_legs" and set(res["categories"]) == {"flat", tp}
    for stats in res["categories"].values():
        assert stats["nan"] == 0 and stats["advance_m"] > 0.15
    capsys.readouterr()
    bad = _write(tmp_path, "bad.yaml", {**robot, "kp": -1})
    assert main(["evaluate", "--robot", bad, "--batch", "2", "--engine", "c"]) == 2
    err = capsys.readouterr().err
    assert "bad.yaml: robot.kp=-1.0: must be a finite number > 0" in err and err.count("\n") == 1


# derived tuning configs: each is its base config but for the keys named here (a change to the base that a copy
# misses fails the test below)
DERIVED_TUNE_CONFIGS = {
    # the gradient recipe of docs/tuning.md; gradients train on the pyramidal cone the implicit gradient needs
    "cpg_step_ditch_grad": ("cpg_step_ditch", {
        "gates": "straight_through", "window": 2.0, "grad_clip": 10.0, "backward": "parallel", "steps": 16,
        "eval_every": 2, "optimizer": {"name": "sgd", "learning_rate": 0.2, "decay_to": 0.1},
        "train_physics": None, "solver_iterations": 4, "solver_grad": "implicit"}),
    # the runs that made the shipped params presets of the same names (docs/results.md, "Tuned presets")
    "cpg_step_ditch_grad_gpu": ("cpg_step_ditch_grad", {
        "train_batch": 64, "held_out_batch": 320, "validation_batch": 160, "eval_every": 4}),
    "cpg_step_ditch_gpu": ("cpg_step_ditch", {
        "train_batch": 128, "held_out_batch": 320, "validation_batch": 160, "steps": 64, "eval_every": 64}),
    "tactile_tripod_es": ("tactile_tripod", {
        "train_physics": "validated", "held_out_batch": 64, "validation_batch": 32, "steps": 48, "eval_every": 48}),
    "tactile_tripod_forward": ("tactile_tripod", {"backward": "forward", "solver_grad": "implicit", "grad_clip": None}),
    # the races of docs/tuning.md, "The race on one GPU": a GPU's batch, judged on the host's certified engine
    "cpg_reflex_grad_gpu": ("cpg_reflex_grad", {
        "train_batch": 64, "held_out_batch": 320, "validation_batch": 160, "eval_every": 4}),
    "cpg_legs_gpu": ("cpg_legs", {
        "train_batch": 64, "held_out_batch": 320, "validation_batch": 160, "es_rollouts": "certified",
        "eval_engine": "certified"}),
    # the layer's gradient trained on validated, by SGD in steps as long as the gradient holds for
    "cpg_reflex_grad_validated": ("cpg_reflex_grad", {
        "train_physics": "validated", "solver_iterations": None, "eval_every": 4,
        "optimizer": {"name": "sgd", "learning_rate": 0.05}}),
    "cpg_reflex_grad_validated_gpu": ("cpg_reflex_grad_gpu", {
        "train_physics": "validated", "solver_iterations": None, "optimizer": {"name": "sgd", "learning_rate": 0.05}}),
}


@pytest.mark.parametrize("name", sorted(DERIVED_TUNE_CONFIGS))
def test_derived_tune_configs_are_their_base_with_the_named_keys(name):
    import dataclasses

    from hexjax.tune.config import load_tune_config

    base, keys = DERIVED_TUNE_CONFIGS[name]
    assert dataclasses.asdict(load_tune_config(name)) == dataclasses.asdict(load_tune_config(base, keys, merge=True))


@pytest.mark.parametrize("config, preset", [("cpg_step_ditch_gpu", "cpg_step_ditch_es"),
                                            ("tactile_tripod_es", "tactile_tripod_es")])
def test_a_shipped_es_preset_records_the_run_of_its_config(config, preset):
    """The preset's `made_by` matches its config's CMA-ES run (held-out batch, rollout budget, training
    physics), and that config continues the same checkpoint as a run given its budget by flags (the digest
    leaves out the step count and the evaluation period)."""
    import dataclasses

    from hexjax.tune.config import load_tune_config
    from hexjax.tune.driver import config_digest

    cfg = load_tune_config(config)
    made = read_yaml(resolve("params", preset))["made_by"]
    assert made["held_out_batch"] == cfg.held_out_batch
    assert made["rollouts"] == cfg.steps * cfg.train_batch
    assert made["train_physics"] == cfg.train_physics
    method = f"es{cfg.es_population}"
    assert config_digest(cfg, method) == config_digest(dataclasses.replace(cfg, steps=20, eval_every=100), method)


def test_shipped_params_presets_load_by_name_into_their_controller():
    """Every configs/params/*.yaml (tuned params, `hexjax tune`'s params.yaml) loads by name and sets its
    controller's params to its values; each says how it was judged (held-out objective on validated physics)."""
    import jax
    import numpy as np

    from hexjax.control.registry import CONTROLLERS, make_controller
    from hexjax.tune.space import load_values, with_values

    names = preset_names("params")
    assert names, "no params preset shipped"
    for name in names:
        doc = read_yaml(resolve("params", name))
        robot = get_robot(CONTROLLERS[doc["controller"]].robot)
        p0 = make_controller(doc["controller"], robot, gait=doc["gait"]).default_params()
        p = with_values(p0, load_values(name))
        for k, v in doc["values"].items():  # a field, or a tree of them (a reflex layer's weights)
            got = jax.tree_util.tree_leaves(getattr(p, k))
            arrays = jax.tree_util.tree_map(np.asarray, v, is_leaf=lambda x: isinstance(x, list))
            want = jax.tree_util.tree_leaves(arrays)
            assert len(got) == len(want), name
            for got, want in zip(got, want):
                np.testing.assert_allclose(np.asarray(got), np.asarray(want, np.float32), rtol=1e-6, err_msg=name)
        made = doc["made_by"]
        assert made["eval_physics"] == "validated", name
        assert made["held_out_objective"] <= made["start_held_out_objective"], name


def test_the_shipped_gradient_preset_records_the_run_of_its_config():
    """cpg_step_ditch_grad's `made_by` matches cpg_step_ditch_grad_gpu: its held-out batch, the rollouts of the
    picked step at that config's batch, and a training step count within the config's."""
    from hexjax.tune.config import load_tune_config

    cfg = load_tune_config("cpg_step_ditch_grad_gpu")
    made = read_yaml(resolve("params", "cpg_step_ditch_grad"))["made_by"]
    assert made["method"] == "grad" and made["held_out_batch"] == cfg.held_out_batch
    assert made["rollouts"] == made["step"] * cfg.train_batch and 0 < made["step"] <= cfg.steps
    assert made["train_physics"] == cfg.train_physics
