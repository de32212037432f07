"""The `hexjax` command: evaluate, experiment, dataset, predictor, bench, tune, plan, render, ppo, terrain."""

from __future__ import annotations

import argparse
import json
import os
import sys


def _write_json(path: str, obj) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(obj, f, indent=2, default=float)
    print(f"wrote {path}")


def _cmd_evaluate(a) -> int:
    from hexjax.analysis.evaluate import DEFAULT_CATEGORIES, evaluate, format_table
    cats = tuple(a.categories.split(",")) if a.categories else DEFAULT_CATEGORIES
    res = evaluate(robot=a.robot, gait=a.gait, distance=a.distance, batch=a.batch, seed=a.seed,
                   categories=cats, step_height=a.step_height / 100.0, backend=a.backend)
    c = res["config"]
    print(f"\n{c['robot']} {c['gait']} gait, {c['distance_m']:g} m ({c['gait_cycles']} cycles, "
          f"{c['duration_s']:.1f} s), {c['batch']} envs per category, seed {c['seed']}, no tactile method")
    print(format_table(res))
    if a.json:
        _write_json(a.json, res)
    return 0


def _cmd_experiment(a) -> int:
    if a.name == "luneckas2020":
        return _cmd_luneckas(a)
    if a.name == "zhao2018":
        return _cmd_zhao(a)
    if a.name == "zhao2018-mjx":
        return _cmd_zhao_mjx(a)
    if a.name == "chen2019":
        return _cmd_chen(a)
    from hexjax.analysis.experiment import format_experiment, plot_experiment, run_experiment
    res = run_experiment(a.name, batch=a.batch, seed=a.seed, duration=a.duration, record=bool(a.png))
    c = res["config"]
    print(f"\n{c['experiment']}: robot {c['robot']}, {c['batch']} randomised terrains per row, "
          f"{c['duration_s']:g} s, seed {c['seed']}")
    print(format_experiment(res))
    if a.png:
        plot_experiment(res, a.png)
        print(f"wrote {a.png}")
    res.pop("_records", None)
    if a.json:
        _write_json(a.json, res)
    return 0


def _cmd_zhao(a) -> int:
    from hexjax.plan.fields import plot_zhao2018, zhao2018_experiment
    res = zhao2018_experiment()
    print(f"\nzhao2018 experiment 1: start {res['start']}, target {res['target']}, 4 obstacles (Table 1), "
          f"d_min {res['d_min']:g} m, d_max {res['d_max']:g} m, n_T {res['n_T']}")
    print(f"{'cycle':>5} {'direction':>9} {'planned (m)':>16} {'Table 2 (m)':>16} {'distance (m)':>12}")
    for row in res["cycles_table"]:
        d = row["direction_deg"]
        d = "-" if d is None else (d if isinstance(d, str) else f"{d:.0f} deg")
        pl = "-" if row["planned"] is None else f"({row['planned'][0]:.3f}, {row['planned'][1]:.3f})"
        t2 = "-" if row["table2"] is None else f"({row['table2'][0]:.3f}, {row['table2'][1]:.3f})"
        dist = "-" if row["distance"] is None else f"{row['distance']:.3f}"
        print(f"{row['cycle']:>5} {d:>9} {pl:>16} {t2:>16} {dist:>12}")
    print(f"reached: {res['reached']} in {res['cycles']} cycles (Table 2: {res['cycles_table2']}); smallest "
          f"robot-obstacle clearance {100 * res['min_clearance']:.1f} cm (overlap: {res['overlap']}); distance to "
          f"Table 2 mean {100 * res['mean_distance_to_table2']:.1f} cm, max {100 * res['max_distance_to_table2']:.1f} cm")
    if a.png:
        plot_zhao2018(res, a.png)
        print(f"wrote {a.png}")
    if a.json:
        _write_json(a.json, res)
    return 0


def _save_results(a, res, plot) -> int:
    """--png via `plot(res, path)`, --json without the `_`-keys (arrays kept for plots)."""
    if a.png:
        plot(res, a.png)
        print(f"wrote {a.png}")
    if a.json:
        _write_json(a.json, {k: v for k, v in res.items() if not k.startswith("_")})
    return 0


def _cmd_zhao_mjx(a) -> int:
    from hexjax.plan.closed_loop import plot_closed_loop, run_closed_loop
    res = run_closed_loop(n=a.batch, seed=a.seed, duration=a.duration, blind=a.blind, chunk=a.chunk)
    c, k, m = res["config"], res["kinematic"], res["mjx"]
    print(f"\nzhao2018-mjx: the planner steering the MJX {c['robot']} robot, {c['fields']} random fields (seed "
          f"{c['seed']}, {res['obstacles_per_field']:.1f} boxes each, straight line blocked in "
          f"{res['straight_line_blocked']}), {c['duration_s']:g} s{', planner BLIND to the obstacles' if c['blind'] else ''}")
    print(f"kinematic planner: success {100 * k['success_rate']:.1f} %, collisions {k['collisions']}")
    rate = m["success_rate_where_kinematic_succeeds"]
    rate = "n/a" if rate is None else f"{100 * rate:.1f} %"
    print(f"MJX closed loop: success {rate} where the kinematic planner succeeds "
          f"({100 * m['success_rate_all']:.1f} % of all); reached {m['reached']}, touched {m['touched']}, fell "
          f"{m['fell']}, NaN {m['nan']}; final distance median {100 * m['final_distance_m']['median']:.1f} cm; "
          f"robot-circle clearance min {100 * m['circle_clearance_m']['min']:.1f} cm")
    print(f"wall {res['wall_s']:.1f} s (compile {res['compile_s']:.1f} s), {res['env_steps_per_s']:,.0f} env-steps/s")
    return _save_results(a, res, plot_closed_loop)


def _cmd_chen(a) -> int:
    from hexjax.plan.rugged import plot_chen2019, run_chen2019
    res = run_chen2019(n=a.batch, seed=a.seed, duration=a.duration or 16.0, chunk=a.chunk)
    c = res["config"]
    print(f"\nchen2019: {c['robot']} robot over {c['patches']} rugged wave patches (seed {c['seed']}, peaks "
          f"{1000 * c['patch']['peak_range'][0]:.0f}-{1000 * c['patch']['peak_range'][1]:.0f} mm), "
          f"{c['speed']:.2f} m/s, {c['duration_s']:g} s")
    print(f"{'controller':>16} {'capsized':>9} {'crossed':>8} {'stalled':>8} {'tilt>30deg':>10} {'max tilt p95':>13}")
    for k in [k for k in res if k == "planned" or k.startswith("fixed")]:
        r = res[k]
        print(f"{k:>16} {r['capsized']:>9} {r['crossed']:>8} {r['stalled']:>8} {r['tilted_over_30deg']:>10} "
              f"{r['max_tilt_deg']['p95']:>12.1f}d")
    p = res["planned"]
    print(f"planned: smallest stability margin at a transition {100 * p['min_stability_margin_m']['min']:.1f} cm "
          f"(median {100 * p['min_stability_margin_m']['median']:.1f} cm); control steps with a leg target out of "
          f"reach {p['steps_with_a_leg_out_of_reach']}")
    return _save_results(a, res, plot_chen2019)


def _cmd_plan(a) -> int:
    import jax

    from hexjax.plan.fields import plan_batch, random_fields
    if a.incenter:
        return _cmd_incenter(a)
    if a.random < 1:
        raise ValueError(f"--random={a.random!r}: plan at least 1 field")
    fields = random_fields(jax.random.PRNGKey(a.seed), a.random, n_obstacles=a.obstacles)
    res, _ = plan_batch(fields)
    res["seed"] = a.seed
    print(f"{res['fields']} fields (seed {a.seed}, {res['obstacles_per_field']:.1f} obstacles each, every one with a "
          f"free lane): success {100 * res['success_rate']:.1f} %, collisions {res['collisions']}, stuck "
          f"{res['stuck_fields']}, min clearance {100 * res['min_clearance']['min']:.1f} cm, path / straight line "
          f"{res['path_ratio']['mean']:.3f} (p95 {res['path_ratio']['p95']:.3f}), "
          f"{res['us_per_cycle_per_field']:.2f} us per plan cycle per field on {res['device']} "
          f"({res['wall_s']:.3f} s for {res['max_cycles']} cycles of all fields; compile {res['compile_s']:.1f} s)")
    if a.json:
        _write_json(a.json, res)
    return 0


def _cmd_incenter(a) -> int:
    import time

    import jax

    from hexjax.plan.support import incenter_study
    if a.incenter < 1:
        raise ValueError(f"--incenter={a.incenter!r}: study at least 1 polygon per side count")
    t0 = time.perf_counter()
    res = incenter_study(jax.random.PRNGKey(a.seed), a.incenter)
    res["seed"], res["wall_s"] = a.seed, time.perf_counter() - t0
    print(f"Chen 2019 iterative incenter (Steps 1-5, {res['iterations']} iterations) against the exact one, "
          f"{a.incenter} random convex polygons per side count (seed {a.seed}):")
    print(f"{'sides':>5} {'radius shortfall p50':>21} {'p99':>9} {'p99.9':>9} {'max':>9} {'within 1e-3':>12} "
          f"{'centre offset p99 / r':>22}")
    for k, d in res["by_sides"].items():
        r, c = d["radius_shortfall"], d["centre_offset"]
        print(f"{k:>5} {r['p50']:>21.2e} {r['p99']:>9.2e} {r['p99.9']:>9.2e} {r['p100']:>9.2e} "
              f"{100 * d['within_1e-3']:>11.2f}% {c['p99']:>22.2e}")
    if a.json:
        _write_json(a.json, res)
    return 0


def _cmd_luneckas(a) -> int:
    from hexjax.analysis.luneckas import format_luneckas, plot_luneckas, run_luneckas2020
    dists = [float(x) for x in a.distances.split(",")] if a.distances else [1.0, 2.0]
    gaits = a.gaits.split(",") if a.gaits else ["wave", "tripod"]
    res = run_luneckas2020(n=a.batch, seed=a.seed, gaits=gaits, distances=dists, keep_sequences=bool(a.dataset))
    c = res["config"]
    print(f"\nluneckas2020: robot {c['robot']}, {c['n']} randomised terrains per cell, seed {c['seed']}")
    print(format_luneckas(res))
    if a.png:
        stem = a.png[:-4] if a.png.endswith(".png") else a.png
        for p in plot_luneckas(res, stem):
            print(f"wrote {p}")
    if a.dataset:
        from hexjax.analysis.predictor import concat_datasets, save_dataset
        save_dataset(a.dataset, concat_datasets(res.pop("_sequences")), {"source": "experiment luneckas2020",
                                                                         "n": a.batch, "seed": a.seed})
        print(f"wrote {a.dataset}")
    if a.json:
        _write_json(a.json, res)
    return 0


def _cmd_dataset(a) -> int:
    from hexjax.analysis.predictor import make_dataset, save_dataset
    gaits = a.gaits.split(",")
    data = make_dataset(n=a.n, seed=a.seed, gaits=gaits, distance=a.distance)
    save_dataset(a.out, data, {"source": "hexjax dataset luneckas2020", "n": a.n, "seed": a.seed, "gaits": gaits,
                               "distance_m": a.distance})
    print(f"{len(data['Y'])} sequences (the runs that stayed upright) of {data['X'].shape[1]} steps; wrote {a.out}")
    return 0


def _cmd_predictor(a) -> int:
    from hexjax.analysis.predictor import TrainConfig, run_training
    cfg = TrainConfig(epochs=a.epochs, learning_rate=a.lr, seed=a.seed)
    res = run_training(a.data.split(","), a.out, cfg, held_out_frac=a.held_out)
    h = res["held_out"]
    print(f"\ntrained on {res['train_sequences']} sequences in {res['train_s']:.0f} s; "
          f"held-out terrains: {res['held_out_sequences']} sequences; saved {res['saved']}")
    print(f"{'goal-error RMS (cm)':24s} {'all steps':>10s} " + " ".join(f"{k:>8s}" for k in h["by_progress"]))
    for name in ("lstm", "last_error", "analytic"):
        print(f"{name:24s} {h['all_steps'][name + '_rms_cm']:10.2f} "
              + " ".join(f"{v[name + '_rms_cm']:8.2f}" for v in h["by_progress"].values()))
    if a.json:
        _write_json(a.json, res)
    return 0


def _cmd_bench(a) -> int:
    from hexjax.analysis.bench import bench, format_bench
    batches = [int(x) for x in a.batches.split(",")]
    res = bench(robot=a.robot, batches=batches, sim_seconds=a.seconds, terrains=a.terrains.split(","),
                controller=a.controller, backend=a.backend, repeats=a.repeats, nthread=a.nthread, devices=a.devices)
    print(format_bench(res))
    if a.json:
        _write_json(a.json, res)
    return 0


def _parse_sets(items):
    """['steps=5', 'optimizer.learning_rate=0.2'] -> nested overrides, values parsed as YAML."""
    import yaml
    out = {}
    for it in items or []:
        key, eq, val = it.partition("=")
        if not eq or not key:
            raise ValueError(f"--set {it!r}: use key=value (e.g. --set steps=5)")
        head, _, rest = key.partition(".")
        v = yaml.safe_load(val)
        if rest:
            out.setdefault(head, {})[rest] = v
        else:
            out[head] = v
    return out


def _cmd_tune(a) -> int:
    from hexjax.analysis.tune import tune, tune_es
    from hexjax.analysis.tune_config import load_tune_config
    sets = _parse_sets(a.set)
    cfg = load_tune_config(a.config, sets, merge=True)
    out = a.out or os.path.join("out", "tune", os.path.splitext(os.path.basename(a.config))[0])
    results = []
    if a.method in ("grad", "both"):
        results.append(tune(cfg, os.path.join(out, "grad"), resume=not a.restart, time_limit=a.time_limit))
    if a.method in ("es", "both"):
        budget = a.rollouts or (results[0]["log"][-1]["rollouts"] if results else cfg.steps * cfg.train_batch)
        results.append(tune_es(cfg, os.path.join(out, "es"), rollouts=budget, resume=not a.restart,
                               time_limit=a.time_limit))
    for r in results:
        s, f = r["start"]["held_out"], r["final"]["held_out"]
        print(f"{r['method']}: held-out objective {s['objective']:.4f} -> {f['objective']:.4f} m "
              f"({r['improvement_pct']:+.1f} %), goal error {s['goal_error_cm']:.1f} -> {f['goal_error_cm']:.1f} cm "
              f"(iterate {r['final']['step']}, picked on the validation terrains), "
              f"{r['log'][-1]['rollouts']} rollouts, {r['log'][-1]['wall_s']:.0f} s")
        for k, v in r["final"]["params"].items():
            print(f"  {k}: {r['start']['params'][k]} -> {v}")
    print(f"logs, checkpoints and plots under {out}/")
    return 0


def _cmd_render(a) -> int:
    from hexjax.render import render_walk
    envs = [int(x) for x in a.envs.split(",") if x.strip()]
    res = render_walk(robot_name=a.robot, terrain_name=a.terrain, controller=a.controller, seconds=a.seconds,
                      seed=a.seed, envs=envs, out=a.out, width=a.width, height=a.height, every=a.every,
                      still=a.still or None)
    for w in res["written"]:
        print(f"wrote {w}")
    print(f"{res['frames_per_video']} frames per video at {res['fps']:.0f} fps; tactile steps per leg "
          f"{res['tactile_steps']}; fell {res['fell']}")
    return 0


def _cmd_ppo(a) -> int:
    import time

    from hexjax.envs import HexapodGoalEnv, train_ppo
    env = HexapodGoalEnv(robot=a.robot, terrain=a.terrain, goal_distance=a.goal)
    t0 = time.perf_counter()
    history, _, _ = train_ppo(env, num_timesteps=a.timesteps, num_envs=a.envs, episode_length=a.episode_length,
                              num_evals=a.evals, seed=a.seed,
                              progress=lambda step, m: print(f"  {int(step):>9,} env steps: eval episode reward "
                                                             f"{float(m['eval/episode_reward']):.3f}", flush=True))
    wall = time.perf_counter() - t0
    first, last = history[0][1], history[-1][1]
    print(f"Brax PPO on HexapodGoalEnv ({a.robot}, {a.terrain}, goal {a.goal:g} m): eval episode reward "
          f"{first:.3f} -> {last:.3f} over {history[-1][0]:,} env steps in {wall:.0f} s")
    if a.json:
        import jax
        _write_json(a.json, {"robot": a.robot, "terrain": a.terrain, "goal_m": a.goal, "timesteps": a.timesteps,
                             "num_envs": a.envs, "episode_length": a.episode_length, "seed": a.seed,
                             "history": [{"env_steps": s, "eval_episode_reward": r} for s, r in history],
                             "wall_s": wall, "device": str(jax.devices()[0].platform)})
    return 0


def _cmd_terrain(a) -> int:
    import jax
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from hexjax.terrain import get_terrain, heightmap, sample
    spec = get_terrain(a.preset)
    t = jax.tree_util.tree_map(lambda x: x[0], sample(spec, jax.random.PRNGKey(a.seed), 1))
    xr = (-0.2, spec.start_x + spec.length + 0.1)
    yr = (-0.5 * spec.width - 0.05, 0.5 * spec.width + 0.05)
    h = heightmap(t, xr, yr, res=0.0025)
    fig, ax = plt.subplots(figsize=(10, 10 * (yr[1] - yr[0]) / (xr[1] - xr[0]) + 1.2))
    im = ax.imshow(100 * h.T, origin="lower", extent=(*xr, *yr), cmap="terrain", aspect="equal")
    fig.colorbar(im, ax=ax, label="height (cm)", shrink=0.8)
    ax.add_patch(plt.Rectangle((-0.1, -0.05), 0.2, 0.1, fill=False, ec="k", lw=1.5))
    ax.set_xlabel("x (m), walking direction")
    ax.set_ylabel("y (m)")
    n = int(np.asarray(t.box_valid).sum())
    ax.set_title(f"terrain {a.preset}, seed {a.seed}: {n} boxes, ground at {100 * float(t.ground_z):.1f} cm "
                 f"(robot torso outline at the start)")
    fig.tight_layout()
    fig.savefig(a.png, dpi=110)
    print(f"wrote {a.png}")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="hexjax", description="Batched MJX hexapods on randomised terrains.")
    sub = p.add_subparsers(dest="cmd", required=True)

    e = sub.add_parser("evaluate", help="seed-000 gait over flat + the four obstacle categories")
    e.add_argument("--robot", default="luneckas2020")
    e.add_argument("--gait", default="tripod", choices=["tripod", "wave"])
    e.add_argument("--distance", type=float, default=1.0, help="m (default 1)")
    e.add_argument("--batch", type=int, default=16, help="envs per category (default 16)")
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--step-height", type=float, default=3.0, help="h_i, cm (default 3)")
    e.add_argument("--categories", default="", help="comma list of terrain presets (default flat + seed-000 four)")
    e.add_argument("--backend", default="mjx", choices=["mjx", "warp", "c"],
                   help="physics: mjx (default), warp (MuJoCo Warp through MJX; needs warp-lang), c (MuJoCo C, all cores)")
    e.add_argument("--json", default="", help="write the numbers here")
    e.set_defaults(fn=_cmd_evaluate)

    x = sub.add_parser("experiment", help="paper experiments: luneckas2020 (seed 000 matrix), yu2019-step, yu2019-ditch, "
                                          "zhao2018 (seed 004 experiment 1, avoidance planner), zhao2018-mjx (the "
                                          "planner steering the MJX robot), chen2019 (seed 002 rugged patch)")
    x.add_argument("name", choices=["luneckas2020", "yu2019-step", "yu2019-ditch", "zhao2018", "zhao2018-mjx",
                                    "chen2019"])
    x.add_argument("--batch", "--n", dest="batch", type=int, default=16,
                   help="randomised terrains per row / cell (default 16)")
    x.add_argument("--gaits", default="", help="luneckas2020: comma list of wave,tripod (default both)")
    x.add_argument("--distances", default="", help="luneckas2020: comma list of m (default 1,2)")
    x.add_argument("--seed", type=int, default=0)
    x.add_argument("--duration", type=float, default=None,
                   help="yu2019 presets: s (default: the preset's); luneckas2020 walks its distances")
    x.add_argument("--json", default="", help="write the numbers here")
    x.add_argument("--blind", action="store_true", help="zhao2018-mjx: the planner is not told of the obstacles")
    x.add_argument("--chunk", type=int, default=0, help="zhao2018-mjx, chen2019: envs per rollout call (default all)")
    x.add_argument("--dataset", default="", help="luneckas2020: also write the runs as a predictor dataset (.npz)")
    x.add_argument("--png", default="", help="write plots here (luneckas2020: <stem>_bars.png, <stem>_field.png)")
    x.set_defaults(fn=_cmd_experiment)

    ds = sub.add_parser("dataset", help="simulate walks and write an error-predictor dataset (.npz)")
    ds.add_argument("name", choices=["luneckas2020"])
    ds.add_argument("--n", type=int, default=16, help="terrains per category and method (default 16)")
    ds.add_argument("--seed", type=int, default=1, help="terrain seed (default 1; the experiment uses 0)")
    ds.add_argument("--gaits", default="wave,tripod")
    ds.add_argument("--distance", type=float, default=2.0, help="m (default 2)")
    ds.add_argument("--out", default="data/luneckas2020_seed1.npz")
    ds.set_defaults(fn=_cmd_dataset)

    pr = sub.add_parser("predictor", help="train the LSTM goal-error predictor (Luneckas 2020 Sect. 2.6)")
    pr.add_argument("--data", default="data/luneckas2020_seed1.npz", help="comma list of dataset files")
    pr.add_argument("--out", default="out/error_predictor.msgpack")
    pr.add_argument("--epochs", type=int, default=50)
    pr.add_argument("--lr", type=float, default=1e-3)
    pr.add_argument("--held-out", type=float, default=0.2, help="fraction of terrains held out (default 0.2)")
    pr.add_argument("--seed", type=int, default=0)
    pr.add_argument("--json", default="", help="write the numbers here")
    pr.set_defaults(fn=_cmd_predictor)

    b = sub.add_parser("bench", help="env-steps/s of the full rollout at several batch sizes")
    b.add_argument("--robot", default="luneckas2020")
    b.add_argument("--batches", default="16,64,256")
    b.add_argument("--terrains", default="flat,high-large")
    b.add_argument("--seconds", type=float, default=2.0, help="simulated seconds per rollout")
    b.add_argument("--controller", default="gait",
                   help="comma list of gait (seed-000 open loop), cpg (Yu 2019), tactile (seed-000 with the tactile "
                        "switch), avoid (seed-000 steered by the Zhao 2018 planner); 'both' = gait,cpg. Rows other than gait "
                        "get their cost against gait")
    b.add_argument("--backend", default="mjx",
                   help="comma list of physics backends: mjx (MJX, JAX implementation; default), warp (MJX with MuJoCo "
                        "Warp kernels; needs warp-lang), c (MuJoCo C on all host cores)")
    b.add_argument("--nthread", type=int, default=0, help="MuJoCo C threads for --backend c (default: all cores)")
    b.add_argument("--devices", type=int, default=1,
                   help="shard each batch over this many devices (backend mjx); for scaling, compare B on 1 device "
                        "with 2B on 2")
    b.add_argument("--repeats", type=int, default=2, help="timed calls per row after the first; the best is kept (0: time the first call, compile included)")
    b.add_argument("--json", default="", help="write the numbers here")
    b.set_defaults(fn=_cmd_bench)

    tu = sub.add_parser("tune", help="tune controller params over randomised terrains (gradients, or CMA-ES)")
    tu.add_argument("--config", default="configs/tune/tactile_tripod.yaml")
    tu.add_argument("--method", default="grad", choices=["grad", "es", "both"],
                    help="grad: Adam on windowed MJX gradients; es: CMA-ES (evosax); both: es gets grad's rollouts")
    tu.add_argument("--out", default="", help="directory for checkpoint, log.json, tune.png (default out/tune/<config>)")
    tu.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a config key, e.g. --set steps=5 --set optimizer.learning_rate=0.2")
    tu.add_argument("--rollouts", type=int, default=0, help="es: rollout budget (default: grad's, or steps x train_batch)")
    tu.add_argument("--time-limit", type=float, default=None, help="s of wall time per method (stops at a step boundary)")
    tu.add_argument("--restart", action="store_true", help="ignore an existing checkpoint")
    tu.set_defaults(fn=_cmd_tune)

    pl = sub.add_parser("plan", help="Zhao 2018 avoidance planner over random obstacle fields, in one batched call "
                                     "(or, with --incenter, the Chen 2019 incenter study)")
    pl.add_argument("--random", type=int, default=1000, help="fields (default 1000)")
    pl.add_argument("--seed", type=int, default=0)
    pl.add_argument("--obstacles", type=int, default=16, help="obstacle circles drawn per field before the lane is "
                                                               "cleared (default 16)")
    pl.add_argument("--incenter", type=int, default=0, metavar="N",
                    help="instead: the Chen 2019 iterative incenter against the exact one on N random convex "
                         "polygons of each of 3-6 sides")
    pl.add_argument("--json", default="", help="write the numbers here")
    pl.set_defaults(fn=_cmd_plan)

    t = sub.add_parser("terrain", help="draw a sampled terrain")
    t.add_argument("--preset", default="high-large")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--png", default="terrain.png")
    t.set_defaults(fn=_cmd_terrain)

    rd = sub.add_parser("render", help="record a short rollout and write an MP4 / GIF of chosen envs (MuJoCo "
                                       "offscreen renderer; feet forces as arrows, tactile pads yellow when on)")
    rd.add_argument("--robot", default="luneckas2020")
    rd.add_argument("--terrain", default="high-large")
    rd.add_argument("--controller", default="tactile", choices=["gait", "tactile", "cpg"])
    rd.add_argument("--seconds", type=float, default=4.0)
    rd.add_argument("--seed", type=int, default=0)
    rd.add_argument("--envs", default="0", help="comma list of env indices (default 0)")
    rd.add_argument("--out", default="out/walk.mp4", help=".mp4 or .gif (one file per env, _envK suffix)")
    rd.add_argument("--width", type=int, default=640)
    rd.add_argument("--height", type=int, default=480)
    rd.add_argument("--every", type=int, default=2, help="render every this many control steps (default 2)")
    rd.add_argument("--still", default="", help="also write the middle frame of the first env as a PNG here")
    rd.set_defaults(fn=_cmd_render)

    pp = sub.add_parser("ppo", help="Brax PPO on the hexjax goal-reaching env (residual on the seed-000 gait)")
    pp.add_argument("--robot", default="luneckas2020")
    pp.add_argument("--terrain", default="flat")
    pp.add_argument("--goal", type=float, default=1.0, help="goal distance ahead, m (default 1)")
    pp.add_argument("--timesteps", type=int, default=60_000)
    pp.add_argument("--envs", type=int, default=16)
    pp.add_argument("--episode-length", type=int, default=100, help="control steps (20 ms each)")
    pp.add_argument("--evals", type=int, default=4)
    pp.add_argument("--seed", type=int, default=0)
    pp.add_argument("--json", default="")
    pp.set_defaults(fn=_cmd_ppo)

    a = p.parse_args(argv)
    try:
        return a.fn(a)
    except ValueError as err:
        print(f"hexjax {a.cmd}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
