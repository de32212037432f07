"""The Zhao 2018 avoidance planner in the loop (Sect. 3.2): `AvoidGaitController` steers the MJX Luneckas 2020
robot among box obstacles to a target, over thousands of random fields in one rollout, beside the kinematic
planner on the same fields; with `blind` the planner is told of no obstacle (the ablation).

Physical obstacles are boxes (the terrain is boxes, docs/terrain.md) inscribed in the planner's circles (Eq. 1
envelopes each obstacle by a circle): square columns and elongated boxes, 0.25 m tall, taller than the robot,
so touching one means a collision, not a step over it (`touches`).
"""

from __future__ import annotations

import math
import time
from typing import Dict, Optional

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from hexjax.control.avoid_gait import AvoidGaitController, fast_gait, field_params, small_robot_params
from hexjax.control.registry import make_controller
from hexjax.experiments.runner import step_bar
from hexjax.plan import avoid
from hexjax.plan.avoid import AvoidConfig
from hexjax.plan.fields import Fields, small_fields, straight_line_blocked
from hexjax.sim.config import RolloutConfig
from hexjax.sim.engines import RANGE_SENSORS, TRACES
from hexjax.sim.physics import pick
from hexjax.sim.rollout import rollout
from hexjax.world.presets import get_robot
from hexjax.world.robot import RobotSpec, hip_positions
from hexjax.world.terrain import Terrain

NEEDS = frozenset({TRACES})  # what it needs of its engine: the walks' traces (the runner picks the engine once)

OBSTACLE_HEIGHT = 0.25  # m: taller than the Luneckas 2020 robot (torso top ~0.12 m)


def obstacle_boxes(key, fields: Fields, height: float = OBSTACLE_HEIGHT) -> Terrain:
    """Each obstacle circle as a box inscribed in it: footprint half extents r (cos a, sin a) with the aspect
    angle a drawn from U(25, 65) deg (45: a square column; elsewhere an elongated box)."""
    a = jax.random.uniform(key, fields.radii.shape, minval=math.radians(25), maxval=math.radians(65))
    hx, hy = fields.radii * jnp.cos(a), fields.radii * jnp.sin(a)
    pos = jnp.concatenate([fields.centres, jnp.full(fields.radii.shape + (1,), 0.5 * height)], -1)
    half = jnp.stack([hx, hy, jnp.full_like(hx, 0.5 * height)], -1)
    return Terrain(box_pos=pos, box_half=half, box_valid=fields.valid,
                   ground_z=jnp.zeros(fields.radii.shape[:-1]))


def _body_points(robot: RobotSpec, n_seg: int = 6):
    """Points of the robot's horizontal outline in the torso frame: the torso's perimeter (radius 0) and
    each leg's hip-to-foot chord (radius foot_radius, added by the caller). Returns (torso (P, 2),
    fractions (n_seg,) along hip -> foot)."""
    hx, hy = 0.5 * robot.body_length, 0.5 * robot.body_width
    s = np.linspace(-1, 1, 9)
    per = np.concatenate([np.stack([hx * s, np.full(9, hy)], 1), np.stack([hx * s, np.full(9, -hy)], 1),
                          np.stack([np.full(9, hx), hy * s], 1), np.stack([np.full(9, -hx), hy * s], 1)])
    return per, np.linspace(0.0, 1.0, n_seg)


def touches(robot: RobotSpec, trace, foot_trace, terrain: Terrain, chunk: int = 256) -> np.ndarray:
    """(B,) bool: at some control step a part of the robot was inside an obstacle box's footprint: a point
    of the torso outline, or a point of a leg's hip-to-foot chord within foot_radius of it (legs splay out,
    so the knee lies over that chord), or the box's centre inside the torso. trace (B, T, 4): x, y, z,
    yaw; foot_trace (B, T, 6, 3); world frame. Obstacles are taller than the robot, so height is ignored."""
    per, frac = _body_points(robot)
    hips = hip_positions(robot)[:, :2]
    out = []

    @jax.jit
    def one(tr, ft, bp, bh, bv):
        c, s = jnp.cos(tr[..., 3]), jnp.sin(tr[..., 3])
        rot = lambda p: jnp.stack([c[..., None] * p[:, 0] - s[..., None] * p[:, 1],
                                   s[..., None] * p[:, 0] + c[..., None] * p[:, 1]], -1)
        torso = rot(jnp.asarray(per)) + tr[..., None, :2]  # (T, P, 2)
        hip = rot(jnp.asarray(hips)) + tr[..., None, :2]  # (T, 6, 2)
        legs = hip[:, :, None] + (ft[..., :2] - hip)[:, :, None] * jnp.asarray(frac)[:, None]  # (T, 6, S, 2)
        pts = jnp.concatenate([torso, legs.reshape(legs.shape[0], -1, 2)], 1)  # (T, N, 2)
        rad = jnp.concatenate([jnp.zeros(torso.shape[1]), jnp.full(legs.shape[1] * legs.shape[2], robot.foot_radius)])
        d = jnp.abs(pts[:, :, None, :] - bp[None, None, :, :2]) - bh[None, None, :, :2]  # (T, N, Q, 2)
        dist = jnp.linalg.norm(jnp.maximum(d, 0.0), axis=-1) - rad[None, :, None]
        hit = jnp.any((dist <= 0.0) & bv[None, None, :])
        # a box centre inside the torso rectangle (a small box could fit between its outline points)
        rel = bp[None, :, :2] - tr[:, None, :2]  # (T, Q, 2)
        lx = c[:, None] * rel[..., 0] + s[:, None] * rel[..., 1]
        ly = -s[:, None] * rel[..., 0] + c[:, None] * rel[..., 1]
        inside = (jnp.abs(lx) <= 0.5 * robot.body_length) & (jnp.abs(ly) <= 0.5 * robot.body_width) & bv[None]
        return hit | jnp.any(inside)

    fn = jax.vmap(one)
    for i in range(0, trace.shape[0], chunk):
        sl = slice(i, i + chunk)
        out.append(np.asarray(fn(trace[sl], foot_trace[sl], terrain.box_pos[sl], terrain.box_half[sl],
                                 terrain.box_valid[sl])))
    return np.concatenate(out)


def field_setup(ctrl: AvoidGaitController):
    """(gait params, planner params) of the closed loop for a planner-gait: `fast_gait` and
    `small_robot_params` at its step length and advance per cycle."""
    g = fast_gait(ctrl)
    return g, small_robot_params(ctrl.robot, float(g.step_length), ctrl.advance(g))


def seed_keys(seed: int):
    """(fields, obstacle boxes, rollouts) keys of the closed loop for `seed`."""
    return tuple(jax.random.split(jax.random.PRNGKey(seed), 3))


def seeded_fields(seed: int, n: int, ap):
    """The n random fields `run_closed_loop` draws for `seed` (`small_fields` with the planner's robot radius
    and d_max), and the key for the obstacle boxes."""
    k_field, k_box, _ = seed_keys(seed)
    return small_fields(k_field, n, float(ap.robot_radii[0]), float(ap.d_max)), k_box


def run_closed_loop(n: int = 32, *, seed: int = 0, robot: str = "luneckas2020", n_T: int = 2,
                    duration: Optional[float] = None, chunk: int = 0, mesh=None, fields: Optional[Fields] = None,
                    blind: bool = False, controller: Optional[AvoidGaitController] = None,
                    progress: bool = False, physics="validated", label: str = "closed loop") -> Dict:
    """Closed-loop avoidance over n random fields (`small_fields`, or the given `fields`): the kinematic
    planner (`avoid.plan`, same params) and the MJX hexapod with `AvoidGaitController`, side by side.
    blind: the MJX robot's planner is not told of the obstacles (they are still in the terrain), the
    ablation that shows what the planner prevents. controller: another `AvoidGaitController` (with the same
    n_T), e.g. one that plans round perceived obstacles (`hexjax.control.perceive_gait`). Returns a JSON-ready
    dict; the `_`-keys hold arrays for plots. A field counts as a closed-loop success when the robot stopped
    within goal_tol of the target, touched no obstacle, did not fall and stayed finite. physics: a physics preset
    on MJX (name, .yaml path or `PhysicsPreset`; the touch test reads MJX's foot traces). progress: a bar over the
    walk's control steps named `label` (a program with a host callback, compiled afresh), or per chunk."""
    rb = get_robot(robot)
    ctrl = controller or make_controller("avoid", rb, avoid=AvoidConfig(n_T=n_T, max_cycles=40))
    # the touch test reads the foot traces; a perceiving controller casts rays
    preset = pick(physics, needs=NEEDS | ({RANGE_SENSORS} if getattr(ctrl, "sensor", None) is not None else set()))
    g, ap = field_setup(ctrl)
    _, k_box, k_roll = seed_keys(seed)
    if fields is None:
        if not (isinstance(n, int) and n >= 1):
            raise ValueError(f"fields n={n!r}: must be an integer >= 1")
        fields, _ = seeded_fields(seed, n, ap)
    n = int(fields.start.shape[0])
    if np.any(np.asarray(fields.start) != 0):
        raise ValueError("fields.start: the MJX robot starts at (0, 0); give fields with start (0, 0)")
    avoid.check_inputs(fields.start, fields.target, fields.centres, fields.radii, fields.valid, ap, ctrl.avoid)
    kin = jax.jit(jax.vmap(lambda s, t, c, r, v: avoid.plan(s, t, c, r, v, ap, ctrl.avoid)))(
        fields.start, fields.target, fields.centres, fields.radii, fields.valid)
    kin_ok = np.asarray(kin.reached) & (np.asarray(kin.min_clearance) > 0)
    blocked = straight_line_blocked(fields, float(ap.robot_radii[0]))
    cycle = float(g.swing_time) * ctrl.pattern.period
    if duration is None:  # the slowest kinematic walk, plus two plan cycles and the stopping cycle
        duration = (int(np.max(np.asarray(kin.cycles))) + 2) * n_T * cycle + cycle
    terrain = obstacle_boxes(k_box, fields)
    params = field_params(ctrl, fields, ap, g)
    if blind:
        params = params.replace(valid=jnp.zeros_like(params.valid))
    cfg = RolloutConfig(record=True)
    chunk, outs, compile_s, t0 = chunk or n, [], 0.0, time.perf_counter()
    with step_bar(f"{label}: {n} fields, {duration:g} s", ctrl.dt, duration, cfg,
                  enabled=progress and n <= chunk) as run_cfg:
        for i in tqdm(range(0, n, chunk), desc=label, unit="chunk", disable=n <= chunk or not progress):
            sl = lambda x: x[i:i + chunk]
            s, st = rollout(rb, jax.tree_util.tree_map(sl, terrain), ctrl, jax.tree_util.tree_map(sl, params),
                            duration, jax.random.fold_in(k_roll, i), config=run_cfg, params_batched=True, mesh=mesh,
                            stats=True, physics=preset.config(kind="obstacles"), engine=preset.engine.name)
            compile_s += st.compile_s
            touched = touches(rb, s.trace, s.foot_trace, jax.tree_util.tree_map(sl, terrain))
            outs.append((jax.device_get(s), touched))
    wall = time.perf_counter() - t0
    cat = lambda f: np.concatenate([np.asarray(f(o[0])) for o in outs])
    touched = np.concatenate([o[1] for o in outs])
    planner = lambda s: getattr(s.final_state, "avoid", s.final_state)  # the planner-gait's own state
    reached = cat(lambda s: planner(s).done)
    fell, nan = cat(lambda s: s.fell), cat(lambda s: s.nan)
    end = cat(lambda s: s.end_pose)
    final_dist = np.linalg.norm(end[:, :2] - np.asarray(fields.target), axis=-1)
    ok = reached & ~touched & ~fell & ~nan
    traces = np.concatenate([np.asarray(o[0].trace) for o in outs])
    # clearance of the robot circle along the executed path (Eq. 1, centre = torso)
    d = jax.vmap(lambda tr, c, r, v: jnp.min(avoid.clearance(tr[:, :2], ap, c, r, v)))(
        jnp.asarray(traces), fields.centres, fields.radii, fields.valid)
    d = np.asarray(d)
    length = np.sum(np.linalg.norm(np.diff(traces[:, :, :2], axis=1), axis=-1), axis=1)
    straight = np.linalg.norm(np.asarray(fields.target - fields.start), axis=-1)
    env_steps = n * (int(round(cfg.settle_time / ctrl.dt)) + int(math.ceil(duration / ctrl.dt - 1e-9))) * 4
    frac = lambda m: float(m.mean()) if m.size else None
    res = {
        "config": {"robot": robot, "fields": n, "seed": seed, "blind": blind, "n_T_gait_cycles": n_T, "duration_s": duration,
                   "step_length": float(g.step_length), "swing_time": float(g.swing_time),
                   "advance_per_cycle": ctrl.advance(g), "robot_radius": float(ap.robot_radii[0]),
                   "d_min": float(ap.d_min), "d_max": float(ap.d_max), "goal_tol": float(ap.goal_tol),
                   "obstacle_height": OBSTACLE_HEIGHT, "device": str(jax.devices()[0].platform)},
        "obstacles_per_field": float(np.asarray(fields.valid).sum(-1).mean()),
        "straight_line_blocked": int(blocked.sum()),
        "kinematic": {"success_rate": frac(kin_ok), "collisions": int((np.asarray(kin.min_clearance) <= 0).sum()),
                      "cycles_mean": float(np.asarray(kin.cycles).mean())},
        "mjx": {
            "success_rate_where_kinematic_succeeds": frac(ok[kin_ok]),
            "success_rate_all": frac(ok),
            "success_rate_where_straight_line_blocked": frac(ok[kin_ok & blocked]),
            "reached": int(reached.sum()), "touched": int(touched.sum()), "fell": int(fell.sum()),
            "nan": int(nan.sum()),
            "touched_where_kinematic_succeeds": int(touched[kin_ok].sum()),
            "final_distance_m": {"median": float(np.median(final_dist)), "max": float(final_dist.max())},
            "circle_clearance_m": {"min": float(d.min()), "p5": float(np.percentile(d, 5)),
                                   "median": float(np.median(d))},
            "path_ratio_mean": float((length / straight)[ok].mean()) if ok.any() else None,
            "plans_mean": float(cat(lambda s: planner(s).plans).mean()),
            "held_cycles": int(cat(lambda s: planner(s).held).sum()),
        },
        "wall_s": wall, "compile_s": compile_s, "env_steps_per_s": env_steps / max(wall - compile_s, 1e-9),
        "_fields": fields, "_terrain": terrain, "_traces": traces, "_ok": ok, "_kin": kin, "_blocked": blocked,
        "_touched": touched, "_final": jax.tree_util.tree_map(lambda *x: np.concatenate(x),
                                                              *[o[0].final_state for o in outs]),
    }
    return res


def plot_closed_loop(res: Dict, png: str, k: int = 6) -> None:
    """k fields, those whose straight line is blocked first: obstacle boxes (and their circles), the kinematic
    plan and the MJX torso path."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    f, tr, kin, ok = res["_fields"], res["_terrain"], res["_kin"], res["_ok"]
    order = np.concatenate([np.flatnonzero(res["_blocked"]), np.flatnonzero(~res["_blocked"])])[:k]
    k = len(order)
    cols = min(3, k)
    rows = int(math.ceil(k / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.6 * rows), squeeze=False)
    for slot, ax in enumerate(axes.ravel()):
        if slot >= k:
            ax.axis("off")
            continue
        i = int(order[slot])
        for p, h, v, c, r in zip(np.asarray(tr.box_pos[i]), np.asarray(tr.box_half[i]), np.asarray(tr.box_valid[i]),
                                 np.asarray(f.centres[i]), np.asarray(f.radii[i])):
            if not v:
                continue
            ax.add_patch(plt.Rectangle(p[:2] - h[:2], 2 * h[0], 2 * h[1], color="tab:red", alpha=0.6))
            ax.add_patch(plt.Circle(c, r, fill=False, color="tab:red", lw=0.5, ls="--"))
        n = int(kin.cycles[i])
        kp = np.asarray(kin.path[i])[: n + 1]
        ax.plot(kp[:, 0], kp[:, 1], "--o", ms=2, color="tab:green", lw=1, label="kinematic plan")
        t = res["_traces"][i]
        ax.plot(t[:, 0], t[:, 1], "-", color="k", lw=1.2, label="MJX torso")
        rad = res["config"]["robot_radius"]
        ax.add_patch(plt.Circle(t[-1, :2], rad, fill=False, color="tab:blue", lw=0.6))
        ax.plot(*np.asarray(f.target[i]), "*", color="tab:orange", ms=10)
        ax.set_aspect("equal")
        ax.set_xlim(-0.4, 2.4)
        ax.set_ylim(-0.9, 0.9)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_title(f"field {i}{' (straight line blocked)' if res['_blocked'][i] else ''}: "
                     f"{'ok' if ok[i] else 'FAILED'}", fontsize=9)
        if slot == 0:
            ax.legend(fontsize=6, loc="lower right")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


# The experiment (configs/experiments/zhao2018-mjx.yaml) ----------------------------------------------------
def run(o, entry) -> Dict:
    return run_closed_loop(n=o.batch, seed=o.seed, robot=o.robot, n_T=entry.preset["n_T"], duration=o.duration,
                           blind=o.blind, chunk=o.chunk, physics=o.physics, progress=True, label="zhao2018-mjx")


def report(res: Dict) -> str:
    c, k, m = res["config"], res["kinematic"], res["mjx"]
    rate = m["success_rate_where_kinematic_succeeds"]
    rate = "n/a" if rate is None else f"{100 * rate:.1f} %"
    return "\n".join([
        f"\nzhao2018-mjx: the planner steering the MJX {c['robot']} robot, {c['fields']} random fields (seed "
        f"{c['seed']}, {res['obstacles_per_field']:.1f} boxes each, straight line blocked in "
        f"{res['straight_line_blocked']}), {c['duration_s']:g} s{', planner BLIND to the obstacles' if c['blind'] else ''}",
        f"kinematic planner: success {100 * k['success_rate']:.1f} %, collisions {k['collisions']}",
        f"MJX closed loop: success {rate} where the kinematic planner succeeds ({100 * m['success_rate_all']:.1f} % of "
        f"all); reached {m['reached']}, touched {m['touched']}, fell {m['fell']}, NaN {m['nan']}; final distance "
        f"median {100 * m['final_distance_m']['median']:.1f} cm; robot-circle clearance min "
        f"{100 * m['circle_clearance_m']['min']:.1f} cm",
        f"wall {res['wall_s']:.1f} s (compile {res['compile_s']:.1f} s), {res['env_steps_per_s']:,.0f} env-steps/s"])


plot = plot_closed_loop  # (result, png): the registry's plot
