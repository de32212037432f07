"""MJX's sphere-box and capsule-box contacts against MuJoCo C's, pose by pose around one box.

A box (half sizes 0.05 x 0.05 x 0.02 m, like a terrain obstacle) and a foot sphere (radius 6 mm, the Luneckas 2020
foot) or a pad capsule (radius 4 mm, half length 15 mm) in a free body, placed on a grid of poses: over each face,
over the edges and corners (where a foot meets an obstacle's rim), slightly inside, and just apart. For every pose
MuJoCo C's `mj_collision` and MJX's `collision` (the pinned mujoco-mjx: sphere-box and capsule-box through its
convex routine) run on the same model and state. Per region the script reports how often the two find a contact
(penetration below 0); each C contact is matched to MJX's contact nearest its point (within 5 mm), and over poses
no deeper than 2 mm the script reports the contacts either engine has alone and the largest differences of depth,
normal (degrees) and point of the matched ones (deeper poses are counted apart).

    python scripts/collide_compare.py --json out/collide_compare.json

About a minute on 2 CPU cores (MJX's collision compiles once per shape)."""

from __future__ import annotations

import argparse

import jax
import mujoco
import numpy as np
from mujoco import mjx

from hexjax.experiments.runner import write_json

HALF = np.array([0.05, 0.05, 0.02])
SHALLOW = 0.002  # m: the deepest penetration compared (a walk's contacts stay within about 1 mm)

XML = """<mujoco><option timestep="0.005"/><worldbody>
  <geom name="box" type="box" size="{hx} {hy} {hz}" pos="0 0 {hz}"/>
  <body name="probe" pos="0 0 0.5"><freejoint/>{probe}</body>
</worldbody></mujoco>"""
RADIUS = {"sphere": 0.006, "capsule": 0.004}
PROBES = {"sphere": '<geom name="probe" type="sphere" size="0.006"/>',
          "capsule": '<geom name="probe" type="capsule" size="0.004 0.015" euler="0 90 0"/>'}


def poses(rng, n: int, r: float):
    """(name of the region, probe centre (3,), probe yaw), `n` per region: the probe's centre within -2 .. +3 mm of
    touching (`r`: its radius) a face, an edge or a corner of the box."""
    top, out = 2 * HALF[2], []
    gap = lambda: r + rng.uniform(-0.002, 0.003)
    for _ in range(n):
        out.append(("top face", [rng.uniform(-0.03, 0.03), rng.uniform(-0.03, 0.03), top + gap()]))
        # the rim along x = +half (the edge a foot meets walking up a step), the centre off it in the x-z plane
        a = rng.uniform(0, np.pi / 2)
        g = gap()
        out.append(("top edge", [HALF[0] + g * np.sin(a), rng.uniform(-0.03, 0.03), top + g * np.cos(a)]))
        out.append(("side face", [HALF[0] + gap(), rng.uniform(-0.03, 0.03), rng.uniform(0.008, top - 0.008)]))
        sx, sy = rng.choice([-1, 1], 2)
        u = rng.normal(size=3)
        u = np.abs(u) / np.linalg.norm(u) * gap()
        out.append(("top corner", [sx * (HALF[0] + u[0]), sy * (HALF[1] + u[1]), top + u[2]]))
    return [(reg, np.array(p), rng.uniform(-np.pi, np.pi)) for reg, p in out]


def c_contacts(m, d, pos, yaw):
    """MuJoCo C's contacts of the probe: [(dist, normal from box to probe, point)]."""
    d.qpos[:3], d.qpos[3:7] = pos, [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
    mujoco.mj_kinematics(m, d)
    mujoco.mj_collision(m, d)
    return [(c.dist, c.frame[:3] * (1 if c.geom1 == 0 else -1), c.pos.copy()) for c in d.contact[:d.ncon]]


def mjx_contacts(m, pos, yaw):
    """MJX's contacts for a batch of probe poses: (dist (B, ncon), normal from box to probe (B, ncon, 3), point)."""
    mx = mjx.put_model(m)

    def one(p, q):
        d = mjx.make_data(mx).replace(qpos=jax.numpy.concatenate([p, q]))
        d = mjx.kinematics(mx, d)
        d = mjx.collision(mx, d)
        sign = jax.numpy.where(d._impl.contact.geom[:, 0] == 0, 1.0, -1.0)[:, None]
        return d._impl.contact.dist, d._impl.contact.frame[:, 0] * sign, d._impl.contact.pos

    quat = np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)], -1)
    return [np.asarray(x) for x in jax.jit(jax.vmap(one))(pos, quat)]


def compare(kind: str, n: int, seed: int):
    m = mujoco.MjModel.from_xml_string(XML.format(hx=HALF[0], hy=HALF[1], hz=HALF[2], probe=PROBES[kind]))
    d = mujoco.MjData(m)
    ps = poses(np.random.default_rng(seed), n, RADIUS[kind])
    dist, normal, point = mjx_contacts(m, np.array([p for _, p, _ in ps]), np.array([y for _, _, y in ps]))
    rows = {}
    for i, (region, pos, yaw) in enumerate(ps):
        r = rows.setdefault(region, dict(poses=0, c_contacts=0, mjx_contacts=0, matched=0, only_c=0, only_mjx=0,
                                         deeper=0, max_ddist_mm=0.0, max_dnormal_deg=0.0, max_dpoint_mm=0.0))
        r["poses"] += 1
        cs = c_contacts(m, d, pos, yaw)
        xs = [(dist[i, j], normal[i, j], point[i, j]) for j in range(dist.shape[1]) if dist[i, j] < 0]
        r["c_contacts"] += len(cs)
        r["mjx_contacts"] += len(xs)
        if any(c[0] < -SHALLOW for c in cs + xs):
            r["deeper"] += 1  # deeper than a walk presses: left out of the differences
            continue
        # each C contact against the MJX contact nearest to its point
        for c in cs:
            if not xs:
                r["only_c"] += 1
                continue
            x = min(xs, key=lambda x: np.linalg.norm(x[2] - c[2]))
            gap = float(np.linalg.norm(x[2] - c[2]))
            if gap > 0.005:  # no MJX contact within 5 mm of it
                r["only_c"] += 1
                continue
            r["matched"] += 1
            cosang = np.clip(np.dot(c[1], x[1]) / np.linalg.norm(c[1]) / np.linalg.norm(x[1]), -1, 1)
            r["max_ddist_mm"] = max(r["max_ddist_mm"], 1e3 * abs(c[0] - x[0]))
            r["max_dnormal_deg"] = max(r["max_dnormal_deg"], float(np.degrees(np.arccos(cosang))))
            r["max_dpoint_mm"] = max(r["max_dpoint_mm"], 1e3 * gap)
        r["only_mjx"] += sum(all(np.linalg.norm(x[2] - c[2]) > 0.005 for c in cs) for x in xs)
    return {reg: {k: (round(v, 4) if isinstance(v, float) else int(v)) for k, v in r.items()} for reg, r in rows.items()}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200, help="poses per region")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default="")
    o = ap.parse_args()
    out = dict(box_half_m=HALF.tolist(), probes=PROBES, n_per_region=o.n, seed=o.seed, mujoco=mujoco.__version__,
               results={k: compare(k, o.n, o.seed) for k in PROBES})
    for kind, rows in out["results"].items():
        print(f"{kind}-box: region  poses deeper  C contacts  MJX  matched  only C  only MJX  max |d dist| mm  "
              "max d normal deg  max d point mm")
        for reg, r in rows.items():
            print(f"  {reg:<12} {r['poses']:5d} {r['deeper']:6d} {r['c_contacts']:11d} {r['mjx_contacts']:4d} "
                  f"{r['matched']:8d} {r['only_c']:7d} {r['only_mjx']:9d} "
                  f"{r['max_ddist_mm']:16.3f} {r['max_dnormal_deg']:17.2f} {r['max_dpoint_mm']:15.3f}")
    if o.json:
        write_json(o.json, out)
        print(f"wrote {o.json}")


if __name__ == "__main__":
    main()
