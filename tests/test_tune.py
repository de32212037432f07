"""Gradients through the MJX rollout agree with central differences per parameter group; the objective's
terms; tuning runs are deterministic and resume from their checkpoints; CMA-ES improves; CLI config errors."""

import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.control.cpg import CPGController
from hexjax.sim.compiled import Compiled, arrays_digest
from hexjax.sim.config import RolloutConfig, physics_for
from hexjax.sim.rollout import rollout_function
from hexjax.sim.step import Summary
from hexjax.tune.config import TuneConfig
from hexjax.tune.es import tune_es
from hexjax.tune.grad import average_iterate, tune
from hexjax.tune.gradcheck import check, check_batch, tactile_check_setting, travel_objective
from hexjax.tune.objective import Problem, per_env_objective
from hexjax.tune.space import make_space, with_values
from hexjax.world.presets import get_terrain, luneckas2020, yu2019

# the tactile preset's parameter groups
GROUPS = {"gait": ["step_length", "step_height", "swing_time"],
          "overcoming": ["overcome_length", "overcome_height"], "threshold": ["tactile_threshold"]}


def _cosines(obj, u0, groups, static, eps=1e-3, one_program=True):
    """Per group: (cosine of the autodiff gradient of obj at u0 with central differences, autodiff, FD). The
    differences come from the value_and_grad program's value (one compiled program, not two), or with
    `one_program=False` from a forward program of their own (`hexjax.tune.gradcheck.check`)."""
    _, by_eps = check(obj, u0, groups, (eps,), static=static, one_program=one_program)
    res = by_eps[eps]
    for group, (_, a, b) in res.items():
        assert np.all(np.isfinite(a)) and np.linalg.norm(b) > 0, (group, a, b)
    return res


@pytest.mark.cost(160)
def test_gradient_matches_central_differences_per_group():
    """The acceptance check: on a smooth objective (the mean travel of 4 envs over a 0.4 s window on flat
    ground, MJX's default two Newton iterations traced as a scan), the autodiff gradient with respect to
    the unconstrained params has cosine >= 0.9 with central differences, for every parameter group."""
    robot = luneckas2020()
    # a fast gait and a threshold inside the gate's width: every group acts within the 0.4 s window
    ctrl, p = tactile_check_setting(robot)
    space = make_space("tactile")
    spec = get_terrain("flat")
    terr, keys = check_batch(spec, 4)
    phys, rc = physics_for(spec.kind), RolloutConfig(settle_time=0.1, solver_grad="unrolled")
    model, fn = rollout_function(robot, ctrl, 0.4, physics=phys, config=rc)
    static = (robot, ctrl, phys, rc, 0.4, space, arrays_digest(p, terr, keys))
    res = _cosines(travel_objective(fn, model, space, p, terr, keys), space.init(p), GROUPS, static)
    for group, (cos, a, b) in res.items():
        assert cos >= 0.9, f"{group}: cosine {cos:.3f}, autodiff {a}, central differences {b}"


@pytest.mark.cost(250)
def test_cpg_gradient_matches_central_differences():
    """The same check for the seed-003 CPG on `yu2019`, for every group of the "cpg" preset: the linear
    converter (trims, clearance; Eq. 6), the contact thresholds F_contact (Eqs. 8-9) and the elevator reflex
    (T_s, regenerated clearance; Eqs. 10-11). Three settings differ from the tactile check (docs/tuning.md):
    4 Newton iterations (with 2 the solver does not converge under the stiff servos and the rollout is rough)
    and phase gates scaled with the network's rate (it runs 5x faster so that the window holds a lift-off,
    so temp_phase is 5x too). As the tactile check puts its threshold inside the gate's width, F_contact-x/y
    of 1 N inside a 3 N force gate lets the elevator fire in part at every swing on flat ground, so its
    params act on the travel. The differences step by 3e-3, not 1e-3: the elevator's derivatives (~1e-5 m) are
    only a few times the differences' rounding noise at 1e-3 (2-3e-6), so its cosine there hung on the
    machine's rounding (0.99 on one machine, 0.73 on an AVX-512 one). 3e-3 cuts that noise threefold and is
    still short of truncation (the converter's cosine is 1.000 at 1e-3, 3e-3 and 1e-2, 0.99 at 3e-2); measured
    on the AVX-512 machine: 1.000, 1.000 and 0.976 for the three groups.
    With the solver converged, the implicit backward (`solver_grad='implicit'`) must give the same gradient as
    the unrolled one (cosine >= 0.99 per group) and pass the same check.
    Both gradients recompute each control step in the backward pass (`remat`), as the tuner's do, so this check
    holds the tuner's backward path to central differences while the tactile check above holds the default one.
    The cosines are those without it to the digits printed, and XLA compiles the two gradient programs in about
    25 s less CPU (a third fewer kernels).
    The 36 differences come from a forward program of their own: there a call costs 0.035 s against 0.46 s for
    the value_and_grad program (13x, 2 cores), so its compile (about 16 s with tracing) pays for itself in a cold
    run, and a warm run of this test takes 14.7 s instead of 31.7 s. (The tactile check above keeps one program:
    its 12 differences would save 3.8 s warm for about 15 s more compile cold.)"""
    robot = yu2019()
    ctrl = CPGController(robot, smooth=True)
    p = ctrl.default_params()
    p = p.replace(net=p.net.replace(omega=5.0 * p.net.omega), temp_phase=5.0 * p.temp_phase,
                  temp_force=jnp.float32(3.0), f_contact=jnp.array([1.0, 1.0, 2.0]))
    space = make_space("cpg")
    spec = get_terrain("flat")
    terr, keys = check_batch(spec, 4)
    phys = dataclasses.replace(physics_for(spec.kind), iterations=4)
    rc = RolloutConfig(settle_time=0.1, solver_grad="unrolled", remat=True)
    model, fn = rollout_function(robot, ctrl, 0.4, physics=phys, config=rc)
    groups = {"converter": ["lc_trim", "clearance"], "contact thresholds": ["f_contact"],
              "elevator": ["elevated_clearance", "ramp_time"]}
    assert sorted(sum(groups.values(), [])) == sorted(space.names)
    static = (robot, ctrl, phys, rc, 0.4, space, arrays_digest(p, terr, keys))
    u0 = space.init(p)
    res = _cosines(travel_objective(fn, model, space, p, terr, keys), u0, groups, static, eps=3e-3, one_program=False)
    for group, (cos, a, b) in res.items():
        print(group, f"cosine {cos:.3f} |autodiff| {np.linalg.norm(a):.3g} |FD| {np.linalg.norm(b):.3g}")
        assert cos >= 0.9, f"{group}: cosine {cos:.3f}, autodiff {a}, central differences {b}"
    # the implicit backward through the constraint solve (hexjax.sim.internals.implicit): with 4 iterations the solver
    # has converged, so it must give the unrolled gradient (cosine >= 0.99) and match the same differences
    rc_i = dataclasses.replace(rc, solver_grad="implicit")
    model_i, fn_i = rollout_function(robot, ctrl, 0.4, physics=phys, config=rc_i)
    g = Compiled(jax.jit(jax.grad(travel_objective(fn_i, model_i, space, p, terr, keys))),
                 static=("test_tune/implicit_grad", robot, ctrl, phys, rc_i, 0.4, space, arrays_digest(p, terr, keys)))
    grad_i = g(u0)
    for group, names in groups.items():
        gi = np.concatenate([np.ravel(np.asarray(grad_i[n])) for n in names])
        _, a, b = res[group]
        cos_u = gi @ a / (np.linalg.norm(gi) * np.linalg.norm(a) + 1e-30)
        cos_fd = gi @ b / (np.linalg.norm(gi) * np.linalg.norm(b) + 1e-30)
        print(group, f"implicit: cosine {cos_u:.4f} with unrolled, {cos_fd:.3f} with FD")
        assert cos_u >= 0.99, f"{group}: implicit {gi} against unrolled {a}: cosine {cos_u:.4f}"
        assert cos_fd >= 0.9, f"{group}: implicit {gi} against central differences {b}: cosine {cos_fd:.3f}"


def _summary(travel, yaw0, fell, nan, energy):
    b = len(yaw0)
    z = jnp.zeros(b)
    start = jnp.stack([z, z, jnp.asarray(yaw0)], -1)
    return Summary(start_pose=start, end_pose=start, fell=jnp.asarray(fell), fall_time=z, nan=jnp.asarray(nan),
                   energy=jnp.asarray(energy), path_length=z, travel=jnp.asarray(travel), max_tilt=z, min_height=z,
                   tactile_steps=jnp.zeros((b, 6), jnp.int32))


def test_objective_terms_in_the_start_frame():
    # env 0 faces +y and walks 0.8 m along it: 0.2 m short, no lateral error;
    # env 1 faces +x, walks 1.0 m and drifts 0.1 m left, turning 0.2 rad; env 2 fell; env 3 went NaN
    s = _summary(travel=[[0.0, 0.8, 0.0], [1.0, 0.1, 0.2], [0.5, 0.0, 0.0], [9.0, 9.0, 0.0]],
                 yaw0=[np.pi / 2, 0.0, 0.0, 0.0], fell=[False, False, True, True], nan=[False, False, False, True],
                 energy=[2.0, 1.0, 0.0, 0.0])
    j = np.asarray(per_env_objective(s, 1.0, {"dx": 1.0, "dy": 1.0, "fall": 3.0}))
    np.testing.assert_allclose(j, [0.2, 0.1, 0.5 + 3.0, 3.0], atol=1e-4)
    j = np.asarray(per_env_objective(s, 1.0, {"dx": 1.0, "dalpha": 1.0, "energy": 0.5}))
    np.testing.assert_allclose(j[:2], [0.2 + 1.0, 0.0 + 0.2 + 0.5], atol=1e-4)


def _small_config(**kw):
    # flat ground: determinism, resuming, bounds and the validation pick need no obstacles, and the flat
    # programs compile in about two thirds of the time of low-small's (fewer collision pairs)
    base = dict(controller="tactile", gait="tripod", terrain="flat", distance=0.08, train_batch=2,
                held_out_batch=2, validation_batch=2, window=0.2, steps=2, eval_every=1, seed=3,
                params={"step_length": {"min": 0.01, "max": 0.08}, "overcome_height": {"min": 0.02, "max": 0.12}},
                optimizer={"name": "adam", "learning_rate": 0.2})
    base.update(kw)
    return TuneConfig(**base)


def _numbers(log):
    """The log without wall times."""
    return [{k: v for k, v in e.items() if k not in ("wall_s", "eval_s", "train_s")} for e in log]


@pytest.mark.cost(200)
def test_tuning_is_deterministic_and_resumes(tmp_path):
    """A 2-step run, extended from its checkpoint to 3 steps, logs exactly what a fresh 3-step run logs (so
    the run is deterministic and resumes where it stopped); the params move inside their bounds; the returned
    iterate is the best on the validation terrains; a checkpoint of another config is refused; with
    `optimizer.average` the optimiser's steps are the same and the logged params are the average of its iterates."""
    cfg = _small_config()
    a = tune(cfg, str(tmp_path / "a"), progress=False)
    assert a["log"][-1]["step"] == 2 and all(e["grad_finite"] for e in a["log"][1:])
    # the params moved, within their bounds; the returned iterate is the best on the validation terrains
    moved = a["last"]["params"]
    assert moved != a["start"]["params"] and 0.01 <= moved["step_length"] <= 0.08
    evaluated = [e for e in a["log"] if "validation" in e]
    assert len(evaluated) == 3 and a["final"]["validation"]["objective"] == min(
        e["validation"]["objective"] for e in evaluated)
    assert os.path.exists(tmp_path / "a" / "tune.png") and os.path.exists(tmp_path / "a" / "log.json")
    # the picked params as a params preset beside the log: they load as the picked iterate's
    from hexjax.tune.space import load_values
    kept = load_values(str(tmp_path / "a" / "params.yaml"))
    assert set(kept) == set(a["final"]["params"])
    for k, v in a["final"]["params"].items():
        np.testing.assert_allclose(kept[k], v, rtol=1e-6)
    # extend run a by one step from its checkpoint; it must match a fresh 3-step run
    c = tune(_small_config(steps=3), str(tmp_path / "a"), progress=False)
    d = tune(_small_config(steps=3), str(tmp_path / "b"), progress=False)
    assert _numbers(c["log"]) == _numbers(d["log"]) and c["log"][-1]["step"] == 3
    assert _numbers(c["log"])[:3] == _numbers(a["log"])
    with open(tmp_path / "a" / "log.json") as fh:
        assert json.load(fh)["log"][-1]["step"] == 3
    # a checkpoint from another config is refused, not silently continued
    with pytest.raises(ValueError, match="different config"):
        tune(_small_config(seed=4), str(tmp_path / "a"), progress=False)
    # optimizer.average: the optimiser takes the same steps (same training objectives), and what is evaluated
    # and logged is the running average of its iterates in the unconstrained params
    beta = 0.5
    e = tune(_small_config(steps=3, optimizer={"name": "adam", "learning_rate": 0.2, "average": beta}),
             str(tmp_path / "e"), progress=False)
    assert [x.get("train_objective") for x in e["log"]] == [x.get("train_objective") for x in d["log"]]
    p = Problem.build(_small_config())
    space = p.space
    u = [space.init(with_values(p.params0, x["params"])) for x in d["log"][1:]]
    avg = None  # step 1's average is its iterate
    for k, uk in enumerate(u):
        avg = average_iterate(avg, uk, k + 1, beta)
        want = space.physical(avg)
        got = e["log"][k + 1]["params"]
        for n in want:
            np.testing.assert_allclose(got[n], want[n], rtol=1e-5, err_msg=f"step {k + 1}, {n}")
    assert e["log"][3]["params"] != d["log"][3]["params"]  # the average is not the last iterate


def test_a_non_finite_step_is_named_with_its_count_and_the_bound():
    """The gradient tuner skips a step whose gradient or objective is not finite and prints why: the number of
    bad entries over the whole pytree, and the config's bound on the backward flow (none in forward mode or with
    grad_clip null, where an exploding gradient is expected: docs/tuning.md, "Non-finite steps")."""
    from hexjax.tune.driver import nonfinite_note
    g = {"a": jnp.array([1.0, jnp.nan, 2.0]), "b": jnp.array([[jnp.inf, 0.5], [0.0, -jnp.inf]])}
    base = _small_config()
    assert nonfinite_note(3, 0.2, {"a": jnp.ones(3)}, base) is None
    note = nonfinite_note(3, 0.2, g, base)
    assert note.startswith("step 4: 3 of 7 gradient entries are not finite; the step is skipped") and \
        f"grad_clip={base.grad_clip:g} per env" in note and "\n" not in note, note
    assert "objective is nan" in nonfinite_note(0, float("nan"), {"a": jnp.ones(3)}, base)
    assert "grad_clip: null leaves the backward flow unbounded" in nonfinite_note(
        0, 0.2, g, dataclasses.replace(base, grad_clip=None))
    fwd = dataclasses.replace(base, grad_clip=None, backward="forward", solver_grad="implicit")
    assert "backward: forward has no bound" in nonfinite_note(0, 0.2, g, fwd)


def test_cli_tune_rejects_bad_configs(capsys):
    from hexjax.cli import main
    for sets, msg in ((["optimizer.learning_rate=0"], "learning_rate=0"),
                      (["params={wing_span: {min: 0, max: 1}}"], "params.wing_span: unknown parameter"),
                      (["params={overcome_height: {min: 0.1, max: 0.02}}"], "min=0.1 must be < max=0.02"),
                      (["solver_iterations=0"], "tune.solver_iterations=0"),
                      (["gates=soft"], "tune.gates='soft'"),
                      (["optimizer.average=1"], "tune.optimizer.average=1"),
                      (["backward=sideways"], "tune.backward='sideways'"),
                      (["backward=parallel", "estimator=hybrid"], "tune.backward='parallel' with tune.estimator"),
                      (["train_physics=validated", "solver_iterations=4"], "give one or the other"),
                      (["train_physics=reference"], "training rollouts take gradients"),
                      (["steps"], "use key=value")):
        rc = main(["tune", "--config", "tactile_tripod"] + sum([["--set", s] for s in sets], []))
        assert rc == 2
        assert msg in capsys.readouterr().err


def test_train_physics_sets_the_training_solver():
    """`train_physics: validated` trains on validated's solver (elliptic cone, 8 iterations) instead of the default
    one; the gradient in forward mode, whose matrix-free contact rows are pyramidal, is refused on it before
    anything is traced (the implicit reverse-mode gradient takes the elliptic cone)."""
    from hexjax.tune.grad import tune as tune_grad
    from hexjax.tune.objective import Problem
    default = Problem.build(_small_config()).physics()
    assert (default.cone, default.iterations) == ("pyramidal", 2)
    cfg = _small_config(train_physics="validated")
    got = Problem.build(cfg).physics()
    assert (got.cone, got.iterations, got.ls_iterations) == ("elliptic", 8, 8)
    with pytest.raises(ValueError, match="elliptic cone has no forward-mode gradient"):
        tune_grad(_small_config(train_physics="validated", solver_grad="implicit", backward="forward",
                                grad_clip=None), "/nonexistent", progress=False)


def test_held_out_figures_per_terrain_family_follow_the_batch_layout():
    """`family_slices` names the envs of each terrain family as `Problem.terrain_batch` lays them out: on a
    flat + low-small batch of 5, the first 3 envs are flat (no box top above the ground) and the last 2 have boxes."""
    from hexjax.tune.objective import Problem, family_slices
    assert [(s.start, s.stop) for s in family_slices(12, 5)] == [(0, 3), (3, 6), (6, 8), (8, 10), (10, 12)]
    problem = Problem.build(_small_config(terrain=["flat", "low-small"]))
    terrain = problem.terrain_batch(jax.random.PRNGKey(0), 5)
    top = np.asarray(terrain.box_pos)[..., 2] + np.asarray(terrain.box_half)[..., 2]
    tall = (top > np.asarray(terrain.ground_z)[:, None] + 0.005).any(-1)  # a box standing above the ground
    flat, boxes = family_slices(5, 2)
    assert not tall[flat].any() and tall[boxes].all(), tall


@pytest.mark.cost(110)
def test_es_baseline_improves_and_is_deterministic(tmp_path):
    """CMA-ES on an objective with a clear way down: the goal error plus 0.05 per joule, the step height
    among the tuned params (a lower swing costs less energy). In 3 generations of 4 x 2 rollouts the mean
    moves down the energy slope and the held-out objective of the returned iterate falls by more than 30 %
    (measured 57 %: 0.099 -> 0.043 m); a rerun is identical."""
    cfg = _small_config(es_population=4, es_sigma=1.0, objective={"dx": 1.0, "dy": 1.0, "energy": 0.05},
                        params={"step_height": {"min": 0.005, "max": 0.1}, "step_length": {"min": 0.01, "max": 0.08}})
    a = tune_es(cfg, str(tmp_path / "a"), rollouts=24, progress=False)
    b = tune_es(cfg, str(tmp_path / "b"), rollouts=24, progress=False)
    assert _numbers(a["log"]) == _numbers(b["log"])
    assert [e["rollouts"] for e in a["log"]] == [0, 8, 16, 24]
    assert a["improvement_pct"] > 30.0, a["improvement_pct"]
    assert a["final"]["held_out"]["objective"] < a["start"]["held_out"]["objective"]
    assert a["final"]["params"]["step_height"] < 0.8 * a["start"]["params"]["step_height"]


def test_params_presets_load_by_path_and_name(tmp_path, monkeypatch):
    """A params preset (`values`) loads from its .yaml path and, placed in configs/params/, by name; a preset
    without values and an unknown name fail in one line."""
    import yaml

    from hexjax.tune.space import load_values
    from hexjax.world import files

    (tmp_path / "params").mkdir()
    doc = {"controller": "cpg", "gait": "tripod", "values": {"clearance": 0.05, "f_contact": [5.0, 5.0, 1.0]}}
    (tmp_path / "params" / "mine.yaml").write_text(yaml.safe_dump(doc))
    (tmp_path / "params" / "empty.yaml").write_text(yaml.safe_dump({"controller": "cpg"}))
    assert load_values(str(tmp_path / "params" / "mine.yaml")) == doc["values"]
    monkeypatch.setattr(files, "config_dir", lambda: tmp_path)
    assert load_values("mine") == doc["values"]
    with pytest.raises(ValueError, match="needs `values`"):
        load_values("empty")
    with pytest.raises(ValueError, match="mines"):
        load_values("mines")


def test_a_tuning_starts_from_a_params_preset_and_tunes_each_leg():
    """`start`: the shipped CMA-ES preset's shared numbers replace the hand rules in both the training (smooth)
    and the judged (hard) params, and cpg_legs tunes the 96 per-leg numbers from there, every leg equal."""
    from hexjax.tune.config import load_tune_config
    from hexjax.tune.space import load_values

    cfg = load_tune_config("cpg_legs")
    pr = Problem.build(cfg)
    v = load_values(cfg.start)
    for p in (pr.params0, pr.eval_params0):
        np.testing.assert_allclose(np.asarray(p.lc_trim), v["lc_trim"], rtol=1e-6)
        np.testing.assert_allclose(float(p.elevated_clearance), v["elevated_clearance"], rtol=1e-6)
    assert float(pr.params0.smooth) == 1.0 and float(pr.eval_params0.smooth) == 0.0
    u = pr.space.init(pr.params0)
    assert sum(int(np.size(x)) for x in u.values()) == 96
    np.testing.assert_allclose(np.asarray(pr.space.apply(u, pr.params0).leg_trim), 0.0, atol=1e-6)
    from hexjax.tune.driver import config_digest
    assert config_digest(cfg, "grad") != config_digest(dataclasses.replace(cfg, start=None), "grad")
    with pytest.raises(ValueError, match="tune.start='nope'"):
        load_tune_config("cpg_legs", overrides={"start": "nope"})


def test_an_equal_wall_race_reads_its_ratio_and_paired_errors_from_the_logs():
    """`hexjax tune --equal-wall`: the strategy is evaluated at the first generation past each of the gradient
    run's evaluation times, and the race says how far the gradient's pick is from the start's and the strategy's
    on the same terrains (paired), and when the gradient first reached the strategy's J, as a fraction of the
    strategy's own seconds. Worked by hand on three terrains."""
    from hexjax.experiments.commands.tuning import race
    from hexjax.tune.es import eval_schedule
    due = eval_schedule(8, 4, eval_at=[10.0, 20.0])
    times = [1.0, 3.0, 9.9, 10.1, 12.0, 25.0, 26.0]  # the strategy's own seconds after each generation
    assert [due(g, now, before) for g, (before, now) in enumerate(zip(times, times[1:]), 1)] == \
        [False, False, True, False, True, False]
    by_rollouts = eval_schedule(8, 16)  # one evaluation every 2 generations of 8 members = 16 gradient steps
    assert [by_rollouts(g, 0.0, 0.0) for g in range(1, 5)] == [False, True, False, True]

    def ev(j, t):
        return {"train_s": t, "wall_s": t, "held_out": {"objective": float(np.mean(j)), "per_env_objective": j}}
    start = [0.3, 0.2, 0.4]
    grad_log = [ev(start, 1.0), ev([0.2, 0.2, 0.3], 50.0), ev([0.1, 0.15, 0.2], 100.0)]
    es_log = [ev(start, 1.0), ev([0.2, 0.1, 0.25], 100.0)]
    run = lambda log, pick: {"method": "m", "log": log, "start": log[0], "final": log[pick]}
    r = race([run(grad_log, 2), run(es_log, 1)])
    d = np.array([0.1, 0.15, 0.2]) - np.array(start)
    assert r["grad_less_start"]["mean"] == pytest.approx(d.mean())
    assert r["grad_less_start"]["se"] == pytest.approx(d.std(ddof=1) / np.sqrt(3))
    a, = r["against"]
    assert a["grad_s_to_reach"] == 100.0 and a["ratio"] == pytest.approx(1.0)  # 0.233 > 0.183 at 50 s
    assert a["grad_less_es"]["mean"] == pytest.approx(np.mean([-0.1, 0.05, -0.05]))
    assert race([run(grad_log, 2), run([ev(start, 1.0), ev([0.5, 0.5, 0.5], 80.0)], 1)])["against"][0]["ratio"] == \
        pytest.approx(1.0 / 80.0)
