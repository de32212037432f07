"""Issue 5 exploration: is the mean advance of the smooth tactile gait on flat ground smooth enough for a
finite-difference check? Prints the per-step-clipped autodiff gradient and central differences at several
steps, for 32 envs over 0.5 s and 1 s. Usage: python scripts/fd_noise_tactile.py (about 4 min on 2 cores).
It uses one Newton iteration, as gradients then required; that unconverged solver is what makes the
differences disagree (docs/tuning.md). tests/test_tune.py does the check with RolloutConfig.solver_grad."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hexjax.control.tactile import TactileGaitController
from hexjax.sim.config import RolloutConfig, physics_for
from hexjax.sim.rollout import rollout_function
from hexjax.world.presets import get_terrain, luneckas2020
from hexjax.world.terrain import sample

robot = luneckas2020(); B = 32
ctrl = TactileGaitController(robot, gait="tripod", smooth=True)
p = ctrl.default_params()
spec = get_terrain("flat")
terr = sample(spec, jax.random.PRNGKey(0), B)
keys = jax.random.split(jax.random.PRNGKey(1), B)
phys = dataclasses.replace(physics_for(spec.kind), iterations=1)
for H in (0.5, 1.0):
    model, fn = rollout_function(robot, ctrl, H, physics=phys, config=RolloutConfig(settle_time=0.1, grad_clip=1.0))
    def obj(x):
        s = fn(model, p.replace(step_length=x[0], step_height=x[1]), terr, keys)
        return jnp.mean(s.end_pose[:, 0] - s.start_pose[:, 0])
    x0 = jnp.array([float(p.step_length), float(p.step_height)])
    g = np.asarray(jax.jit(jax.grad(obj))(x0)); f = jax.jit(obj)
    print(f"H={H} grad(clip 1) {g}")
    for eps in (1e-4, 1e-3, 3e-3, 1e-2):
        fd = np.array([(f(x0.at[i].add(eps)) - f(x0.at[i].add(-eps))) / (2 * eps) for i in range(2)])
        print(f"  eps {eps:g}: fd {fd}, cos {float(fd @ g / np.linalg.norm(fd) / np.linalg.norm(g)):.2f}")
