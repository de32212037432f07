"""`hexjax robustness`: success, goal error, falls and energy of one or more controllers over a sweep of one
or two axes, each a randomisation range (`hexjax.world.randomization`) or a terrain dimension, with each
controller's robustness envelope.

Every cell of the sweep runs `batch` envs in one call of one compiled rollout per controller (the cell's values
are data: terrain boxes padded to one count, per-env draws, per-cell params), so a sweep compiles once per
controller whatever its size. Cells share their terrains and draws across controllers (common random
numbers), finished cells are kept beside the JSON (`<json>.partial.json`) and a rerun resumes after them.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math
import os
import sys
from typing import Dict, List, Sequence, Tuple

import numpy as np

from hexjax import cache
from hexjax.control.registry import CONTROLLERS
from hexjax.experiments.runner import read_partial, write_partial
# plot and report are the registry's (this module is the entry)
from hexjax.experiments.commands.robustness_view import ENVELOPE_SUCCESS, plot, report  # noqa: F401
from hexjax.world.files import read_yaml
from hexjax.world.randomization import AXES as RANDOM_AXES
from hexjax.world.randomization import randomization_from_dict

# terrain axes: the sweep value v sets the obstacle terrain spec's range to [v, v]; `difficulty` sets any
# family's difficulty in [0, 1] (`TerrainSpec.at_difficulty`, its lengths scaled to the robot's leg)
TERRAIN_AXES = {"obstacle_height": "height_range", "obstacle_length": "length_range",
                "obstacle_width": "width_range", "obstacle_spacing": "spacing_range", "difficulty": "difficulty"}
# which way an axis gets harder (+1: larger values are harder), for the envelope
HARDER = {"obstacle_height": 1, "obstacle_length": 1, "obstacle_width": 1, "obstacle_spacing": -1, "difficulty": 1,
          "friction": -1, "torso_mass_scale": 1, "payload_kg": 1, "payload_offset_m": 1, "kp_scale": -1,
          "torque_scale": -1, "damping_scale": 1, "latency_steps": 1, "force_noise_n": 1, "force_bias_n": 1,
          "force_dropout": 1, "tactile_noise_n": 1, "tactile_bias_n": 1, "tactile_dropout": 1,
          "fault_time_s": -1, "fault_probability": 1}
# the controllers a sweep can walk: from their default params, or by their registry rule for a terrain cell
SWEEPABLE = tuple(n for n, e in CONTROLLERS.items() if e.sweeps)


def parse_axis(text: str) -> Tuple[str, List[float]]:
    """'name=low:high:n' (n evenly spaced values, ends included) or 'name=v1,v2,...' -> (name, values)."""
    if "=" not in str(text):
        raise ValueError(f"--axis {text!r}: write name=low:high:n or name=v1,v2,...")
    name, spec = (s.strip() for s in str(text).split("=", 1))
    if name not in TERRAIN_AXES and name not in RANDOM_AXES:
        raise ValueError(f"--axis {name!r}: unknown axis; terrain axes: {', '.join(TERRAIN_AXES)}; "
                         f"randomisation axes: {', '.join(RANDOM_AXES)}")
    try:
        if ":" in spec:
            lo, hi, n = spec.split(":")
            lo, hi, n = float(lo), float(hi), int(n)
            if not (math.isfinite(lo) and math.isfinite(hi) and (lo < hi or lo == hi and n == 1) and 1 <= n <= 64):
                raise ValueError
            values = [lo] if n == 1 else [round(float(v), 9) for v in np.linspace(lo, hi, n)]
        else:
            values = [float(v) for v in spec.split(",")]
            if not values or not all(math.isfinite(v) for v in values) or len(set(values)) < len(values):
                raise ValueError
    except ValueError:
        raise ValueError(f"--axis {text!r}: values must be low:high:n with low < high (or n = 1) and 1 <= n <= 64, "
                         "or a comma list of distinct numbers") from None
    return name, values


def wilson(k: int, n: int, z: float = 1.96) -> Tuple[float, float]:
    """95 % Wilson score interval of a success rate k / n."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    den = 1 + z * z / n
    mid = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return max(0.0, mid - half), min(1.0, mid + half)


def envelope(values: Sequence[float], successes: Sequence[Tuple[int, int]], axis: str) -> Dict:
    """The hardest level of `axis` reached from its easiest with success >= 90 % at every level on the way
    (None if the easiest already fails), with the success rate there and its 95 % interval; `sure`: the
    hardest such level whose interval's lower end is >= 90 % too."""
    order = sorted(range(len(values)), key=lambda i: HARDER.get(axis, 1) * values[i])
    best = sure = None
    for i in order:
        k, n = successes[i]
        if n == 0 or k / n < ENVELOPE_SUCCESS:
            break
        best = i
        if wilson(k, n)[0] >= ENVELOPE_SUCCESS:
            sure = i
    if best is None:
        return {"level": None, "success": None, "ci95": None, "sure_level": None}
    k, n = successes[best]
    return {"level": values[best], "success": k / n, "ci95": list(wilson(k, n)),
            "sure_level": None if sure is None else values[sure]}


def solver_note(kind: str, engine, iterations: int):
    """A line for the user where the cells' physics is known to distort the result, else None: MJX with fewer
    than 4 Newton iterations leaves the contact solve unconverged below friction 1.0 (the open-loop gait's success
    at friction 0.6 read 12 % against converged MuJoCo's 43 %), and on stepping stones it turns stalls into falls
    (docs/physics.md, docs/robustness.md)."""
    if engine.culls and iterations < 4:  # the MJX family (MuJoCo C's reference settings converge)
        where = "on stepping stones most falls at wide gaps are the solver's" if kind == "stones" else \
            "success below friction 1.0 is the solver's"
        return (f"note: {iterations} Newton iterations leave MJX's contact solve unconverged and {where}, not the "
                "physics' (docs/physics.md); --physics validated judges the terrain")
    return None


def _digest(o) -> str:
    keys = ("controllers", "axis", "batch", "terrain", "robot", "distance", "seed", "randomization", "per_env",
            "engine")
    blob = {k: getattr(o, k) for k in keys}
    blob["physics"] = _engine(o).record()
    return hashlib.sha256(json.dumps(blob, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _engine(o):
    """The physics the sweep runs (`hexjax.sim.physics.pick`; across several processes an engine with a device
    mesh)."""
    import jax

    from hexjax.sim.engines import MESH
    from hexjax.sim.physics import pick
    return pick(o.physics, o.engine or None, needs={MESH} if jax.process_count() > 1 else ())


def check_controller(label) -> None:
    """One ValueError line for a --controllers label that names no controller a sweep can walk (no JAX)."""
    if str(label).partition("@")[0] not in SWEEPABLE:
        raise ValueError(f"--controllers {label!r}: use some of {', '.join(SWEEPABLE)} (optionally name@robot)")


def _controllers(names, default_robot):
    """{label: (controller, robot)} for labels 'name' or 'name@robot' (a robot preset or .yaml path; default
    --robot): gait and tactile (Luneckas 2020 tripod), cpg (Yu 2019, reflexes on), avoid (the tripod steered
    by the Zhao 2018 planner round the terrain's boxes)."""
    from hexjax.control.registry import make_controller
    from hexjax.world.presets import get_robot
    out = {}
    for label in names:
        name, _, rname = str(label).partition("@")
        check_controller(label)
        robot = get_robot(rname) if rname else default_robot
        out[str(label)] = (make_controller(name, robot), robot)
    return out


def _checked(o):
    """(axes, base randomization) of parsed options `o`, checked without JAX, so a bad --axis answers at once."""
    axes = [parse_axis(a) for a in o.axis]
    if not 1 <= len(axes) <= 2:
        raise ValueError(f"--axis given {len(axes)} times: sweep one or two axes")
    if len(axes) == 2 and axes[0][0] == axes[1][0]:
        raise ValueError(f"--axis {axes[0][0]} given twice")
    if not (isinstance(o.batch, int) and o.batch >= 1):
        raise ValueError(f"--batch={o.batch!r}: must be a whole number >= 1")
    for label in o.controllers:
        check_controller(label)
    if not (0 < o.distance <= 5):
        raise ValueError(f"--distance={o.distance!r}: must be in (0, 5] m")
    raw = read_yaml(o.randomization) if o.randomization else None
    if raw is not None and "randomization" in raw:  # a file with a randomization: block, or the block alone
        raw = raw["randomization"]
    if o.randomization and not raw:  # as an empty --physics file is refused: it most likely is not the one meant
        raise ValueError(f"--randomization={o.randomization!r}: an empty randomization: give its keys "
                         "(docs/robustness.md lists them)")
    return axes, randomization_from_dict(raw, source=o.randomization or "randomization")


def sweep(o) -> Dict:
    """The sweep of parsed options `o` (configs/commands/robustness.yaml), after `prepare`."""
    axes, base_rand = _checked(o)
    import jax
    from tqdm.auto import tqdm

    from hexjax.world.presets import get_robot

    chosen = _engine(o)  # one ValueError line for an --engine without a device mesh across several processes
    engine = chosen.engine
    if jax.process_index() == 0 and chosen is not o.physics:  # the runner printed the one it chose
        print(chosen.header(), flush=True)
    robot = get_robot(o.robot)
    ctrls = _controllers(o.controllers, robot)
    base_terrain, cells, t_specs, r_specs = _cells(o, axes, base_rand, robot)
    physics = chosen.config(base_terrain)
    physics.validate()
    n_dev, mesh = _devices(o.batch, engine)
    lead = jax.process_index() == 0  # writes the partial file; the others only compute their shards
    note = solver_note(base_terrain.kind, engine, physics.iterations)
    if note and lead:
        print(note, file=sys.stderr)
    n_box = max(s.max_boxes for s in t_specs)
    plan = {}
    for cname, (ctrl, rb) in ctrls.items():
        ctrl, duration = ctrl.for_distance(o.distance)
        for r in r_specs:
            r.check_horizon(duration)
        plan[cname] = (ctrl, rb, duration)

    digest = _digest(o)
    partial = (o.json + ".partial.json") if o.json else ""
    key = jax.random.PRNGKey(o.seed)
    jobs = [(c, i) for c in ctrls for i in range(len(cells))]
    done = read_partial(partial, digest, "cells", "robustness", "cells", len(jobs)) if lead else {}
    if jax.process_count() > 1:  # every process skips the cells process 0 has kept
        from jax.experimental import multihost_utils
        kept = multihost_utils.broadcast_one_to_all(np.array([f"{c}|{i}" in done for c, i in jobs]))
        skip = {f"{c}|{i}" for (c, i), k in zip(jobs, np.asarray(kept)) if k}
    else:
        skip = set(done)
    bar = tqdm(jobs, desc="robustness", unit="cell", disable=not getattr(o, "progress", True) or not lead)
    compile_s = {c: 0.0 for c in ctrls}
    for cname, i in bar:
        tag = f"{cname}|{i}"
        bar.set_postfix_str(f"{cname} " + ", ".join(f"{n}={v:g}" for (n, _), v in zip(axes, cells[i])))
        if tag in skip:
            continue
        stats = _walk_cell(o, cname, plan[cname], t_spec=t_specs[i], r_spec=r_specs[i],
                           key=jax.random.fold_in(key, i), n_box=n_box, physics=physics, mesh=mesh, engine=engine)
        compile_s[cname] += stats["compile_s"]
        done[tag] = stats
        if partial and lead:
            write_partial(partial, {"digest": digest, "cells": done},
                          f"{len(done)} of {len(jobs)} cells kept in {partial}; the same command resumes after them")
    if not lead:  # process 0 gathers every cell and writes the results
        return {"process": jax.process_index(), "cells_run": len(jobs) - len(skip)}
    rows = [dict(controller=cname, **{n: v for (n, _), v in zip(axes, values)}, **done[f"{cname}|{i}"])
            for cname in ctrls for i, values in enumerate(cells)]
    return {"config": dict(controllers=list(ctrls), axes={n: v for n, v in axes}, batch=o.batch, robot=robot.name,
                           terrain=o.terrain, distance_m=o.distance, seed=o.seed, randomization=base_rand.to_dict(),
                           robots={c: plan[c][1].name for c in ctrls},
                           durations_s={c: plan[c][2] for c in ctrls}, backend=jax.default_backend(),
                           devices=n_dev, processes=jax.process_count(), engine=engine.name),
            "cells": rows, "envelope": _envelopes(rows, axes, ctrls), "compile_s": compile_s,
            "physics": chosen.record()}


def _cells(o, axes, base_rand, robot):
    """(base terrain, the cells' axis values, each cell's terrain spec and randomization) of the sweep."""
    from hexjax.world.presets import get_terrain
    from hexjax.world.terrain import leg_scale
    base_terrain = get_terrain(o.terrain, length=o.distance + 0.3)
    for name, _ in axes:
        if name in TERRAIN_AXES and name != "difficulty" and base_terrain.kind != "obstacles":
            raise ValueError(f"--axis {name}: needs an obstacle terrain (--terrain {o.terrain!r} is "
                             f"{base_terrain.kind!r})")
    cells = list(itertools.product(*[v for _, v in axes]))
    t_specs, r_specs = [], []
    for values in cells:
        t, r = base_terrain, base_rand
        for (name, _), v in zip(axes, values):
            if name == "difficulty":
                t = t.at_difficulty(v, leg_scale(robot))
            elif name in TERRAIN_AXES:
                t = dataclasses.replace(t, **{TERRAIN_AXES[name]: (v, v)})
            else:
                r = r.with_value(name, v)
        t.validate()
        t_specs.append(t)
        r_specs.append(r)
    return base_terrain, cells, t_specs, r_specs


def _devices(batch: int, engine):
    """(devices, mesh or None): each cell's envs sharded over as many devices as divide the batch (several GPUs,
    or a CPU's cores); with several processes (jax.distributed) over every device of every process."""
    import jax

    from hexjax.sim.engines import MESH
    from hexjax.sim.rollout import make_mesh
    if jax.process_count() > 1:
        n_dev = len(jax.devices())
        if batch % n_dev:
            raise ValueError(f"--batch={batch}: must be a multiple of the {n_dev} devices of the "
                             f"{jax.process_count()} processes")
    else:
        n_dev = max(d for d in range(1, len(jax.devices()) + 1) if batch % d == 0)
    if engine.lacks({MESH}):  # warp and c run on one device / the host's threads
        n_dev = 1
    return n_dev, make_mesh(jax.devices()[:n_dev]) if n_dev > 1 else None


def _walk_cell(o, cname: str, planned, *, t_spec, r_spec, key, n_box: int, physics, mesh, engine) -> Dict:
    """One cell's walks for controller `cname` ((controller, robot, seconds) in `planned`): its statistics."""
    import jax

    from hexjax.sim.config import RolloutConfig
    from hexjax.sim.metrics import batch_stats, goal_errors
    from hexjax.sim.rollout import rollout
    from hexjax.world.randomization import sample_perturbation
    from hexjax.world.terrain import pad_terrain, sample
    ctrl, rb, duration = planned
    k_t, k_r, k_p = jax.random.split(key, 3)
    terr = pad_terrain(sample(t_spec, k_t, o.batch), n_box)
    pert = sample_perturbation(r_spec, k_p, o.batch)
    rule = CONTROLLERS[cname.partition("@")[0]].cell_params  # e.g. Eq. 7's H: the cell's highest obstacle
    params, batched = rule(ctrl, t_spec, terr, o.distance) if rule else (ctrl.default_params(), False)
    summ, st = rollout(rb, terr, ctrl, params, duration, k_r, physics=physics, config=RolloutConfig(),
                       perturbation=pert, stats=True, mesh=mesh, params_batched=batched, engine=engine.name)
    errs = goal_errors(summ, o.distance)
    stats = batch_stats(summ, errs, o.distance)
    k = int(np.asarray(errs.success).sum())
    stats.update(successes=k, success_ci95=list(wilson(k, o.batch)), wall_s=st.run_s, compile_s=st.compile_s)
    if getattr(o, "per_env", False):
        stats["per_env"] = {f: np.asarray(getattr(errs, f)).tolist() for f in ("dx", "dy", "dalpha", "success")}
        stats["per_env"].update(fell=np.asarray(summ.fell).tolist(), energy_J=np.asarray(summ.energy).tolist())
    return stats


def _envelopes(rows, axes, ctrls) -> Dict:
    """Each controller's success envelope along the first axis (per value of the second, where there is one)."""
    env = {}
    first = axes[0][0]
    for cname in ctrls:
        groups = [()] if len(axes) == 1 else [(v,) for v in axes[1][1]]
        for g in groups:
            sel = [r for r in rows if r["controller"] == cname and (not g or r[axes[1][0]] == g[0])]
            label = cname if not g else f"{cname} | {axes[1][0]}={g[0]:g}"
            env[label] = envelope([r[first] for r in sel], [(r["successes"], r["n"]) for r in sel], first)
    return env


def _host_devices():
    """On a CPU, one XLA device runs a batch on about one core; as many host devices as cores let each cell's
    envs be sharded over all of them. Set before JAX loads, unless the user set the count already."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "jax" not in sys.modules and "xla_force_host_platform_device_count" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={os.cpu_count() or 1}".strip()


def _distributed(o) -> None:
    """Join JAX's multi-process runtime (`jax.distributed`) when --processes > 1: every process runs the same
    command with its own --process-id, the global mesh spans all their devices, process 0 writes."""
    n, pid, coord = o.processes, o.process_id, str(o.coordinator)
    if not (isinstance(n, int) and n >= 1):
        raise ValueError(f"--processes={n!r}: must be a whole number >= 1")
    if not (isinstance(pid, int) and 0 <= pid < n):
        raise ValueError(f"--process-id={pid!r}: must be in [0, {n - 1}] (--processes {n})")
    if n == 1:
        return
    host, _, port = coord.rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"--coordinator={coord!r}: write host:port (process 0's address)")
    import jax
    jax.config.update("jax_cpu_collectives_implementation", "gloo")  # CPU hosts; GPUs use NCCL
    jax.distributed.initialize(coordinator_address=coord, num_processes=n, process_id=pid)
    cache.every_cpu_process_writes()


def prepare(o, entry=None) -> None:
    """What the runner calls before it picks the physics (which loads JAX): the options checked without JAX, the
    host's cores as devices and, with --processes > 1, JAX's multi-process runtime, both set before JAX loads."""
    _checked(o)
    _host_devices()
    _distributed(o)


def run(o, entry) -> Dict:
    res = sweep(o)
    if "process" in res:  # not process 0: nothing to write
        o.json = o.png = ""
    return res
