"""What a new user meets at the command line: the version, a batch too large for the machine, SI units, the
evaluate picture, a gradient batch too large, the sweep's device wording, and a finished run's partial file."""
import dataclasses
import json
import os
import subprocess
import sys

import pytest

from hexjax.cli import main


def test_version_answers_without_running_anything():
    out = subprocess.run([sys.executable, "-m", "hexjax.cli", "--version"], capture_output=True, text=True)
    from hexjax import __version__
    assert out.returncode == 0 and out.stdout.strip() == f"hexjax {__version__}"


def test_a_batch_beyond_the_machine_fails_in_one_line_before_any_work(capsys, monkeypatch):
    from hexjax.experiments import runner
    from hexjax.sim import memory
    monkeypatch.setattr(memory, "available_bytes", lambda host=False: 24 * 2**30)
    assert main(["evaluate", "--batch", "100000000"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--batch=100000000" in err[0] and "more than the 24 GiB here" in err[0], err
    # a batch that fits is not questioned by the estimate
    runner.check_batch_memory(type("O", (), {"batch": 16})())
    # once the engine is chosen, its own measured figure sizes the batch and names the largest that fits
    from hexjax.sim.engines import get_engine
    warp = get_engine("warp")
    monkeypatch.setattr(memory, "available_bytes", lambda host=False: 80 * 2**30)
    with pytest.raises(ValueError) as err:
        runner.check_batch_memory(type("O", (), {"batch": 10**6})(), warp)
    fits = 80 * 2**30 // int(memory.HEADROOM * warp.bytes_per_env)
    said = str(err.value)
    assert "on MuJoCo Warp needs about" in said and f"the largest batch that fits is {fits:,}" in said
    runner.check_batch_memory(type("O", (), {"batch": fits})(), warp)


def test_a_gradient_batch_beyond_the_machine_fails_in_one_line_before_anything_is_traced(capsys, monkeypatch):
    from hexjax.sim import memory
    from hexjax.sim.engines import get_engine
    from hexjax.tune import grad
    from hexjax.tune.config import load_tune_config
    from hexjax.tune.objective import Problem
    monkeypatch.setattr(memory, "available_bytes", lambda host=False: 24 * 2**30)
    traced = []
    monkeypatch.setattr(Problem, "gradient_program", lambda self, *a, **k: traced.append(1))
    # the walk's control steps at MJX's measured bytes an env and control step, with the headroom
    per_env = lambda steps: int(memory.HEADROOM * get_engine("mjx").grad_bytes_per_env_step * steps)
    assert main(["bench", "--grad", "--tune", "tactile_tripod_validated", "--solver-grad", "implicit",
                 "--batches", "4,1000000", "--walk", "10"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    fits = 24 * 2**30 // per_env(500)  # 10 s at the tactile controller's 20 ms
    assert len(err) == 1 and "--batches=1000000" in err[0] and "500-control-step walk" in err[0], err
    assert f"the largest batch that fits is {fits:,}" in err[0], err
    # the tuner refuses its train_batch the same way, before its gradient program is made
    cfg = dataclasses.replace(load_tune_config("tactile_tripod_validated"), train_batch=10**6)
    with pytest.raises(ValueError, match="tune.train_batch=1000000: .* largest batch that fits is") as e:
        grad.tune(cfg, "/nonexistent/never-written", progress=False)
    assert "1521-control-step walk" in str(e.value) and not traced
    # the largest batch named fits
    Problem.build(load_tune_config("tactile_tripod_validated")).check_gradient_fits(24 * 2**30 // per_env(1521))


def test_lengths_on_the_command_line_are_in_metres():
    from hexjax.experiments.registry import commands
    h = next(o for o in commands()["evaluate"].options if o.name == "step_height")
    assert h.default == pytest.approx(0.03) and "m" in h.help
    with pytest.raises(ValueError):
        h.check_value(3.0)  # 3 m: the old reading in cm fails instead of building a 3 m swing


def test_evaluate_draws_its_picture(tmp_path):
    from hexjax.experiments.commands.evaluate import plot
    cats = {c: dict(abs_dx_cm=v, abs_dy_cm=v / 3, dx_std_cm=v / 2, dy_std_cm=v / 5, fall_pct=f)
            for c, v, f in [("flat", 2, 0), ("high-large", 40, 25)]}
    out = plot({"categories": cats, "config": dict(robot="luneckas2020", gait="tripod", distance_m=1.0, batch=8),
                "physics": {"name": "validated"}}, str(tmp_path / "ev.png"))
    assert out == [str(tmp_path / "ev.png")] and os.path.getsize(out[0]) > 10_000


def test_the_sweep_says_cores_on_a_cpu():
    from hexjax.experiments.commands.robustness_view import _devices
    assert _devices({"devices": 2, "backend": "cpu"}) == "2 CPU cores (one XLA device each)"
    assert _devices({"devices": 1, "backend": "gpu"}) == "1 GPU"


def test_a_finished_run_leaves_no_partial_file(tmp_path, monkeypatch, capsys):
    """The runner removes `<json>.partial.json` once the JSON holds the whole result; a resumed run says
    how many pieces it took from the partial file."""
    from hexjax.experiments import runner
    from hexjax.interrupt import kept
    path = str(tmp_path / "r.json")
    runner.write_partial(path + ".partial.json", {"digest": "d", "cells": {"a": 1, "b": 2}}, "2 of 3 cells kept")
    assert kept() == "2 of 3 cells kept"
    assert runner.read_partial(path + ".partial.json", "other", "cells", "x", "cells", 3) == {}
    done = runner.read_partial(path + ".partial.json", "d", "cells", "robustness", "cells", 3)
    assert done == {"a": 1, "b": 2}
    # counting only the pieces this run asks for (a run of fewer gaits than the kept file holds)
    runner.read_partial(path + ".partial.json", "d", "cells", "luneckas2020", "gaits", 1, ["b"])
    assert capsys.readouterr().out.splitlines()[-1].startswith("luneckas2020: resumed 1 of 1 gaits")

    class Mod:
        @staticmethod
        def run(o, entry):
            return {"config": {}, "cells": done}

        @staticmethod
        def report(res):
            return "done"

    monkeypatch.setattr(runner.importlib, "import_module", lambda name: Mod)
    entry = type("E", (), {"options": (), "entry": "x", "physics_by": ""})()
    runner.run(entry, type("O", (), {"json": path, "png": ""})())
    assert json.load(open(path))["cells"] == done and not os.path.exists(path + ".partial.json")
