"""Measure the collision representation choice (docs/terrain.md): per-env heightfield vs culled box slots.

Both models hold the same robot standing on a sampled high-large obstacle field. The heightfield variant
rasterises the field at `--res` (per-env hfield_data, vmapped); the box variant uses hexjax's per-leg
slots. Prints and writes JSON: compile seconds and env-steps/s of plain mjx.step at batch B."""

import argparse
import json
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

import hexjax  # noqa: F401  (sets the XLA CPU flag)
from hexjax.sim.config import PhysicsConfig
from hexjax.sim.mjcf import build_mjcf
from hexjax.sim.engines import sim_model
from hexjax.sim.model import batch_model, mjx
from hexjax.world.presets import get_terrain, luneckas2020
from hexjax.world.terrain import heightmap, sample


def hfield_xml(xml: str, nx: int, ny: int, sx: float, sy: float, top: float) -> str:
    xml = xml.replace('<geom name="ground" type="plane" size="0 0 0.05" rgba="0.8 0.85 0.8 1"/>',
                      f'<geom name="ground" type="hfield" hfield="terrain" pos="{sx - 0.3:.4f} 0 0"/>')
    xml = xml.replace("<worldbody>", f'<asset><hfield name="terrain" nrow="{ny}" ncol="{nx}" '
                      f'size="{sx:.4f} {sy:.4f} {top:.4f} 0.01"/></asset>\n  <worldbody>')
    return xml.replace('<pair geom1="ground" geom2="torso"/>', '<pair geom1="ground" geom2="torso"/>')


def time_steps(mx, in_axes, d0, batch, n):
    def run(m, d):
        def body(d, _):
            return mjx.step(m, d), None
        return jax.lax.scan(body, d, None, length=n)[0]
    f = jax.jit(jax.vmap(run, in_axes=(in_axes, None)))
    t0 = time.perf_counter()
    exe = f.lower(mx, d0).compile()
    c = time.perf_counter() - t0
    jax.block_until_ready(exe(mx, d0).qpos)
    t0 = time.perf_counter()
    out = exe(mx, d0)
    jax.block_until_ready(out.qpos)
    return c, batch * n / (time.perf_counter() - t0), bool(np.isfinite(np.asarray(out.qpos)).all())


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--res", type=float, default=0.01, help="heightfield cell, m (obstacles are 2-3 cm long)")
    ap.add_argument("--json", default="docs/results/terrain_repr_cpu.json")
    a = ap.parse_args()
    spec = luneckas2020()
    terr = sample(get_terrain("high-large"), jax.random.PRNGKey(0), a.batch)
    res = {"batch": a.batch, "steps": a.steps, "backend": jax.default_backend(), "hfield_res_m": a.res}

    # boxes: hexjax's per-leg culled slots
    sm = sim_model(spec, PhysicsConfig())
    mx, in_axes = batch_model(sm, terr)
    d0 = mjx.make_data(sm.mj_model).replace(qpos=jnp.asarray(sm.qpos0), ctrl=jnp.asarray(sm.ctrl0))
    c, r, ok = time_steps(mx, in_axes, d0, a.batch, a.steps)
    res["boxes"] = dict(pairs=int(sm.mj_model.npair), compile_s=round(c, 1), env_steps_per_s=round(r), finite=ok)
    print("boxes", res["boxes"], flush=True)

    # heightfield: same field rasterised, one hfield per env (hfield_data batched)
    sx, sy = 0.9, 0.4
    nx, ny = int(2 * sx / a.res) + 1, int(2 * sy / a.res) + 1
    xml = hfield_xml(build_mjcf(spec, PhysicsConfig(slots_per_leg=0, torso_slots=0)), nx, ny, sx, sy, 0.1)
    m = mujoco.MjModel.from_xml_string(xml)
    maps = []
    for b in range(a.batch):
        t = jax.tree_util.tree_map(lambda x: x[b], terr)
        h = heightmap(t, (-0.3 - a.res / 2, 1.5 + a.res / 2), (-sy - a.res / 2, sy + a.res / 2), a.res)[:nx, :ny]
        maps.append((h.T / 0.1).reshape(-1))  # MuJoCo hfield rows run along y
    mxh = mjx.put_model(m)
    mxh = mxh.replace(hfield_data=jnp.asarray(np.stack(maps), jnp.float32))
    axes = jax.tree_util.tree_map(lambda _: None, mxh).replace(hfield_data=0)
    key = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "stance")
    d0 = mjx.make_data(m).replace(qpos=jnp.asarray(m.key_qpos[key]), ctrl=jnp.asarray(m.key_ctrl[key]))
    try:
        c, r, ok = time_steps(mxh, axes, d0, a.batch, a.steps)
        res["heightfield"] = dict(pairs=int(m.npair), cells=nx * ny, compile_s=round(c, 1),
                                  env_steps_per_s=round(r), finite=ok)
    except Exception as e:  # report, do not hide, an MJX limitation
        res["heightfield"] = dict(error=f"{type(e).__name__}: {str(e)[:300]}")
    print("heightfield", res["heightfield"], flush=True)
    with open(a.json, "w") as f:
        json.dump(res, f, indent=2)
    print("wrote", a.json)


if __name__ == "__main__":
    main()
