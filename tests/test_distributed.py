"""Sweeps past one machine: `hexjax robustness` over JAX's multi-process runtime (`jax.distributed`), two local
processes with one CPU device each and a coordinator on 127.0.0.1, against one process with two devices."""

import json
import os
import socket
import subprocess
import sys

import numpy as np
import pytest

from conftest import TEST_XLA_FLAGS

SWEEP = ["robustness", "--controllers", "gait", "--terrain", "flat", "--axis", "friction=0.4,1.0", "--batch", "4",
         "--distance", "0.05", "--per-env", "--engine", "mjx"]  # MJX: its envs shard over devices


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(devices: int):
    env = dict(os.environ)
    env["XLA_FLAGS"] = TEST_XLA_FLAGS.format(devices=devices)
    env["JAX_PLATFORMS"] = "cpu"
    return env


def _cells(path):
    with open(path) as f:
        res = json.load(f)
    return res, {(r["controller"], r["friction"]): r["per_env"] for r in res["cells"]}


@pytest.mark.cost(180)
def test_two_processes_give_the_per_env_numbers_of_one(tmp_path):
    cmd = [sys.executable, "-m", "hexjax.cli"] + SWEEP
    one = tmp_path / "one.json"
    subprocess.run(cmd + ["--json", str(one)], env=_env(2), check=True, capture_output=True, timeout=900)

    two = tmp_path / "two.json"
    port = _free_port()
    procs = [subprocess.Popen(cmd + ["--json", str(two), "--processes", "2", "--process-id", str(i),
                                     "--coordinator", f"127.0.0.1:{port}"],
                              env=_env(1), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for i in range(2)]
    outs = [p.communicate(timeout=900)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs[0][-2000:] + outs[1][-2000:]
    assert "process 1: ran its shards of 2 cells" in outs[1]

    res1, cells1 = _cells(one)
    res2, cells2 = _cells(two)
    assert res1["config"]["devices"] == 2 and res1["config"]["processes"] == 1
    assert res2["config"]["devices"] == 2 and res2["config"]["processes"] == 2
    assert cells1.keys() == cells2.keys() and len(cells1) == 2
    for k in cells1:
        for field in ("dx", "dy", "dalpha", "energy_J"):
            a, b = np.asarray(cells1[k][field]), np.asarray(cells2[k][field])
            assert a.shape == (4,)
            np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-7, err_msg=f"{k} {field}")
        assert cells1[k]["success"] == cells2[k]["success"]
        assert cells1[k]["fell"] == cells2[k]["fell"]
    # the friction axis reached the envs: the walks differ between the cells
    assert not np.allclose(cells1[("gait", 0.4)]["dx"], cells1[("gait", 1.0)]["dx"])
