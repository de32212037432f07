"""Success of the Luneckas 2020 gaits against the difficulty of each terrain family, every (family, difficulty) in
one rollout per controller: terrains padded to one box count, one compiled program. Prints a table, writes JSON
and a PNG (docs/robustness.md, "Terrain families"). Run on a GPU for thousands of envs per cell:

    python scripts/terrain_families.py --batch 1024 --json out/families.json --png out/families.png

Physics: the `validated` preset (--physics, docs/physics.md) with the most box slots any family takes, recorded
in the JSON.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np

from hexjax.control.registry import make_controller
from hexjax.control.tactile import overcome_height
from hexjax.experiments.metrics import goal_errors
from hexjax.experiments.robustness import wilson
from hexjax.sim.physics import get_physics, shared_config
from hexjax.sim.rollout import rollout
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import pad_terrain, sample

FAMILIES = ("stairs-up", "stairs-down", "slope-up", "slope-down", "stones", "boxes")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=16, help="envs per (family, difficulty)")
    ap.add_argument("--levels", default="0,0.25,0.5,0.75,1")
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--controllers", default="gait,tactile")
    ap.add_argument("--distance", type=float, default=0.3)
    ap.add_argument("--start-x", type=float, default=0.1, help="where the features begin (m)")
    ap.add_argument("--physics", default="validated", help="physics preset name or .yaml path (an MJX one)")
    ap.add_argument("--json", default="")
    ap.add_argument("--png", default="")
    a = ap.parse_args(argv)
    preset = get_physics(a.physics)
    if preset.backend == "c":
        raise SystemExit(f"--physics={a.physics!r}: a MuJoCo C preset; this script runs one MJX rollout")
    print(preset.header(preset.backend))
    levels = [float(v) for v in a.levels.split(",")]
    fams = a.families.split(",")
    robot = get_robot("luneckas2020")
    specs = [get_terrain(f, start_x=a.start_x, length=a.distance + 0.4).at_difficulty(d) for f in fams for d in levels]
    m = max(s.max_boxes for s in specs)
    parts = [pad_terrain(sample(s, jax.random.PRNGKey(i), a.batch), m) for i, s in enumerate(specs)]
    terr = jax.tree_util.tree_map(lambda *x: np.concatenate(x), *parts)
    physics = shared_config(preset, specs)  # the most slots any family takes (stones: 3 per leg, 8 for the torso)
    out = {"config": dict(vars(a), robot=robot.name, backend=jax.default_backend(),
                          slots_per_leg=physics.slots_per_leg, torso_slots=physics.torso_slots),
           "physics": preset.record(preset.backend), "rows": []}
    for cname in a.controllers.split(","):
        ctrl, duration = make_controller(cname, robot).for_distance(a.distance)
        params = ctrl.default_params()
        if cname == "tactile":  # per env: Eq. 7's h_k from the env's own stairs / box heights (else the default)
            h = np.array([s.height_range[1] if s.kind in ("stairs", "boxes") else 0.03 for s in specs])
            nb = len(specs) * a.batch
            params = jax.tree_util.tree_map(lambda x: np.broadcast_to(np.asarray(x), (nb,) + np.shape(x)), params)
            params = params.replace(overcome_height=np.repeat(overcome_height(h), a.batch).astype(np.float32))
        t0 = time.perf_counter()
        s, st = rollout(robot, terr, ctrl, params, duration, jax.random.PRNGKey(9), physics=physics, stats=True,
                        params_batched=cname == "tactile")
        e = goal_errors(s, a.distance)
        ok = np.asarray(e.success).reshape(len(fams), len(levels), a.batch)
        fell = np.asarray(s.fell).reshape(ok.shape)
        err = np.hypot(np.asarray(e.dx), np.asarray(e.dy)).reshape(ok.shape)
        print(f"{cname}: {ok.size} envs, compile {st.compile_s:.1f} s, run {st.wall_s - st.compile_s:.1f} s "
              f"({st.env_steps / (st.wall_s - st.compile_s):,.0f} env-steps/s)")
        for fi, f in enumerate(fams):
            for li, d in enumerate(levels):
                k = int(ok[fi, li].sum())
                row = dict(controller=cname, family=f, difficulty=d, success_pct=100 * k / a.batch,
                           success_ci95=list(wilson(k, a.batch)), fall_pct=100 * float(fell[fi, li].mean()),
                           goal_error_cm=100 * float(np.nanmean(err[fi, li])), n=a.batch)
                out["rows"].append(row)
                print(f"  {f:12s} difficulty {d:4.2f}: success {row['success_pct']:5.1f} % "
                      f"(95 % CI {100 * row['success_ci95'][0]:.0f}-{100 * row['success_ci95'][1]:.0f}), falls "
                      f"{row['fall_pct']:5.1f} %, goal error {row['goal_error_cm']:5.1f} cm")
        out.setdefault("timing", {})[cname] = dict(compile_s=st.compile_s, run_s=st.wall_s - st.compile_s,
                                                  env_steps=st.env_steps, wall_s=time.perf_counter() - t0)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=2)
    if a.png:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, axs = plt.subplots(1, len(fams), figsize=(3.2 * len(fams), 3.2), sharey=True)
        for ax, f in zip(np.atleast_1d(axs), fams):
            for cname in a.controllers.split(","):
                rows = [r for r in out["rows"] if r["family"] == f and r["controller"] == cname]
                x = [r["difficulty"] for r in rows]
                ax.plot(x, [r["success_pct"] for r in rows], "o-", label=cname)
                ax.fill_between(x, [100 * r["success_ci95"][0] for r in rows],
                                [100 * r["success_ci95"][1] for r in rows], alpha=0.2)
            ax.set_title(f)
            ax.set_xlabel("difficulty")
            ax.grid(alpha=0.3)
        np.atleast_1d(axs)[0].set_ylabel("success %")
        np.atleast_1d(axs)[0].legend()
        fig.suptitle(f"Luneckas 2020 robot, {a.distance:g} m, {a.batch} envs per point (95 % Wilson bands)")
        fig.tight_layout()
        fig.savefig(a.png, dpi=100)


if __name__ == "__main__":
    main()
