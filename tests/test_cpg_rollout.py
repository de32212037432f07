"""The Yu 2019 CPG controller inside the batched MJX rollout (seeded, jitted; shapes kept small)."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.control.cpg import CPGController, gait_fields
from hexjax.sim.config import RolloutConfig, physics_for
from hexjax.sim.rollout import rollout
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import sample

ROBOT = get_robot("yu2019")
FLAT = physics_for("flat")


def _stack(params_list):
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *params_list)


@pytest.mark.cost(70)
def test_tripod_tetrapod_wave_walk_1m_on_flat_ground():
    """Eq. 16 gaits (gamma = 2, 3, 6), two robots each with random headings, one compiled rollout (the
    gait is a traced parameter): every robot covers >= 1 m in 66 s without falling or NaN. Nominal
    speeds are 2 l gamma / ((gamma - 1) T_g) / 2: 2.8, 2.1 and 1.7 cm/s for l = 7 cm, T_g = 5 s."""
    ctrl = CPGController(ROBOT)
    gaits = ["tripod", "tetrapod", "wave"] * 2
    params = _stack([ctrl.default_params(**gait_fields(g)) for g in gaits])
    terrain = sample(get_terrain("flat"), jax.random.PRNGKey(0), len(gaits))
    s = rollout(ROBOT, terrain, ctrl, params, 66.0, jax.random.PRNGKey(3), physics=FLAT, params_batched=True)
    advance = np.asarray(s.end_pose[:, 0] - s.start_pose[:, 0])
    assert not np.asarray(s.fell).any() and not np.asarray(s.nan).any()
    assert np.all(advance >= 1.0), dict(zip(gaits, advance.round(3)))
    # the slower gaits are slower, as Eq. 16 says
    assert advance[0] > advance[1] > advance[2] and advance[3] > advance[4] > advance[5]


@pytest.mark.cost(55)
def test_toe_forces_point_up_on_terrain_boxes():
    """The robot stands on a slab (a terrain box; the ditch terrain's ground plane is 18 mm lower): the
    toe forces it reads are upward and carry its weight (MJX orders box pairs the other way round from
    plane pairs; see SimModel.contact_sign)."""
    ctrl = CPGController(ROBOT)
    p = ctrl.default_params()
    terrain = sample(get_terrain("ditch18"), jax.random.PRNGKey(0), 1)
    s = rollout(ROBOT, terrain, ctrl, p, 1.0, jax.random.PRNGKey(1), physics=physics_for("ditch"),
                config=RolloutConfig(record=True, yaw_noise=0.0))
    f = np.asarray(s.ctrl_trace["force"][0])  # (T, 6, 3) torso frame
    total = f[:, :, 2].sum(-1)
    weight = ROBOT.total_mass * 9.81
    assert np.all(f[:, :, 2] > -0.5)
    np.testing.assert_allclose(total[-10:].mean(), weight, rtol=0.15)


@pytest.mark.cost(100)
def test_smooth_rollout_tends_to_hard_rollout():
    """Smooth gates with temperatures scaled by 1 ... 1e-6 against the hard controller, 10 s on flat ground, in
    one compiled, batched rollout (the form is the `smooth` param): the smooth runs' advance and heading
    approach the hard run's, down to the floor set by the simulation itself, measured as the hard run moved
    by its body height changed by 0.1 um (~7 float32 ulps: rounding amplified by the contacts; the same
    hard rollout compiled for 1 and for 4 envs differs by ~1 cm and ~0.04 rad after 10 s)."""
    ctrl = CPGController(ROBOT)
    p = ctrl.default_params()
    scales = [1.0, 1e-2, 1e-4, 1e-6]
    rows = [p.replace(smooth=jnp.asarray(1.0), temp_force=p.temp_force * k, temp_phase=p.temp_phase * k,
                      temp_height=p.temp_height * k) for k in scales]
    rows += [p, p.replace(body_height=p.body_height + 1e-7)]
    terrain = sample(get_terrain("flat"), jax.random.PRNGKey(0), len(rows))
    s = rollout(ROBOT, terrain, ctrl, _stack(rows), 10.0, jax.random.PRNGKey(1), physics=FLAT,
                config=RolloutConfig(yaw_noise=0.0), params_batched=True)
    delta = np.asarray(s.end_pose - s.start_pose)
    hard, nudged = delta[4], delta[5]
    floor = np.abs(nudged - hard).max()
    err = np.abs(delta[:4] - hard).max(-1)
    print("smooth vs hard, max |d advance|, |d heading| per temperature scale", scales, err, "floor", floor)
    assert err[0] > 5 * max(floor, 0.01)  # at the default temperatures the forms do differ
    assert err[-1] <= 2 * floor + 0.005, (err, floor)


def test_cpg_rollout_rejects_bad_params_before_tracing():
    ctrl = CPGController(ROBOT)
    p = ctrl.default_params()
    terrain = sample(get_terrain("flat"), jax.random.PRNGKey(0), 1)
    with pytest.raises(ValueError, match="cpg.step_length"):
        rollout(ROBOT, terrain, ctrl, p.replace(step_length=jnp.asarray(0.0)), 1.0, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="cpg.leg_slot"):
        rollout(ROBOT, terrain, ctrl, p.replace(leg_slot=jnp.full(6, 5.0)), 1.0, jax.random.PRNGKey(0))


def test_experiment_rejects_bad_input():
    from hexjax.experiments.papers.yu2019.steps import run_experiment
    with pytest.raises(ValueError, match="experiment 'yu2019-stairs' unknown"):
        run_experiment("yu2019-stairs")
    with pytest.raises(ValueError, match="batch=0"):
        run_experiment("yu2019-step", batch=0)
    with pytest.raises(ValueError, match="duration=-1"):
        run_experiment("yu2019-ditch", duration=-1.0)
