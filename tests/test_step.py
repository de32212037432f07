"""The control step's pieces (hexjax.sim.step), worked by hand: the fall test and the summary accumulators
that the MJX rollout, the MuJoCo C backend and the Brax env share."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.sim.config import PhysicsConfig, RolloutConfig, control_steps, settle_steps, substeps, total_physics_steps
from hexjax.sim.step import StepClock, accumulate, fall_state, init_acc, tilt


def _q(x, y, z, yaw=0.0, roll=0.0):
    """Generalised position (25,): torso at (x, y, z), heading yaw then roll about the torso x axis."""
    cy, sy, cr, sr = math.cos(yaw / 2), math.sin(yaw / 2), math.cos(roll / 2), math.sin(roll / 2)
    quat = [cy * cr, cy * sr, sy * sr, sy * cr]  # q_yaw * q_roll
    return jnp.asarray([x, y, z, *quat] + [0.0] * 18, jnp.float32)


def test_counts():
    assert substeps(PhysicsConfig(timestep=0.005), 0.02) == 4
    with pytest.raises(ValueError, match="whole multiple"):
        substeps(PhysicsConfig(timestep=0.003), 0.02)
    assert settle_steps(RolloutConfig(settle_time=0.3), 0.02) == 15
    assert control_steps(1.0, 0.02) == 50 and control_steps(1.01, 0.02) == 51
    # 15 settling + 50 walking control steps of 4 physics steps each
    assert total_physics_steps(RolloutConfig(settle_time=0.3), PhysicsConfig(timestep=0.005), 0.02, 50) == 260


def test_fall_state_is_tilt_or_height():
    cfg = RolloutConfig()  # 60 deg, 3 cm
    for roll, z, ground, fallen in ((0.0, 0.1, 0.0, False), (math.radians(59), 0.1, 0.0, False),
                                    (math.radians(61), 0.1, 0.0, True), (0.0, 0.029, 0.0, True),
                                    (0.0, 0.01, -0.04, False)):  # a ditch floor 4 cm down: 5 cm above it
        f, t, h = fall_state(cfg, _q(0.0, 0.0, z, yaw=1.0, roll=roll), ground)
        assert bool(f) == fallen, (roll, z, ground)
        assert float(t) == pytest.approx(max(roll, 1.4e-3), abs=2e-3)
        assert float(h) == pytest.approx(z - ground, abs=1e-7)
    assert float(tilt(_q(0, 0, 0, roll=math.pi / 2)[3:7])) == pytest.approx(math.pi / 2, abs=1e-4)


def test_accumulators_worked_by_hand():
    """Two settling steps, then three walking steps: the start pose is the pose after the last settling
    step; travel and path sum the walking steps only; the heading change crosses +-pi and unwraps; a fall
    at walking step 2 is timed at 2 dt; energy skips the non-finite step; tactile counts walking steps."""
    cfg, dt, n_settle = RolloutConfig(), 0.02, 2
    step = jax.jit(lambda acc, i, qo, qn, fin, e, tac: accumulate(acc, cfg, StepClock(i, n_settle, dt), qo, qn, fin, e,
                                                                  tac, 0.0))
    poses = [_q(0.0, 0.0, 0.1, 3.0), _q(0.01, 0.0, 0.1, 3.1),  # settling
             _q(0.04, 0.04, 0.1, -3.1),  # walk: (0.03, 0.04) and yaw 3.1 -> -3.1 (+0.083 rad through pi)
             _q(0.04, 0.04, 0.02, -3.1),  # falls (torso 2 cm over the ground)
             _q(0.04, 0.04, 0.02, -3.1)]  # non-finite step: state kept
    acc = init_acc(jnp.array([0.0, 0.0, 3.0]))
    tactile = jnp.array([True, False, False, False, False, True])
    q_old = _q(0.0, 0.0, 0.1, 3.0)
    for i, (q_new, fin, e) in enumerate(zip(poses, [True, True, True, True, False], [9.0, 9.0, 1.0, 2.0, 4.0])):
        acc = step(acc, i, q_old, q_new, jnp.asarray(fin), jnp.float32(e), tactile)
        q_old = q_new
    a = jax.tree_util.tree_map(np.asarray, acc)
    np.testing.assert_allclose(a["start_pose"], [0.01, 0.0, 3.1], atol=1e-6)
    np.testing.assert_allclose(a["travel"], [0.03, 0.04, 2 * math.pi - 6.2], atol=1e-5)
    assert a["path_length"] == pytest.approx(0.05, abs=1e-6)
    assert a["energy"] == pytest.approx(3.0) and bool(a["nan"]) and bool(a["fell"])
    assert a["fall_time"] == pytest.approx(2 * dt) and a["min_height"] == pytest.approx(0.02, abs=1e-7)
    np.testing.assert_array_equal(a["tactile_steps"], [3, 0, 0, 0, 0, 3])


@pytest.mark.cost(60)
def test_the_mjx_and_c_backends_run_one_controller_phase_and_one_summarise(monkeypatch):
    """Both backends run their controller through `step.controller_phase` and build their `Summary` with
    `step.summarise`: with those two wrapped here, the MJX scan and the MuJoCo C backend each call the phase,
    and the mark the wrapped `summarise` leaves (an energy of -7 J) is in both backends' summaries."""
    from hexjax import cache
    from hexjax.control.registry import make_controller
    from hexjax.sim import rollout as rollout_module
    from hexjax.sim import step
    from hexjax.sim.engines import c as mujoco_c
    from hexjax.sim.engines import mjx as mjx_engine
    from hexjax.world.presets import get_robot, get_terrain
    from hexjax.world.terrain import sample

    robot = get_robot("luneckas2020")
    ctrl = make_controller("gait", robot)
    terrain = sample(get_terrain("flat"), jax.random.PRNGKey(0), 2)
    phase_calls, step_phase, summarise = [], step.controller_phase, step.summarise

    def phase(*args, **kwargs):
        phase_calls.append(1)
        return step_phase(*args, **kwargs)

    def marked(acc, qpos_end, final_state, **traces):
        return summarise(dict(acc, energy=jnp.full_like(acc["energy"], -7.0)), qpos_end, final_state, **traces)

    caches = (mjx_engine.compiled_rollout, mujoco_c._controller_fns)
    # no kept programs: one loaded from disk is not traced (so calls neither wrapper), and one kept from here
    # would hand the -7 J mark to every later run of this setting, as its key names only the source files
    monkeypatch.setenv(cache.ENV, "off")
    monkeypatch.setattr(step, "controller_phase", phase)
    monkeypatch.setattr(step, "summarise", marked)
    try:
        for backend in ("mjx", "c"):
            for c in caches:  # the compiled functions of earlier tests hold the unwrapped ones
                c.cache_clear()
            phase_calls.clear()
            s = rollout_module.rollout(robot, terrain, ctrl, ctrl.default_params(), 0.1, jax.random.PRNGKey(1),
                                       engine=backend, nthread=1)
            assert phase_calls, backend
            assert np.all(np.asarray(s.energy) == -7.0), (backend, s.energy)
            assert np.all(np.isfinite(np.asarray(s.end_pose))), backend
    finally:
        for c in caches:  # nor may a later test get the wrapped ones
            c.cache_clear()
