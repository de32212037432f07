"""Per-env randomisation of dynamics, sensing and faults (`hexjax.world.randomization`, `hexjax.sim.perturb`):
the ranges are checked before anything is traced, draws reproduce from their seed, and each perturbation
does to the MJX robot what it should, measured in one batched rollout (one compiled program)."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.control.tactile import TactileGaitController
from hexjax.sim.config import PhysicsConfig, RolloutConfig
from hexjax.sim.rollout import rollout
from hexjax.world.presets import luneckas2020
from hexjax.world.randomization import (RandomizationSpec, concat_perturbations, randomization_from_dict,
                                        sample_perturbation)
from hexjax.world.terrain import Terrain


@pytest.mark.parametrize("raw, msg", [
    ({"friction": [0.2, 0.9], "frcition": 1.0}, "randomization.frcition: unknown key (did you mean 'friction'?)"),
    ({"payload_kg": [0.5, 0.1]}, "randomization.payload_kg=[0.5, 0.1]: low > high"),
    ({"force_dropout": 1.5}, "randomization.force_dropout=[1.5, 1.5]: must lie in [0, 1] (probability)"),
    ({"fault": {"kind": "locked", "probability": -0.1}}, "randomization.fault.probability=-0.1: must be in [0, 1]"),
    ({"fault": {"kind": "broken"}}, "randomization.fault.kind='broken'"),
    ({"latency_steps": [0, 2.5]}, "randomization.latency_steps=[0.0, 2.5]: whole control steps"),
    ({"kp_scale": "big"}, "randomization.kp_scale='big': must be a list of 2 values"),
])
def test_bad_ranges_fail_in_one_line_naming_the_key(raw, msg):
    with pytest.raises(ValueError) as err:
        randomization_from_dict(raw, source="my.yaml")
    text = str(err.value)
    assert "\n" not in text and text.startswith("my.yaml: ") and msg in text, text


def test_a_fault_past_the_horizon_is_refused_and_sweep_values_are_checked():
    spec = randomization_from_dict({"fault": {"kind": "limp", "time_s": [12.0, 15.0]}})
    with pytest.raises(ValueError, match=r"fault.time_s=\[12.0, 15.0\]: starts at or after the 10 s walk ends"):
        spec.check_horizon(10.0)
    spec.check_horizon(20.0)
    with pytest.raises(ValueError, match="randomization.gravity: unknown key"):
        spec.with_value("gravity", 1.0)
    with pytest.raises(ValueError, match=r"randomization.friction=\[-1.0, -1.0\]: must lie in \[0, 10\]"):
        spec.with_value("friction", -1.0)
    assert spec.with_value("fault_time_s", 3.0).fault.time_s == (3.0, 3.0)


def test_draws_reproduce_from_their_seed_and_keep_to_their_ranges():
    spec = randomization_from_dict({"friction": [0.4, 1.0], "payload_kg": [0.0, 0.5], "payload_offset_m": [-0.05, 0.05],
                                    "latency_steps": [0, 3], "force_bias_n": [-0.2, 0.2],
                                    "fault": {"kind": "locked", "legs": [1, 4], "time_s": [1.0, 2.0],
                                              "probability": 0.5}})
    key = jax.random.PRNGKey(7)
    a, b = sample_perturbation(spec, key, 400), sample_perturbation(spec, key, 3)
    # env i's draw depends on (spec, key, i) only: the same in a batch of 3 as in one of 400, bit for bit
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x)[:3], np.asarray(y))
    c = sample_perturbation(spec, jax.random.PRNGKey(8), 400)
    assert not np.array_equal(np.asarray(a.friction), np.asarray(c.friction))
    f = np.asarray(a.friction)
    assert f.min() >= 0.4 and f.max() <= 1.0 and f.max() - f.min() > 0.5
    lat = np.asarray(a.latency)
    assert set(np.unique(lat)) == {0, 1, 2, 3}
    off = np.asarray(a.payload_offset)
    assert np.abs(off[:, :2]).max() <= 0.05 and np.all(off[:, 2] == 0)
    kind, leg, t = np.asarray(a.fault_kind), np.asarray(a.fault_leg), np.asarray(a.fault_time)
    assert 0.4 < (kind == 1).mean() < 0.6 and set(np.unique(leg)) == {1, 4}
    assert np.all((t[kind == 1] >= 1.0) & (t[kind == 1] <= 2.0)) and np.all(np.isinf(t[kind == 0]))
    # absent keys draw the neutral values
    n = sample_perturbation(RandomizationSpec(), key, 2)
    assert np.all(np.asarray(n.friction) < 0) and np.all(np.asarray(n.kp_scale) == 1.0)
    assert np.all(np.asarray(n.fault_kind) == 0) and np.all(np.asarray(n.force_bias) == 0.0)


ROWS = {
    "nominal": {},
    "payload": {"payload_kg": 0.6},
    "no friction": {"friction": 0.0},
    "locked leg": {"fault": {"kind": "locked", "legs": [0], "time_s": 1.0}},
    "limp leg": {"fault": {"kind": "limp", "legs": [1], "time_s": 1.0}},
    "pad dropout": {"tactile_dropout": 1.0},
    "latency": {"latency_steps": 3},
    "nominal again": {},
}


@pytest.fixture(scope="module")
def perturbed_walks():
    """The tactile tripod (the method on) walking at a 5 cm bar, one env per row of ROWS, all on the same
    terrain with no heading noise: the rows differ only by their draw. Run twice with the same key."""
    robot = luneckas2020()
    ctrl = TactileGaitController(robot, gait="tripod", max_obstacle_height=0.05, n_cycles=9)
    bar = Terrain(box_pos=jnp.array([[0.26, 0.0, 0.025]]), box_half=jnp.array([[0.012, 0.35, 0.025]]),
                  box_valid=jnp.array([True]), ground_z=jnp.zeros(()))
    n = len(ROWS)
    terr = jax.tree_util.tree_map(lambda x: jnp.stack([x] * n), bar)
    pert = concat_perturbations([sample_perturbation(randomization_from_dict(r), jax.random.PRNGKey(i), 1)
                                 for i, r in enumerate(ROWS.values())])
    _, dur = ctrl.duration_for(0.6)
    cfg = RolloutConfig(record=True, yaw_noise=0.0)
    # the elliptic friction cone: with the pyramidal one MJX's two Newton iterations diverge below a friction
    # of about 0.3 (docs/robustness.md)
    phys = PhysicsConfig(cone="elliptic")
    run = lambda: rollout(robot, terr, ctrl, ctrl.default_params(), dur, jax.random.PRNGKey(0), config=cfg,
                          physics=phys, perturbation=pert)
    # the same draws on the MuJoCo C and MJX-Warp backends (no traces there)
    other = {be: rollout(robot, terr, ctrl, ctrl.default_params(), dur, jax.random.PRNGKey(0), physics=phys,
                         config=RolloutConfig(yaw_noise=0.0, record=be == "warp"), perturbation=pert,
                         engine=be, nthread=2 if be == "c" else None) for be in ("c", "warp")}
    return {name: i for i, name in enumerate(ROWS)}, run(), run(), other


@pytest.mark.cost(400)
class TestPerturbedWalks:
    """The checks on the perturbed walks: one class, so that one worker runs them together and the walks (three
    backends, about 4 min on a cold cache) are built once (tests/conftest.py's scheduler)."""

    def test_same_key_gives_bit_identical_results(self, perturbed_walks):
        _, s1, s2, _ = perturbed_walks
        for x, y in zip(jax.tree_util.tree_leaves(s1), jax.tree_util.tree_leaves(s2)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))

    def test_each_perturbation_does_what_it_should(self, perturbed_walks):
        row, s, _, _ = perturbed_walks
        assert not np.asarray(s.nan).any()
        z = np.asarray(s.trace)[..., 2]  # torso height per control step
        adv = np.asarray(s.end_pose[:, 0] - s.start_pose[:, 0])
        dyaw = np.abs(np.asarray(s.travel)[:, 2])
        n_over = np.asarray(s.final_state.n_overcome).sum(-1)
        nom = row["nominal"]
        print({k: dict(adv=round(float(adv[i]), 5), z=round(float(z[i].mean()), 5), dyaw=round(float(dyaw[i]), 3),
                       over=int(n_over[i]), tilt=round(float(np.asarray(s.max_tilt)[i]), 3)) for k, i in row.items()})
        # a neutral draw changes nothing: the two nominal rows are the same walk
        assert adv[nom] == adv[row["nominal again"]] and z[nom].mean() == z[row["nominal again"]].mean()
        # the nominal walk crosses the bar with overcoming steps
        assert adv[nom] > 0.3 and n_over[nom] >= 2  # the bar stands at 0.26 m
        # a 0.6 kg payload (the robot weighs about 1.5 kg) sinks the torso, measured on the flat ground before the bar:
        # the control steps before a foot of either walk passes x = 0.2 m (139 of 987; 0.86 mm lower there, and
        # 0.6-1.1 mm in each 25 steps of it). Over the whole walk the crossing of the bar moves the means of 25 steps
        # by up to 14 mm either way, so the mean of the whole walk is no measure of it: 3.1 mm on one machine,
        # 1.1 mm on another (AVX-512), whose rounding the chaotic crossing amplifies
        front = np.asarray(s.foot_trace)[..., 0].max(-1)  # the foremost foot's x per control step
        before_bar = int(np.argmax((front[nom] > 0.2) | (front[row["payload"]] > 0.2)))
        assert before_bar >= 50, before_bar
        assert z[row["payload"], :before_bar].mean() < z[nom, :before_bar].mean() - 0.0005
        # without friction the feet slip: the robot hardly advances (measured 0.02 m against 0.38 m)
        assert adv[row["no friction"]] < 0.25 * adv[nom]
        # a locked leg turns the walk (measured 0.79 rad of heading change against 0.12 rad)
        assert dyaw[row["locked leg"]] > dyaw[nom] + 0.3
        # a limp middle leg lets the torso sag (measured 4.5 mm lower on average) and shortens the walk
        assert z[row["limp leg"]].mean() < z[nom].mean() - 0.002 and adv[row["limp leg"]] < 0.75 * adv[nom]
        # the pads still touch the bar, but with every reading lost the tactile switch never fires
        assert np.asarray(s.tactile_steps)[row["pad dropout"]].sum() > 0 and n_over[row["pad dropout"]] == 0
        # three control steps of latency change the walk without stopping it
        assert adv[row["latency"]] != adv[nom] and adv[row["latency"]] > 0.2

    @pytest.mark.parametrize("backend", ["c", "warp"])
    def test_every_backend_honours_the_same_draws(self, perturbed_walks, backend):
        """The MuJoCo C and MJX-Warp backends, given the same `Perturbation`, show every effect the MJX rollout
        shows (the same checks on their summaries; torso height: its mean over the walk on Warp, which records
        traces, its lowest point on C, which does not) and each draw moves the robot about as far as on MJX (advance
        within 5 cm, nominal 0.38 m; the engines' contacts differ, as in tests/test_backends.py)."""
        row, m, _, other = perturbed_walks
        c = other[backend]
        assert not np.asarray(c.nan).any()
        adv = lambda s: np.asarray(s.end_pose[:, 0] - s.start_pose[:, 0])
        ac, am = adv(c), adv(m)
        low = np.asarray(c.trace)[..., 2].mean(-1) if backend == "warp" else np.asarray(c.min_height)
        dyaw = np.abs(np.asarray(c.travel)[:, 2])
        n_over = np.asarray(c.final_state.n_overcome).sum(-1)
        nom = row["nominal"]
        print({k: dict(adv_c=round(float(ac[i]), 4), adv_mjx=round(float(am[i]), 4), low=round(float(low[i]), 4),
                       dyaw=round(float(dyaw[i]), 3), over=int(n_over[i])) for k, i in row.items()})
        assert ac[nom] == ac[row["nominal again"]] and ac[nom] > 0.3 and n_over[nom] >= 2
        assert low[row["payload"]] < low[nom] - 0.001
        assert ac[row["no friction"]] < 0.25 * ac[nom]
        assert dyaw[row["locked leg"]] > dyaw[nom] + 0.3
        assert low[row["limp leg"]] < low[nom] - 0.002 and ac[row["limp leg"]] < 0.75 * ac[nom]
        assert np.asarray(c.tactile_steps)[row["pad dropout"]].sum() > 0 and n_over[row["pad dropout"]] == 0
        assert ac[row["latency"]] != ac[nom] and ac[row["latency"]] > 0.2
        np.testing.assert_allclose(ac, am, atol=0.05)


def test_sweep_axes_envelope_and_interval():
    from hexjax.experiments.commands.robustness import envelope, parse_axis, wilson
    assert parse_axis("friction=0.3:1.0:3") == ("friction", [0.3, 0.65, 1.0])
    assert parse_axis("obstacle_height=0.02,0.05") == ("obstacle_height", [0.02, 0.05])
    assert parse_axis("friction=0.5:0.5:1") == ("friction", [0.5])
    for bad, msg in (("gravity=1:2:3", "unknown axis"), ("friction=1:0.3:3", r"low < high \(or n = 1\)"),
                     ("friction=0.5:0.5:3", "low < high"), ("friction=0.5,1,0.5", "distinct numbers"),
                     ("friction", "name=low:high:n"), ("payload_kg=0:1:0", "1 <= n <= 64")):
        with pytest.raises(ValueError, match=msg):
            parse_axis(bad)
    lo, hi = wilson(45, 50)
    assert 0.78 < lo < 0.8 and 0.95 < hi < 0.97  # 90 % of 50: 95 % interval about 78.6-95.7 %
    # obstacles get harder upwards: success 100, 96, 92, 60 % -> the envelope is the third level
    e = envelope([0.02, 0.04, 0.06, 0.08], [(50, 50), (48, 50), (46, 50), (30, 50)], "obstacle_height")
    assert e["level"] == 0.06 and e["sure_level"] == 0.02  # 48 of 50: interval from 86.5 %
    # friction gets harder downwards, whatever the order given
    e = envelope([1.0, 0.3, 0.65], [(50, 50), (10, 50), (47, 50)], "friction")
    assert e["level"] == 0.65
    assert envelope([0.3], [(10, 50)], "friction")["level"] is None
    # MJX's unconverged solve (the fast preset) gets a note, converged or MuJoCo C does not (docs/physics.md)
    from hexjax.experiments.commands.robustness import solver_note
    from hexjax.sim.engines import ENGINES
    mjx, warp, c = ENGINES["mjx"], ENGINES["warp"], ENGINES["c"]
    assert "--physics validated" in solver_note("stones", mjx, 2) and "stepping stones" in solver_note("stones", mjx, 2)
    assert "below friction 1.0" in solver_note("stairs", warp, 2)
    assert solver_note("stones", mjx, 8) is None and solver_note("stones", c, 2) is None


def test_robustness_command_refuses_bad_input_before_any_rollout(capsys, tmp_path):
    from hexjax.cli import main
    late = tmp_path / "late.yaml"
    late.write_text("randomization:\n  fault: {kind: limp, time_s: 100.0}\n")
    for argv, msg in ((["--axis", "gravity=1:2:3"], "--axis 'gravity': unknown axis"),
                      (["--axis", "friction=1.0:0.3:3"], "low < high"),
                      ([], "--axis given 0 times"),
                      (["--axis", "force_dropout=0:1.5:2"], "randomization.force_dropout=[1.5, 1.5]: must lie in [0, 1]"),
                      (["--axis", "friction=0.5,1", "--randomization", str(late)],
                       "fault.time_s=[100.0, 100.0]: starts at or after the"),
                      (["--axis", "obstacle_height=0.02:0.04:2", "--terrain", "flat"], "needs an obstacle terrain"),
                      (["--axis", "difficulty=0:1.5:2", "--terrain", "stairs-up"],
                       "terrain.difficulty=1.5: must be in [0, 1]"),
                      (["--axis", "friction=0.5,1", "--controllers", "gait,walk"], "--controllers 'walk': use some of"),
                      (["--axis", "friction=0.5,1", "--controllers", "cpg@robot9"], "robot preset 'robot9' unknown"),
                      (["--axis", "friction=0.5,1", "--processes", "2", "--process-id", "3"],
                       "--process-id=3: must be in [0, 1]"),
                      (["--axis", "friction=0.5,1", "--processes", "2", "--coordinator", "nohost"],
                       "--coordinator='nohost'")):
        assert main(["robustness"] + argv + ["--json", str(tmp_path / "r.json")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and msg in err[0], err
    assert not (tmp_path / "r.json.partial.json").exists()

