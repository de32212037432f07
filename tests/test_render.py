"""`hexjax render`: offscreen frames of recorded rollouts and the video files."""

import os
import types
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.render import render_env, write_video
from hexjax.sim.config import PhysicsConfig, physics_for
from hexjax.sim.engines import sim_model
from hexjax.world.presets import get_robot
from hexjax.world.terrain import Terrain

ROBOT = get_robot("luneckas2020")


def _fake_recording(t=4):
    """A Summary-like record: the stance keyframe walking 5 cm per frame, every pad off, then on from frame 2."""
    sm = sim_model(ROBOT, physics_for("flat"))
    q = np.tile(sm.qpos0, (1, t, 1))
    q[0, :, 0] = 0.05 * np.arange(t)
    tactile = np.zeros((1, t, 6), bool)
    tactile[0, 2:, :] = True
    force = np.zeros((1, t, 6, 3))
    force[0, :, :, 2] = 5.0
    return types.SimpleNamespace(qpos_trace=q, force_trace=force, tactile_trace=tactile)


def _terrain():
    return Terrain(box_pos=jnp.array([[[0.3, 0.0, 0.03]]]), box_half=jnp.array([[[0.02, 0.05, 0.03]]]),
                   box_valid=jnp.ones((1, 1), bool), ground_z=jnp.zeros(1))


def test_frames_show_the_robot_forces_and_tactile_pads(tmp_path):
    rec = _fake_recording()
    frames = render_env(ROBOT, PhysicsConfig(), _terrain(), rec, every=1, width=160, height=120, progress=False)
    assert frames.shape == (4, 120, 160, 3) and frames.dtype == np.uint8
    assert frames.std() > 10  # not a blank image
    f = frames.astype(int)
    red = lambda x: int(((x[..., 0] > 120) & (x[..., 0] - x[..., 1] > 70) & (x[..., 2] < 90)).sum())
    yellow = lambda x: int(((x[..., 0] > 120) & (x[..., 1] > 100) & (abs(x[..., 0] - x[..., 1]) < 50)
                            & (x[..., 2] < 60)).sum())
    green = lambda x: int(((x[..., 1] > 150) & (x[..., 0] < 100) & (x[..., 2] < 100)).sum())
    # the red shin pads turn yellow while their tactile is on (measured: red 10 -> 0 px, yellow 0 -> 50 px)
    assert red(f[0]) > 5 and yellow(f[0]) == 0 and red(f[3]) == 0 and yellow(f[3]) > 20
    assert green(f[0]) > 5  # the foot-force arrows
    for suffix in (".gif", ".mp4"):
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            path = write_video(frames, str(tmp_path / f"walk{suffix}"), fps=10)
        assert os.path.getsize(path) > 1000
        assert not [w for w in said if "os.fork()" in str(w.message)], suffix  # ffmpeg's start worried users


def test_scene_floor_sits_at_the_terrains_ground_z():
    """A ditch terrain's floor is its lowered ground plane: drawn at z = 0, it hid the ditches."""
    import mujoco

    from hexjax.render import scene_model
    m = scene_model(ROBOT, PhysicsConfig(), np.zeros((1, 3)), np.full((1, 3), 0.01), np.zeros(1, bool), -0.1)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    assert d.geom_xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "ground"), 2] == pytest.approx(-0.1)


def test_render_rejects_bad_input(tmp_path):
    rec = _fake_recording()
    with pytest.raises(ValueError, match="env=3"):
        render_env(ROBOT, PhysicsConfig(), _terrain(), rec, env=3, progress=False)
    with pytest.raises(ValueError, match="record=True"):
        render_env(ROBOT, PhysicsConfig(), _terrain(), types.SimpleNamespace(qpos_trace=None), progress=False)
    with pytest.raises(ValueError, match="suffix"):
        write_video(np.zeros((2, 16, 16, 3), np.uint8), str(tmp_path / "walk.avi"), fps=10)
    with pytest.raises(ValueError, match="width=5000"):
        render_env(ROBOT, PhysicsConfig(), _terrain(), rec, width=5000, progress=False)


def test_frames_wider_than_the_models_framebuffer():
    """A frame wider than the 1920 px the scene model's framebuffer starts with (MuJoCo refused it)."""
    frames = render_env(ROBOT, PhysicsConfig(), _terrain(), _fake_recording(t=1), width=2400, height=16,
                        progress=False)
    assert frames.shape == (1, 16, 2400, 3) and frames.std() > 10


@pytest.mark.filterwarnings(r"ignore:os\.fork\(\) was called:RuntimeWarning")  # this test's own ffmpeg read
def test_render_command_writes_a_video_and_a_still(tmp_path):
    """The video holds one frame per `every` control steps of the walk; the still is its middle frame and
    shows the robot (its blue torso and dark feet in the middle of the picture, over the grey floor)."""
    import imageio.v2 as imageio

    from hexjax.cli import main
    out, still = tmp_path / "walk.mp4", tmp_path / "still.png"
    assert main(["render", "--terrain", "flat", "--controller", "gait", "--seconds", "0.4", "--width", "96",
                 "--height", "72", "--out", str(out), "--still", str(still)]) == 0
    frames = np.stack(imageio.mimread(str(out)))
    assert frames.shape == (10, 72, 96, 3)  # 0.4 s at 20 ms per control step, every 2nd step
    img = imageio.imread(str(still))[..., :3].astype(int)
    assert img.shape == (72, 96, 3)
    assert np.abs(frames[5].astype(int) - img).mean() < 12  # the still is the middle frame (MP4 is lossy)
    centre = img[18:54, 24:72]
    torso = (centre[..., 2] > centre[..., 0] + 30) & (centre[..., 2] > centre[..., 1] + 10)  # rgba 0.3 0.4 0.7
    dark = centre.sum(-1) < 150  # feet and legs' shadows of 0.2 0.2 0.2
    assert torso.sum() > 20 and dark.sum() > 5, (torso.sum(), dark.sum())
    floor = img[-6:, :]  # the checker floor in front of the robot: light grey
    assert floor.mean() > 120 and np.abs(floor[..., 0] - floor[..., 2]).mean() < 25
