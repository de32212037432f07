"""Diagnostic: does the autodiff gradient of a short smooth rollout agree with central differences?

One robot, one controller, one solver setting per call; prints the cosine and the norms per parameter
(or group) at several finite-difference steps. The objective is `hexjax.tune.gradcheck.travel_objective`, as in tests/test_tune.py: the mean
travel x + 0.3 y + 0.1 yaw of B envs over a `--window` s rollout on flat ground (or before a face across
the path, `--face X`), with MJX's Newton iterations traced as a scan. About 2-3 min per call on 2 cores.

  python scripts/fd_probe.py --robot yu2019 --ctrl gait                 # open-loop Luneckas 2020 gait
  python scripts/fd_probe.py --ctrl cpg-blind --iters 2                  # CPG without feedback, 2 iterations
  python scripts/fd_probe.py --ctrl cpg --iters 4 --omega 5 --tphase 5 --tforce 3   # the test's setting
  python scripts/fd_probe.py --ctrl gait --physics validated            # on a physics preset (docs/physics.md)
  python scripts/fd_probe.py --ctrl gait --physics validated --cone pyramidal --solver-grad implicit

docs/tuning.md lists what these calls measured.
"""
import argparse
import dataclasses
import time

import jax.numpy as jnp
import numpy as np

from hexjax.control.cpg import CPGController
from hexjax.control.gait import GaitController
from hexjax.sim.config import RolloutConfig, physics_for
from hexjax.sim.physics import get_physics, pick
from hexjax.sim.rollout import rollout_function
from hexjax.tune.gradcheck import check, check_batch, tactile_check_setting, travel_objective
from hexjax.tune.space import Bound, ParamSpace, make_space
from hexjax.world.presets import get_robot, get_terrain

ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
ap.add_argument("--robot", default="yu2019", help="robot preset")
ap.add_argument("--ctrl", default="cpg", choices=["cpg", "cpg-blind", "tactile", "gait"],
                help="the probe: the CPG (with or without its reflexes), the tactile gait, the open-loop gait")
ap.add_argument("--iters", type=int, default=0, help="MJX Newton iterations (0: the physics preset's)")
ap.add_argument("--physics", default="fast", help="physics preset name or .yaml path (an MJX one)")
ap.add_argument("--cone", default="", choices=["", "pyramidal", "elliptic"], help="override the preset's cone")
ap.add_argument("--solver-grad", default="unrolled", choices=["unrolled", "implicit"],
                help="through the Newton iterations, or implicitly at the solution (either cone)")
ap.add_argument("--window", type=float, default=0.4, help="rollout seconds after settling")
ap.add_argument("--settle", type=float, default=0.1)
ap.add_argument("--eps", default="1e-3,1e-2", help="central-difference steps on the unconstrained scale")
ap.add_argument("--B", type=int, default=4, help="envs")
ap.add_argument("--fields", default="", help="cpg: comma-separated subset of the preset's fields")
ap.add_argument("--omega", type=float, default=1.0, help="cpg: factor on the network's frequencies")
ap.add_argument("--tphase", type=float, default=1.0, help="cpg: factor on temp_phase")
ap.add_argument("--tforce", type=float, default=1.0, help="cpg: factor on temp_force (1 N)")
ap.add_argument("--fc", type=float, default=0.0, help="cpg: set F_contact-x/y to this (N); 0 keeps 10 N")
ap.add_argument("--face", type=float, default=0.0, help="put a full-width face at this x (m); 0: flat")
ap.add_argument("--faceh", type=float, default=0.06, help="face height, m")
a = ap.parse_args()


def _cpg(robot, feedback=True):
    ctrl = CPGController(robot, smooth=True, feedback=feedback)
    p = ctrl.default_params()
    p = p.replace(temp_force=p.temp_force * a.tforce, temp_phase=p.temp_phase * a.tphase,
                  net=p.net.replace(omega=p.net.omega * a.omega))
    if a.fc:
        p = p.replace(f_contact=p.f_contact.at[:2].set(a.fc))
    space = make_space("cpg", only=a.fields.split(",") if a.fields else None)
    return ctrl, p, space, {n: [n] for n in space.names}


def _tactile(robot):  # the setting of tests/test_tune.py
    ctrl, p = tactile_check_setting(robot)
    return ctrl, p, make_space("tactile"), {"gait": ["step_length", "step_height", "swing_time"],
                                            "overcoming": ["overcome_length", "overcome_height"],
                                            "threshold": ["tactile_threshold"]}


def _gait(robot):
    ctrl = GaitController(robot, gait="tripod")
    p = ctrl.default_params().replace(swing_time=jnp.float32(0.2))
    space = ParamSpace.from_dict({"step_length": Bound(0.005, 0.15), "step_height": Bound(0.005, 0.12),
                                  "swing_time": Bound(0.05, 3.0)})
    return ctrl, p, space, {"gait": list(space.names)}


# each --ctrl's probe: (controller, params, the tuned space, the parameter groups a cosine is read for)
PROBES = {"cpg": _cpg, "cpg-blind": lambda robot: _cpg(robot, feedback=False), "tactile": _tactile, "gait": _gait}
robot = get_robot(a.robot)
ctrl, p, space, groups = PROBES[a.ctrl](robot)

u0 = space.init(p)
spec = get_terrain("flat")
if a.face:
    spec = dataclasses.replace(get_terrain("step40"), height_range=(a.faceh, a.faceh), step_side="full",
                               start_x=a.face, length=0.004, step_length_range=(0.3, 0.3))
terr, keys = check_batch(spec, a.B)
overrides = {k: v for k, v in (("iterations", a.iters), ("cone", a.cone)) if v}
preset = get_physics(a.physics, **overrides)
print(pick(preset, "mjx").header())
phys = physics_for(spec.kind, preset.config(spec))
model, fn = rollout_function(robot, ctrl, a.window, physics=phys,
                             config=RolloutConfig(settle_time=a.settle, solver_grad=a.solver_grad))


t0 = time.time()
value, by_eps = check(travel_objective(fn, model, space, p, terr, keys), u0, groups,
                      [float(e) for e in a.eps.split(",")])
print(f"{vars(a)}\nobjective {value:.6g} (compile, gradient and differences {time.time() - t0:.0f} s)", flush=True)
for eps, res in by_eps.items():
    for group, (cos, ad, b) in res.items():
        print(f"eps {eps:g} {group:20s} cos {cos:+.3f} |autodiff| {np.linalg.norm(ad):.3g} "
              f"|FD| {np.linalg.norm(b):.3g}", flush=True)
