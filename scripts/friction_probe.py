"""The open-loop Luneckas 2020 gait on flat ground for 3 s at several friction coefficients, one env each, with a
given friction cone and Newton iteration count: advance, tilt, how far the stance feet slide, NaN. What
docs/robustness.md's friction table comes from.

    python scripts/friction_probe.py --cone elliptic --iterations 2
"""

import argparse
import dataclasses

import jax
import numpy as np

from hexjax.control.gait import GaitController
from hexjax.sim.config import RolloutConfig, physics_for
from hexjax.sim.rollout import rollout
from hexjax.world.presets import get_terrain, luneckas2020
from hexjax.world.randomization import concat_perturbations, randomization_from_dict, sample_perturbation
from hexjax.world.terrain import sample

ap = argparse.ArgumentParser()
ap.add_argument("--cone", default="pyramidal", choices=["pyramidal", "elliptic"])
ap.add_argument("--iterations", type=int, default=2)
ap.add_argument("--friction", default="1.0,0.3,0.1,0.01,1e-5,0")
a = ap.parse_args()
robot, frictions = luneckas2020(), [float(f) for f in a.friction.split(",")]
ctrl = GaitController(robot)
pert = concat_perturbations([sample_perturbation(randomization_from_dict({"friction": f}), jax.random.PRNGKey(0), 1)
                             for f in frictions])
terr = sample(get_terrain("flat"), jax.random.PRNGKey(0), len(frictions))
phys = dataclasses.replace(physics_for("flat"), iterations=a.iterations, cone=a.cone)
s = rollout(robot, terr, ctrl, ctrl.default_params(), 3.0, jax.random.PRNGKey(0), physics=phys,
            config=RolloutConfig(record=True, yaw_noise=0.0), perturbation=pert)
feet = np.asarray(s.foot_trace)
for i, f in enumerate(frictions):
    z = feet[i, :, :, 2]
    low = z < z.min() + 0.002  # a foot within 2 mm of its lowest: in stance
    slide = (np.linalg.norm(np.diff(feet[i, :, :, :2], axis=0), axis=-1) * (low[1:] & low[:-1])).sum()
    print(f"{a.cone} {a.iterations} it, friction {f:g}: advance {float(s.end_pose[i, 0] - s.start_pose[i, 0]):.3f} m, "
          f"max tilt {float(s.max_tilt[i]):.3f} rad, stance feet slide {slide:.3f} m, NaN {bool(s.nan[i])}")
