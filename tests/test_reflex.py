"""The learned reflex layer (`hexjax.control.reflex`): over a thousand numbers, the paper's controller exactly
while the layer is untrained, a gradient that reaches every layer once it is not, and bad settings refused."""
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
