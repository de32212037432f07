"""The Zhao 2018 avoidance planner over thousands of random obstacle fields, each with a free lane by
construction (`hexjax.plan.fields.random_fields`), planned in one jitted, vmapped call."""

from __future__ import annotations

from typing import Dict

import jax

from hexjax.plan.fields import plan_batch, random_fields


# The experiment (configs/experiments/zhao2018-random.yaml) -------------------------------------------------
def run(o, entry) -> Dict:
    if o.fields < 1:
        raise ValueError(f"--fields={o.fields!r}: plan at least 1 field")
    fields = random_fields(jax.random.PRNGKey(o.seed), o.fields, n_obstacles=o.obstacles)
    res, _ = plan_batch(fields)
    res["seed"] = o.seed
    return res


def report(res: Dict) -> str:
    return (f"{res['fields']} fields (seed {res['seed']}, {res['obstacles_per_field']:.1f} obstacles each, every one "
            f"with a free lane): success {100 * res['success_rate']:.1f} %, collisions {res['collisions']}, stuck "
            f"{res['stuck_fields']}, min clearance {100 * res['min_clearance']['min']:.1f} cm, path / straight line "
            f"{res['path_ratio']['mean']:.3f} (p95 {res['path_ratio']['p95']:.3f}), "
            f"{res['us_per_cycle_per_field']:.2f} us per plan cycle per field on {res['device']} "
            f"({res['wall_s']:.3f} s for {res['max_cycles']} cycles of all fields; compile {res['compile_s']:.1f} s)")
