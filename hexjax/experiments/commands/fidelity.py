"""`hexjax fidelity`: how far one physics preset's figures are from another's (default: `validated` against
`reference`, converged MuJoCo C) over a matrix of scenarios, with the contract every reported figure must meet.

The matrix (configs/commands/fidelity.yaml, `preset:`): flat ground and the four Luneckas 2020 categories;
every terrain family at three difficulties; the friction coefficients on an obstacle field and on a slope; a
payload. The gait and the tactile switch (Luneckas 2020) walk every cell, the Yu 2019 CPG the flat, step and
ditch cells, the Zhao 2018 avoiding gait the box cells. Both presets see the same terrains, heading draws and
perturbation draws (common random numbers), so each env is a pair and every difference is reported with a
paired 95 % interval.

Per cell: success (upright, within 10 cm of the goal), mean advance, lateral drift |dy|, heading error |d alpha|,
falls and foot slip (cm per m walked), for both presets, and the differences. The contract: |d success| <= 5
points, |d mean advance| <= 1.5 cm, |d heading| <= 1.5 deg (`CONTRACT`). Besides the walks, open-loop replays
(the Luneckas 2020 gait, whose joint targets do not read the sensors, so both engines get the same targets)
give the torso's divergence after 0.5, 1 and 2 s.

All cells of one controller that share a physics configuration (terrain slot count) run as the envs of one
rollout call (on a host-only engine, MuJoCo C, all of them: it splits a call by box count itself), each group
with its own heading draws: terrains padded to one box count, friction and payload as per-env draws. Finished
rollouts are kept beside the JSON (`<json>.partial.json`); a rerun of the same command resumes after them. Each
finished rollout is also kept in the cache (`<cache>/fidelity/`, by the matrix's digest and the physics' own
key), so a later run against the same reference (another engine or settings under test) runs only its own side.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import hashlib
import json
import math
import threading
from typing import Dict, List, Optional

import numpy as np

# plot and report are the registry's (this module is the entry)
from hexjax.experiments.commands.fidelity_view import CONTRACT, plot, report  # noqa: F401
from hexjax.experiments.runner import keep_piece, read_kept, read_partial, write_partial

ALL = "all"


@dataclasses.dataclass(frozen=True)
class Cell:
    """One scenario: a terrain preset (at a difficulty, or as written), a friction coefficient (None: the robot's
    own) and a payload on the torso (kg)."""

    terrain: str
    difficulty: Optional[float] = None
    friction: Optional[float] = None
    payload: float = 0.0

    @property
    def name(self) -> str:
        out = self.terrain + (f" d={self.difficulty:g}" if self.difficulty is not None else "")
        if self.friction is not None:
            out += f" mu={self.friction:g}"
        if self.payload:
            out += f" +{self.payload:g} kg"
        return out


def matrix(spec: Dict) -> List[Cell]:
    """The cells of the matrix block `spec` (see configs/commands/fidelity.yaml), each once, in order."""
    cells: List[Cell] = []
    add = lambda c: cells.append(c) if c not in cells else None
    for t in spec.get("terrains", []):
        add(Cell(t))
    for t in spec.get("families", []):
        for d in spec.get("difficulties", []):
            add(Cell(t, difficulty=float(d)))
    for t in spec.get("friction_terrains", []):
        for f in spec.get("frictions", []):
            add(Cell(t, friction=None if float(f) == 1.0 else float(f)))
    for t in spec.get("payload_terrains", []):
        for p in spec.get("payloads", []):
            add(Cell(t, payload=float(p)))
    return cells


def _digest(o, spec: Dict) -> str:
    """What the kept rollouts depend on besides the physics (each run is kept under its own preset's key): the
    options and the matrix itself (a run is kept by its cells' positions in it)."""
    keys = ("batch", "distance", "seed", "controllers", "only", "robot")
    blob = {k: getattr(o, k, None) for k in keys}
    blob["matrix"] = spec
    blob["groups"] = "slots per leg and torso"  # how cells share a rollout (and so its draws): runs kept under
    # an older grouping are not paired with new ones
    return hashlib.sha256(json.dumps(blob, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _physics_key(record: Dict) -> str:
    """A kept run's physics: every setting and the engine, not the preset's name (a copy under another name
    reuses it)."""
    blob = {k: v for k, v in record.items() if k not in ("name", "picked", "certified", "certificates")}
    return hashlib.sha256(json.dumps(blob, sort_keys=True, default=str).encode()).hexdigest()[:12]


def _presets(o):
    """(A, B): the physics under test and the physics it is held against (`Physics`, each a preset's own
    settings on an engine). With --refine, B is --against itself and A the same with its timestep halved and its
    iterations doubled (is it converged?); else A is --physics on --engine (default: the preset's own)."""
    from hexjax.sim.engines import get_engine
    from hexjax.sim.physics import Physics, get_physics
    own = lambda p, e=None, why="": Physics(p, get_engine(e or p.engine), p.settings, p.name, (), why)
    b = get_physics(o.against)
    if o.refine:
        a = get_physics(b, timestep=b.timestep / 2, iterations=2 * b.iterations,
                        ls_iterations=2 * b.ls_iterations, name=f"{b.name}-refined")
        return own(a, b.engine, "refined"), own(b, why="held against")
    a = get_physics(o.physics)
    e = get_engine(o.engine or a.engine)
    if not e.available():
        raise ValueError(f"--engine={e.name}: {e.title} is not installed here: {e.install}")
    return own(a, e.name, "under test"), own(b, why="held against")


def _runs(o, cells: List[Cell], controllers: Dict, kinds: Dict[str, str], entry_preset: Dict):
    """[(label, controller, robot, duration, [cell indices])]: which cells each controller walks."""
    allowed = entry_preset.get("controllers", {})
    out = []
    for label, (ctrl, rb) in controllers.items():
        which = allowed.get(label, allowed.get(label.partition("@")[0], ALL))
        idx = [i for i, c in enumerate(cells) if which == ALL or kinds[c.terrain] in which]
        if idx:
            ctrl, duration = ctrl.for_distance(o.distance)
            out.append((label, ctrl, rb, duration, idx))
    return out


def _cell_inputs(o, cell: Cell, j: int, rb, label: str, ctrl, key):
    """(terrain spec, terrain batch, perturbation batch, params or None) of cell j for one controller; the draws
    depend on (seed, j) alone, so both presets and every controller see the same ones."""
    import jax

    from hexjax.control.registry import CONTROLLERS
    from hexjax.world.presets import get_terrain
    from hexjax.world.randomization import randomization_from_dict, sample_perturbation
    from hexjax.world.terrain import leg_scale, sample
    spec = get_terrain(cell.terrain, length=o.distance + 0.3)
    if cell.difficulty is not None:
        spec = spec.at_difficulty(cell.difficulty, leg_scale(rb))
    k_t, k_p = jax.random.split(jax.random.fold_in(key, j))
    terr = sample(spec, k_t, o.batch)
    rnd = {"payload_kg": cell.payload}
    if cell.friction is not None:
        rnd["friction"] = cell.friction
    pert = sample_perturbation(randomization_from_dict(rnd), k_p, o.batch)
    rule = CONTROLLERS[label.partition("@")[0]].cell_params  # None: every env walks the controller's defaults
    params = None
    if rule is not None:  # per env, so that cells of one group concatenate
        params, batched = rule(ctrl, spec, terr, o.distance)
        if not batched:
            params = jax.tree_util.tree_map(lambda x: np.broadcast_to(np.asarray(x), (o.batch,) + np.shape(x)),
                                            params)
    return spec, terr, pert, params


def _walk(o, preset, label: str, ctrl, rb, duration: float, idx: List[int], cells: List[Cell], key,
          mesh_for) -> Dict[str, List]:
    """Per-env outcomes (lists, cells in `idx` order, `o.batch` envs each) of one controller under one physics
    (`Physics`): one rollout call per group of cells that share a physics configuration."""
    from hexjax.sim.engines import MESH
    import jax

    from hexjax.sim.metrics import goal_errors
    from hexjax.sim.config import RolloutConfig
    from hexjax.sim.rollout import rollout
    from hexjax.world.randomization import concat_perturbations
    from hexjax.world.terrain import pad_terrain
    # drawn on the host: each cell's terrain family is its own small program, which a GPU compiles far more slowly
    # than the host does (52 cells cost minutes there before the first rollout)
    with jax.default_device(jax.devices("cpu")[0]):
        inputs = {j: _cell_inputs(o, cells[j], j, rb, label, ctrl, key) for j in idx}
    # grouped by the terrain's own slot counts, whatever the preset does with them, so that both presets split the
    # cells alike and every env gets the same heading draw under both
    groups: Dict = {}
    for j in idx:
        groups.setdefault((inputs[j][0].slots_per_leg, inputs[j][0].torso_slots), []).append(j)
    per_cell = {}
    # a host-only engine (MuJoCo C: every box a geom, no slots) takes every group in one call, whose lanes it splits
    # by box count itself: big calls keep its threads busy; each group's envs keep the group's heading draws
    calls = [[js] for js in groups.values()]
    if preset.engine.host_only:
        calls = [list(groups.values())]
    for parts in calls:
        js = [j for part in parts for j in part]
        physics = preset.config(inputs[js[0]][0], kind="mixed")
        n_box = max(inputs[j][1].box_pos.shape[1] for j in js)
        cat = lambda *xs: jax.tree_util.tree_map(lambda *a: np.concatenate([np.asarray(x) for x in a]), *xs)
        terr = cat(*[pad_terrain(inputs[j][1], n_box) for j in js])
        pert = concat_perturbations([inputs[j][2] for j in js])
        batched = inputs[js[0]][3] is not None
        params = cat(*[inputs[j][3] for j in js]) if batched else ctrl.default_params()
        group_key = lambda part: jax.random.fold_in(key, 10_000 + part[0])
        keys = group_key(parts[0]) if len(parts) == 1 else \
            np.concatenate([jax.random.split(group_key(part), len(part) * o.batch) for part in parts])
        s, st = rollout(rb, terr, ctrl, params, duration, keys, physics=physics,
                        config=RolloutConfig(), perturbation=pert, params_batched=batched, engine=preset.engine.name,
                        mesh=None if preset.engine.lacks({MESH}) else mesh_for(len(js) * o.batch), stats=True)
        if getattr(o, "progress", True):
            print(f"  {label} on {preset.name} ({preset.engine.name}): {len(js)} cells x {o.batch} envs in "
                  f"{st.wall_s:.0f} s (compile {st.compile_s:.0f} s, {st.env_steps_per_s:,.0f} env-steps/s)",
                  flush=True)
        e = goal_errors(s, o.distance)
        cols = dict(success=e.success, advance=e.advance, dy=e.dy, dalpha=e.dalpha, fell=s.fell, nan=s.nan,
                    slip=s.foot_slip, path=s.path_length)
        cols = {k: np.asarray(v, float) for k, v in cols.items()}
        for n, j in enumerate(js):
            per_cell[j] = {k: v[n * o.batch:(n + 1) * o.batch].tolist() for k, v in cols.items()}
    return {str(j): per_cell[j] for j in idx}


def _replay(o, preset, spec: Dict, key, robot) -> Dict[str, List]:
    """Torso traces (x, y, z, yaw) at the replay times of the open-loop Luneckas 2020 gait on the replay cells,
    under one preset: {cell name: (B, times, 4) as lists}."""
    import jax

    from hexjax.control.registry import make_controller
    from hexjax.sim.config import RolloutConfig
    from hexjax.sim.rollout import rollout
    from hexjax.world.presets import get_terrain
    from hexjax.world.randomization import randomization_from_dict, sample_perturbation
    from hexjax.world.terrain import sample
    ctrl = make_controller("gait", robot)
    cpu = jax.devices("cpu")[0]
    times = [float(t) for t in spec["times"]]
    steps = [int(round(t / ctrl.dt)) - 1 for t in times]
    out = {}
    for j, (t_name, f) in enumerate((t, f) for t in spec["terrains"] for f in spec["frictions"]):
        cell = Cell(t_name, friction=None if float(f) == 1.0 else float(f))
        tspec = get_terrain(t_name, length=o.distance + 0.3)
        with jax.default_device(cpu):  # drawn on the host (see `_walk`)
            k_t, k_p, k_r = jax.random.split(jax.random.fold_in(key, 20_000 + j), 3)
            terr = sample(tspec, k_t, o.batch)
            rnd = {} if cell.friction is None else {"friction": cell.friction}
            pert = sample_perturbation(randomization_from_dict(rnd), k_p, o.batch)
        s = rollout(robot, terr, ctrl, ctrl.default_params(), max(times), k_r, physics=preset.config(tspec),
                    config=RolloutConfig(record=True), perturbation=pert, engine=preset.engine.name)
        out[cell.name] = np.asarray(s.trace)[:, steps].tolist()
    return out


def _compare(cells: List[Cell], runs, res_a: Dict, res_b: Dict) -> List[Dict]:
    """One row per (controller, cell): both presets' figures and the paired differences, with the verdict."""
    from hexjax.sim.metrics import paired
    rows = []
    for label, _, _, _, idx in runs:
        for j in idx:
            a, b = res_a[label][str(j)], res_b[label][str(j)]
            A = {k: np.asarray(v, float) for k, v in a.items()}
            B = {k: np.asarray(v, float) for k, v in b.items()}
            ds, ds_ci = paired(100 * A["success"], 100 * B["success"])
            da, da_ci = paired(100 * A["advance"], 100 * B["advance"])
            dy, dy_ci = paired(100 * np.abs(A["dy"]), 100 * np.abs(B["dy"]))
            dh, dh_ci = paired(np.degrees(np.abs(A["dalpha"])), np.degrees(np.abs(B["dalpha"])))
            df, df_ci = paired(100 * A["fell"], 100 * B["fell"])
            per_m = lambda r: float(np.nanmean(100 * r["slip"] / np.maximum(r["path"], 0.05)))
            row = dict(controller=label, cell=cells[j].name, n=int(A["success"].size),
                       success_pct=[100 * float(A["success"].mean()), 100 * float(B["success"].mean())],
                       advance_cm=[100 * float(np.nanmean(A["advance"])), 100 * float(np.nanmean(B["advance"]))],
                       drift_cm=[100 * float(np.nanmean(np.abs(A["dy"]))), 100 * float(np.nanmean(np.abs(B["dy"])))],
                       heading_deg=[float(np.degrees(np.nanmean(np.abs(A["dalpha"])))),
                                    float(np.degrees(np.nanmean(np.abs(B["dalpha"]))))],
                       fall_pct=[100 * float(A["fell"].mean()), 100 * float(B["fell"].mean())],
                       nan=[int(A["nan"].sum()), int(B["nan"].sum())],
                       slip_cm_per_m=[per_m(A), per_m(B)],
                       d_success_pts=ds, d_success_ci=list(ds_ci), d_advance_cm=da, d_advance_ci=list(da_ci),
                       d_drift_cm=dy, d_drift_ci=list(dy_ci), d_heading_deg=dh, d_heading_ci=list(dh_ci),
                       d_fall_pts=df, d_fall_ci=list(df_ci))
            row["within"] = bool(abs(ds) <= CONTRACT["success_pts"] and abs(da) <= CONTRACT["advance_cm"]
                                 and abs(dh) <= CONTRACT["heading_deg"])
            # a miss the pairing cannot tell from sampling noise: the contract band overlaps the 95 % interval
            row["within_ci"] = bool(ds_ci[0] <= CONTRACT["success_pts"] and ds_ci[1] >= -CONTRACT["success_pts"]
                                    and da_ci[0] <= CONTRACT["advance_cm"] and da_ci[1] >= -CONTRACT["advance_cm"]
                                    and dh_ci[0] <= CONTRACT["heading_deg"] and dh_ci[1] >= -CONTRACT["heading_deg"])
            rows.append(row)
    return rows


def _replay_rows(times, rep_a: Dict, rep_b: Dict) -> List[Dict]:
    rows = []
    for name in rep_a:
        a, b = np.asarray(rep_a[name]), np.asarray(rep_b[name])
        pos = 100 * np.linalg.norm(a[..., :3] - b[..., :3], axis=-1)  # (B, times) cm
        yaw = np.degrees(np.abs(np.arctan2(np.sin(a[..., 3] - b[..., 3]), np.cos(a[..., 3] - b[..., 3]))))
        rows.append(dict(cell=name, times_s=list(times), position_cm_mean=pos.mean(0).tolist(),
                         position_cm_max=pos.max(0).tolist(), yaw_deg_mean=yaw.mean(0).tolist(),
                         yaw_deg_max=yaw.max(0).tolist()))
    return rows


def _cells(o, spec: Dict) -> List[Cell]:
    """The matrix's cells that --only names (all without it); one ValueError line where it names none."""
    cells = matrix(spec)
    if o.only:
        cells = [c for c in cells if any(s in c.name for s in o.only)]
        if not cells:
            raise ValueError(f"--only {','.join(o.only)}: no cell of the matrix matches; cells: "
                             + ", ".join(c.name for c in matrix(spec)))
    return cells


def prepare(o, entry) -> None:
    """What the runner calls before anything loads JAX: the batch, the cells and the controllers checked."""
    from hexjax.experiments.commands.robustness import check_controller
    if not (isinstance(o.batch, int) and o.batch >= 1):
        raise ValueError(f"--batch={o.batch!r}: must be a whole number >= 1")
    _cells(o, entry.preset)
    for label in o.controllers:
        check_controller(label)


def run(o, entry) -> Dict:
    from hexjax.experiments.commands.robustness import _controllers, _host_devices
    prepare(o, entry)  # also for a caller in Python
    spec = entry.preset
    cells = _cells(o, spec)
    a, b = _presets(o)
    _host_devices()
    import jax
    from tqdm.auto import tqdm

    from hexjax.sim.rollout import make_mesh
    from hexjax.world.presets import get_robot, get_terrain
    robot = get_robot(o.robot)
    kinds = {t: get_terrain(t).kind for t in {c.terrain for c in cells}}
    controllers = _controllers(o.controllers, robot)
    runs = _runs(o, cells, controllers, kinds, spec)

    def mesh_for(n):
        n_dev = max(d for d in range(1, len(jax.devices()) + 1) if n % d == 0)
        return make_mesh(jax.devices()[:n_dev]) if n_dev > 1 else None

    presets = {"a": a.record(), "b": b.record()}
    pkey = {side: _physics_key(r) for side, r in presets.items()}
    digest = _digest(o, spec)
    partial = (o.json + ".partial.json") if o.json else ""
    key = jax.random.PRNGKey(o.seed)
    rep = spec.get("replay") if not o.only else None
    labels = [r[0] for r in runs] + (["replay"] if rep else [])
    done: Dict = read_partial(partial, digest, "runs", "fidelity", "rollouts", 2 * len(labels))
    done |= read_kept("fidelity", digest, [f"{lb}|{pkey[s]}" for lb in labels for s in pkey], done)
    sides = {"a": a, "b": b}
    todo = {side: [lb for lb in labels if f"{lb}|{pkey[side]}" not in done] for side in sides}
    bar = tqdm(total=2 * len(labels), initial=2 * len(labels) - sum(map(len, todo.values())), desc="fidelity",
               unit="rollout", disable=not getattr(o, "progress", True))
    lock = threading.Lock()

    def work(side):
        preset = sides[side]
        for label in todo[side]:
            if f"{label}|{pkey[side]}" in done:  # the other side ran the same physics
                continue
            if label == "replay":
                out = _replay(o, preset, rep, key, robot)
            else:
                _, ctrl, rb, duration, idx = next(r for r in runs if r[0] == label)
                out = _walk(o, preset, label, ctrl, rb, duration, idx, cells, key, mesh_for)
            with lock:
                done[f"{label}|{pkey[side]}"] = out
                keep_piece("fidelity", digest, f"{label}|{pkey[side]}", out)
                if partial:
                    write_partial(partial, {"digest": digest, "runs": done}, f"{len(done)} of "
                                  f"{2 * len(labels)} rollouts kept in {partial}; the same command resumes")
                bar.set_postfix_str(f"{label} on {preset.name} ({preset.engine.name}) done")
                bar.update(1)

    try:
        if sides["a"].engine.host_only != sides["b"].engine.host_only:
            # an engine on the host's cores beside another engine, each side in its own thread
            with concurrent.futures.ThreadPoolExecutor(2) as pool:
                for f in [pool.submit(work, side) for side in ("b", "a")]:
                    f.result()
        else:
            work("b")
            work("a")
    finally:
        bar.close()
    res_a = {label: done[f"{label}|{pkey['a']}"] for label in labels}
    res_b = {label: done[f"{label}|{pkey['b']}"] for label in labels}
    rows = _compare(cells, runs, res_a, res_b)
    replay = _replay_rows(rep["times"], res_a["replay"], res_b["replay"]) if rep else []
    worst = lambda k: max((abs(r[k]) for r in rows), default=math.nan)
    return {"config": dict(batch=o.batch, distance_m=o.distance, seed=o.seed, robot=robot.name,
                           controllers=[r[0] for r in runs], cells=[c.name for c in cells], refine=o.refine,
                           durations_s={r[0]: r[3] for r in runs}, device=jax.default_backend()),
            "physics": presets["a"], "against": presets["b"], "contract": CONTRACT, "cells": rows, "replay": replay,
            "summary": dict(rows=len(rows), within=sum(r["within"] for r in rows),
                            within_ci=sum(r["within_ci"] for r in rows),
                            worst_success_pts=worst("d_success_pts"), worst_advance_cm=worst("d_advance_cm"),
                            worst_heading_deg=worst("d_heading_deg"))}

