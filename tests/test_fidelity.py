"""`hexjax fidelity` on a small paired matrix: the validated preset (MJX) against the reference (MuJoCo C,
converged), and the matrix's bookkeeping."""

import json
import subprocess
import sys
import types

import numpy as np
import pytest

from hexjax.experiments.commands import fidelity


def _options(**kw):
    o = dict(physics="validated", against="reference", engine="", refine=False, batch=64, controllers=["gait"],
             only=[], robot="luneckas2020", distance=0.25, seed=0, json="", png="", progress=False)
    o.update(kw)
    return types.SimpleNamespace(**o)


def _run_in_own_process(options, preset, path, env):
    """`fidelity.run(options, preset)`'s result, run in a child process with environment `env`."""
    code = ("import json, sys, types\nfrom hexjax.experiments.commands import fidelity\n"
            "from hexjax.experiments.runner import write_json\n"
            "res = fidelity.run(types.SimpleNamespace(**json.loads(sys.argv[1])), "
            "types.SimpleNamespace(preset=json.loads(sys.argv[2])))\nwrite_json(sys.argv[3], res)\n")
    r = subprocess.run([sys.executable, "-c", code, json.dumps(options), json.dumps(preset), str(path)], env=env,
                       capture_output=True, text=True, timeout=3000)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(path.read_text())


@pytest.mark.cost(300)
def test_validated_mjx_meets_the_reference_on_a_paired_matrix(tmp_path, default_xla_env):
    """64 envs per cell, the open-loop gait 0.25 m on flat ground and on low-small obstacles at friction 0.2 and
    0.6 (the frictions where 2 Newton iterations read 12 % against converged MuJoCo's 43 %), both engines on the
    same terrains and heading draws. The tolerance is the contract widened by each cell's own paired 95 % interval
    (`Cell row["within_ci"]`): |d success| <= 5 points, |d advance| <= 1.5 cm, |d heading| <= 1.5 deg must each
    meet the interval of the paired differences (at 64 envs, independent chaotic walks give a success interval of
    about +-12 points; the advance and heading ones are tighter). Run as `hexjax fidelity` runs, in a process
    with XLA's default settings (the suite's older fusion emitters slow MJX's elliptic-cone solve 3.4x)."""
    preset = {"friction_terrains": ["flat", "low-small"], "frictions": [0.2, 0.6], "controllers": {"gait": "all"}}
    res = _run_in_own_process(vars(_options()), preset, tmp_path / "fid.json", default_xla_env)
    assert res["physics"]["name"] == "validated" and res["physics"]["engine"] == "mjx"
    assert res["against"]["name"] == "reference" and res["against"]["engine"] == "c"
    rows = {r["cell"]: r for r in res["cells"]}
    assert sorted(rows) == ["flat mu=0.2", "flat mu=0.6", "low-small mu=0.2", "low-small mu=0.6"]
    for name, r in rows.items():
        assert r["n"] == 64 and r["nan"] == [0, 0], name
        assert r["within_ci"], (name, r["d_success_pts"], r["d_success_ci"], r["d_advance_cm"], r["d_heading_deg"])
    # on flat ground nothing is chaotic: the two engines walk the same walk
    for f in ("flat mu=0.2", "flat mu=0.6"):
        assert abs(rows[f]["d_advance_cm"]) < 0.1 and abs(rows[f]["d_heading_deg"]) < 0.1, rows[f]
    assert "fidelity: validated (mjx) against reference (c)" in fidelity.report(res)


def test_matrix_lists_each_cell_once_and_paired_intervals():
    spec = {"terrains": ["flat", "low-small"], "families": ["low-small"], "difficulties": [0.0],
            "friction_terrains": ["low-small"], "frictions": [0.2, 1.0], "payload_terrains": ["flat"], "payloads": [0.6]}
    names = [c.name for c in fidelity.matrix(spec)]
    # friction 1.0 is the robot's own: the same cell as the plain category, listed once
    assert names == ["flat", "low-small", "low-small d=0", "low-small mu=0.2", "flat +0.6 kg"]
    from hexjax.sim.metrics import paired  # what the comparison's rows use
    m, (lo, hi) = paired([1, 1, 0, 1], [1, 0, 0, 1])
    assert m == pytest.approx(0.25) and lo < 0.25 < hi
    m, (lo, hi) = paired(np.ones(8), np.ones(8))
    assert m == lo == hi == 0.0


def test_bad_fidelity_options_fail_in_one_line():
    entry = types.SimpleNamespace(preset={"terrains": ["flat"]})
    with pytest.raises(ValueError, match="--only nowhere: no cell of the matrix matches"):
        fidelity.run(_options(only=["nowhere"]), entry)
    with pytest.raises(ValueError, match="physics preset 'refrence' unknown"):
        fidelity.run(_options(against="refrence"), entry)


def test_refine_holds_the_reference_against_itself_at_half_the_step_and_twice_the_iterations():
    a, b = fidelity._presets(_options(refine=True))
    assert b.name == "reference" and a.name == "reference-refined" and a.engine.name == b.engine.name == "c"
    a, b = a.settings, b.settings
    assert a.timestep == b.timestep / 2 and a.iterations == 2 * b.iterations
    assert a.ls_iterations == 2 * b.ls_iterations and a.tolerance == b.tolerance and a.cone == b.cone
    a, b = fidelity._presets(_options(engine="warp"))
    assert (a.name, b.name, a.engine.name, a.settings_from) == ("validated", "reference", "warp", "validated")
