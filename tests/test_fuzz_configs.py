"""Fuzzed presets: mutated robot, terrain and tuning YAML files (wrong types, missing and extra keys, negative,
zero, huge, NaN and infinite values) either load and run a tiny rollout with finite results, or fail with one
ValueError line. Any other exception, a multi-line error, a non-finite result or a hang fails the test.

The tiny rollouts go through the MuJoCo C backend, jitted: its programs (the controller step and the
accumulators) compile in about 0.1 s each, so even a new one per mutated robot costs less than running the
rollout op by op with JAX's jit off, as this test did until 2026-11-26. Warm runs on 2 cores, eager against
jitted: robots 11.0 s against 2.3 s, high-small 5.6 against 1.8, waves 5.5 against 0.9, tactile_tripod 10.4
against 2.5; with an empty cache the module took 24.1 s against 53.9 s. A config gives the same outcome either
way (the 40 high-small examples, both ways in one process). Which examples Hypothesis draws can still move
between runs of the module, jitted or not (robots: 14 or 16 of the 80 ran)."""

import copy
import math
import signal

import jax
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings, strategies as st

from hexjax.control.gait import GaitController
from hexjax.sim.config import PhysicsConfig, RolloutConfig
from hexjax.sim.rollout import rollout
from hexjax.tune.config import load_tune_config
from hexjax.tune.objective import Problem
from hexjax.world.files import read_yaml, resolve
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import sample

BAD_TYPES = ["abc", [1, 2, 3], {"a": 1}, True, None]
KINDS = ("delete", "extra", "wrong_type", "negative", "zero", "huge", "nan", "inf", "swap")
TINY = RolloutConfig(settle_time=0.04, yaw_noise=0.0)
SETTINGS = dict(deadline=None, derandomize=True, suppress_health_check=list(HealthCheck), database=None)


def _mutate_value(v, kind, draw):
    if kind == "wrong_type":
        return draw(st.sampled_from(BAD_TYPES))
    if isinstance(v, (list, tuple)) and v and kind != "swap":
        i = draw(st.integers(0, len(v) - 1))
        return [(_mutate_value(x, kind, draw) if j == i else x) for j, x in enumerate(v)]
    if kind == "swap":
        return list(reversed(v)) if isinstance(v, (list, tuple)) else v
    if isinstance(v, dict):
        k = draw(st.sampled_from(sorted(v))) if v else None
        return {**v, k: _mutate_value(v[k], kind, draw)} if k else v
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return {"negative": -1, "zero": 0, "huge": 10 ** 9, "nan": float("nan"), "inf": float("inf")}[kind]
    return {"negative": -abs(v) - (1 if isinstance(v, int) else 0.01), "zero": type(v)(0),
            "huge": type(v)(1e9), "nan": float("nan"), "inf": float("inf")}[kind]


@st.composite
def mutated(draw, base):
    d = copy.deepcopy(base)
    for _ in range(draw(st.integers(1, 2))):
        kind = draw(st.sampled_from(KINDS))
        key = draw(st.sampled_from(sorted(d))) if d else "x"
        if kind == "delete":
            d.pop(key, None)
        elif kind == "extra":
            d[draw(st.sampled_from(["colour", key + "s", "Kp", "coxa_lenght"]))] = 1.0
        elif key in d:
            d[key] = _mutate_value(d[key], kind, draw)
    return d


class _Hang(Exception):
    pass


def _alarm(*_):
    raise _Hang("took over 120 s")


def _check(tmp_path, doc, load, run):
    """Write `doc`, load it: a ValueError must be one line; a config that loads must run finite."""
    path = tmp_path / "fuzzed.yaml"
    path.write_text(yaml.safe_dump(doc))
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(120)
    try:
        try:
            spec = load(str(path))
        except ValueError as err:
            assert "\n" not in str(err) and str(err), repr(err)
            return "rejected"
        try:
            s = run(spec)
        except ValueError as err:  # a check of the rollout before it starts: still one line
            assert "\n" not in str(err) and str(err), repr(err)
            return "rejected by the rollout"
        for name in ("start_pose", "end_pose", "energy", "path_length", "travel", "max_tilt"):
            assert np.all(np.isfinite(np.asarray(getattr(s, name)))), (name, doc)
        assert not np.asarray(s.nan).any(), doc
        return "ran"
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


FLAT = sample(get_terrain("flat"), jax.random.PRNGKey(0), 1)


def _robot_run(robot):
    ctrl = GaitController(robot)
    return rollout(robot, FLAT, ctrl, ctrl.default_params(), 0.1, jax.random.PRNGKey(1), engine="c", nthread=1,
                   physics=PhysicsConfig(slots_per_leg=0, torso_slots=0), config=TINY)


def _terrain_run(spec):
    robot = get_robot("luneckas2020")
    ctrl = GaitController(robot)
    terr = sample(spec, jax.random.PRNGKey(2), 2)
    return rollout(robot, terr, ctrl, ctrl.default_params(), 0.1, jax.random.PRNGKey(1), engine="c", nthread=1,
                   config=TINY)


def _tune_run(cfg):
    problem = Problem.build(cfg)
    terr, _ = problem.eval_batch()
    terr = jax.tree_util.tree_map(lambda x: x[:1], terr)
    return rollout(problem.robot, terr, problem.eval_ctrl, problem.eval_params0, 0.1, jax.random.PRNGKey(1), engine="c",
                   nthread=1, physics=problem.physics(), config=TINY)


OUTCOMES = {}


@pytest.mark.parametrize("kind,base,load,run,n", [
    ("robot", "robots/luneckas2020", get_robot, _robot_run, 80),
    ("terrain", "terrains/high-small", get_terrain, _terrain_run, 40),
    ("terrain", "terrains/waves", get_terrain, _terrain_run, 30),
    ("tune", "tune/tactile_tripod", load_tune_config, _tune_run, 60),
])
def test_fuzzed_configs_load_and_run_or_fail_in_one_line(tmp_path, kind, base, load, run, n):
    folder, name = base.split("/")
    doc0 = read_yaml(resolve(folder, name))
    seen = []

    @settings(max_examples=n, **SETTINGS)
    @given(mutated(doc0))
    def one(doc):
        seen.append(_check(tmp_path, doc, load, run))

    one()
    counts = {k: seen.count(k) for k in set(seen)}
    OUTCOMES[base] = counts
    print(base, counts)
    assert len(seen) == n
    # the mutations reach both sides: some configs still load and run, most are refused
    assert counts.get("ran", 0) >= 1 and counts.get("rejected", 0) >= n // 3, counts


def test_the_unmutated_presets_run():
    for kind, load, run in (("robots/yu2019", get_robot, _robot_run), ("terrains/step40", get_terrain, _terrain_run)):
        folder, name = kind.split("/")
        s = run(load(str(resolve(folder, name))))
        assert not np.asarray(s.nan).any() and math.isfinite(float(np.asarray(s.energy).sum()))
