"""`hexjax families`: success of the Luneckas 2020 gaits against the difficulty of each terrain family
(docs/terrain.md's families, `TerrainSpec.at_difficulty`), every (family, difficulty) in one rollout per
controller: the terrains padded to one box count, so one compiled program walks them all.
docs/robustness.md, "Terrain families"; tests/test_terrain.py checks the open-loop gait's trend with it."""

from __future__ import annotations

import time
from typing import Dict, List, Sequence

import jax
import numpy as np

from hexjax.control.registry import CONTROLLERS, make_controller
from hexjax.sim.metrics import error_stats, goal_errors
from hexjax.experiments.commands.robustness import wilson
from hexjax.experiments.runner import step_bar
from hexjax.sim.physics import PhysicsConfig, shared_config
from hexjax.sim.rollout import rollout
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import pad_terrain, sample

WALK_KEY = 9  # the walk's key; terrain i of the (family, difficulty) grid is sampled with PRNGKey(i)


def walk_families(controller: str, families: Sequence[str], levels: Sequence[float], batch: int, distance: float,
                  start_x: float, physics: PhysicsConfig, robot: str = "luneckas2020", progress: bool = True,
                  engine: str = "mjx"):
    """`batch` envs of every (family, difficulty), in that order, walking `distance` m with the features from
    `start_x` on, in one rollout. The physics takes the most box slots any family needs (`shared_config`).
    The tactile method's overcome height (Luneckas 2020 Eq. 7's h_k) is set per env from its stairs' or boxes'
    height. A bar counts the rollout's control steps (`progress`). engine: the engine (`rollout`'s). Returns
    (summary, goal errors, rollout stats, the physics run)."""
    rob = get_robot(robot)
    specs = [get_terrain(f, start_x=start_x, length=distance + 0.4).at_difficulty(d) for f in families
             for d in levels]
    m = max(s.max_boxes for s in specs)
    parts = [pad_terrain(sample(s, jax.random.PRNGKey(i), batch), m) for i, s in enumerate(specs)]
    terr = jax.tree_util.tree_map(lambda *x: np.concatenate(x), *parts)
    phys = shared_config(physics, specs)
    ctrl, duration = make_controller(controller, rob).for_distance(distance)
    rule = CONTROLLERS[controller].family_params  # e.g. the tactile method's h_k per env (Eq. 7)
    per_env = rule is not None
    params = rule(ctrl, specs, batch) if per_env else ctrl.default_params()
    with step_bar(f"{controller} x {len(specs) * batch} envs", ctrl.dt, duration, every=10, enabled=progress) as cfg:
        s, st = rollout(rob, terr, ctrl, params, duration, jax.random.PRNGKey(WALK_KEY), physics=phys, stats=True,
                        params_batched=per_env, config=cfg, engine=engine)
    return s, goal_errors(s, distance), st, phys


# The command (configs/commands/families.yaml) ------------------------------------------------------------------
def run(o, entry) -> Dict:
    from hexjax.sim.physics import pick
    physics = pick(o.physics, o.engine or None)  # as the runner chose it (the fastest certified on this host)
    fams, levels = list(o.families), [float(v) for v in o.levels]
    out: Dict = {"config": dict(batch=o.batch, levels=levels, families=fams, controllers=list(o.controllers),
                                distance=o.distance, start_x=o.start_x, robot="luneckas2020",
                                backend=jax.default_backend(), engine=physics.engine.name), "rows": [],
           "timing": {}, "physics": physics.record()}
    for cname in o.controllers:
        t0 = time.perf_counter()
        s, e, st, phys = walk_families(cname, fams, levels, o.batch, o.distance, o.start_x, physics,
                                       engine=physics.engine.name)
        out["config"].update(slots_per_leg=phys.slots_per_leg, torso_slots=phys.torso_slots)
        shape = (len(fams), len(levels), o.batch)
        ok = np.asarray(e.success).reshape(shape)
        fell = np.asarray(s.fell).reshape(shape)
        dx, dy, da, adv = (np.asarray(v).reshape(shape) for v in (e.dx, e.dy, e.dalpha, e.advance))
        nan = np.asarray(s.nan).reshape(shape)
        for fi, f in enumerate(fams):
            for li, d in enumerate(levels):
                k = int(ok[fi, li].sum())
                out["rows"].append(dict(controller=cname, family=f, difficulty=d, success_pct=100 * k / o.batch,
                                        success_ci95=list(wilson(k, o.batch)),
                                        fall_pct=100 * float(fell[fi, li].mean()),
                                        advance_cm=100 * float(adv[fi, li].mean()), nan_envs=int(nan[fi, li].sum()),
                                        goal_error_cm=error_stats(dx[fi, li], dy[fi, li], da[fi, li],
                                                                  o.distance)["goal_error_cm"], n=o.batch))
        run_s = st.wall_s - st.compile_s
        out["timing"][cname] = dict(compile_s=st.compile_s, run_s=run_s, env_steps=st.env_steps,
                                    env_steps_per_s=st.env_steps / run_s, wall_s=time.perf_counter() - t0)
    return out


def report(res: Dict) -> str:
    lines: List[str] = []
    for cname, t in res["timing"].items():
        n = len(res["config"]["families"]) * len(res["config"]["levels"]) * res["config"]["batch"]
        lines.append(f"{cname}: {n} envs, compile {t['compile_s']:.1f} s, run {t['run_s']:.1f} s "
                     f"({t['env_steps_per_s']:,.0f} env-steps/s)")
        for r in (r for r in res["rows"] if r["controller"] == cname):
            lo, hi = (100 * v for v in r["success_ci95"])
            lines.append(f"  {r['family']:12s} difficulty {r['difficulty']:4.2f}: success {r['success_pct']:5.1f} % "
                         f"(95 % CI {lo:.0f}-{hi:.0f}), falls {r['fall_pct']:5.1f} %, goal error "
                         f"{r['goal_error_cm']:5.1f} cm")
    return "\n".join(lines)


def plot(res: Dict, png: str) -> List[str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    cfg = res["config"]
    fams = cfg["families"]
    fig, axs = plt.subplots(1, len(fams), figsize=(3.2 * len(fams), 3.2), sharey=True, squeeze=False)
    for ax, f in zip(axs[0], fams):
        for cname in cfg["controllers"]:
            rows = [r for r in res["rows"] if r["family"] == f and r["controller"] == cname]
            x = [r["difficulty"] for r in rows]
            ax.plot(x, [r["success_pct"] for r in rows], "o-", label=cname)
            ax.fill_between(x, [100 * r["success_ci95"][0] for r in rows], [100 * r["success_ci95"][1] for r in rows],
                            alpha=0.2)
        ax.set_title(f)
        ax.set_xlabel("difficulty")
        ax.set_ylim(-3, 103)
        ax.grid(alpha=0.3)
    axs[0, 0].set_ylabel("success %")
    axs[0, 0].legend()
    fig.suptitle(f"Luneckas 2020 robot, {cfg['distance']:g} m, {cfg['batch']} envs per point (95 % Wilson bands)\n"
                 f"physics: {res.get('physics', {}).get('name', '')}", fontsize=10)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return [png]
