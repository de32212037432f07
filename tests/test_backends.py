"""The rollout's physics backends: MuJoCo C on host threads and MJX with MuJoCo Warp kernels walk
the same robot, terrain and tactile controller as the default MJX (JAX) backend and report the same summary."""

import os

import jax
import mujoco
import numpy as np
import pytest

from hexjax.control.tactile import TactileGaitController
from hexjax.sim.config import PhysicsConfig, RolloutConfig, SensorConfig
from hexjax.sim.mjcf import build_mjcf, sensor_layout
from hexjax.sim.engines import sim_model
from hexjax.sim.model import obs_from_sensordata
from hexjax.sim.rollout import rollout
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import sample

ROBOT = get_robot("luneckas2020")
CTRL = TactileGaitController(ROBOT)
TERRAIN = sample(get_terrain("high-large"), jax.random.PRNGKey(0), 6)
SECONDS = 5.0
PHYSICS = PhysicsConfig()  # the same raw settings on every engine (a preset would run each engine's own)
PHYSICS_STEPS = (15 + 250) * 4  # per env in SECONDS: 15 settling and 250 control steps of 4 physics steps


@pytest.fixture(scope="module")
def mjx_run():
    return rollout(ROBOT, TERRAIN, CTRL, CTRL.default_params(), SECONDS, jax.random.PRNGKey(1), physics=PHYSICS)


def _agree(ref, out):
    """Same walk on the same obstacles: per-env forward travel within 2 cm (the robot walks up to 17 cm and is
    stopped by different amounts on each terrain), pads on in every env where they were on for >= 20 steps
    with MJX, and the summed pad-on steps within 25 % (a pad grazing an edge for a few steps differs between
    engines: 12 steps with MJX and 0 with Warp was seen on one terrain)."""
    tx_ref, tx = np.asarray(ref.travel)[:, 0], np.asarray(out.travel)[:, 0]
    assert np.ptp(tx_ref) > 0.03, "the terrains should stop the robot by different amounts"
    np.testing.assert_allclose(tx, tx_ref, atol=0.02)
    tac_ref, tac = np.asarray(ref.tactile_steps).sum(1), np.asarray(out.tactile_steps).sum(1)
    assert tac_ref.sum() > 50
    assert np.all(tac[tac_ref >= 20] > 0)
    assert np.all(tac[tac_ref == 0] <= 5)
    assert abs(tac.sum() - tac_ref.sum()) <= 0.25 * tac_ref.sum()
    np.testing.assert_allclose(np.asarray(out.energy), np.asarray(ref.energy), rtol=0.2)
    assert not np.asarray(out.nan).any() and not np.asarray(out.fell).any()


@pytest.mark.cost(45)
class TestAgainstTheMjxWalk:
    """The other backends against one MJX walk: one class, so that one worker runs them and the MJX walk is made once
    (tests/conftest.py's scheduler)."""

    def test_mujoco_c_backend_walks_like_mjx(self, mjx_run):
        out, st = rollout(ROBOT, TERRAIN, CTRL, CTRL.default_params(), SECONDS, jax.random.PRNGKey(1), engine="c",
                          nthread=2, stats=True, physics=PHYSICS)
        assert st.engine == "c" and st.compile_s > 0 and st.env_steps == 6 * PHYSICS_STEPS
        np.testing.assert_allclose(np.asarray(out.start_pose), np.asarray(mjx_run.start_pose), atol=5e-3)
        _agree(mjx_run, out)

    def test_warp_backend_walks_like_mjx(self, mjx_run):
        _warp()
        from hexjax.sim.internals import warp_cpu
        recorded, replayed = warp_cpu.STATS["recorded"], warp_cpu.STATS["replayed"]
        walk = lambda: rollout(ROBOT, TERRAIN, CTRL, CTRL.default_params(), SECONDS, jax.random.PRNGKey(1), engine="warp",
                               physics=PHYSICS)
        out = walk()
        _agree(mjx_run, out)
        if jax.default_backend() == "cpu":
            # Warp's step was recorded a few times (once per set of buffers) and replayed at every other physics
            # step of the walk (one call for all 6 envs) ...
            new, again = warp_cpu.STATS["recorded"] - recorded, warp_cpu.STATS["replayed"] - replayed
            assert 0 < new <= 8 and again >= PHYSICS_STEPS - new, (new, again)
            # ... which changes the speed only: with Warp's Python run at every call the walk is the same bit for bit
            was, counts = warp_cpu.set_enabled(False), dict(warp_cpu.STATS)
            try:  # the switch is read when the call runs, so wait for the walk (XLA dispatches it asynchronously)
                plain = jax.block_until_ready(walk())
            finally:
                warp_cpu.set_enabled(was)
            assert dict(warp_cpu.STATS) == counts, "nothing recorded or replayed while the replay was off"
            for x, y in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(plain)):
                np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_mujoco_c_ground_plane_sits_at_the_terrains_ground_z():
    """Terrains with a lowered ground plane (Yu 2019's ditches, stairs-down, slope-down, stones) move the plane
    per env. The same flat walk with the plane at 0 and at -5 cm: the torso keeps the same height above its
    plane (it was 5 cm higher while MuJoCo ignored the moved plane and the robot walked at z = 0). The recorded
    torso trace (the one trace MuJoCo C keeps) has a pose per control step, ends at the summary's end pose and
    sits 5 cm lower over the lowered plane."""
    flat = sample(get_terrain("flat"), jax.random.PRNGKey(0), 2)
    terr = flat.replace(ground_z=np.array([0.0, -0.05], np.float32))
    out = rollout(ROBOT, terr, CTRL, CTRL.default_params(), 1.0, jax.random.PRNGKey(1), engine="c", nthread=1,
                  config=RolloutConfig(record=True))
    h = np.asarray(out.min_height)
    assert 0.03 < h[0] < 0.15 and abs(h[1] - h[0]) < 0.005, h
    tr = np.asarray(out.trace)
    assert tr.shape == (2, round(1.0 / CTRL.dt), 4), tr.shape
    np.testing.assert_allclose(tr[:, -1, :2], np.asarray(out.end_pose)[:, :2], atol=1e-5)
    np.testing.assert_allclose(tr[1, :, 2] - tr[0, :, 2], -0.05, atol=0.005)


def _warp():
    """The warp module, or a skip without warp-lang; under HEXJAX_REQUIRE_WARP (`make test`, and so CI, whose test
    extra installs warp-lang) its absence fails instead."""
    if os.environ.get("HEXJAX_REQUIRE_WARP"):
        import warp
        return warp
    return pytest.importorskip("warp")


def test_warp_cpu_hessian_launch_gives_the_same_steps():
    """On a CPU, hexjax launches MuJoCo Warp's elliptic-cone Hessian kernel with one thread per matrix element
    looping over the contacts (`hexjax.sim.internals.warp_cpu`). 60 MuJoCo Warp steps of 2 worlds, the robot
    standing on the elliptic cone with its joints driven 0.3 rad off the stance so that the feet slip, give the
    same state bit for bit with and without it. The kernel matters here: with its launch skipped `qpos` ended up
    to 1.2e-3 elsewhere, and with only the first 3 contacts summed the test failed (both checked once, 2026-11-29)."""
    wp = _warp()
    from mujoco.mjx.third_party import mujoco_warp as mjw

    from hexjax.sim.internals import warp_cpu
    sm = sim_model(ROBOT, PhysicsConfig(cone="elliptic"), "warp")  # the model and pool sizes hexjax's walks use
    m = sm.mj_model
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    for _ in range(100):  # settle onto the feet (MuJoCo C)
        mujoco.mj_step(m, d)
    assert d.ncon == 6
    d.ctrl[:] += 0.3
    assert warp_cpu.enable(), "the pinned Warp version gets hexjax's CPU changes"

    def steps(on):
        was = warp_cpu.set_enabled(on)
        try:
            with wp.ScopedDevice("cpu"):
                mw, dw = mjw.put_model(m), mjw.put_data(m, d, nworld=2, **sm.warp_pools(2))
                for _ in range(60):
                    mjw.step(mw, dw)
                return {k: getattr(dw, k).numpy().copy() for k in ("qpos", "qvel", "qacc", "qfrc_constraint")}
        finally:
            warp_cpu.set_enabled(was)

    before = warp_cpu.STATS["hessian"]
    new = steps(True)
    assert warp_cpu.STATS["hessian"] >= before + 60, "the Hessian's launch was not reshaped at every step"
    plain = steps(False)
    assert np.abs(new["qpos"] - d.qpos).max() > 0.1  # the joints moved
    for k in new:
        np.testing.assert_array_equal(new[k], plain[k], err_msg=k)


def test_contact_sensors_read_the_forces_mujoco_reports():
    """The sensor block decoded by obs_from_sensordata equals mj_contactForce summed per foot / pad (on the MuJoCo C
    engine's own model of one box: a world-body geom with its refitted tree)."""
    from hexjax.sim.engines.c_models import _models, _template
    tp = _template(ROBOT, PhysicsConfig(slots_per_leg=0, torso_slots=0), 1)
    assert tp.model.nsensordata == sensor_layout()["size"]
    d = mujoco.MjData(tp.model)
    mujoco.mj_resetDataKeyframe(tp.model, d, 0)
    mujoco.mj_forward(tp.model, d)
    # a box under the front-left foot, so that feet stand on the ground and on a box (its top 4 mm above the ground)
    foot = mujoco.mj_name2id(tp.model, mujoco.mjtObj.mjOBJ_SITE, "LF_foot")
    box_pos = np.array([[[*d.site_xpos[foot, :2], -0.006]]])
    m = _models(tp, box_pos, np.full((1, 1, 3), 0.01), np.ones((1, 1), bool), np.zeros(1))[0]
    box_geom = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "terrain_0")
    mujoco.mj_resetDataKeyframe(m, d, 0)
    for _ in range(300):
        mujoco.mj_step(m, d)
    obs = obs_from_sensordata(SensorConfig(), d.qpos, d.qvel, d.sensordata, d.time)
    gids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"{n}_foot") for n in ("LF", "LM", "LH", "RF", "RM", "RH")]
    world = np.zeros((6, 3))
    normal = np.zeros(6)
    assert d.ncon > 0
    for i in range(d.ncon):
        c = d.contact[i]
        f = np.zeros(6)
        mujoco.mj_contactForce(m, d, i, f)
        for leg, g in enumerate(gids):
            if g in (c.geom1, c.geom2):
                w = c.frame.reshape(3, 3).T @ f[:3]
                world[leg] += w if c.geom2 == g else -w  # the force on the foot
                normal[leg] += f[0]
    on_box = [c for c in d.contact[:d.ncon] if box_geom in (c.geom1, c.geom2)]
    assert on_box and (normal > 0.5).sum() >= 3, "the LF foot on the box, and a support polygon under the robot"
    np.testing.assert_allclose(np.asarray(obs.foot_force), world, atol=1e-6)
    np.testing.assert_allclose(np.asarray(obs.tactile_force), 0.0, atol=1e-9)  # nothing touches a pad here
    np.testing.assert_allclose(np.asarray(obs.foot_force)[:, 2].sum(), ROBOT.total_mass * 9.81, rtol=0.05)
    np.testing.assert_array_equal(np.asarray(obs.foot_contact), normal > 0.5)


def test_backend_bad_input_raises_before_tracing():
    p = CTRL.default_params()
    with pytest.raises(ValueError, match="engine='gpu'"):
        rollout(ROBOT, TERRAIN, CTRL, p, 1.0, jax.random.PRNGKey(0), engine="gpu")
    with pytest.raises(ValueError, match="needs gradients, which MuJoCo C does not give"):
        rollout(ROBOT, TERRAIN, CTRL, p, 1.0, jax.random.PRNGKey(0), engine="c",
                config=RolloutConfig(solver_grad="unrolled"))
    with pytest.raises(ValueError, match="nthread"):
        rollout(ROBOT, TERRAIN, CTRL, p, 1.0, jax.random.PRNGKey(0), engine="c", nthread=-1)
    with pytest.raises(ValueError, match="terrain_boxes"):
        build_mjcf(ROBOT, PhysicsConfig(), terrain_boxes=3)


def test_mujoco_c_keeps_every_trace_the_mjx_engine_keeps():
    """With `record`, MuJoCo C returns the traces the paper experiments read (feet from its foot-site position
    sensors, the controller's own trace, the joints, the forces and pads it read), shaped as MJX's: standing feet
    rest at the foot radius above the ground, the torso trace is the joints trace's position, and the summed
    vertical foot force carries the robot."""
    terr = sample(get_terrain("flat"), jax.random.PRNGKey(2), 2)
    s = rollout(ROBOT, terr, CTRL, CTRL.default_params(), 0.5, jax.random.PRNGKey(3), engine="c", nthread=1,
                physics=PhysicsConfig(slots_per_leg=0, torso_slots=0), config=RolloutConfig(record=True))
    t = 25  # control steps of 0.5 s
    assert s.foot_trace.shape == (2, t, 6, 3) and s.qpos_trace.shape == (2, t, 25) and s.trace.shape == (2, t, 4)
    assert s.force_trace.shape == (2, t, 6, 3) and s.tactile_trace.shape == (2, t, 6)
    np.testing.assert_allclose(np.asarray(s.trace)[..., :3], np.asarray(s.qpos_trace)[..., :3])
    low = np.asarray(s.foot_trace)[..., 2].min(-1)  # the lowest foot of each step stands
    np.testing.assert_allclose(low, ROBOT.foot_radius, atol=2e-3)
    weight = np.asarray(s.force_trace)[:, 0, :, 2].sum(-1)  # the first walking step, the stance of the settle
    np.testing.assert_allclose(weight, ROBOT.total_mass * 9.81, rtol=0.05)
    assert jax.tree_util.tree_leaves(s.ctrl_trace)[0].shape[:2] == (2, t)


def test_a_recorded_walk_too_big_for_the_host_is_refused_at_its_first_step(monkeypatch):
    """MuJoCo C keeps `record`'s traces in the host's memory; a walk whose traces cannot fit is refused one
    walking step in (a 90 s step experiment at 1,024 terrains a row was killed by the host after 40 min). The
    measured bytes an env are the kept traces' own (the joints, feet, controller trace, forces and pads; the
    torso trace is made from the joints), three copies of them over the walk."""
    import hexjax.sim.engines.c as c_engine

    seen = []
    monkeypatch.setattr(c_engine, "check_fits", lambda flag, n, per_env, what, host: seen.append((flag, n, per_env)))
    terr = sample(get_terrain("flat"), jax.random.PRNGKey(2), 2)
    run = lambda: rollout(ROBOT, terr, CTRL, CTRL.default_params(), 0.5, jax.random.PRNGKey(3), engine="c",
                          nthread=1, physics=PhysicsConfig(slots_per_leg=0, torso_slots=0),
                          config=RolloutConfig(record=True))
    s = run()
    kept = sum(np.asarray(x).nbytes for x in jax.tree_util.tree_leaves(
        (s.qpos_trace, s.foot_trace, s.ctrl_trace, s.force_trace, s.tactile_trace)))
    assert seen == [("envs", 2, c_engine.RECORD_COPIES * kept // 2)]
    monkeypatch.undo()
    monkeypatch.setattr(c_engine, "RECORD_COPIES", 10**9)  # as if each env's traces took more than the host has
    with pytest.raises(ValueError, match=r"^envs=2: keeping every trace of a 25-control-step walk on MuJoCo C"):
        run()


def test_warp_overflow_bits_are_mujoco_warps():
    """The limit bits hexjax reads from MuJoCo Warp's overflow flags (written in hexjax so that reading them does
    not load Warp) are those of its `OverflowType`."""
    _warp()
    from mujoco.mjx.third_party.mujoco_warp._src.types import OverflowType

    from hexjax.sim.internals.contacts import OVERFLOW_ITERATIONS, OVERFLOW_LS_ITERATIONS
    assert (OVERFLOW_ITERATIONS, OVERFLOW_LS_ITERATIONS) == (int(OverflowType.ITERATIONS),
                                                            int(OverflowType.LS_ITERATIONS))


def test_warp_limit_lines_can_be_summed_by_the_caller_instead(capsys):
    """A MuJoCo Warp rollout whose envs hit its solver's limits says so in one stderr line; a caller that rolls out
    many times (the evolution strategy on Warp) turns the line off and reads the counts from the stats. One Newton
    iteration and one line-search step, so that the limits are hit."""
    _warp()
    import dataclasses
    tight = dataclasses.replace(PHYSICS, iterations=1, ls_iterations=1)
    two = jax.tree_util.tree_map(lambda x: x[:2], TERRAIN)
    walk = lambda **kw: rollout(ROBOT, two, CTRL, CTRL.default_params(), 0.5, jax.random.PRNGKey(1), physics=tight,
                                engine="warp", stats=True, **kw)
    _, st = walk(say_limits=False)
    assert "MuJoCo Warp:" not in capsys.readouterr().err
    assert st.overflow["envs"] == 2 and st.overflow["iteration_limit"] + st.overflow["line_search_limit"] > 0
    walk()
    assert "MuJoCo Warp:" in capsys.readouterr().err
