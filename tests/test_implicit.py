"""Implicit differentiation of MJX's constraint solve (`hexjax.sim.implicit`): same values as MJX, and where
the solver has converged the same derivatives as differentiating its unrolled Newton iterations, which
match central differences. The rollout-level checks (per parameter group, against central differences and
against the unrolled path) are in tests/test_tune.py."""

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from hexjax.control.gait import GaitController
from hexjax.sim.config import PhysicsConfig, RolloutConfig, physics_for
from hexjax.sim.implicit import implicit_solve, implicit_solver
from hexjax.sim.model import mjx, reversible_solver, sim_model
from hexjax.sim.rollout import rollout_function
from hexjax.sim.step import stop_derived
from hexjax.world.presets import luneckas2020

ITERATIONS = 30  # enough Newton iterations for the solve to converge on every step below


@pytest.fixture(scope="module")
def standing():
    """(model, data) of the Luneckas 2020 robot after 0.5 s standing on flat ground: six feet in contact."""
    phys = dataclasses.replace(physics_for("flat"), iterations=ITERATIONS)
    sm = sim_model(luneckas2020(), phys)
    m = sm.mjx_model
    d = sm.init_data(jnp.zeros(3))
    ctrl0 = jnp.asarray(sm.ctrl0)
    d = d.replace(ctrl=ctrl0, qpos=d.qpos.at[7:].set(ctrl0))
    d = jax.jit(lambda d: jax.lax.fori_loop(0, 100, lambda i, x: mjx.step(m, x), d))(d)
    assert int(jnp.sum(d._impl.efc_force != 0)) >= 6, "expected the feet in contact"
    return m, d


def _walk(m, d, k: int, stop: bool = False):
    """f(a): torso position and velocity after k physics steps with the servo targets swept by a * w sin(t);
    `stop`: gradient from step to step through `hexjax.sim.step.GRAD_FIELDS` only, as in a rollout."""
    w = jnp.asarray(np.random.RandomState(0).randn(m.nu).astype(np.float32))

    def f(a):
        def body(x, i):
            x = x.replace(ctrl=d.ctrl + a * 0.3 * w * jnp.sin(0.05 * (i + 1)))
            x = mjx.step(m, x)
            return (stop_derived(x) if stop else x), None
        x, _ = jax.lax.scan(body, d, jnp.arange(k))
        return jnp.concatenate([x.qpos[:3], x.qvel[:3]])
    return f


def test_converged_jacobian_matches_unrolled_and_central_differences(standing):
    """Five physics steps in contact: d(torso pose, velocity)/d(servo sweep) by the implicit backward equals
    the unrolled one to 1e-3 and both match central differences; the forward values are bit-identical."""
    m, d = standing
    f = _walk(m, d, 5)
    with reversible_solver(ITERATIONS):
        j_unrolled = np.asarray(jax.jit(jax.jacrev(f))(1.0))
    with implicit_solver():
        j_implicit = np.asarray(jax.jit(jax.jacrev(f))(1.0))
        v_implicit = np.asarray(jax.jit(f)(1.0))
    fj = jax.jit(f)
    v = np.asarray(fj(1.0))
    np.testing.assert_array_equal(v_implicit, v)
    fd = (np.asarray(fj(1.0 + 1e-3)) - np.asarray(fj(1.0 - 1e-3))) / 2e-3
    scale = np.linalg.norm(j_unrolled)
    assert scale > 1e-3, j_unrolled
    assert np.linalg.norm(j_implicit - j_unrolled) <= 1e-3 * scale, (j_implicit, j_unrolled)
    assert np.linalg.norm(j_implicit - fd) <= 0.05 * scale, (j_implicit, fd)


def test_steps_depend_on_each_other_through_grad_fields_only(standing):
    """MJX's step reads nothing from the previous step's Data outside `GRAD_FIELDS`: with the gradient
    stopped on every other field between steps, the 5-step Jacobian is the same (unrolled solver, so the
    warm start's path counts too)."""
    m, d = standing
    with reversible_solver(ITERATIONS):
        full = np.asarray(jax.jit(jax.jacrev(_walk(m, d, 5)))(1.0))
        cut = np.asarray(jax.jit(jax.jacrev(_walk(m, d, 5, stop=True)))(1.0))
    assert np.abs(full).max() > 1e-4
    np.testing.assert_allclose(cut, full, rtol=1e-5, atol=1e-6 * np.abs(full).max())


def test_forces_and_acceleration_jacobian_against_unrolled(standing):
    """One forward pass: the Jacobian of (qacc, qfrc_constraint, efc_force) with respect to the joint
    velocities (which move the constraints' reference accelerations) and the controls."""
    m, d = standing

    def f(qvel, ctrl):
        x = mjx.forward(m, d.replace(qvel=qvel, ctrl=ctrl))
        return jnp.concatenate([x.qacc, x.qfrc_constraint, x._impl.efc_force])

    jac = jax.jit(jax.jacrev(f, argnums=(0, 1)))
    with reversible_solver(ITERATIONS):
        ju = [np.asarray(x) for x in jac(d.qvel, d.ctrl)]
    with implicit_solver():
        ji = [np.asarray(x) for x in jac(d.qvel, d.ctrl)]
    for a, b in zip(ji, ju):
        assert np.linalg.norm(b) > 0
        assert np.linalg.norm(a - b) <= 1e-3 * np.linalg.norm(b)


def test_elliptic_cone_is_refused():
    m = mjx.put_model(mujoco.MjModel.from_xml_string(
        "<mujoco><option cone='elliptic'/><worldbody><geom type='plane' size='1 1 .1'/>"
        "<body pos='0 0 .1'><freejoint/><geom type='sphere' size='.1'/></body></worldbody></mujoco>"))
    with pytest.raises(ValueError, match="pyramidal"):
        implicit_solve(m, mjx.make_data(m))


def test_solver_grad_is_checked_before_tracing():
    with pytest.raises(ValueError, match="rollout.solver_grad='newton'"):
        RolloutConfig(solver_grad="newton").validate()
    robot = luneckas2020()
    with pytest.raises(ValueError, match="physics.cone='elliptic'"):
        rollout_function(robot, GaitController(robot), 0.1, config=RolloutConfig(solver_grad="implicit"),
                         physics=dataclasses.replace(PhysicsConfig(), cone="elliptic"))


def test_rollout_gradient_unchanged_by_stopping_derived_fields(monkeypatch):
    """A rollout's gradient is the same with the gradient stopped outside `GRAD_FIELDS` between steps (what
    the rollout does) and without: nothing hexjax reads from the last step's Data (foot sites for the slot
    assignment, contact forces and frames for the tactile pads) is missing from the list. Obstacle terrain,
    smooth tactile gait, implicit backward, truncated windows and bound as in tuning."""
    from jax.flatten_util import ravel_pytree

    import hexjax.cache
    from hexjax.sim import rollout as rollout_mod
    from hexjax.sim import step as step_mod
    from hexjax.tune.gradcheck import check_batch, tactile_check_setting, travel_objective
    from hexjax.tune.space import make_space
    from hexjax.world.presets import get_terrain

    robot = luneckas2020()
    ctrl, p = tactile_check_setting(robot)
    space = make_space("tactile")
    spec = get_terrain("high-small")
    terr, keys = check_batch(spec, 2)
    rc = RolloutConfig(settle_time=0.1, solver_grad="implicit", grad_window=10, grad_clip=1.0, remat=True)

    def grad():
        rollout_mod._compiled.cache_clear()
        model, fn = rollout_function(robot, ctrl, 0.3, physics=physics_for(spec.kind), config=rc)
        u0 = space.init(p)
        return np.asarray(ravel_pytree(jax.jit(jax.grad(travel_objective(fn, model, space, p, terr, keys)))(u0))[0])

    # programs kept on disk are keyed by hexjax's source, not by the patch below: trace both here
    monkeypatch.setattr(hexjax.cache, "cache_dir", lambda: None)
    cut = grad()
    identity = lambda d: d  # noqa: E731
    monkeypatch.setattr(step_mod, "stop_derived", identity)
    monkeypatch.setattr(rollout_mod, "stop_derived", identity)
    full = grad()
    rollout_mod._compiled.cache_clear()  # later tests must not get the patched program
    assert np.all(np.isfinite(full)) and np.abs(full).max() > 1e-4
    np.testing.assert_allclose(cut, full, rtol=1e-4, atol=1e-5 * np.abs(full).max())


def test_backward_keeps_only_what_it_reads(standing):
    """The implicit backward stores, per physics step, only the arrays whose values it reads (mass matrix and
    constraint rows), not the whole mjx.Data: if JAX's dead-code pass moved and the fallback kept everything,
    the gradient would stay right but cost memory and time on every step."""
    from hexjax.sim import implicit

    m, d = standing
    leaves, treedef = jax.tree_util.tree_flatten_with_path((m, d))
    traced = [(jax.tree_util.keystr(p), x) for p, x in leaves if isinstance(x, jax.Array)]

    def rebuild(xs):
        it = iter(xs)
        return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure((m, d)),
                                            [next(it) if isinstance(x, jax.Array) else x for _, x in leaves])
    read = implicit._read_by_backward(m, d, d.qacc, rebuild, [x for _, x in traced])
    kept = {k for (k, _), r in zip(traced, read) if r}
    assert "[1]._impl.efc_J" in kept and "[1]._impl.efc_D" in kept
    assert "[1].qfrc_smooth" not in kept and "[1].qpos" not in kept  # enter linearly, or not at all
    assert len(kept) < len(traced) // 10


def test_unrolled_physics_steps_give_the_same_state(standing):
    """`RolloutConfig.unroll_substeps` traces a control step's physics steps one after another instead of as
    a `lax.scan`: the same state and power. (Reverse mode differentiates the same operations either way; a
    Jacobian check would add ~100 s of compile to the suite for what `lax.scan`'s unroll already guarantees.)"""
    from hexjax.sim.step import physics

    m, d = standing
    w = jnp.asarray(np.random.RandomState(1).randn(m.nu).astype(np.float32))

    def f(unroll):
        def g(a):
            out, power = physics(m, d.replace(ctrl=d.ctrl + a * 0.3 * w), 2, stop=True, unroll=unroll)
            return jnp.concatenate([out.qpos, out.qvel, power])
        return jax.jit(g)
    v0, v1 = (np.asarray(f(u)(1.0)) for u in (False, True))
    assert np.abs(v0[:3] - np.asarray(d.qpos[:3])).max() > 1e-6  # the steps moved the robot
    # XLA fuses the loop body and the unrolled steps differently: equal to float32 rounding (measured 1.3e-5)
    np.testing.assert_allclose(v1, v0, rtol=1e-4, atol=1e-5)
