import json

import numpy as np

from hexjax.cli import main


def test_evaluate_obstacles_lose_distance(tmp_path, capsys):
    """Acceptance: without the tactile method the robot loses distance on obstacle terrain, the table
    shows it, and nothing NaNs. One compile serves both categories (padded to one box count)."""
    out = tmp_path / "ev.json"
    rc = main(["evaluate", "--gait", "tripod", "--distance", "1.0", "--batch", "8", "--seed", "3",
               "--categories", "flat,high-large", "--json", str(out)])
    assert rc == 0
    table = capsys.readouterr().out
    assert "high-large" in table and "|dx| cm" in table
    res = json.loads(out.read_text())
    flat, obst = res["categories"]["flat"], res["categories"]["high-large"]
    assert flat["nan"] == 0 and obst["nan"] == 0
    assert flat["abs_dx_cm"] < 4.0 and flat["success_pct"] == 100.0
    assert obst["advance_m"] < flat["advance_m"] - 0.05  # lost > 5 cm of the metre on average
    assert obst["abs_dx_cm"] > flat["abs_dx_cm"]
    assert np.isfinite(obst["env_steps_per_s"]) and obst["env_steps_per_s"] > 0


def test_terrain_png(tmp_path):
    png = tmp_path / "t.png"
    assert main(["terrain", "--preset", "low-large", "--seed", "2", "--png", str(png)]) == 0
    assert png.stat().st_size > 10_000


def test_cli_reports_bad_input(capsys):
    assert main(["terrain", "--preset", "volcano", "--png", "x.png"]) == 2
    assert "volcano" in capsys.readouterr().err
    assert main(["evaluate", "--batch", "0"]) == 2


def test_luneckas_commands_report_bad_input(capsys, tmp_path):
    """Errors before any simulation: bad n, gait, distance, missing dataset."""
    assert main(["experiment", "luneckas2020", "--n", "0"]) == 2
    assert "n=0" in capsys.readouterr().err
    assert main(["experiment", "luneckas2020", "--gaits", "trot"]) == 2
    assert "trot" in capsys.readouterr().err
    assert main(["experiment", "luneckas2020", "--distances", "-1"]) == 2
    assert "distances" in capsys.readouterr().err
    assert main(["predictor", "--data", str(tmp_path / "none.npz")]) == 2
    assert "hexjax dataset" in capsys.readouterr().err
    assert main(["predictor", "--lr", "0", "--data", str(tmp_path / "none.npz")]) == 2
    assert "learning_rate" in capsys.readouterr().err
