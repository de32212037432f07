"""Diagnostic for docs/tactile.md: on large obstacles, how often an obstacle top is within 5 mm of the
torso bottom under its footprint, and how often feet stand on obstacle tops (tripod, 1 m, 8 runs per
row, high density, with and without the tactile method). Usage: python scripts/luneckas_torso_contact.py"""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hexjax.control.tactile import TactileGaitController, overcome_height
from hexjax.sim.config import RolloutConfig
from hexjax.sim.rollout import rollout
from hexjax.world.presets import get_terrain, luneckas2020
from hexjax.world.terrain import pad_terrain, sample

robot = luneckas2020(); n = 8
cats = ["high-small", "high-large"]
specs = {c: get_terrain(c, length=1.3) for c in cats}
m = max(s.max_boxes for s in specs.values())
ctrl = TactileGaitController(robot, gait="tripod")
ncyc, dur = ctrl.duration_for(1.0); ctrl = dataclasses.replace(ctrl, n_cycles=ncyc)
terrs, ps = [], []
for i, c in enumerate(cats):
    t = pad_terrain(sample(specs[c], jax.random.PRNGKey(i), n), m)
    for en in (0, 1):
        terrs.append(t); ps += [ctrl.default_params(enable=float(en), overcome_height=overcome_height(specs[c].height_range[1]))] * n
terr = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *terrs)
params = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *ps)
s = rollout(robot, terr, ctrl, params, dur, jax.random.PRNGKey(9), params_batched=True, config=RolloutConfig(record=True))
tr = np.asarray(s.trace); feet = np.asarray(s.foot_trace)
pos, half, val = np.asarray(terr.box_pos), np.asarray(terr.box_half), np.asarray(terr.box_valid)
top = pos[..., 2] + half[..., 2]
bl, bw = robot.body_length / 2, robot.body_width / 2
for g in range(4):
    sl = slice(g * n, (g + 1) * n)
    rest, onfoot, hiz = [], [], []
    for b in range(sl.start, sl.stop):
        x, y, z, yaw = tr[b, :, 0], tr[b, :, 1], tr[b, :, 2], tr[b, :, 3]
        # boxes under the torso footprint (torso frame, ignoring tilt)
        dxw = pos[b, None, :, 0] - x[:, None]; dyw = pos[b, None, :, 1] - y[:, None]
        c, s_ = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        bx, by = c * dxw + s_ * dyw, -s_ * dxw + c * dyw
        under = (np.abs(bx) < bl + half[b, None, :, 0]) & (np.abs(by) < bw + half[b, None, :, 1]) & val[b][None]
        hmax = np.where(under, top[b][None], 0).max(-1)
        bottom = z - robot.body_thickness / 2
        rest.append(np.mean(bottom - hmax < 0.005))
        # feet standing on an obstacle top
        f = feet[b]  # T, 6, 3
        inside = (np.abs(f[:, :, None, 0] - pos[b, None, None, :, 0]) < half[b, None, None, :, 0]) & (np.abs(f[:, :, None, 1] - pos[b, None, None, :, 1]) < half[b, None, None, :, 1]) & val[b][None, None]
        on = (inside & (f[:, :, None, 2] > top[b][None, None] - 0.003)).any(-1)
        onfoot.append(on.mean())
        hiz.append(np.mean(z < robot.hip_height - 0.015))
    print(cats[g // 2], "with" if g % 2 else "without", f"torso on/against obstacles {100*np.mean(rest):.0f}% of time; foot-steps on obstacle tops {100*np.mean(onfoot):.1f}%; torso sagged >15mm {100*np.mean(hiz):.0f}%; adv {np.asarray(s.end_pose[sl,0]-s.start_pose[sl,0]).mean():.2f} m")
