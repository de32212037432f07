"""Tunable parameter spaces (issue 5, step 1): bounds, reparametrisation, and clear errors for bad configs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.control.cpg import CPGController
from hexjax.control.tactile import TactileGaitController
from hexjax.tune.space import Bound, make_space, to_physical, to_unconstrained
from hexjax.world.presets import luneckas2020, yu2019


def test_reparametrisation_round_trips_and_stays_in_bounds():
    two, one = Bound(0.02, 0.12), Bound(0.5)
    p = jnp.array([0.021, 0.05, 0.1199])
    np.testing.assert_allclose(np.asarray(to_physical(to_unconstrained(p, two), two)), np.asarray(p), rtol=1e-5)
    q = jnp.array([0.6, 3.0, 40.0])
    np.testing.assert_allclose(np.asarray(to_physical(to_unconstrained(q, one), one)), np.asarray(q), rtol=1e-5)
    # any unconstrained value, however large a step took it, maps inside the bounds
    u = jnp.array([-1e4, -30.0, 0.0, 30.0, 1e4])
    pt = np.asarray(to_physical(u, two))
    assert np.all(pt >= 0.02) and np.all(pt <= 0.12)
    assert np.all(np.asarray(to_physical(u, one)) >= 0.5)
    # sigmoid centre is the middle of the range; its slope there is (hi - lo) / 4
    assert float(to_physical(0.0, two)) == pytest.approx(0.07)
    assert float(jax.grad(lambda x: to_physical(x, two))(0.0)) == pytest.approx(0.025)


def test_space_applies_to_tactile_and_cpg_params_and_grad_flows():
    ctrl = TactileGaitController(luneckas2020(), max_obstacle_height=0.05)
    p0 = ctrl.default_params()
    space = make_space("tactile")
    u = space.init(p0)
    p1 = space.apply(u, p0)
    for name in space.names:
        assert float(getattr(p1, name)) == pytest.approx(float(getattr(p0, name)), rel=1e-4)
    # a gradient through the reparametrisation reaches u: apex height of an overcoming step wrt h_k
    t = 2 * ctrl.cycle_time + 0.5 * float(p0.swing_time)
    g = jax.grad(lambda uu: ctrl.foot_offsets(space.apply(uu, p0), t, jnp.ones(6), jnp.zeros(6))[:, 2].sum())(u)
    assert float(g["overcome_height"]) > 0 and float(g["step_height"]) == 0.0
    cpg = CPGController(yu2019())
    c0 = cpg.default_params()
    cs = make_space("cpg", only=["lc_trim", "f_contact"])
    cu = cs.init(c0)
    assert cu["lc_trim"].shape == (2, 2, 3) and cu["f_contact"].shape == (3,)
    c1 = cs.apply(jax.tree_util.tree_map(lambda x: x + 0.1, cu), c0)
    assert np.all(np.asarray(c1.lc_trim) > 0) and np.all(np.asarray(c1.f_contact) > np.asarray(c0.f_contact))
    assert np.all(np.asarray(c1.lc_trim) <= 0.3)
    # the per-leg fields join only when named: 6 x 12 trims, 6 clearance offsets, 6 x 3 threshold factors
    assert not any(n.startswith("leg_") for n in make_space("cpg").names)
    legs = make_space("cpg", only=["leg_trim", "leg_clearance", "leg_f_scale"])
    lu = legs.init(c0)
    assert sum(int(np.size(v)) for v in lu.values()) == 96
    np.testing.assert_allclose(np.asarray(legs.apply(lu, c0).leg_f_scale), 1.0, rtol=1e-5)


def test_bad_configs_raise_clear_errors():
    with pytest.raises(ValueError, match="params.swing_height: unknown parameter"):
        make_space("tactile", only=["swing_height"])
    with pytest.raises(ValueError, match=r"params.overcome_height: min=0.1 must be < max=0.05"):
        make_space("tactile", overrides={"overcome_height": {"min": 0.1, "max": 0.05}})
    with pytest.raises(ValueError, match="unknown keys"):
        make_space("tactile", overrides={"overcome_height": {"low": 0.1}})
    with pytest.raises(ValueError, match="controller='ppo'"):
        make_space("ppo")
    ctrl = TactileGaitController(luneckas2020(), max_obstacle_height=0.08)  # h_k = 10 cm
    space = make_space("tactile", overrides={"overcome_height": {"min": 0.02, "max": 0.09}})
    with pytest.raises(ValueError, match=r"params.overcome_height=.*outside \[0.02, 0.09\]"):
        space.init(ctrl.default_params())


def test_tune_config_file_and_its_errors(tmp_path):
    from hexjax.tune.config import load_tune_config
    cfg = load_tune_config("tactile_tripod")
    assert cfg.space().names == ("overcome_height", "overcome_length", "step_height", "step_length",
                                 "tactile_threshold")
    assert cfg.optimizer["learning_rate"] > 0
    for bad, match in (({"optimizer": {"name": "adam", "learning_rate": 0.0}}, "learning_rate=0.0"),
                       ({"optimizer": {"name": "adam", "learning_rate": -1e-3}}, "learning_rate=-0.001"),
                       ({"params": {"overcome_height": {"min": 0.1, "max": 0.02}}}, "min=0.1 must be < max=0.02"),
                       ({"params": {"wing_span": {"min": 0.0, "max": 1.0}}}, "params.wing_span: unknown parameter"),
                       ({"objective": {"dx": 1.0, "beauty": 2.0}}, "objective.beauty"),
                       ({"objective": {"dx": 0.0}}, "nothing to minimise"),
                       ({"steps": 0}, "tune.steps=0"),
                       ({"terrain": "moon"}, "terrain='moon'"),
                       ({"colour": "red"}, "tune.colour: unknown key")):
        with pytest.raises(ValueError, match=match):
            load_tune_config("tactile_tripod", overrides=bad)
    with pytest.raises(ValueError, match="nope.yaml: no such file"):
        load_tune_config(str(tmp_path / "nope.yaml"))
    with pytest.raises(ValueError, match="tune config 'tactile_tripd' unknown \\(did you mean 'tactile_tripod'"):
        load_tune_config("tactile_tripd")


def test_every_shipped_tune_config_builds():
    """Each configs/tune/*.yaml validates, its start lies inside its bounds, and its physics is the one it
    asks for (the CPG config's 4 solver iterations or cpg_step_ditch's validated preset reach the training rollouts)."""
    from hexjax.tune.config import load_tune_config
    from hexjax.tune.objective import Problem
    from hexjax.world.files import preset_names
    paths = preset_names("tune")
    assert len(paths) >= 2
    for path in paths:
        cfg = load_tune_config(path)
        problem = Problem.build(cfg)
        problem.space.init(problem.params0)
        if cfg.train_physics is None:
            assert problem.physics().iterations == (cfg.solver_iterations or 2), path
        else:  # a preset's solver (cpg_step_ditch trains on validated: 8 iterations, the elliptic cone)
            from hexjax.sim.physics import get_physics
            want = get_physics(cfg.train_physics)
            got = problem.physics()
            assert (got.iterations, got.cone) == (want.iterations, want.cone), path
    cpg = Problem.build(load_tune_config("cpg_tripod"))
    assert cpg.robot.name == "yu2019" and cpg.physics().iterations == 4
    assert float(cpg.params0.temp_force) == 1.0  # the controller's own temperatures when the config sets none
