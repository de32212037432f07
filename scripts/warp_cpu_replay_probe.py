"""MuJoCo Warp on the CPU device, without JAX: time `mujoco_warp.step` launched from Python against the same step
recorded once (`wp.ScopedCapture`) and replayed (`wp.capture_launch`), and check that both give the same `qpos`.
The measurement behind `hexjax.sim.backends.warp_cpu` (docs/ecosystem.md).

    python scripts/warp_cpu_replay_probe.py --worlds 1,8,64 --steps 100 --json out/warp_cpu_replay.json
"""

import argparse
import json
import time

import mujoco
import numpy as np
import warp as wp
from mujoco.mjx.third_party import mujoco_warp as mjw

from hexjax.sim.config import PhysicsConfig
from hexjax.sim.mjcf import build_mjcf
from hexjax.world.presets import luneckas2020


def probe(mjm, nworld: int, steps: int) -> dict:
    mjd = mujoco.MjData(mjm)
    mjd.ctrl[:] = 0.3  # some drive, so that the legs move and contacts change
    with wp.ScopedDevice("cpu"):
        m = mjw.put_model(mjm)
        fresh = lambda: mjw.put_data(mjm, mjd, nworld=nworld, nconmax=64, njmax=256)
        d = fresh()
        mjw.step(m, d)  # loads the kernels
        t = time.perf_counter()
        for _ in range(steps):
            mjw.step(m, d)
        wp.synchronize()
        launched_s = (time.perf_counter() - t) / steps
        launched_qpos = d.qpos.numpy().copy()
        d = fresh()
        with wp.ScopedCapture() as capture:  # records the launches; on the CPU nothing runs yet
            mjw.step(m, d)
        t = time.perf_counter()
        for _ in range(steps + 1):
            wp.capture_launch(capture.graph)
        wp.synchronize()
        replayed_s = (time.perf_counter() - t) / (steps + 1)
        same = bool(np.array_equal(launched_qpos, d.qpos.numpy()))
    return {"worlds": nworld, "launched_ms": 1e3 * launched_s, "replayed_ms": 1e3 * replayed_s, "same_qpos": same,
            "contacts": int(d.nacon.numpy()[0])}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worlds", default="1,8,64", help="comma list of batch sizes")
    ap.add_argument("--steps", type=int, default=100, help="timed steps each way (the replay runs one more)")
    ap.add_argument("--json", default=None, help="write the rows here")
    a = ap.parse_args()
    wp.config.quiet = True
    wp.init()
    mjm = mujoco.MjModel.from_xml_string(build_mjcf(luneckas2020(), PhysicsConfig(cone="elliptic"),
                                                    contact_sensors=True))
    rows = []
    for n in (int(x) for x in a.worlds.split(",")):
        r = probe(mjm, n, a.steps)
        rows.append(r)
        print(f"worlds {n:4d}: launched {r['launched_ms']:7.2f} ms/step, replayed {r['replayed_ms']:7.2f} ms/step, "
              f"same qpos after {a.steps + 1} steps: {r['same_qpos']} ({r['contacts']} contacts)", flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"steps": a.steps, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
