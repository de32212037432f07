"""Where MJX's contacts first part from MuJoCo C's along a walk: the Yu 2019 CPG on the fidelity matrix's `step40
d=0.5` cell, contact by contact, control step by control step.

The walk is rolled out once on MJX at `validated`'s settings, its state recorded at every control step (MJX's own
sphere-box and capsule-box contacts, as mujoco-mjx ships them, unless `--contacts c`). At each recorded state, three
collision routines run on one model with every terrain box a geom (MuJoCo C's own model, `hexjax.sim.engines.c`):
MuJoCo C's `mj_collision` (what MuJoCo Warp ports), MJX's convex routines, and hexjax's C-faithful ones
(`hexjax.sim.internals.collide`). Per geom pair the script compares the contacts within the pair's margin: their
count, depth and normal. For each env it reports the first control step where MJX's routine parts from C's (the
geom pair by name, the quantity, both values), and over all steps how often each routine parts from C's.

    python scripts/contact_steps.py --envs 8 --json out/contact_steps.json

About 10 minutes on 2 CPU cores."""

from __future__ import annotations

import argparse
import contextlib
import os

os.environ.setdefault("HEXJAX_CACHE_DIR", "off")  # the walk's program is traced anew: it may swap MJX's routines

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from hexjax.control.registry import make_controller
from hexjax.experiments.runner import write_json
from hexjax.sim.config import RolloutConfig
from hexjax.sim.engines.c_models import _slot_layout, place_boxes
from hexjax.sim.internals.collide import c_box_contacts
from hexjax.sim.mjcf import build_mjcf, compile_mjcf
from hexjax.sim.physics import get_physics
from hexjax.sim.rollout import rollout
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import sample

DIST_TOL, NORMAL_TOL = 1e-4, 1e-2  # m, unit-vector components: what counts as a different contact


def walk(robot, envs: int, seed: int, distance: float, contacts: str):
    """The recorded MJX walk: (terrain, qpos at every control step (envs, T, nq), control dt)."""
    ctrl = make_controller("cpg", robot)
    spec = get_terrain("step40", length=distance + 0.3)
    key_t, key_r = jax.random.split(jax.random.PRNGKey(seed))
    terr = sample(spec, key_t, envs)
    physics = get_physics("validated").config(spec)
    duration = 80.0 * distance  # the CPG's 0.5 m with the step takes about 40 s
    if contacts == "mjx":  # MJX's own routines: trace the walk with hexjax's swapped back out
        import hexjax.sim.internals as internals
        internals.c_box_contacts, kept = contextlib.nullcontext, internals.c_box_contacts
    try:
        s = rollout(robot, terr, ctrl, ctrl.default_params(), duration, key_r, physics=physics,
                    config=RolloutConfig(record=True), engine="mjx")
    finally:
        if contacts == "mjx":
            internals.c_box_contacts = kept
    return terr, np.asarray(s.qpos_trace, np.float64), physics, ctrl.dt


def env_models(robot, physics, terr, envs: int):
    """One MjModel per env with every terrain box a geom of the world body (MuJoCo C's layout, `c_models`), without
    contact sensors (MJX has none) and without the mid-phase (its tree was built for the placeholder grid)."""
    import dataclasses
    box_pos, box_half = np.asarray(terr.box_pos, np.float64), np.asarray(terr.box_half, np.float64)
    valid = np.asarray(terr.box_valid, bool)
    k = int(np.ceil(np.sqrt(max(1, valid.sum(1).max()))))
    phys = dataclasses.replace(physics, slots_per_leg=0, torso_slots=0)
    pos, half, ok = _slot_layout(box_pos, box_half, valid, k)
    ground = np.broadcast_to(np.asarray(terr.ground_z, np.float64), (envs,))
    base = compile_mjcf(build_mjcf(robot, phys, terrain_boxes=k * k))
    base.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_MIDPHASE
    boxes = [mujoco.mj_name2id(base, mujoco.mjtObj.mjOBJ_GEOM, f"terrain_{j}") for j in range(k * k)]
    ground_geom = mujoco.mj_name2id(base, mujoco.mjtObj.mjOBJ_GEOM, "ground")
    out = []
    for i in range(envs):
        m = mujoco.MjModel.__copy__(base)
        place_boxes(m, boxes, ground_geom, pos[i], half[i], np.where(ok[i], base.geom_conaffinity[boxes], 0),
                    ground[i])
        out.append(m)
    return out


def geom_name(m, g: int) -> str:
    return mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom {g}"


def c_contacts(m, d, qpos):
    """{(g1, g2): [(dist, normal g1 -> g2)]} of MuJoCo C's contacts within their margin."""
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    mujoco.mj_collision(m, d)
    out = {}
    for c in d.contact[:d.ncon]:
        if c.dist <= c.includemargin:
            out.setdefault((int(c.geom1), int(c.geom2)), []).append((float(c.dist), np.array(c.frame[:3])))
    return out


def mjx_contacts_fn(m):
    """jitted qpos (T, nq) -> (dist, normal, geom) of MJX's collision for every recorded state."""
    mx = mjx.put_model(m)

    def one(q):
        d = mjx.kinematics(mx, mjx.make_data(mx).replace(qpos=q))
        c = mjx.collision(mx, d)._impl.contact
        return c.dist, c.frame[:, 0], c.geom, c.includemargin
    return jax.jit(jax.vmap(one))


def as_pairs(dist, normal, geom, margin):
    out = {}
    for k in np.flatnonzero(dist <= margin):
        out.setdefault((int(geom[k, 0]), int(geom[k, 1])), []).append((float(dist[k]), np.array(normal[k])))
    return out


def parts(c: dict, x: dict):
    """The first way contacts `x` differ from C's `c`: (pair, quantity, C's value, x's value) or None."""
    for pair in sorted(set(c) | set(x)):
        a, b = sorted(c.get(pair, []), key=lambda t: t[0]), sorted(x.get(pair, []), key=lambda t: t[0])
        if len(a) != len(b):
            return pair, "count", len(a), len(b)
        for (da, na), (db, nb) in zip(a, b):
            if abs(da - db) > DIST_TOL:
                return pair, "dist", da, db
            if np.abs(na - nb).max() > NORMAL_TOL:
                return pair, "normal", na.round(4).tolist(), nb.round(4).tolist()
    return None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--distance", type=float, default=0.5)
    ap.add_argument("--contacts", choices=("mjx", "c"), default="mjx", help="the walk's own contact routines")
    ap.add_argument("--json", default=None)
    o = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", False)
    robot = get_robot("yu2019")
    terr, qpos, physics, dt = walk(robot, o.envs, o.seed, o.distance, o.contacts)
    models = env_models(robot, physics, terr, o.envs)
    report = dict(cell="step40 d=0.5", controller="cpg@yu2019", envs=o.envs, seed=o.seed, control_dt=dt,
                  walk_contacts=o.contacts, tolerances=dict(dist_m=DIST_TOL, normal=NORMAL_TOL), per_env=[])
    totals = {"mjx": 0, "hexjax": 0}
    steps = qpos.shape[1]
    for i, m in enumerate(models):
        d = mujoco.MjData(m)
        q = jnp.asarray(qpos[i], jnp.float32)
        found = {}
        for name, ctx in (("mjx", contextlib.nullcontext), ("hexjax", c_box_contacts)):
            with ctx():  # MJX reads its table of collision routines when the function is traced
                out = [np.asarray(a) for a in mjx_contacts_fn(m)(q)]
            first, n_diff = None, 0
            for t in range(steps):
                c = c_contacts(m, d, qpos[i, t])
                diff = parts(c, as_pairs(out[0][t], out[1][t], out[2][t], out[3][t]))
                if diff is not None:
                    n_diff += 1
                    if first is None:
                        pair, what, cv, xv = diff
                        first = dict(step=t, time_s=round(t * dt, 3), quantity=what, mujoco_c=cv, this=xv,
                                     pair=[geom_name(m, pair[0]), geom_name(m, pair[1])])
            found[name] = dict(first_difference=first, steps_that_differ=n_diff)
            totals[name] += n_diff
        report["per_env"].append(dict(env=i, steps=steps, **found))
        print(f"env {i}: MJX's contacts part from C's at step "
              f"{found['mjx']['first_difference'] and found['mjx']['first_difference']['step']} "
              f"({found['mjx']['steps_that_differ']} of {steps} steps differ); hexjax's at "
              f"{found['hexjax']['first_difference'] and found['hexjax']['first_difference']['step']} "
              f"({found['hexjax']['steps_that_differ']})", flush=True)
        if found["mjx"]["first_difference"]:
            f = found["mjx"]["first_difference"]
            print(f"   first: {f['pair'][0]} / {f['pair'][1]}: {f['quantity']} C {f['mujoco_c']} vs MJX {f['this']}")
    report["steps_that_differ"] = dict(totals)
    report["steps"] = steps * o.envs
    print(f"steps whose contacts differ from MuJoCo C's: MJX {totals['mjx']}, hexjax {totals['hexjax']} "
          f"of {steps * o.envs}")
    if o.json:
        write_json(o.json, report)
        print(f"wrote {o.json}")


if __name__ == "__main__":
    main()
