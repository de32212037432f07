"""Videos and stills of recorded rollouts with MuJoCo's offscreen renderer.

A rollout run with `RolloutConfig(record=True)` keeps each env's full qpos, foot forces and tactile states
per control step. `render_env` replays one env kinematically in MuJoCo C (qpos set, `mj_forward`, render): the
env's own terrain boxes are added to the robot's model as static geoms, foot forces are drawn as arrows
(length `force_scale` m per N), and a shin's tactile pad turns yellow while it is on. The camera follows the
torso. `write_video` writes MP4 (imageio-ffmpeg) or GIF (Pillow) by the file's suffix.

OpenGL: MuJoCo picks its backend from MUJOCO_GL when it is imported (GLFW when unset, which needs a
display). With no display and MUJOCO_GL unset, `render_env` switches MuJoCo's renderer to EGL, which works
headless on NVIDIA drivers and with Mesa's EGL (software rendering, llvmpipe, as on this project's CPU
machine). It does not set MUJOCO_GL globally: on a machine without libEGL, importing mujoco with
MUJOCO_GL=egl fails outright (seen on the GPU machine), which would break every hexjax command.
"""

from __future__ import annotations

import os
import warnings
from typing import Optional, Sequence

import numpy as np

from hexjax.control.registry import CONTROLLERS, make_controller
from hexjax.sim.config import PhysicsConfig, RolloutConfig
from hexjax.sim.engines import TRACES
from hexjax.sim.physics import pick
from hexjax.sim.mjcf import build_mjcf
from hexjax.sim.rollout import rollout
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.robot import LEG_NAMES, RobotSpec
from hexjax.world.terrain import sample

NEEDS = frozenset({TRACES})  # the video replays the joint traces (the runner picks the engine once)

# the controllers a video can show: those that walk from their default params alone (hexjax.control.registry)
RENDERABLE = tuple(n for n, e in CONTROLLERS.items() if e.walks_alone)

PAD_ON = np.array([1.0, 0.85, 0.1, 1.0])


def _headless_gl() -> None:
    """Use EGL for MuJoCo's offscreen renderer when there is no display and MUJOCO_GL is unset (module notes)."""
    if os.environ.get("MUJOCO_GL") or os.environ.get("DISPLAY"):
        return
    from mujoco.rendering.classic import gl_context
    try:
        from mujoco.egl import GLContext
    except Exception as err:  # a missing libEGL surfaces as AttributeError inside PyOpenGL, not ImportError
        raise RuntimeError(f"no display, and MuJoCo's EGL backend does not load here ({err!r}); set MUJOCO_GL="
                           "osmesa (needs libOSMesa) or run with a display") from err
    gl_context.GLContext = GLContext


def scene_model(robot: RobotSpec, physics: PhysicsConfig, box_pos, box_half, box_valid, ground_z: float):
    """A MuJoCo model of the robot with one env's terrain boxes as static, visual-only geoms."""
    import mujoco
    spec = mujoco.MjSpec.from_string(build_mjcf(robot, physics))
    world = spec.worldbody
    for p, h, v in zip(np.asarray(box_pos), np.asarray(box_half), np.asarray(box_valid)):
        if v:
            world.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, pos=p.tolist(), size=h.tolist(),
                           rgba=[0.62, 0.5, 0.36, 1.0], contype=0, conaffinity=0)
    spec.add_texture(name="sky", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX, builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
                     rgb1=[0.55, 0.7, 0.9], rgb2=[0.95, 0.97, 1.0], width=256, height=256)
    spec.add_texture(name="grid", type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
                     rgb1=[0.84, 0.86, 0.84], rgb2=[0.72, 0.75, 0.72], width=256, height=256)
    mat = spec.add_material(name="grid", texrepeat=[24, 24])  # 0.5 m squares on the 12 m floor
    mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "grid"
    floor = spec.geom("ground")
    floor.material = "grid"
    floor.size = [6.0, 6.0, 0.05]  # finite: an infinite plane drew dark bands near the horizon
    floor.rgba = [1.0, 1.0, 1.0, 1.0]
    # placed before compiling: a geom compiled at its body's origin ignores later writes to geom_pos
    floor.pos = [0.0, 0.0, float(ground_z)]
    m = spec.compile()
    m.vis.global_.offwidth = max(m.vis.global_.offwidth, 1920)
    m.vis.global_.offheight = max(m.vis.global_.offheight, 1080)
    return m


def render_env(robot: RobotSpec, physics: PhysicsConfig, terrain, summary, *, env: int = 0, width: int = 640,
               height: int = 480, every: int = 2, force_scale: float = 0.03, distance: float = 0.9,
               azimuth: float = 135.0, elevation: float = -25.0, progress: bool = True):
    """Frames (N, H, W, 3) uint8 of env `env` of a recorded rollout (`summary.qpos_trace` etc.), one per
    `every` control steps. terrain: the batched Terrain the rollout ran on."""
    import mujoco
    from tqdm.auto import tqdm
    if summary.qpos_trace is None:
        raise ValueError("summary.qpos_trace is None: run the rollout with RolloutConfig(record=True)")
    n_env = int(np.shape(summary.qpos_trace)[0])
    if not (0 <= env < n_env):
        raise ValueError(f"env={env!r}: the rollout has envs 0..{n_env - 1}")
    if every < 1 or not (16 <= width <= 4096 and 16 <= height <= 4096):
        raise ValueError(f"every={every!r}, width={width!r}, height={height!r}: need every >= 1 and a frame of "
                         "16-4096 px a side")
    _headless_gl()
    m = scene_model(robot, physics, terrain.box_pos[env], terrain.box_half[env], terrain.box_valid[env],
                    float(np.asarray(terrain.ground_z)[env]))
    vis = m.vis.global_  # the offscreen framebuffer holds the frame asked for
    vis.offwidth, vis.offheight = max(vis.offwidth, width), max(vis.offheight, height)
    d = mujoco.MjData(m)
    pads = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"{n}_pad") for n in LEG_NAMES])
    feet = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{n}_foot") for n in LEG_NAMES])
    pad_rgba = m.geom_rgba[pads].copy()
    qpos = np.asarray(summary.qpos_trace[env])
    force = None if summary.force_trace is None else np.asarray(summary.force_trace[env])
    tactile = None if summary.tactile_trace is None else np.asarray(summary.tactile_trace[env])
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.distance, cam.azimuth, cam.elevation = distance, azimuth, elevation
    frames = []
    with mujoco.Renderer(m, height, width) as r:
        for t in tqdm(range(0, qpos.shape[0], every), desc="render", unit="frame", disable=not progress):
            d.qpos[:] = qpos[t]
            if tactile is not None:
                m.geom_rgba[pads] = np.where(tactile[t][:, None], PAD_ON, pad_rgba)
            mujoco.mj_forward(m, d)
            cam.lookat[:] = d.qpos[:3]
            r.update_scene(d, camera=cam)
            r.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0  # software GL speckled the floor with shadow acne
            if force is not None:
                _add_arrows(r.scene, d.site_xpos[feet], force[t], force_scale)
            frames.append(r.render().copy())
    return np.stack(frames)


def _add_arrows(scene, starts, forces, scale: float) -> None:
    """Append one arrow per foot with a force over 0.2 N: from the foot along the force, `scale` m per N."""
    import mujoco
    for p, f in zip(starts, forces):
        if np.linalg.norm(f) < 0.2 or scene.ngeom >= scene.maxgeom:
            continue
        g = scene.geoms[scene.ngeom]
        mujoco.mjv_initGeom(g, mujoco.mjtGeom.mjGEOM_ARROW, np.zeros(3), np.zeros(3), np.zeros(9),
                            np.array([0.1, 0.9, 0.2, 1.0], np.float32))
        mujoco.mjv_connector(g, mujoco.mjtGeom.mjGEOM_ARROW, 0.01, p, p + scale * np.asarray(f, float))
        scene.ngeom += 1


def write_video(frames: np.ndarray, path: str, fps: float) -> str:
    """Write frames (N, H, W, 3) uint8 as MP4 (H.264 via imageio-ffmpeg) or GIF, by the suffix of `path`."""
    import imageio.v2 as imageio
    suffix = os.path.splitext(path)[1].lower()
    if suffix not in (".mp4", ".gif"):
        raise ValueError(f"out={path!r}: the suffix must be .mp4 or .gif")
    if frames.ndim != 4 or frames.shape[0] < 1:
        raise ValueError(f"frames shape={frames.shape!r}: need (N >= 1, H, W, 3)")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    if suffix == ".gif":
        imageio.mimsave(path, list(frames), duration=1.0 / fps, loop=0)
    else:
        # H.264 wants even sizes; macro_block_size=1 keeps the frame as rendered
        h, w = frames.shape[1:3]
        frames = frames[:, : h - h % 2, : w - w % 2]
        with warnings.catch_warnings():  # JAX warns at every fork; imageio-ffmpeg's fork execs ffmpeg at once
            warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
            imageio.mimsave(path, list(frames), fps=fps, codec="libx264", quality=7, macro_block_size=1)
    return path


def render_walk(robot_name: str = "luneckas2020", *, terrain_name: str = "high-large", controller: str = "tactile",
                seconds: float = 4.0, seed: int = 0, envs: Sequence[int] = (0,), out: str = "out/walk.mp4",
                width: int = 640, height: int = 480, every: int = 2, still: Optional[str] = None,
                physics="validated") -> dict:
    """Roll out a small batch (max(envs) + 1 terrains of `terrain_name`) with recording, render each env of
    `envs` into `out` (one file per env: a `_envK` suffix when more than one) and optionally a PNG still of
    the middle frame of the first. physics: the physics preset (on MJX: the video replays MJX's traces).
    Returns what was written."""
    import imageio.v2 as imageio
    import jax
    envs = list(dict.fromkeys(envs))  # each env once, in the order given
    if not envs or min(envs) < 0:
        raise ValueError(f"envs={envs!r}: give one or more env indices >= 0")
    if not seconds > 0:
        raise ValueError(f"seconds={seconds!r}: must be > 0")
    rb = get_robot(robot_name)
    tspec = get_terrain(terrain_name)
    preset = pick(physics, needs=NEEDS)
    physics = preset.config(tspec)
    if controller not in RENDERABLE:
        raise ValueError(f"controller={controller!r}: choose one of {sorted(RENDERABLE)}")
    ctrl = make_controller(controller, rb)
    terrain = sample(tspec, jax.random.PRNGKey(seed), max(envs) + 1)
    s = rollout(rb, terrain, ctrl, ctrl.default_params(), seconds, jax.random.PRNGKey(seed + 1), physics=physics,
                config=RolloutConfig(record=True), engine=preset.engine.name)
    s = jax.device_get(s)
    fps = 1.0 / (ctrl.dt * every)
    written = []
    for k in envs:
        frames = render_env(rb, physics, terrain, s, env=k, width=width, height=height, every=every)
        path = out if len(envs) == 1 else f"{os.path.splitext(out)[0]}_env{k}{os.path.splitext(out)[1]}"
        written.append(write_video(frames, path, fps))
        if still and k == envs[0]:
            os.makedirs(os.path.dirname(os.path.abspath(still)), exist_ok=True)
            imageio.imwrite(still, frames[len(frames) // 2])
            written.append(still)
    return {"written": written, "frames_per_video": int(len(frames)), "fps": fps,
            "tactile_steps": np.asarray(s.tactile_steps)[envs].tolist(), "fell": np.asarray(s.fell)[envs].tolist(),
            "physics": preset.record()}


# The command (configs/commands/render.yaml) --------------------------------------------------------------------
def run(o, entry) -> dict:
    return render_walk(robot_name=o.robot, terrain_name=o.terrain, controller=o.controller, seconds=o.seconds,
                       seed=o.seed, envs=o.envs, out=o.out, width=o.width, height=o.height, every=o.every,
                       still=o.still or None, physics=o.physics)


def report(res: dict) -> str:
    return "\n".join([f"wrote {w}" for w in res["written"]] + [
        f"{res['frames_per_video']} frames per video at {res['fps']:.3g} fps; tactile steps per leg "
        f"{res['tactile_steps']}; fell {res['fell']}"])
