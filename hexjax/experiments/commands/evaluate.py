"""`hexjax evaluate`: the Luneckas 2020 gait over flat ground and the paper's four obstacle categories.

All categories share one physics configuration and are padded to one box count, so the whole evaluation
compiles the rollout once."""

from __future__ import annotations

from typing import Dict, Sequence

import jax
from tqdm.auto import tqdm

from hexjax.control.registry import make_controller
from hexjax.sim.metrics import batch_stats, goal_errors
from hexjax.sim.config import RolloutConfig
from hexjax.sim.engines import MESH
from hexjax.sim.physics import pick, shared_config
from hexjax.sim.rollout import rollout
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import LUNECKAS2020_CATEGORIES, pad_terrain, sample

DEFAULT_CATEGORIES = ("flat",) + LUNECKAS2020_CATEGORIES


def evaluate(robot: str = "luneckas2020", gait: str = "tripod", *, distance: float = 1.0, batch: int = 16,
             seed: int = 0, categories: Sequence[str] = DEFAULT_CATEGORIES, step_height: float = 0.03,
             physics="validated", progress: bool = True, mesh=None, engine: str | None = None) -> Dict:
    """Walk `distance` m with the open-loop Luneckas 2020 gait on each category; returns
    {"config": ..., "categories": {name: batch_stats + env_steps_per_s}, "physics": the preset's record}.
    robot, categories: preset names or YAML paths; physics: the physics chosen for the command
    (`hexjax.sim.physics.pick`: a `Physics`), or a physics preset (name, .yaml path or `PhysicsPreset`), run on
    `engine` ('mjx', 'warp', 'c'; default: the fastest engine certified for the preset on this host)."""
    chosen = pick(physics, engine, needs={MESH} if mesh is not None else ())
    if progress and chosen is not physics:  # a command's runner printed it already
        print(chosen.header(), flush=True)
    if not (isinstance(distance, (int, float)) and 0 < distance <= 20):
        raise ValueError(f"distance={distance!r}: must be in (0, 20] m")
    if not isinstance(batch, int) or batch < 1:
        raise ValueError(f"batch={batch!r}: must be an integer >= 1")
    spec = get_robot(robot)
    specs = {name: get_terrain(name, length=distance + 0.3) for name in categories}
    ctrl = make_controller("gait", spec, gait=gait, step_height=step_height)
    params = ctrl.default_params()
    ctrl, duration = ctrl.for_distance(distance, params)
    m = max(s.max_boxes for s in specs.values())
    physics = shared_config(chosen, specs.values())  # one program for every category
    chosen.engine.prepare(spec, physics)  # so that no category's timing includes it
    key = jax.random.PRNGKey(seed)
    results = {}
    bar = tqdm(list(specs.items()), desc=f"evaluate {gait} {distance:g} m", disable=not progress, unit="cat")
    for i, (name, tspec) in enumerate(bar):
        bar.set_postfix_str(name)
        k_t, k_r = jax.random.split(jax.random.fold_in(key, i))
        terr = pad_terrain(sample(tspec, k_t, batch), m)
        summ, st = rollout(spec, terr, ctrl, params, duration, k_r, physics=physics, config=RolloutConfig(), mesh=mesh,
                           engine=chosen.engine.name, stats=True)
        stats = batch_stats(summ, goal_errors(summ, distance), distance)
        stats.update(wall_s=st.run_s, compile_s=st.compile_s, env_steps_per_s=st.env_steps_per_s)
        results[name] = stats
    return {"config": dict(robot=spec.name, gait=gait, distance_m=distance, batch=batch, seed=seed,
                           gait_cycles=ctrl.n_cycles, duration_s=duration, step_height_m=step_height,
                           step_length_m=float(params.step_length), swing_time_s=float(params.swing_time),
                           slots_per_leg=physics.slots_per_leg, torso_slots=physics.torso_slots,
                           backend=jax.default_backend(), devices=len(jax.devices()), engine=chosen.engine.name),
            "categories": results, "physics": chosen.record()}


def format_table(result: Dict) -> str:
    head = f"{'category':<11} {'|dx| cm':>8} {'|dy| cm':>8} {'|da| deg':>9} {'fall %':>7} {'succ %':>7} {'NaN':>4} {'env-steps/s':>12}"
    lines = [head, "-" * len(head)]
    for name, s in result["categories"].items():
        lines.append(f"{name:<11} {s['abs_dx_cm']:8.1f} {s['abs_dy_cm']:8.1f} {s['abs_dalpha_deg']:9.1f} "
                     f"{s['fall_pct']:7.1f} {s['success_pct']:7.1f} {s['nan']:4d} {s['env_steps_per_s']:12.0f}")
    lines.append("|dx|, |dy|, |da|: mean goal errors in the start frame (Luneckas 2020 Sect. 2.5); succ: upright and "
                 "within 10 cm of the goal")
    return "\n".join(lines)


# The command (configs/commands/evaluate.yaml) ---------------------------------------------------------------
def run(o, entry) -> Dict:
    return evaluate(robot=o.robot, gait=o.gait, distance=o.distance, batch=o.batch, seed=o.seed,
                    categories=tuple(o.categories), step_height=o.step_height, physics=o.physics,
                    engine=o.engine or None)


def report(res: Dict) -> str:
    c = res["config"]
    compile_s = sum(s["compile_s"] for s in res["categories"].values())
    return (f"\n{res['physics']['name']} physics ({c['engine']}); {c['robot']} {c['gait']} gait, {c['distance_m']:g} m ({c['gait_cycles']} cycles, "
            f"{c['duration_s']:.1f} s), {c['batch']} envs per category, seed {c['seed']}, no tactile method\n"
            + format_table(res) + f"\ncompile {compile_s:.1f} s (one program for every category)")


def plot(res: Dict, png: str):
    """Mean |dx| and |dy| at the goal per category (bars, the envs' spread of dx as whiskers), and the share of
    envs that fell (right axis)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    cats = list(res["categories"])
    s = [res["categories"][c] for c in cats]
    x = np.arange(len(cats))
    fig, ax = plt.subplots(figsize=(1.4 * len(cats) + 2.5, 3.6))
    ax.bar(x - 0.2, [r["abs_dx_cm"] for r in s], 0.4, yerr=[r["dx_std_cm"] for r in s], capsize=3,
           label="|dx| (along the walk)", color="#4878a8")
    ax.bar(x + 0.2, [r["abs_dy_cm"] for r in s], 0.4, yerr=[r["dy_std_cm"] for r in s], capsize=3,
           label="|dy| (across)", color="#e0a030")
    ax.set_xticks(x, cats)
    ax.set_ylabel("goal error (cm)")
    ax.set_ylim(bottom=0)
    ax2 = ax.twinx()
    ax2.plot(x, [r["fall_pct"] for r in s], "kv", label="fell")
    ax2.set_ylabel("envs fallen (%)")
    ax2.set_ylim(0, 100)
    c = res["config"]
    ax.set_title(f"{c['robot']} {c['gait']} gait, {c['distance_m']:g} m, {c['batch']} envs a category "
                 f"({res['physics']['name']} physics)", fontsize=10)
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return [png]
