"""Forward mode through MJX's constraint solve (`hexjax.sim.internals.forward_mode`): the gradient it carries forward equals
reverse mode's through the implicit solve, and what it does not handle is refused before tracing. Its matrix-free
products of the contact rows are checked against MJX's rows in tests/test_implicit.py (they share its standing
state)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from hexjax.sim.compiled import Compiled, arrays_digest
from hexjax.sim.config import PhysicsConfig, RolloutConfig, physics_for
from hexjax.sim.internals.forward_mode import check_model
from hexjax.sim.engines import sim_model
from hexjax.sim.rollout import rollout_function
from hexjax.tune.config import load_tune_config
from hexjax.tune.driver import config_digest
from hexjax.tune.gradcheck import check_batch, tactile_check_setting
from hexjax.tune.objective import Problem
from hexjax.world.presets import get_terrain, luneckas2020


@pytest.mark.cost(130)
def test_forward_mode_gradient_equals_reverse_mode():
    """The tactile gradient check's setting on flat ground (2 envs, 0.4 s after 0.1 s of settling, windows of 4
    control steps, implicit solve, no bound): the derivatives of sum(travel x + 0.3 travel y) along three random
    directions of the float params, carried forward (`RolloutConfig.grad_mode='forward'`), equal reverse mode's
    gradient along them within 1e-3 of the largest."""
    robot = luneckas2020()
    ctrl, p = tactile_check_setting(robot)
    spec = get_terrain("flat")
    terr, keys = check_batch(spec, 2)
    phys = physics_for(spec.kind)
    duration = 0.4
    rev = RolloutConfig(settle_time=0.1, remat=True, solver_grad="implicit", grad_window=4)
    fwd = dataclasses.replace(rev, remat=False, grad_mode="forward")
    digest = arrays_digest(p, terr, keys)
    assert all(jnp.issubdtype(v.dtype, jnp.floating) for v in jax.tree_util.tree_leaves(p))
    rng = np.random.default_rng(1)
    dirs = [jax.tree_util.tree_map(lambda v: jnp.asarray(rng.normal(size=v.shape), v.dtype), p) for _ in range(3)]

    def total(fn, model):
        return lambda params: jnp.sum(fn(model, params, terr, keys).travel @ jnp.array([1.0, 0.3, 0.0]))

    model, fn = rollout_function(robot, ctrl, duration, physics=phys, config=rev)
    g = Compiled(jax.jit(jax.grad(total(fn, model))),
                 static=("test_forward_mode/reverse", robot, ctrl, phys, rev, duration, digest))(p)
    model_f, fn_f = rollout_function(robot, ctrl, duration, physics=phys, config=fwd)
    jvp = Compiled(jax.jit(lambda params, ts: [jax.jvp(total(fn_f, model_f), (params,), (t,))[1] for t in ts]),
                   static=("test_forward_mode/forward", robot, ctrl, phys, fwd, duration, digest))
    got = np.array([float(v) for v in jvp(p, dirs)])
    leaves = jax.tree_util.tree_leaves
    want = np.array([sum(float(jnp.vdot(a, b)) for a, b in zip(leaves(g), leaves(t))) for t in dirs])
    scale = np.max(np.abs(want))
    assert scale > 0.01, want  # the params move the travel
    assert np.max(np.abs(got - want)) <= 1e-3 * scale, (got, want)


@pytest.mark.cost(140)
def test_tuner_forward_mode_gives_reverse_modes_gradient():
    """The tuner's step (`Problem.gradient_program`) with `backward: forward` against `backward: sequential`, both
    without a bound: the tactile_tripod objective over 2 terrains, a 0.6 s walk after 0.1 s of settling (three 0.2 s
    windows). Same value, and the gradient in the unconstrained params within 1e-3 of its largest entry: the
    ravelling, the batch mean and the params' transform around `jax.jacfwd` are the reverse path's."""
    out, walk, settle = {}, 0.6, 0.1
    for backward in ("sequential", "forward"):
        cfg = load_tune_config("tactile_tripod", {"solver_grad": "implicit", "grad_clip": None, "backward": backward})
        pb = Problem.build(cfg)
        u0 = pb.space.init(pb.params0)
        terr, keys = pb.train_batch(0, 2)
        f = Compiled(jax.jit(pb.gradient_program(walk, settle)),
                     static=("test_forward_mode/tuner", walk, settle, pb.static("grad", config_digest(cfg, "grad"))))
        (loss, _), g = f(u0, terr, keys)
        out[backward] = float(loss), np.asarray(ravel_pytree(g)[0])
    (l_rev, g_rev), (l_fwd, g_fwd) = out["sequential"], out["forward"]
    assert abs(l_fwd - l_rev) <= 1e-5 * abs(l_rev), (l_fwd, l_rev)
    scale = np.max(np.abs(g_rev))
    assert scale > 1e-4, g_rev
    assert np.max(np.abs(g_fwd - g_rev)) <= 1e-3 * scale, (g_fwd, g_rev)


def test_forward_mode_is_refused_where_it_does_not_apply():
    """Each refusal names the setting, before anything is traced."""
    with pytest.raises(ValueError, match="solver_grad='unrolled'"):
        RolloutConfig(solver_grad="unrolled", grad_mode="forward").validate()
    with pytest.raises(ValueError, match="remat"):
        RolloutConfig(solver_grad="implicit", grad_mode="forward", remat=True).validate()
    with pytest.raises(ValueError, match="grad_clip"):
        RolloutConfig(solver_grad="implicit", grad_mode="forward", grad_clip=1.0).validate()
    with pytest.raises(ValueError, match="grad_mode='sideways'"):
        RolloutConfig(grad_mode="sideways").validate()
    with pytest.raises(ValueError, match="pyramidal"):
        check_model(sim_model(luneckas2020(), dataclasses.replace(PhysicsConfig(), cone="elliptic")).mjx_model)
    with pytest.raises(ValueError, match="grad_clip: null"):
        load_tune_config("tactile_tripod", {"backward": "forward", "solver_grad": "implicit"}).validate()
    with pytest.raises(ValueError, match="solver_grad: implicit"):
        load_tune_config("tactile_tripod", {"backward": "forward", "grad_clip": None}).validate()
    load_tune_config("tactile_tripod", {"backward": "forward", "solver_grad": "implicit", "grad_clip": None}).validate()
