"""Implicit differentiation of MJX's constraint solve (`hexjax.sim.internals.implicit`): same values as MJX, and where
the solver has converged the same derivatives as differentiating its unrolled Newton iterations, which
match central differences. The rollout-level checks (per parameter group, against central differences and
against the unrolled path) are in tests/test_tune.py. Forward mode's matrix-free contact rows
(`hexjax.sim.internals.forward_mode`) are checked here too, on the same standing state; its gradient in
tests/test_forward_mode.py."""

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco.mjx._src import forward as mjx_forward

from hexjax.control.gait import GaitController
from hexjax.sim.compiled import Compiled, arrays_digest
from hexjax.sim.config import PhysicsConfig, RolloutConfig, physics_for
from hexjax.sim.internals.forward_mode import _contacts, check_model, contact_parts, rows_t_times, rows_times
from hexjax.sim.internals.implicit import implicit_solver
from hexjax.sim.engines import sim_model
from hexjax.sim.model import mjx
from hexjax.sim.internals.rules import reversible_solver
from hexjax.sim.rollout import rollout_function
from hexjax.world.presets import luneckas2020

ITERATIONS = 30  # enough Newton iterations for the solve to converge on every step below
ROBOT = luneckas2020()  # the standing fixture's robot, and part of every kept program's key (`_kept`)


@pytest.fixture(scope="module")
def standing():
    """(model, data) of the Luneckas 2020 robot after 0.5 s standing on flat ground: six feet in contact."""
    phys = dataclasses.replace(physics_for("flat"), iterations=ITERATIONS)
    sm = sim_model(ROBOT, phys)
    m = sm.mjx_model
    d = sm.init_data(jnp.zeros(3))
    ctrl0 = jnp.asarray(sm.ctrl0)
    d = d.replace(ctrl=ctrl0, qpos=d.qpos.at[7:].set(ctrl0))
    d = _kept(lambda d: jax.lax.fori_loop(0, 100, lambda i, x: mjx.step(m, x), d), d, "stand100", "mjx")(d)
    assert int(jnp.sum(d._impl.efc_force != 0)) >= 6, "expected the feet in contact"
    return m, d


def _walk(m, d, k: int):
    """f(a): torso position and velocity after k physics steps with the servo targets swept by a * w sin(t)."""
    w = jnp.asarray(np.random.RandomState(0).randn(m.nu).astype(np.float32))

    def f(a):
        def body(x, i):
            x = x.replace(ctrl=d.ctrl + a * 0.3 * w * jnp.sin(0.05 * (i + 1)))
            return mjx.step(m, x), None
        x, _ = jax.lax.scan(body, d, jnp.arange(k))
        return jnp.concatenate([x.qpos[:3], x.qvel[:3]])
    return f


def _kept(fn, d, *tag):
    """jax.jit(fn) kept on disk (`hexjax.sim.compiled.Compiled`) under `tag` (test, solver mode), the standing
    fixture's robot (its preset is a YAML file, which the key's hash of hexjax's sources does not cover) and
    state: a warm run loads it instead of tracing it again (20-60 s a program on 2 cores). Pass a fresh `fn` per
    solver mode: `jax.jit` reuses the trace of a function it has traced before, whatever solver patch is open."""
    return Compiled(jax.jit(fn), static=("test_implicit",) + tag + (ITERATIONS, ROBOT, arrays_digest(d)))


@pytest.mark.cost(120)
class TestStanding:
    """The checks from the standing robot: one class, so that one worker runs them and the standing state is made once
    (tests/conftest.py's scheduler)."""

    def test_converged_jacobian_matches_unrolled_and_central_differences(self, standing):
        """Five physics steps in contact: d(torso pose, velocity)/d(servo sweep) by the implicit backward equals
        the unrolled one to 1e-3 and both match central differences; the forward values are bit-identical."""
        m, d = standing
        with reversible_solver(ITERATIONS):
            j_unrolled = np.asarray(_kept(jax.jacrev(_walk(m, d, 5)), d, "walk5-jac", "unrolled")(1.0))
        with implicit_solver():
            j_implicit = np.asarray(_kept(jax.jacrev(_walk(m, d, 5)), d, "walk5-jac", "implicit")(1.0))
            v_implicit = np.asarray(_kept(_walk(m, d, 5), d, "walk5", "implicit")(1.0))
        fj = _kept(_walk(m, d, 5), d, "walk5", "mjx")
        v = np.asarray(fj(1.0))
        np.testing.assert_array_equal(v_implicit, v)
        fd = (np.asarray(fj(1.0 + 1e-3)) - np.asarray(fj(1.0 - 1e-3))) / 2e-3
        scale = np.linalg.norm(j_unrolled)
        assert scale > 1e-3, j_unrolled
        assert np.linalg.norm(j_implicit - j_unrolled) <= 1e-3 * scale, (j_implicit, j_unrolled)
        assert np.linalg.norm(j_implicit - fd) <= 0.05 * scale, (j_implicit, fd)

    def test_forces_and_acceleration_jacobian_against_central_differences_and_unrolled(self, standing):
        """One forward pass: the Jacobian of (qacc, qfrc_constraint, efc_force) with respect to the joint
        velocities (which move the constraints' reference accelerations) and the controls. The implicit backward's
        equals central differences, and the unrolled Newton iterations' equals it, each to 1e-3 of its norm per
        input (measured: 2.6e-4 and 9e-5 for d qacc / d qvel).

        The solve starts cold (warm start cleared), so that the unrolled iterations run. From the standing state's
        own warm start MJX's solver finds its gradient below tolerance before the first iteration and returns the
        warm start, a constant: the unrolled derivative of qacc is then exactly 0 (measured), the implicit one is
        unchanged. (Until 2026-11-25 this test compared one traced program with itself: a jitted function traced
        under the first solver patch kept that trace under the second, which hid that.)"""
        m, d = standing
        d = d.replace(qacc_warmstart=jnp.zeros_like(d.qacc_warmstart))

        def f(qvel, ctrl):
            x = mjx.forward(m, d.replace(qvel=qvel, ctrl=ctrl))
            return jnp.concatenate([x.qacc, x.qfrc_constraint, x._impl.efc_force])

        # a jitted function per solver mode (jax.jacrev makes a new one each call): one jitted function would be
        # traced once, under the first patch
        with reversible_solver(ITERATIONS):
            ju = _kept(jax.jacrev(f, argnums=(0, 1)), d, "forward-jac", "unrolled")(d.qvel, d.ctrl)
        with implicit_solver():
            ji = _kept(jax.jacrev(f, argnums=(0, 1)), d, "forward-jac", "implicit")(d.qvel, d.ctrl)
        # central differences: every entry of both inputs, +eps and -eps, in one batched call of MJX's own forward
        eps, n_v = 1e-3, d.qvel.shape[0]
        n = n_v + d.ctrl.shape[0]
        steps = np.concatenate([np.eye(n, dtype=np.float32), -np.eye(n, dtype=np.float32)]) * eps
        values = np.asarray(_kept(jax.vmap(f), d, "forward-vmap", "mjx")(d.qvel + steps[:, :n_v], d.ctrl + steps[:, n_v:]))
        fd = ((values[:n] - values[n:]) / (2 * eps)).T  # (outputs, inputs)
        fd = (fd[:, :n_v], fd[:, n_v:])
        for name, a, b, c in zip(("qvel", "ctrl"), ji, ju, fd):
            a, b = np.asarray(a), np.asarray(b)
            assert np.linalg.norm(c) > 1.0, (name, c)
            assert np.linalg.norm(a - c) <= 1e-3 * np.linalg.norm(c), (name, np.linalg.norm(a - c), np.linalg.norm(c))
            assert np.linalg.norm(b - a) <= 1e-3 * np.linalg.norm(a), (name, np.linalg.norm(b - a), np.linalg.norm(a))

    def test_integrator_rule_keeps_mjx_values_and_derivative(self, standing):
        """`hexjax.sim.internals.rules.integrator_rule`, under which every rollout that reverse or forward mode goes through is
        traced: MJX's implicitfast integration bit for bit on the standing robot, and its Jacobian (reverse and forward
        mode) in the mass matrix, the constraint force and the velocity equal to the one through JAX's Cholesky
        rule; `spd_solve` likewise on random SPD matrices; MJX's integrator back in place after the context."""
        from mujoco.mjx._src import forward as mjx_forward

        from hexjax.sim.internals.rules import integrator_rule, spd_solve

        m, d = standing
        mjx_implicit = mjx_forward.implicit
        with integrator_rule():
            ruled = mjx_forward.implicit
        assert ruled is not mjx_implicit and mjx_forward.implicit is mjx_implicit

        def integrate(fn):
            def f(mass, frc, qvel):
                out = fn(m, d.replace(qfrc_constraint=frc, qvel=qvel).tree_replace({"_impl.M": mass}))
                return jnp.concatenate([out.qvel, out.qpos])
            return f

        args = (d._impl.M, d.qfrc_constraint, d.qvel)
        assert float(jnp.abs(d.qfrc_constraint).max()) > 0.1, "expected contact forces"
        # kept on disk (`_kept`), as every MJX program of this module: as plain `jax.jit`s their persistent-cache keys
        # can change with what the worker traced before
        kept = lambda fn, *tag: _kept(fn, d, "integrator", *tag)  # noqa: E731
        np.testing.assert_array_equal(kept(integrate(ruled), "rule")(*args), kept(integrate(mjx_implicit), "mjx")(*args))
        # the mass matrix moves only symmetrically: compare the Jacobian on symmetric directions, (J + J^T) / 2 in M's
        # two axes (single entries are a convention of each rule: the factor reads one triangle)
        sym = lambda j: 0.5 * (j + jnp.swapaxes(j, -1, -2))  # noqa: E731
        for jac in (jax.jacrev, jax.jacfwd):
            got = kept(jac(integrate(ruled), argnums=(0, 1, 2)), jac.__name__, "rule")(*args)
            want = kept(jac(integrate(mjx_implicit), argnums=(0, 1, 2)), jac.__name__, "mjx")(*args)
            for k, (g, w) in enumerate(zip(got, want)):
                g, w = (sym(g), sym(w)) if k == 0 else (g, w)
                assert float(jnp.abs(w).max()) > 1e-4
                np.testing.assert_allclose(g, w, rtol=1e-4, atol=1e-6 * float(jnp.abs(w).max()))

        k1, k2 = jax.random.split(jax.random.PRNGKey(5))
        r = jax.random.normal(k1, (16, 6, 6))
        a = r @ jnp.swapaxes(r, 1, 2) + 0.5 * jnp.eye(6)
        b = jax.random.normal(k2, (16, 6))
        cho = jax.vmap(lambda a, b: jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(a), b))
        np.testing.assert_array_equal(jax.vmap(spd_solve)(a, b), cho(a, b))
        on_sym = lambda f: (lambda s, b: f(0.5 * (s + jnp.swapaxes(s, 1, 2)), b))  # noqa: E731  symmetric directions
        for jac in (jax.jacrev, jax.jacfwd):
            got = jac(on_sym(jax.vmap(spd_solve)), argnums=(0, 1))(a, b)
            want = jac(on_sym(cho), argnums=(0, 1))(a, b)
            for g, w in zip(got, want):
                np.testing.assert_allclose(g, w, rtol=1e-4, atol=1e-5 * float(jnp.abs(w).max()))
        with pytest.raises(RuntimeError, match="inside"):
            with integrator_rule():
                raise RuntimeError("inside")
        assert mjx_forward.implicit is mjx_implicit

    def test_matrix_free_rows_match_mjx_with_their_derivative(self, standing):
        """J x and J^T f of the contact rows, from `rows_times` / `rows_t_times`, against MJX's efc_J at the standing
        state, and the tangents of both along a random change of qpos (through MJX's kinematics and collisions): equal
        to float32 rounding (1e-5 of the largest value, 1e-4 of the largest tangent)."""
        m, d = standing
        n0 = check_model(m)
        rng = np.random.default_rng(0)
        ncon = d._impl.contact.dist.shape[0]
        x = jnp.asarray(rng.normal(size=m.nv), jnp.float32)
        f = jnp.asarray(rng.normal(size=4 * ncon), jnp.float32)
        dq = jnp.asarray(rng.normal(size=m.nq), jnp.float32)

        def products(q):
            d2 = mjx_forward.fwd_position(m, d.replace(qpos=q))
            bodies, on = _contacts(m, d2)
            parts, jac = contact_parts(d2), d2._impl.efc_J[n0:]
            return (jac @ x, rows_times(m, parts, bodies, on, x), jac.T @ f, rows_t_times(m, parts, bodies, on, f),
                    jnp.sum(on))

        vals, tans = Compiled(jax.jit(lambda q, t: jax.jvp(products, (q,), (t,))),
                              static=("test_forward_mode/products", arrays_digest(d)))(d.qpos, dq)
        assert int(vals[4]) >= 6, "expected the feet in contact"
        for mjx_v, ours, tol in ((vals[0], vals[1], 1e-5), (vals[2], vals[3], 1e-5),
                                 (tans[0], tans[1], 1e-4), (tans[2], tans[3], 1e-4)):
            mjx_v, ours = np.asarray(mjx_v), np.asarray(ours)
            scale = np.max(np.abs(mjx_v))
            assert scale > 1e-2, mjx_v  # a zero on both sides would pass any comparison
            assert np.max(np.abs(ours - mjx_v)) <= tol * scale, (ours, mjx_v)


def _incline(cone: str, mu: float, incline_deg: float = 30.0):
    """(mjx model, data, g, theta) of a flat box (10 x 10 x 2 cm, 1 kg) on an incline (gravity tilted by `incline_deg` instead of the plane), Coulomb friction `mu`,
    a 5 ms step and MuJoCo's Newton solver converged (100 iterations, tolerance 1e-12)."""
    th = np.deg2rad(incline_deg)
    g = 9.81
    xml = (f"<mujoco><option timestep='0.005' cone='{cone}' iterations='100' ls_iterations='50' tolerance='1e-12' "
           f"gravity='{g * np.sin(th)} 0 {-g * np.cos(th)}'/><worldbody>"
           f"<geom type='plane' size='5 5 .1' friction='{mu} 0.005 0.0001'/>"
           f"<body pos='0 0 .01'><freejoint/><geom type='box' size='.05 .05 .01' mass='1' "
           f"friction='{mu} 0.005 0.0001'/></body></worldbody></mujoco>")
    m = mjx.put_model(mujoco.MjModel.from_xml_string(xml))
    return m, mjx.make_data(m), g, th


def test_elliptic_implicit_derivative_of_a_sliding_box_matches_differences_and_the_hand_worked_slope():
    """The implicit derivative through MJX's elliptic cone where its Newton Hessian has the cone's dense blocks:
    contacts on the cone's surface, a box sliding down a 30 deg incline at mu = 0.2.

    One solve (the box at 0.5 m/s, pressed 0.5 mm into the incline): d qacc / d mu by the implicit backward (through
    the contacts' friction) equals central differences of MJX's own forward and the unrolled Newton iterations'
    derivative to 1e-3, and the forward values are MJX's, bit for bit.

    A whole slide, by hand: Coulomb's law gives a = g (sin - mu cos), so da/dmu = -g cos(30 deg) = -8.50 m/s^2.
    The implicit derivative of the velocity gained between 0.5 and 1.5 s (300 physics steps) is within 3 % of that
    (the soft contact's sliding friction sits ~1 % above mu N, docs/physics.md). Finite differences of a slide
    are no check there: the sliding box hops by a fraction of a millimetre now and then (the elliptic cone's
    soft contact pushes a sliding contact outwards), and the hops move the measured rate by up to 10 % between
    mu +- 0.02."""
    from mujoco.mjx._src import solver as mjx_solver
    m, d, g, th = _incline("elliptic", 0.2)
    mu = jnp.float32(0.2)
    with_mu = lambda u: m.replace(geom_friction=m.geom_friction.at[:, 0].set(u))  # noqa: E731

    pressed = d.replace(qpos=d.qpos.at[2].set(0.0095), qvel=d.qvel.at[0].set(0.5))
    accel = lambda u: mjx.forward(with_mu(u), pressed).qacc  # noqa: E731
    plain = jax.jit(accel)
    with implicit_solver():
        v_i, j_i = jax.jit(lambda u: (accel(u), jax.jacrev(accel)(u)))(mu)
    with reversible_solver(100):
        j_u = jax.jit(jax.jacrev(accel))(mu)
    np.testing.assert_array_equal(np.asarray(v_i), np.asarray(plain(mu)))
    ctx = mjx_solver.Context.create(m, mjx.forward(m, pressed), grad=False)
    assert float(jnp.abs(ctx.h).max()) > 0, "no contact on the cone's surface"
    eps = 1e-3
    fd = (np.asarray(plain(mu + eps)) - np.asarray(plain(mu - eps))) / (2 * eps)
    j_i, j_u = np.asarray(j_i), np.asarray(j_u)
    assert np.linalg.norm(fd) > 1.0, fd
    assert np.linalg.norm(j_i - fd) <= 1e-3 * np.linalg.norm(fd), (j_i, fd)
    assert np.linalg.norm(j_i - j_u) <= 1e-3 * np.linalg.norm(fd), (j_i, j_u)

    def rate(u):
        mm = with_mu(u)
        _, v = jax.lax.scan(lambda x, _: (mjx.step(mm, x), x.qvel[0]), d, None, length=300)
        return (v[-1] - v[100]) / (199 * 0.005)

    with implicit_solver():
        a, da = jax.jit(jax.value_and_grad(rate))(mu)
    np.testing.assert_allclose(float(a), g * (np.sin(th) - 0.2 * np.cos(th)), rtol=0.03)  # sliding, not stuck
    np.testing.assert_allclose(float(da), -g * np.cos(th), rtol=0.03)


def test_solver_grad_is_checked_before_tracing():
    with pytest.raises(ValueError, match="rollout.solver_grad='newton'"):
        RolloutConfig(solver_grad="newton").validate()
    robot = luneckas2020()
    with pytest.raises(ValueError, match="pyramidal"):  # forward mode's matrix-free rows are pyramidal rows
        rollout_function(robot, GaitController(robot), 0.1,
                         config=RolloutConfig(solver_grad="implicit", grad_mode="forward"),
                         physics=dataclasses.replace(PhysicsConfig(), cone="elliptic"))


def test_a_step_reads_nothing_of_the_last_step_outside_grad_fields():
    """A rollout stops the gradient on every float field of mjx.Data outside `hexjax.sim.step.GRAD_FIELDS`
    (`stop_derived`) between control steps and between the physics steps inside one, which is right only if
    nothing a step computes depends on those fields of the last step's Data. Checked on the traced control step
    (JAX's dead-code elimination): what it hands on (the next Data's GRAD_FIELDS, the controller state, the
    summary's accumulators, the recorded traces) depends on the last Data's float fields in GRAD_FIELDS only
    (fields of size 0 aside: this robot has no tendons). The step covers MJX's physics steps and everything
    hexjax reads from the last Data (foot sites for the slot assignment, contact forces and frames for the
    tactile pads), here on obstacle terrain (slots) with the tactile gait. A value that does not depend on a
    field has no derivative through it, so the rollout's gradient is the same with the cut and without. (This
    replaced two tests that compared those gradients numerically, a 5-step MJX Jacobian and a tactile rollout
    gradient on high-small, 7-8 min of compile on 2 cores; the check is the stronger, the cause of equality.)"""
    from jax._src.interpreters import partial_eval as pe

    from hexjax.sim.config import SensorConfig, settle_steps
    from hexjax.sim.step import GRAD_FIELDS, init_acc, make_control_step
    from hexjax.tune.gradcheck import check_batch, tactile_check_setting
    from hexjax.world.presets import get_terrain

    robot = luneckas2020()
    ctrl, p = tactile_check_setting(robot)
    spec = get_terrain("high-small")
    terr, keys = check_batch(spec, 1)
    terr = jax.tree_util.tree_map(lambda x: x[0], terr)
    rc = RolloutConfig(settle_time=0.1, record=True)
    sm = sim_model(robot, physics_for(spec.kind))
    assert sm.physics.slots_per_leg > 0
    n_settle = settle_steps(rc, ctrl.dt)
    step = make_control_step(sm, SensorConfig(), rc, ctrl, n_settle)
    d = sm.init_data(jnp.zeros(3))
    leaves, tree = jax.tree_util.tree_flatten_with_path(d)
    names = [jax.tree_util.keystr(k) for k, _ in leaves]
    assert GRAD_FIELDS <= set(names), sorted(GRAD_FIELDS - set(names))  # a field MJX renamed would slip the cut
    floats = [i for i, (_, x) in enumerate(leaves) if jnp.issubdtype(x.dtype, jnp.inexact) and x.size]
    carry = (ctrl.init(p, keys[0]), init_acc(jnp.zeros(3)))

    def handed_on(*xs):
        values = [x for _, x in leaves]
        for i, x in zip(floats, xs):
            values[i] = x
        (d2, *rest), rec = step((jax.tree_util.tree_unflatten(tree, values), *carry), jnp.int32(n_settle + 3), p,
                                terr, sm.mjx_model, jnp.asarray(sm.ctrl0))
        nxt = [x for k, x in jax.tree_util.tree_flatten_with_path(d2)[0] if jax.tree_util.keystr(k) in GRAD_FIELDS]
        return nxt, rest, rec

    closed = jax.make_jaxpr(handed_on)(*[jax.ShapeDtypeStruct(leaves[i][1].shape, leaves[i][1].dtype) for i in floats])
    _, used = pe.dce_jaxpr(closed.jaxpr, [True] * len(closed.jaxpr.outvars))
    read = {names[i] for i, u in zip(floats, used) if u}
    assert {".qpos", ".qvel", ".site_xpos", "._impl.efc_force"} <= read, sorted(read)  # the check sees reads
    assert read <= GRAD_FIELDS, sorted(read - GRAD_FIELDS)


def test_backward_keeps_only_what_it_reads(standing):
    """The implicit backward stores, per physics step, only the arrays whose values it reads (mass matrix and
    constraint rows), not the whole mjx.Data: if JAX's dead-code pass moved and the fallback kept everything,
    the gradient would stay right but cost memory and time on every step."""
    from hexjax.sim.internals import implicit

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
    from hexjax.sim.step import physics, stop_derived

    m, d = standing
    w = jnp.asarray(np.random.RandomState(1).randn(m.nu).astype(np.float32))

    def f(unroll):
        def g(a):
            out, power = physics(m, d.replace(ctrl=d.ctrl + a * 0.3 * w), 2, detach=stop_derived, unroll=unroll)
            return jnp.concatenate([out.qpos, out.qvel, power])
        # kept on disk: as a plain jax.jit its persistent-cache key changed with what the worker ran before (two
        # compiles, 11 s, in one warm run of the suite)
        return _kept(g, d, "physics2", "unrolled" if unroll else "scan")
    v0, v1 = (np.asarray(f(u)(1.0)) for u in (False, True))
    assert np.abs(v0[:3] - np.asarray(d.qpos[:3])).max() > 1e-6  # the steps moved the robot
    # XLA fuses the loop body and the unrolled steps differently: equal to float32 rounding (measured 1.3e-5)
    np.testing.assert_allclose(v1, v0, rtol=1e-4, atol=1e-5)


def test_rotation_rule_keeps_mjx_values_and_derivative():
    """`hexjax.sim.internals.rules.rotation_rule`, under which every rollout that reverse mode goes through is traced: MJX's
    rotation matrices bit for bit, their Jacobian (reverse and forward mode) equal to MJX's own, and MJX's function
    back in place after the context, also when the body raises."""
    from mujoco.mjx._src import math as mjx_math

    from hexjax.sim.internals.rules import rotation_rule

    mjx_q2m = mjx_math.quat_to_mat
    q = jax.random.normal(jax.random.PRNGKey(3), (64, 4))
    q = q.at[:48].set(q[:48] / jnp.linalg.norm(q[:48], axis=-1, keepdims=True))  # unit and non-unit quaternions
    with rotation_rule():
        ruled = mjx_math.quat_to_mat
    assert ruled is not mjx_q2m and mjx_math.quat_to_mat is mjx_q2m
    np.testing.assert_array_equal(jax.vmap(ruled)(q), jax.vmap(mjx_q2m)(q))
    for jac in (jax.jacrev, jax.jacfwd):
        got, want = jax.vmap(jac(ruled))(q), jax.vmap(jac(mjx_q2m))(q)
        assert float(jnp.abs(want).max()) > 0.5
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
    with pytest.raises(RuntimeError, match="inside"):
        with rotation_rule():
            raise RuntimeError("inside")
    assert mjx_math.quat_to_mat is mjx_q2m


def test_unrolled_gradient_through_the_elliptic_cone_is_finite_and_matches_differences():
    """The `validated` preset's elliptic cone: the robot standing on flat ground (feet in contact, the parked
    slots without friction force) stepped 5 times with the unrolled solver. MJX's elliptic line search takes the
    square root of each contact's tangential force squared, 0 for a contact without friction force; with
    jnp.sqrt's infinite derivative there the whole gradient was NaN. `reversible_solver` gives that root a
    finite derivative (`hexjax.sim.internals.rules._sqrt`, whose values are jnp.sqrt's bit for bit): the derivative of the
    torso's x in a sweep of the servo targets is finite and matches central differences."""
    from hexjax.sim.internals.rules import _sqrt
    x = jnp.array([0.0, 4.0, 2.25])
    np.testing.assert_array_equal(np.asarray(_sqrt(x)), np.sqrt(np.asarray(x)))
    np.testing.assert_allclose(np.asarray(jax.vmap(jax.grad(_sqrt))(x)), [0.0, 0.25, 1 / 3], rtol=1e-6)

    phys = dataclasses.replace(physics_for("flat"), iterations=8, ls_iterations=8, cone="elliptic")
    sm = sim_model(ROBOT, phys)
    m = sm.mjx_model
    d = sm.init_data(jnp.zeros(3))
    ctrl0 = jnp.asarray(sm.ctrl0)
    d = d.replace(ctrl=ctrl0, qpos=d.qpos.at[7:].set(ctrl0))
    d = jax.jit(lambda d: jax.lax.fori_loop(0, 100, lambda i, x: mjx.step(m, x), d))(d)
    sweep = _walk(m, d, 5)  # the servo targets swept by a * w sin(t) for 5 steps

    def torso_x(a):
        return sweep(a)[0]

    plain = jax.jit(lambda a: torso_x(a))(jnp.float32(0.01))
    with reversible_solver(8):
        v, g = jax.jit(jax.value_and_grad(torso_x))(jnp.float32(0.01))
        f = jax.jit(lambda a: torso_x(a))
        eps = 1e-3
        fd = (f(jnp.float32(0.01 + eps)) - f(jnp.float32(0.01 - eps))) / (2 * eps)
    assert np.isfinite(float(g)), "NaN through the elliptic cone"
    np.testing.assert_allclose(float(v), float(plain), rtol=1e-3)  # MJX's while loop's value (other rounding)
    np.testing.assert_allclose(float(g), float(fd), rtol=0.05, atol=1e-7)
