"""The Yu 2019 CPG controller against a kinematic stand-in world (no physics): feet follow the joint
commands exactly, the ground under each leg is a height, contact forces are a stiff penalty. Fast and
deterministic, so the FSM, the reflexes and the hard/smooth forms can be checked step by step (jitted)."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.control.cpg import (MODE_NAMES, TRIPOD_GROUP, CPGController, converter_output, converter_points,
                               linear_converter)
from hexjax.control.vdp import locked_state
from hexjax.sim.model import Obs
from hexjax.world.presets import get_robot
from hexjax.world.robot import forward_sign, leg_fk

ROBOT = get_robot("yu2019")
RF = 3  # the paper's Leg4: right front


def _obs(q, floor, wall_x, wall_top, t):
    """Obs of the stand-in world. q (6, 3) joints = measured; floor (6,) ground height in each leg frame,
    m; a wall at forward distance wall_x (6,) up to wall_top (6,) pushes back on a foot inside it."""
    p = leg_fk(ROBOT, q)
    fwd = p[:, 1] * jnp.asarray(forward_sign())
    pen = floor - p[:, 2]
    fz = jnp.where(pen > 0, 15.0 + 2000.0 * pen, 0.0)
    in_wall = (fwd > wall_x) & (p[:, 2] < wall_top)
    fx = jnp.where(in_wall, -25.0, 0.0)
    force = jnp.stack([fx, jnp.zeros(6), fz], -1)
    return Obs(qpos=q.reshape(-1), qvel=jnp.zeros(18), torso_pos=jnp.zeros(3),
               torso_quat=jnp.array([1.0, 0.0, 0.0, 0.0]), foot_force=force, foot_contact=fz > 0.5,
               tactile_force=jnp.zeros(6), tactile=jnp.zeros(6, bool), time=t)


N_MAX = 4000  # control steps of the longest stand-in walk (80 s): every walk runs this long and is cut


@functools.partial(jax.jit, static_argnums=0)
def _run(ctrl, params, z0, delta, t_on, t_off, wall_x, wall_top):
    """One compiled program per controller: the floor under each leg is z0, plus delta (6,) between t_on and
    t_off s; walls as in `_obs`. Returns the stacked states (N_MAX, ...)."""
    def body(s, i):
        t = i * ctrl.dt
        floor = z0 + jnp.where((t > t_on) & (t < t_off), delta, 0.0)
        s, _ = ctrl.step(params, s, _obs(s.q_cmd, floor, wall_x, wall_top, t))
        return s, s

    return jax.lax.scan(body, ctrl.init(params, None), jnp.arange(N_MAX))[1]


def _walk(ctrl, params, seconds, z0, delta=0.0, t_on=0.0, t_off=np.inf, wall_x=None, wall_top=None):
    """The controller in the stand-in world for `seconds`; returns the stacked states (T, ...)."""
    wall_x = jnp.full(6, 10.0) if wall_x is None else wall_x
    wall_top = jnp.full(6, -10.0) if wall_top is None else wall_top
    st = _run(ctrl, params, jnp.float32(z0), jnp.broadcast_to(jnp.asarray(delta, jnp.float32), (6,)),
              jnp.float32(t_on), jnp.float32(t_off), wall_x, wall_top)
    n = int(round(seconds / ctrl.dt))
    return jax.tree_util.tree_map(lambda a: a[:n], st)


def _rf(value):
    """(6,): `value` under RF, 0 elsewhere."""
    return jnp.zeros(6).at[RF].set(value)


def _z_aep(ctrl, p):
    """Ground height in the leg frames: the nominal AEP height raised 2 mm, because in the physics model
    the loaded servos let the torso sit a few mm low (a foot swung to the nominal AEP then presses)."""
    return -(float(p.body_height) - ROBOT.foot_radius) + 0.002


def test_converter_hits_aep_pep_apex_and_stance_midpoint():
    """Eq. 6 coefficients from IK (Sect. 3.2): on the locked cycle the converter puts the foot on the
    four design points within 1 mm."""
    ctrl = CPGController(ROBOT)
    p = ctrl.default_params()
    lc = linear_converter(ROBOT, p, ctrl.stance_radial)
    pts = np.asarray(converter_points(ROBOT, p.step_length, p.clearance, p.body_height, ctrl.stance_radial))
    w = float(p.net.omega[0])
    zero = jnp.zeros(6)
    cases = [  # (leader phase, swing?, design point index) ; x1 = cos(theta)
        (math.pi, 1.0, 1), (1.5 * math.pi, 1.0, 3), (0.0, 1.0, 0), (0.5 * math.pi, 0.0, 2), (0.0, 0.0, 0)]
    for theta, sw, k in cases:
        z = locked_state(jnp.full(6, theta), w)
        q = converter_output(p, lc, z, jnp.full(6, sw), zero, jnp.zeros((6, 3)), jnp.zeros((6, 3)), zero)
        np.testing.assert_allclose(np.asarray(leg_fk(ROBOT, q)), pts[:, k], atol=1e-3)


def test_flat_stand_in_world_walks_a_regular_tripod():
    """No reflex fires on flat ground; the two tripod groups alternate, each leg swinging once per 5 s
    (T_g = 2 pi / omega_1, Sect. 6.1.1), and the FSM holds are brief hand-overs."""
    ctrl = CPGController(ROBOT)
    p = ctrl.default_params()
    z0 = _z_aep(ctrl, p)
    st = _walk(ctrl, p, 20.0, z0)
    fs = jax.tree_util.tree_map(lambda a: np.asarray(a[-1]), st)
    assert fs.n_elev.sum() == 0 and fs.n_search.sum() == 0
    swing = np.asarray(st.swing) > 0.5
    lifts = (np.diff(swing.astype(int), axis=0) == 1).sum(0)
    assert np.all((lifts >= 3) & (lifts <= 4)), lifts  # 20 s / 5 s, first swing starts at t = 0
    both = swing[:, TRIPOD_GROUP == 0].all(1) & swing[:, TRIPOD_GROUP == 1].any(1)
    assert not both.any()  # never a leg of each group in the air at once


def test_raised_foothold_sets_the_level_of_stance_and_next_swing():
    """A step top under RF (40 mm up from t = 3 s; down again from t = 30 s). The first swing that meets it
    lands early and records the foothold's level (40 mm within 3 mm); from then on RF's swings end on the
    top at the AEP (full strides, no early touchdown, no search) and, from the next touchdown on, its
    stance holds the foot on the top (the first touchdown is detected at the apex, 2-3 mm into the top).
    When the top ends the foot finds no ground at its AEP and the searching reflex takes it down (the
    third period reaches 40 mm), after which the level is zero again."""
    ctrl = CPGController(ROBOT)
    p = ctrl.default_params()
    z0 = _z_aep(ctrl, p)

    st = _walk(ctrl, p, 80.0, z0, _rf(0.04), 3.0, 30.0)
    t = np.arange(st.t.shape[0]) * ctrl.dt
    level = np.asarray(st.level[:, RF])
    first = np.nonzero(np.abs(level - 0.04) < 0.003)[0]
    assert first.size and t[first[0]] < 12.0, level.max()
    on_top = (t > t[first[0]]) & (t < 30.0)
    assert np.all(np.abs(level[on_top] - 0.04) < 0.003)
    # stance on the top: the foot stays on it (no gap above, no push-through deeper than 2 mm)
    z_foot = np.asarray(leg_fk(ROBOT, st.q_cmd[:, RF]))[:, 2]
    stance = on_top & (t > t[first[0]] + 5.0) & (np.asarray(st.swing[:, RF]) < 0.5) & (np.asarray(st.hold[:, RF]) < 0.5)
    assert stance.sum() > 100
    np.testing.assert_allclose(z_foot[stance], z0 + 0.04, atol=0.002)
    # swings on the top run to the AEP: the leader reaches x_1 ~ 1 before each touchdown
    x1 = np.asarray(st.z[:, RF, 0, 0])
    sw = np.asarray(st.swing[:, RF]) > 0.5
    ends = np.nonzero(sw[:-1] & ~sw[1:] & on_top[1:])[0]
    assert ends.size >= 2 and np.all(x1[ends] > 0.95), x1[ends]
    n_search = np.asarray(st.n_search[:, RF])
    assert n_search[on_top].max() == n_search[first[0]]
    # down again: found by a search, level back to ~0
    assert n_search[-1] > n_search[first[0]] and np.asarray(st.n_found[-1, RF]) >= 1
    assert abs(level[-1]) < 0.003, level[-1]


@pytest.mark.parametrize("depth,found", [(0.018, True), (0.040, True), (0.080, False)])
def test_searching_reflex_depths_and_fsm(depth, found):
    """Sect. 6.1.2 in the stand-in world: from t = 3 s the ground under RF (the paper's Leg4) is `depth`
    lower. 18 and 40 mm: the search finds it, the recorded depth is within 3 mm of it, and the gait goes
    on. 80 mm: beyond reach, so after `search_periods` the leg is back at its AEP posture (q_ref) and
    gives up; meanwhile the alien tripod stays in stance-prolong."""
    ctrl = CPGController(ROBOT)
    p = ctrl.default_params()
    z0 = _z_aep(ctrl, p)

    st = _walk(ctrl, p, 60.0, z0, _rf(-depth), 3.0)
    fs = jax.tree_util.tree_map(lambda a: np.asarray(a[-1]), st)
    mode = np.asarray(jax.vmap(CPGController.mode)(st))
    searching = mode[:, RF] == MODE_NAMES.index("search")
    assert searching.any() and fs.n_search[RF] >= 1
    alien = TRIPOD_GROUP != TRIPOD_GROUP[RF]
    # whenever RF has searched for more than 0.5 s, every alien leg waits in stance-prolong
    idx = np.nonzero(searching)[0]
    late = idx[idx > idx[0] + int(0.5 / ctrl.dt)]
    assert np.all(mode[late][:, alien] == MODE_NAMES.index("stance-prolong"))
    if found:
        assert fs.n_found[RF] >= 1 and fs.n_fail.sum() == 0
        assert abs(fs.depth[RF] - depth) < 0.003, fs.depth[RF]
        # the walk resumed: every leg swung again after the foothold was found
        t_found = np.nonzero(np.diff(np.asarray(st.n_found[:, RF])) > 0)[0][0]
        assert np.all(np.asarray(st.swing[t_found:]).max(0) > 0.5)
    else:
        assert fs.n_fail[RF] == 1 and fs.failed[RF] > 0.5 and fs.n_found[RF] == 0
        assert mode[-1, RF] == MODE_NAMES.index("search-failed")
        np.testing.assert_allclose(fs.q_cmd[RF], fs.q_ref[RF], atol=1e-6)
        assert np.all(mode[-1][alien] == MODE_NAMES.index("stance-prolong"))
        # the search lasted search_periods slowed leader periods (2 pi / (0.5 omega_1) = 10 s each)
        assert abs(searching.sum() * ctrl.dt - ctrl.search_periods * 10.0) < 1.0


def test_walk_on_after_a_give_up_releases_the_gait():
    """The 80 mm case with `walk_on`: the search gives up as before (one give-up after its search periods, the leg
    at its AEP posture), and then the gait goes on instead of waiting for good: the alien tripod swings again and
    RF, in the air over the hole, takes its next stance with its group and swings again after it."""
    ctrl = CPGController(ROBOT)
    p = ctrl.default_params(walk_on=1.0)
    z0 = _z_aep(ctrl, p)
    st = _walk(ctrl, p, 80.0, z0, _rf(-0.080), 3.0)
    n_fail = np.asarray(st.n_fail[:, RF])
    assert n_fail[-1] >= 1 and np.asarray(st.n_found[-1, RF]) == 0
    t_fail = int(np.nonzero(np.diff(n_fail) > 0)[0][0]) + 1
    alien = TRIPOD_GROUP != TRIPOD_GROUP[RF]
    swing = np.asarray(st.swing)
    assert np.all(swing[t_fail:, alien].max(0) > 0.5)  # every alien leg swung again
    assert swing[t_fail:, RF].min() < 0.5  # RF went into stance with its group
    # the waiting default never releases: after its give-up the alien legs never swing again
    hold = jax.tree_util.tree_map(np.asarray, _walk(ctrl, ctrl.default_params(), 80.0, z0, _rf(-0.080), 3.0))
    t_fail0 = int(np.nonzero(np.diff(hold.n_fail[:, RF]) > 0)[0][0]) + 1
    assert np.all(hold.swing[t_fail0:, alien].max(0) < 0.5)


def test_elevator_reflex_reverses_leader_and_raises_clearance():
    """Eqs. 10-11: RF meets a 40 mm wall 1 cm before its AEP. On the rising edge of lambda_ob the leader's
    y_1 jumps to -1 (retraction), and the regenerated swing reaches the 80 mm clearance, clearing the
    wall; without the reflex the foot stays pressed against it."""
    ctrl = CPGController(ROBOT)
    p = ctrl.default_params()
    z0 = _z_aep(ctrl, p)
    wall_x = jnp.full(6, 10.0).at[RF].set(0.5 * float(p.step_length) - 0.01)
    wall_top = jnp.full(6, -10.0).at[RF].set(z0 + 0.04)
    st = _walk(ctrl, p, 12.0, z0, wall_x=wall_x, wall_top=wall_top)
    n_elev = np.asarray(st.n_elev[:, RF])
    k = int(np.nonzero(np.diff(n_elev) > 0)[0][0]) + 1  # first step with the reflex fired
    assert abs(float(st.z[k, RF, 0, 1]) - (-1.0)) < 0.1  # y1 set to -1 (then one RK4 step)
    assert float(st.z[k - 1, RF, 0, 1]) > 0
    z_foot = np.asarray(leg_fk(ROBOT, st.q_cmd[k:, RF]))[:, 2]
    assert z_foot.max() - z0 > 0.075  # regenerated clearance ~80 mm
    assert np.asarray(st.elev[k:, RF]).max() == pytest.approx(1.0)
    # without the reflex: the `elevator` param off, the same compiled program (the static flag only sets the
    # default params)
    assert float(CPGController(ROBOT, elevator=False).default_params().elevator) == 0.0
    st_off = _walk(ctrl, p.replace(elevator=jnp.asarray(0.0)), 12.0, z0, wall_x=wall_x, wall_top=wall_top)
    assert np.asarray(st_off.n_elev).sum() == 0
    assert np.asarray(leg_fk(ROBOT, st_off.q_cmd[:, RF]))[:, 2].max() - z0 < 0.045


def test_smooth_form_tends_to_hard_form():
    """Every gate has a temperature; as they go to zero the smooth controller's joint commands approach
    the hard one's in a run with a search (18 mm ditch) and elevator events (wall). Small leaks of the
    smooth FSM compound over 25 s (at a scale of 1e-3 the commands still differed by 0.57 rad); from
    1e-5 down they were identical."""
    z0 = -(ROBOT.hip_height - ROBOT.foot_radius) + 0.002

    hard = CPGController(ROBOT)
    p = hard.default_params()
    wall_x = jnp.full(6, 10.0).at[1].set(0.5 * float(p.step_length) - 0.01)
    wall_top = jnp.full(6, -10.0).at[1].set(z0 + 0.04)
    q_hard = np.asarray(_walk(hard, p, 25.0, z0, _rf(-0.018), 3.0, wall_x=wall_x, wall_top=wall_top).q_cmd)
    assert float(CPGController(ROBOT, smooth=True).default_params().smooth) == 1.0
    errs = []
    for scale in (1.0, 1e-2, 1e-4, 1e-6):  # the `smooth` param on: the same compiled program as the hard run
        ps = p.replace(smooth=jnp.asarray(1.0), temp_force=p.temp_force * scale, temp_phase=p.temp_phase * scale,
                       temp_height=p.temp_height * scale)
        q_s = np.asarray(_walk(hard, ps, 25.0, z0, _rf(-0.018), 3.0, wall_x=wall_x, wall_top=wall_top).q_cmd)
        errs.append(np.abs(q_s - q_hard).max())
    print("smooth-hard max |dq| per temperature scale 1, 1e-2, 1e-4, 1e-6:", errs)
    assert errs[-1] < 0.02, errs  # rad
    assert errs[-1] < errs[0]


def test_straight_through_form_is_the_hard_controller_with_the_sigmoid_slope():
    """`straight_through=True` with the `smooth` param on (`hexjax.control.gates`): over the search-and-wall walk
    of the test above its states equal the hard controller's bit for bit, while reverse mode sees each gate's
    sigmoid. One step with the right front foot pushed back by 0.3 N more than F_contact-x: the obstacle
    neuron reads 1 (the hard value; the smooth form reads sigmoid(0.3) = 0.57), and its derivative with
    respect to F_contact-x is -sigmoid'(0.3 / T) / T, where the hard form's is 0."""
    z0 = -(ROBOT.hip_height - ROBOT.foot_radius) + 0.002
    hard, st = CPGController(ROBOT), CPGController(ROBOT, smooth=True, straight_through=True)
    p, ps = hard.default_params(), st.default_params()
    assert float(ps.smooth) == 1.0
    wall_x = jnp.full(6, 10.0).at[1].set(0.5 * float(p.step_length) - 0.01)
    wall_top = jnp.full(6, -10.0).at[1].set(z0 + 0.04)
    a = _walk(hard, p, 25.0, z0, _rf(-0.018), 3.0, wall_x=wall_x, wall_top=wall_top)
    b = _walk(st, ps, 25.0, z0, _rf(-0.018), 3.0, wall_x=wall_x, wall_top=wall_top)
    assert int(np.asarray(a.n_elev).max()) >= 1 and int(np.asarray(a.n_search).max()) >= 1  # both events happen
    for name, x, y in zip(a.__dataclass_fields__, jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=name)

    force = jnp.zeros((6, 3)).at[RF, 0].set(-(float(p.f_contact[1]) + 0.3)).at[:, 2].set(15.0)
    s0 = hard.init(p, None)
    obs = Obs(qpos=s0.q_cmd.reshape(-1), qvel=jnp.zeros(18), torso_pos=jnp.zeros(3),
              torso_quat=jnp.array([1.0, 0.0, 0.0, 0.0]), foot_force=force, foot_contact=jnp.ones(6, bool),
              tactile_force=jnp.zeros(6), tactile=jnp.zeros(6, bool), time=jnp.float32(0.0))

    def lam_ob(ctrl, params, fc):
        return ctrl.step(params.replace(f_contact=fc), s0, obs)[0].lam_ob[RF]

    fc = p.f_contact
    assert float(lam_ob(st, ps, fc)) == 1.0 and float(lam_ob(hard, p, fc)) == 1.0
    assert abs(float(lam_ob(CPGController(ROBOT, smooth=True), ps, fc)) - float(jax.nn.sigmoid(0.3))) < 1e-3
    temp = float(p.temp_force)
    sig = float(jax.nn.sigmoid(0.3 / temp))
    g_st = np.asarray(jax.grad(lambda f: lam_ob(st, ps, f))(fc))
    np.testing.assert_allclose(g_st, [0.0, -sig * (1 - sig) / temp, 0.0], rtol=1e-4, atol=1e-7)
    assert np.all(np.asarray(jax.grad(lambda f: lam_ob(hard, p, f))(fc)) == 0.0)


def test_bad_params_raise_before_tracing():
    ctrl = CPGController(ROBOT)
    p = ctrl.default_params()
    with pytest.raises(ValueError, match="cpg.clearance"):
        ctrl.validate_params(p.replace(clearance=jnp.asarray(-0.01)))
    with pytest.raises(ValueError, match="cpg.f_contact"):
        ctrl.validate_params(p.replace(f_contact=jnp.array([10.0, -1.0, 2.0])))
    with pytest.raises(ValueError, match="out of reach"):
        ctrl.validate_params(p.replace(elevated_clearance=jnp.asarray(0.5)))
    with pytest.raises(ValueError, match="cpg.duty"):
        ctrl.validate_params(p.replace(duty=jnp.asarray(1.0)))
    with pytest.raises(ValueError, match="cpg.gait"):
        CPGController(ROBOT, gait="gallop")
    with pytest.raises(ValueError, match="cpg.stance_radial"):
        CPGController(ROBOT, stance_radial=-0.1)
    # a batch of params (an evolution strategy's population on its terrains): one short line naming the first
    # offending member, not every value
    batch = p.replace(clearance=jnp.full(512, 0.05), elevated_clearance=jnp.full(512, 0.06).at[300].set(0.04))
    with pytest.raises(ValueError) as err:
        ctrl.validate_params(batch)
    msg = str(err.value)
    assert msg == ("cpg.elevated_clearance=0.04 at (300,) (shape (512,)): must be >= clearance=0.05 at (300,) "
                   "(shape (512,))")


def test_each_leg_has_its_own_converter_clearance_and_thresholds():
    """The per-leg params (`leg_trim`, `leg_clearance`, `leg_f_scale`): a leg's own number moves that leg's
    converter or gate and no other, and the same number on every leg is the paper's shared one."""
    ctrl = CPGController(ROBOT)
    p = ctrl.default_params()
    lc = linear_converter(ROBOT, p, ctrl.stance_radial)
    d = jnp.array([[[0.02, -0.01, 0.03], [0.01, 0.0, -0.02]], [[-0.03, 0.02, 0.0], [0.0, 0.01, 0.02]]])
    shared = linear_converter(ROBOT, p.replace(lc_trim=d), ctrl.stance_radial)
    each = linear_converter(ROBOT, p.replace(leg_trim=jnp.broadcast_to(d, (6, 2, 2, 3))), ctrl.stance_radial)
    for f in ("g_sw", "h_sw", "g_st", "h_st", "dg_sw", "dh_sw"):
        np.testing.assert_array_equal(np.asarray(getattr(shared, f)), np.asarray(getattr(each, f)), err_msg=f)
    one = linear_converter(ROBOT, p.replace(leg_trim=jnp.zeros((6, 2, 2, 3)).at[RF].set(d)), ctrl.stance_radial)
    moved = np.abs(np.asarray(one.g_sw) - np.asarray(lc.g_sw)).sum(-1) + np.abs(np.asarray(one.h_st) - np.asarray(lc.h_st)).sum(-1)
    assert moved[RF] > 0 and np.all(np.delete(moved, RF) == 0)
    # a leg's clearance: its swing set's apex rises by the offset, every other leg's stays
    up = p.replace(leg_clearance=jnp.zeros(6).at[RF].set(0.01))
    q = converter_output(up, linear_converter(ROBOT, up, ctrl.stance_radial), jnp.ones((6, 3, 2)), jnp.ones(6),
                         jnp.zeros(6), jnp.zeros((6, 3)), jnp.zeros((6, 3)), jnp.zeros(6))
    q0 = converter_output(p, lc, jnp.ones((6, 3, 2)), jnp.ones(6), jnp.zeros(6), jnp.zeros((6, 3)),
                          jnp.zeros((6, 3)), jnp.zeros(6))
    z, z0 = np.asarray(leg_fk(ROBOT, q))[:, 2], np.asarray(leg_fk(ROBOT, q0))[:, 2]
    assert abs((z - z0)[RF] - 0.01) < 1e-4 and np.all(np.abs(np.delete(z - z0, RF)) < 1e-6)
    # a leg's thresholds: RF pushed 0.3 N past F_contact-y sees an obstacle; doubling only its factor hides it
    force = jnp.zeros((6, 3)).at[:, 0].set(-(float(p.f_contact[1]) + 0.3)).at[:, 2].set(15.0)
    s0 = ctrl.init(p, None)
    obs = Obs(qpos=s0.q_cmd.reshape(-1), qvel=jnp.zeros(18), torso_pos=jnp.zeros(3),
              torso_quat=jnp.array([1.0, 0.0, 0.0, 0.0]), foot_force=force, foot_contact=jnp.ones(6, bool),
              tactile_force=jnp.zeros(6), tactile=jnp.zeros(6, bool), time=jnp.float32(0.0))
    seen = np.asarray(ctrl.step(p, s0, obs)[0].lam_ob)
    hid = np.asarray(ctrl.step(p.replace(leg_f_scale=jnp.ones((6, 3)).at[RF].set(2.0)), s0, obs)[0].lam_ob)
    assert np.all(seen == 1.0) and hid[RF] == 0.0 and np.all(np.delete(hid, RF) == 1.0)
    with pytest.raises(ValueError, match="cpg.leg_f_scale"):
        ctrl.validate_params(p.replace(leg_f_scale=jnp.ones((6, 3)).at[0, 2].set(0.0)))
    with pytest.raises(ValueError, match="cpg.leg_trim shape"):
        ctrl.validate_params(p.replace(leg_trim=jnp.zeros((2, 2, 3))))
    with pytest.raises(ValueError, match="leg_clearance"):
        ctrl.validate_params(p.replace(leg_clearance=jnp.zeros(6).at[2].set(-0.05)))
