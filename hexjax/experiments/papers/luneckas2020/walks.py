"""The walks of the Luneckas 2020 experiments: one compiled, batched rollout per gait over every obstacle
category with and without the tactile method (and flat calibration terrains), and the readouts shared by
the experiment matrix and the error predictor's dataset."""

from __future__ import annotations

import math
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from hexjax.control.registry import make_controller
from hexjax.control.tactile import TactileGaitController, overcome_height
from hexjax.experiments.runner import step_bar
from hexjax.sim.metrics import pose_errors
from hexjax.sim.config import RolloutConfig
from hexjax.sim.engines import TRACES
from hexjax.sim.physics import pick, shared_config
from hexjax.sim.rollout import rollout
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import LUNECKAS2020_CATEGORIES, pad_terrain, sample

GAITS = ("wave", "tripod")
DISTANCES = (1.0, 2.0)
METHODS = ("without", "with")
STUCK_WINDOW = 0.2  # fraction of the commanded path before the readout over which progress is checked
STUCK_RATIO = 0.25  # stuck: advanced less than this fraction of what was commanded in that window


def concat(trees):
    """Concatenate pytrees (terrains) along their leading axis."""
    return jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *trees)


def readout_index(ctrl: TactileGaitController, params, d: float, n_steps: int) -> int:
    """Trace index at which the gait has commanded `d` m of advance (last index if never)."""
    t = (np.arange(n_steps) + 1) * ctrl.dt
    adv = np.asarray(ctrl.commanded_advance(jax.tree_util.tree_map(lambda x: x[0], params), jnp.asarray(t)))
    hit = np.nonzero(adv >= d - 1e-6)[0]
    return int(hit[0]) if hit.size else n_steps - 1


def errors_from(start_pose, pose, d: float):
    """`metrics.pose_errors` in numpy: (dx, dy, dalpha, advance), (B,) each."""
    return pose_errors(np.asarray(start_pose), np.asarray(pose), d, xp=np)


STRIKE_GAP = 0.005  # m: an obstacle top this close below the torso's underside (or above it) is a torso strike


def torso_strikes(robot, trace, terrain, chunk: int = 256) -> np.ndarray:
    """(B, T) bool: control steps where an obstacle top under the torso's footprint (the body box, turned by
    the torso's yaw) reaches within `STRIKE_GAP` of the torso's underside: the torso rests on or rides against
    a box, which the paper's robot avoids by its height over 5-8 cm obstacles. From the torso trace (x, y, z,
    yaw per control step) and the terrain boxes; tilt is ignored (the underside is taken level)."""
    half_l, half_w, below = 0.5 * robot.body_length, 0.5 * robot.body_width, 0.5 * robot.body_thickness

    @jax.jit
    def one(tr, pos, half, valid):  # (T, 4), (M, 3), (M, 3), (M,) -> (T,)
        dx, dy = pos[None, :, 0] - tr[:, None, 0], pos[None, :, 1] - tr[:, None, 1]
        c, s_ = jnp.cos(tr[:, 3])[:, None], jnp.sin(tr[:, 3])[:, None]
        bx, by = c * dx + s_ * dy, -s_ * dx + c * dy
        under = (jnp.abs(bx) < half_l + half[None, :, 0]) & (jnp.abs(by) < half_w + half[None, :, 1]) & valid[None]
        top = jnp.where(under, (pos[:, 2] + half[:, 2])[None], -jnp.inf).max(-1)
        return tr[:, 2] - below - top < STRIKE_GAP

    many = jax.jit(jax.vmap(one))
    pos, half, valid = (np.asarray(a) for a in (terrain.box_pos, terrain.box_half, terrain.box_valid))
    trace = np.asarray(trace)
    return np.concatenate([np.asarray(many(trace[i:i + chunk], pos[i:i + chunk], half[i:i + chunk],
                                           valid[i:i + chunk])) for i in range(0, trace.shape[0], chunk)])


def robot_width(robot) -> float:
    """a of Luneckas 2020 Eq. 12: the robot's width between its left and right front/hind feet, m."""
    return 2 * (robot.hip_y + robot.stance_radial * math.cos(robot.stance_splay))


def simulate_gait(gait: str, n: int, seed: int = 0, distance: float = 2.0,
                  categories: Sequence[str] = LUNECKAS2020_CATEGORIES, methods: Sequence[str] = METHODS,
                  calibration: bool = True, progress: bool = True, robot_name: str = "luneckas2020",
                  physics="validated"):
    """One compiled, batched rollout of `gait` over every (category, method) x n terrains (+ n flat), under the
    physics preset `physics` (name, .yaml path or `PhysicsPreset`).

    Returns (ctrl, params, terrain, summary, groups, RolloutStats) with groups a list of (category, method,
    slice)."""
    preset = pick(physics, needs={TRACES})
    robot = get_robot(robot_name)
    specs = {c: get_terrain(c, length=distance + 0.3) for c in categories}
    m = max([s.max_boxes for s in specs.values()] + [1])
    ctrl, dur = make_controller("tactile", robot, gait=gait).for_distance(distance)
    terrs, params, groups = [], [], []
    base = jax.random.PRNGKey(seed)
    for i, c in enumerate(categories):
        # the same terrains for both methods and both gaits: the key depends on the category only
        t = pad_terrain(sample(specs[c], jax.random.fold_in(base, i), n), m)
        H = specs[c].height_range[1]
        for meth in methods:
            groups.append((c, meth, slice(len(params), len(params) + n)))
            terrs.append(t)
            params += [ctrl.default_params(enable=float(meth == "with"), overcome_height=overcome_height(H))] * n
    if calibration:
        groups.append(("flat", "without", slice(len(params), len(params) + n)))
        terrs.append(pad_terrain(sample(get_terrain("flat"), base, n), m))
        params += [ctrl.default_params(enable=0.0)] * n
    terrain = concat(terrs)
    params = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *params)
    with step_bar(f"{gait} x {len(params.enable)} envs, {dur:.0f} s simulated", ctrl.dt, dur,
                  RolloutConfig(record=True), enabled=progress) as cfg:
        s, st = rollout(robot, terrain, ctrl, params, dur, jax.random.fold_in(base, 1000), params_batched=True,
                        config=cfg, stats=True, physics=shared_config(preset, specs.values()),
                        engine=preset.engine.name)
    return ctrl, params, terrain, s, groups, st
