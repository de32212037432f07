"""The learned reflex layer (`hexjax.control.reflex`): over a thousand numbers, the paper's controller exactly
while the layer is untrained, a gradient that reaches every layer once it is not, and bad settings refused; the
tuner moving its weights (and the evolution strategy suited to that many, rolling out on the certified engine);
its preset running the Yu 2019 experiment."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.control.registry import make_controller
from hexjax.sim.model import Obs
from hexjax.world.presets import get_robot


def _obs(key):
    """A random but plausible reading of one env: joints, a tilted torso, forces on feet and pads."""
    k = jax.random.split(key, 6)
    quat = jnp.concatenate([jnp.ones(1), 0.05 * jax.random.normal(k[0], (3,))])
    return Obs(qpos=0.3 * jax.random.normal(k[1], (18,)), qvel=jax.random.normal(k[2], (18,)),
               torso_pos=jnp.array([0.0, 0.0, 0.1]), torso_quat=quat / jnp.linalg.norm(quat),
               foot_force=jnp.abs(5.0 * jax.random.normal(k[3], (6, 3))), foot_contact=jnp.ones(6, bool),
               tactile_force=jnp.abs(jax.random.normal(k[4], (6,))), tactile=jnp.zeros(6, bool),
               time=jnp.asarray(0.0))


def _walk(ctrl, params, n=40):
    """Joint targets of n control steps on a fixed stream of readings."""
    def body(state, key):
        state, q = ctrl.step(params, state, _obs(key))
        return state, q
    _, qs = jax.lax.scan(body, ctrl.init(params, jax.random.PRNGKey(0)), jax.random.split(jax.random.PRNGKey(1), n))
    return qs


@pytest.mark.parametrize("name,base", [("cpg-reflex", "cpg"), ("gait-reflex", "gait")])
def test_an_untrained_layer_is_the_papers_controller(name, base):
    robot = get_robot("yu2019" if base == "cpg" else "luneckas2020")
    kw = {"smooth": True} if base == "cpg" else {}  # the CPG's training form: its gates' sigmoids
    ctrl, paper = make_controller(name, robot, **kw), make_controller(base, robot, **kw)
    p = ctrl.default_params()
    assert ctrl.n_params() >= 1000 and ctrl.n_params(p) == ctrl.n_params()
    np.testing.assert_array_equal(np.asarray(_walk(ctrl, p)), np.asarray(_walk(paper, p.base)))
    assert ctrl.for_distance(1.0)[1] == paper.for_distance(1.0)[1]
    # once its last layer moves, the layer changes the targets and its gradient reaches every layer
    p1 = p.replace(net=jax.tree_util.tree_map(lambda x: x + 0.01, p.net))
    assert not np.allclose(np.asarray(_walk(ctrl, p1)), np.asarray(_walk(paper, p.base)))
    g = jax.grad(lambda net: jnp.sum(_walk(ctrl, p.replace(net=net), 10) ** 2))(p1.net)
    for path, leaf in jax.tree_util.tree_leaves_with_path(g):
        assert np.all(np.isfinite(np.asarray(leaf))) and np.any(np.asarray(leaf) != 0), jax.tree_util.keystr(path)


def test_bad_layer_settings_are_refused_naming_the_field():
    robot = get_robot("yu2019")
    with pytest.raises(ValueError, match=r"reflex.max_offset=2.0: must be in \(0, 1\] rad"):
        make_controller("cpg-reflex", robot, max_offset=2.0)
    with pytest.raises(ValueError, match=r"reflex.hidden=\(0,\)"):
        make_controller("cpg-reflex", robot, hidden=(0,))
    ctrl = make_controller("cpg-reflex", robot)
    p = ctrl.default_params()
    bad = p.replace(net=jax.tree_util.tree_map(lambda x: x * jnp.nan, p.net))
    with pytest.raises(ValueError, match=r"reflex.net\['params'\].*: not finite"):
        ctrl.validate_params(bad)


def test_the_tuner_moves_the_layers_weights_unbounded():
    """The `cpg-reflex` space: the layer's weights as they are (p = u), the CPG's own fields by `base.<name>`; a
    tuning log's weights load back into the params; a bound on the weights or a misshapen array is refused."""
    from hexjax.tune.config import load_tune_config
    from hexjax.tune.objective import Problem
    from hexjax.tune.space import make_space, with_values
    problem = Problem.build(load_tune_config("cpg_reflex_grad"))
    assert problem.space.names == ("net",) and type(problem.train_ctrl).__name__ == "ReflexController"
    u = problem.space.init(problem.params0)
    assert sum(np.size(x) for x in jax.tree_util.tree_leaves(u)) == problem.train_ctrl.n_params() == 3122
    moved = jax.tree_util.tree_map(lambda x: x + 0.5, u)
    p = problem.space.apply(moved, problem.params0)
    for a, b in zip(jax.tree_util.tree_leaves(p.net), jax.tree_util.tree_leaves(problem.params0.net)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b) + 0.5, rtol=1e-6)
    logged = {k: jax.tree_util.tree_map(lambda x: np.asarray(x).tolist(), v)
              for k, v in problem.space.physical(moved).items()}
    back = with_values(problem.params0, logged)
    for a, b in zip(jax.tree_util.tree_leaves(back.net), jax.tree_util.tree_leaves(p.net)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError, match=r"params: net.params.Dense_1.bias: must be finite with shape \(18,\)"):
        bad = jax.tree_util.tree_map(lambda x: x, logged)
        bad["net"]["params"]["Dense_1"]["bias"] = [0.0] * 17
        with_values(problem.params0, bad)
    assert make_space("cpg-reflex", {"base.lc_trim": {"min": -0.2, "max": 0.2}, "net": {}}).names == (
        "base.lc_trim", "net")
    with pytest.raises(ValueError, match=r"params.net: has no bounds"):
        make_space("cpg-reflex", {"net": {"min": -1.0}})


def test_the_evolution_strategy_suits_the_dimension():
    """`es_strategy: auto`: CMA-ES's full covariance for the tactile preset's few numbers, sep-CMA-ES for the
    layer's 3,122; a strategy evosax lacks here is refused naming the choices."""
    import dataclasses

    from hexjax.tune.config import load_tune_config
    from hexjax.tune.es import strategy
    from hexjax.tune.objective import Problem
    for name, want in (("tactile_tripod", "cma_es"), ("cpg_reflex_grad", "sep_cma_es")):
        cfg = load_tune_config(name)
        problem = Problem.build(cfg)
        assert strategy(cfg, problem.space.init(problem.params0)) == want
    assert strategy(dataclasses.replace(cfg, es_strategy="snes"), None) == "snes"
    with pytest.raises(ValueError, match=r"tune.es_strategy='openai': use one of \('auto', 'cma_es'"):
        load_tune_config("cpg_reflex_grad", {"es_strategy": "openai"})


def test_a_layer_preset_runs_the_yu2019_experiment_under_the_layer():
    """`hexjax experiment yu2019-step --params <a reflex preset>`: the preset's `net` makes the experiment run the
    CPG under the layer; an untrained layer's preset gives the paper's figures to the last digit (MuJoCo C, a
    short walk of 2 envs a row)."""
    from hexjax.experiments.papers.yu2019.steps import run_experiment
    from hexjax.tune.driver import _jsonable
    net = make_controller("cpg-reflex", get_robot("yu2019")).init_net()
    preset = _jsonable({"net": net})  # as a params preset's YAML holds it
    kw = dict(batch=2, duration=3.0, record=True, progress=False)
    paper, layer = run_experiment("yu2019-step", **kw), run_experiment("yu2019-step", params=preset, **kw)
    assert layer["config"]["params"] == {"net": "3,122 numbers (a learned reflex layer)"}
    assert layer["results"] == paper["results"]
    # the shipped, tuned layer loads by name (as `--params cpg_reflex_es` does) and moves the walk
    from hexjax.tune.space import load_values
    tuned = run_experiment("yu2019-step", params=load_values("cpg_reflex_es"), **kw)
    assert tuned["config"]["params"] == {"net": "3,122 numbers (a learned reflex layer)"}
    assert tuned["results"] != paper["results"]


def test_the_evolution_strategy_rolls_out_on_the_certified_engine():
    """`es_rollouts: certified`: each member of a population is scored by the hard rollout on the evaluation
    physics on this host's certified engine (MuJoCo C here), every member on the same terrains: member k's
    score is the mean J of a rollout of member k alone."""
    import dataclasses

    from hexjax.sim.physics import pick, shared_config
    from hexjax.sim.rollout import rollout
    from hexjax.tune.config import load_tune_config
    from hexjax.tune.es import population_objective
    from hexjax.tune.objective import Problem, evaluate_held_out, per_env_objective
    cfg = load_tune_config("cpg_step_ditch", {"es_rollouts": "certified", "horizon": 2.0, "train_batch": 5})
    problem = Problem.build(cfg)
    u0 = problem.space.init(problem.params0)
    moved = dict(u0, clearance=u0["clearance"] + 2.0)
    # within each field's bounds, but the elevated swing (Yu 2019's elevator) below the plain one: the CPG's own
    # check refuses it, so the member scores the worst (+inf) instead of stopping the generation
    outside = dict(u0, clearance=u0["clearance"] + 6.0, elevated_clearance=u0["elevated_clearance"] - 6.0)
    pop_u = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), u0, moved, outside)
    terr, keys = problem.train_batch(0)
    scores = np.asarray(population_objective(problem, 3, 5)(pop_u, terr, keys))
    phys = pick(cfg.eval_physics)
    alone = rollout(problem.robot, terr, problem.eval_ctrl, problem.space.apply(moved, problem.eval_params0),
                    problem.duration, keys, physics=shared_config(phys, problem.specs), engine=phys.engine.name)
    assert phys.engine.name == "c" and scores[0] != scores[1] and np.isfinite(scores[:2]).all()
    assert scores[1] == pytest.approx(float(np.mean(per_env_objective(alone, cfg.distance, cfg.objective))), abs=1e-6)
    assert scores[2] == np.inf
    # judged on the certified engine too (`eval_engine: certified`): the same rollout, and the iterate out of the
    # controller's domain the worst, with the reason
    judge = Problem.build(dataclasses.replace(cfg, eval_engine="certified", held_out_batch=5))
    held = evaluate_held_out(judge, moved)
    terr, keys = judge.eval_batch()
    s = judge.certified_rollout(judge.space.apply(moved, judge.eval_params0), terr, keys)
    assert held["objective"] == pytest.approx(float(np.mean(per_env_objective(s, cfg.distance, cfg.objective))),
                                              abs=1e-6)
    assert len(held["per_env_objective"]) == 5 and held["objective_se"] > 0
    bad = evaluate_held_out(judge, outside)
    assert bad["objective"] == np.inf and bad["infeasible"].startswith("cpg.elevated_clearance=")
    with pytest.raises(ValueError, match=r"tune.es_rollouts='certified' runs the evaluated \(hard\) rollout"):
        dataclasses.replace(cfg, es_objective="smooth").validate()


def test_the_gait_layer_tunes_from_the_papers_gait():
    """`gait_reflex_grad`: the tuner lays the layer over the Luneckas 2020 open-loop gait (which has no gates, so
    its training and judged forms are one gait), tunes the layer's 2,802 weights from zero, walks the config's
    distance with the gait's stop, and refuses a smooth-gate temperature the gait does not have."""
    from hexjax.control.gait import GaitController
    from hexjax.tune.config import load_tune_config
    from hexjax.tune.objective import Problem
    problem = Problem.build(load_tune_config("gait_reflex_grad"))
    assert problem.space.names == ("net",)
    assert type(problem.train_ctrl.base) is type(problem.eval_ctrl.base) is GaitController
    assert problem.train_ctrl.base.n_cycles is not None  # the walk stops at the goal
    weights = jax.tree_util.tree_leaves(problem.params0.net)
    assert sum(int(np.size(w)) for w in weights) == 2802
    assert not any(np.any(np.asarray(w)) for w in weights[-2:])  # the last layer's bias and kernel: zero
    with pytest.raises(ValueError, match=r"tune.temperature=0.1: the gait-reflex controller has no smooth gate"):
        load_tune_config("gait_reflex_grad", {"temperature": 0.1})
