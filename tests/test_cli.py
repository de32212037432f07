"""The `hexjax` command: built from the registry, fast to answer, checks before it works, and runs evaluate."""

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from hexjax.cli import main
from hexjax.experiments.registry import commands, experiments


@pytest.mark.cost(95)
def test_evaluate_obstacles_lose_distance(tmp_path, default_xla_env):
    """Without the tactile method the robot loses distance on obstacle terrain, the table shows it (with its
    legend), and nothing NaNs. On a CPU-only host `validated` runs on MuJoCo C with the reference's settings, the
    fastest engine it certifies there: the header says so and the JSON records it. The command runs as a user
    runs it, in a process of its own."""
    out = tmp_path / "ev.json"
    r = subprocess.run([sys.executable, "-m", "hexjax.cli", "evaluate", "--gait", "tripod", "--distance", "1.0",
                        "--batch", "8", "--seed", "3", "--categories", "flat,high-large", "--json", str(out)],
                       env=default_xla_env, capture_output=True, text=True, timeout=1200)
    assert r.returncode == 0, r.stderr[-2000:]
    table = r.stdout
    assert "high-large" in table and "|dx| cm" in table and "succ: upright and within 10 cm" in table
    res = json.loads(out.read_text())
    flat, obst = res["categories"]["flat"], res["categories"]["high-large"]
    assert flat["nan"] == 0 and obst["nan"] == 0
    assert flat["abs_dx_cm"] < 4.0 and flat["success_pct"] == 100.0
    assert obst["advance_m"] < flat["advance_m"] - 0.05  # lost > 5 cm of the metre on average
    assert obst["abs_dx_cm"] > flat["abs_dx_cm"]
    assert np.isfinite(obst["env_steps_per_s"]) and obst["env_steps_per_s"] > 0
    assert ("engine: c (MuJoCo C, certified; the fastest certified engine on this CPU-only host); reference's "
            "settings") in table
    engine = res["physics"]["engine"]
    assert res["physics"]["name"] == "validated" and res["physics"]["iterations"] == 100
    assert (engine, res["physics"]["settings_from"]) == ("c", "reference") and res["config"]["engine"] == "c"


def test_help_and_errors_import_no_jax():
    """`hexjax --help`, an experiment's `--help`, `--list`, a bad flag, numbers out of their range (the
    registry's bounds), a bad sweep axis and a missing randomization file answer before JAX is imported (so in
    well under a second); a bad tuning key answers before MuJoCo and the tuners are imported (about a second)."""
    code = ("import sys\nfrom hexjax.cli import main\n"
            "for argv in (['--help'], ['experiment', 'zhao2018-mjx', '--help'], ['evaluate', '--gait', 'gallop'],\n"
            "             ['evaluate', '--batch', '-3'], ['experiment', 'yu2019-step', '--duration', 'nan'],\n"
            "             ['bench', '--batches', '16,0'], ['terrain', '--difficulty', '0.5,1.5']):\n"
            "    try:\n        main(argv)\n    except SystemExit:\n        pass\n"
            "main(['experiment', '--list'])\n"
            "assert main(['robustness', '--axis', 'friction=1:0:3']) == 2\n"
            "assert main(['robustness', '--axis', 'friction=0.5,1', '--randomization', 'no/such.yaml']) == 2\n"
            "assert 'jax' not in sys.modules, 'jax was imported'\n"
            "assert main(['tune', '--set', 'stpes=5']) == 2\n"  # the config's check needs JAX, not the tuners
            "assert 'mujoco' not in sys.modules and 'hexjax.tune.grad' not in sys.modules\nprint('NO-JAX')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "NO-JAX" in r.stdout, r.stderr[-2000:]
    assert "invalid choice: 'gallop'" in r.stderr
    assert "argument --batch: -3: must be >= 1" in r.stderr
    assert "argument --duration: nan: must be a finite number" in r.stderr
    assert "argument --batches: 0: must be >= 1" in r.stderr
    assert "argument --difficulty: 1.5: must be in [0, 1]" in r.stderr
    assert "--axis 'friction=1:0:3': values must be" in r.stderr and "tune.stpes: unknown key" in r.stderr
    assert "no/such.yaml: no such file" in r.stderr


def test_experiment_list_and_per_experiment_flags(capsys):
    assert main(["experiment", "--list"]) == 0
    listed = capsys.readouterr().out.splitlines()
    names = sorted(experiments())
    assert len(listed) == len(names) >= 10
    for name, line in zip(names, listed):
        papers = ("Luneckas 2020", "Yu 2019", "Zhao 2018", "Chen 2019")
        assert line.split()[0] == name and any(p in line for p in papers)
    with pytest.raises(SystemExit):
        main(["experiment", "zhao2018-mjx", "--help"])
    text = capsys.readouterr().out
    assert "--blind" in text and "--chunk" in text and "[default: 32]" in text
    assert "--gaits" not in text and "--dataset" not in text  # luneckas2020's own flags stay its own
    with pytest.raises(SystemExit):
        main(["experiment", "luneckas2020", "--blind"])
    assert "unrecognized arguments: --blind" in capsys.readouterr().err
    # every help text names papers, not seed files, and every command shows its defaults
    for entry in list(experiments().values()) + list(commands().values()):
        assert "seed 0" not in entry.summary.lower() and "seed-0" not in entry.summary.lower()
    with pytest.raises(SystemExit):
        main(["evaluate", "--help"])
    text = capsys.readouterr().out
    assert "presets: " in text and "luneckas2020" in text and "[default: tripod]" in text


def test_cli_reports_bad_input_before_any_work(capsys, tmp_path):
    assert main(["terrain", "--preset", "volcano", "--png", str(tmp_path / "x.png")]) == 2
    assert "volcano" in capsys.readouterr().err
    assert main(["render", "--out", str(tmp_path / "w.txt")]) == 2  # checked before ~100 s of simulation
    assert "--out=" in capsys.readouterr().err
    assert main(["experiment", "zhao2018", "--png", str(tmp_path / "plot.jpg")]) == 2
    assert "must end in .png" in capsys.readouterr().err
    if sys.platform.startswith("linux"):  # /proc takes no new files, though `os.access` tells root it is writable
        assert main(["evaluate", "--json", "/proc/hexjax.json"]) == 2  # checked before ~80 s of walking
        assert "--json='/proc/hexjax.json': cannot write in its folder /proc" in capsys.readouterr().err
        assert main(["tune", "--out", "/proc/hexjax-tune"]) == 2  # its checkpoints, before the first step
        assert "--out='/proc/hexjax-tune': cannot make its folder" in capsys.readouterr().err
    # numbers out of their registry bounds fail as the arguments parse (argparse's exit 2), naming flag and value
    for argv, said in ((["evaluate", "--batch", "0"], "--batch: 0: must be >= 1"),
                       (["experiment", "luneckas2020", "--n", "0"], "--n: 0: must be >= 1"),
                       (["experiment", "luneckas2020", "--distances", "1,-1"], "--distances: -1: must be in (0, 10]"),
                       (["experiment", "luneckas2020-predictor", "--lr", "0"], "--lr: 0: must be > 0"),
                       (["experiment", "luneckas2020-predictor", "--held-out", "1.0"],
                        "--held-out: 1: must be in (0, 1)"),
                       (["bench", "--seconds", "inf"], "--seconds: inf: must be a finite number"),
                       (["bench", "--batches", "16,x"], "'x' in '16,x': not a value of type int"),
                       (["robustness", "--controllers", ","], "--controllers: ',': give at least one value"),
                       (["render", "--seconds", "1e9"], "--seconds: 1000000000: must be in (0, 600]"),
                       (["evaluate", "--categories", "flat,low-small,flat"],
                        "--categories: 'flat' given twice in 'flat,low-small,flat'")):
        with pytest.raises(SystemExit) as ex:
            main(argv)
        assert ex.value.code == 2 and said in capsys.readouterr().err, argv
    with pytest.raises(SystemExit):
        main(["experiment", "luneckas2020", "--gaits", "trot"])
    assert "'trot' is not one of" in capsys.readouterr().err
    assert main(["experiment", "luneckas2020-predictor", "--data", str(tmp_path / "none.npz")]) == 2
    assert "luneckas2020-dataset" in capsys.readouterr().err
    (tmp_path / "text.npz").write_text("not an archive\n")  # numpy took it for a pickle and said so
    assert main(["experiment", "luneckas2020-predictor", "--data", str(tmp_path / "text.npz")]) == 2
    assert "text.npz: not an .npz archive numpy can read (ValueError)" in capsys.readouterr().err
    # a flag of the other benchmark would be ignored (--seconds with --grad was, in a recorded run)
    for argv, said in ((["bench", "--grad", "--seconds", "1"], "--seconds: sets the forward benchmark, not --grad"),
                       (["bench", "--backward", "forward"], "--backward: sets the gradient benchmark: add --grad")):
        assert main(argv) == 2 and said in capsys.readouterr().err, argv
    # that check reads two hand lists beside configs/commands/bench.yaml: a flag added to the file and to
    # neither list would be ignored again without a word, so every flag must be in one list or used by both
    from hexjax.experiments.commands import bench
    both = {"batches", "repeats", "grad", "json"}
    names = {o.name for o in commands()["bench"].options}
    assert not set(bench.FORWARD_ONLY) & set(bench.GRAD_ONLY)
    unsorted = names - set(bench.FORWARD_ONLY) - set(bench.GRAD_ONLY) - both
    assert not unsorted, f"bench.yaml's flags in neither FORWARD_ONLY nor GRAD_ONLY: {sorted(unsorted)}"
    assert set(bench.FORWARD_ONLY) | set(bench.GRAD_ONLY) | both <= names  # and no list names a flag gone


def test_the_first_hours_bad_inputs_are_one_line_before_any_work(capsys, tmp_path):
    """Inputs a new user tried on a fresh clone, each once accepted or answered late: every one is now a
    one-line error (exit 2) before anything loads or compiles, so no finished run's numbers are lost."""
    import time
    folder = tmp_path / "out.json"
    folder.mkdir()  # a folder where the JSON would go: the job used to run, then lose its numbers
    (tmp_path / "plot.png").mkdir()
    (tmp_path / "empty.yaml").write_text("")
    (tmp_path / "block.yaml").write_text("randomization:\n")
    (tmp_path / "binary.yaml").write_bytes(bytes(range(128, 256)))
    cases = ((["evaluate", "--json", str(folder)], f"--json={str(folder)!r}: a folder is there"),
             (["terrain", "--png", str(tmp_path / "plot.png")], "a folder is there"),
             (["experiment", "zhao2018", "--json", str(folder)], "a folder is there"),
             (["tune", "--method", "es", "--equal-wall"], "--equal-wall with --method es"),
             (["robustness", "--axis", "friction=0.5,1", "--processes", "1", "--process-id", "3"],
              "--process-id=3: must be in [0, 0]"),
             (["robustness", "--axis", "friction=0.5,1", "--randomization", str(tmp_path / "empty.yaml")],
              "an empty randomization"),
             (["robustness", "--axis", "friction=0.5,1", "--randomization", str(tmp_path / "block.yaml")],
              "an empty randomization"),
             (["robustness", "--axis", "friction=0.5,1", "--randomization", str(tmp_path / "binary.yaml")],
              f"{tmp_path / 'binary.yaml'}: not a text file"),
             (["evaluate", "--physics", str(tmp_path / "binary.yaml")], f"{tmp_path / 'binary.yaml'}: not a text file"))
    for argv, said in cases:
        t0 = time.perf_counter()
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and said in err[0], (argv, err)
        assert time.perf_counter() - t0 < 10, argv  # nothing walked or compiled first
    assert not list(folder.iterdir())


def test_inputs_once_answered_after_jax_loaded_are_answered_before():
    """A wrong cell or controller for fidelity, a tuning config's unknown controller, an unknown params preset
    and a robustness controller used to be refused only after JAX had loaded (11-24 s on a fresh machine); each is
    now one line from the checks before it, in a process that never imports JAX."""
    import subprocess
    import sys
    cases = [(["fidelity", "--only", "nosuchcell"], "--only nosuchcell: no cell of the matrix matches"),
             (["fidelity", "--controllers", "nosuch"], "--controllers 'nosuch': use some of"),
             (["tune", "--set", "controller=nosuch"], "controller='nosuch': use one of gait, tactile, cpg"),
             (["experiment", "yu2019-step", "--params", "nosuch"], "params preset 'nosuch' unknown"),
             (["robustness", "--axis", "friction=0.5", "--controllers", "nosuch"], "--controllers 'nosuch'"),
             (["experiment", "luneckas2020-predictor", "--data", "nosuch.npz"], "--data='nosuch.npz': no such file")]
    code = ("import sys\nfrom hexjax.cli import main\n"
            f"for argv in {[c[0] for c in cases]!r}:\n"
            "    assert main(argv) == 2, argv\n"
            "    assert 'jax' not in sys.modules, argv\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == len(cases), lines
    for line, (argv, said) in zip(lines, cases):
        assert said in line, (argv, line)


def test_out_of_memory_is_one_line_naming_the_sizes(capsys, monkeypatch):
    """XLA's allocation failure (`chen2019-incenter --polygons 100000000` asked for 42 GB) ends the command with
    one line; any other runtime error keeps its traceback."""
    import jax

    from hexjax.experiments import runner

    def fail(text):
        def run(entry, o):
            raise jax.errors.JaxRuntimeError(text)
        return run

    monkeypatch.setattr(runner, "run", fail("INTERNAL: Error dispatching computation: Out of memory allocating "
                                            "42000001488 bytes.\nmore"))
    assert main(["experiment", "chen2019-incenter"]) == 1
    err = capsys.readouterr().err
    assert err == ("hexjax experiment chen2019-incenter: error: Out of memory allocating 42000001488 bytes on the "
                   "device: lower the sizes asked for (envs, fields, polygons) or give the run a --chunk where it "
                   "has one\n"), err
    monkeypatch.setattr(runner, "run", fail("INTERNAL: something else"))
    with pytest.raises(jax.errors.JaxRuntimeError, match="something else"):
        main(["experiment", "chen2019-incenter"])


def test_the_library_checks_what_the_cli_bounds_check():
    """The registry's bounds only answer sooner: a Python caller of the same functions gets the library's own
    one-line error for the same values."""
    from hexjax.experiments.commands.evaluate import evaluate
    from hexjax.experiments.papers.luneckas2020.matrix import run_luneckas2020
    from hexjax.experiments.papers.luneckas2020.predictor import TrainConfig
    for call, said in ((lambda: evaluate(batch=0), "batch=0"),
                       (lambda: evaluate(distance=float("nan")), "distance=nan"),
                       (lambda: run_luneckas2020(n=0), "n=0"),
                       (lambda: run_luneckas2020(distances=[1.0, -1.0]), "distances="),
                       (lambda: TrainConfig(learning_rate=0.0).validate(), "learning_rate=0.0")):
        with pytest.raises(ValueError, match=said):
            call()


def test_registry_bounds_are_checked_on_load(tmp_path):
    """A bound on a text option, a bound that is not a number, min with above, or a default outside its own
    bounds fails on load, naming the file and the option."""
    from hexjax.experiments.registry import load_entry
    head = "summary: s\nentry: hexjax.experiments.commands.evaluate\noptions:\n"
    for opt, said in (("  name: {default: a, min: 1}", "need a number option"),
                      ("  n: {default: 2, min: one}", "n.min='one': a bound must be a finite number"),
                      ("  n: {default: 2, min: 1, above: 0}", "give min or above"),
                      ("  n: {default: 0, min: 1}", "n.default=0 is outside its own bounds"),
                      ("  d: {default: [0.5, 2.0], max: 1}", "d.default=2.0 is outside")):
        f = tmp_path / "bad.yaml"
        f.write_text(head + opt + "\n")
        with pytest.raises(ValueError, match=said) as ex:
            load_entry(f, "commands")
        assert str(f) in str(ex.value)
    # an entry says who picks its physics (no guessing from its option names), and only where it has the option
    for text, said in (("  physics: {default: validated, preset: physics}\n", "physics_by='': an entry with a physics"),
                       ("  n: {default: 2}\n", "physics_by='runner': the entry has no physics option")):
        f = tmp_path / "bad.yaml"
        f.write_text(head.replace("options:", "physics_by: runner\noptions:" if "n:" in text else "options:")
                     + text)
        with pytest.raises(ValueError, match=re.escape(said)):
            load_entry(f, "commands")


def test_terrain_png_shows_the_obstacles(tmp_path):
    """The drawn height map shows the preset's boxes: in the middle of the map, each pixel's colour is read
    back through the colormap to a height; a few per cent of them are obstacle tops (the boxes cover ~5 %
    of a low-density field) and most are ground. A blank, an all-ground or a noise picture fails."""
    import matplotlib
    import matplotlib.image as mpimg
    png = tmp_path / "t.png"
    assert main(["terrain", "--preset", "low-large", "--seed", "2", "--png", str(png)]) == 0
    img = mpimg.imread(str(png))[..., :3]
    h, w = img.shape[:2]
    mid = img[h // 4: 3 * h // 4, w // 5: 3 * w // 5].reshape(-1, 3)  # inside the map, left of the colorbar
    lut = matplotlib.colormaps["terrain"](np.linspace(0, 1, 256))[:, :3]
    d = np.linalg.norm(mid[:, None, :] - lut[None], axis=-1)
    level = d.argmin(1) / 255.0  # the pixel's height as a fraction of the map's range
    on_map = d.min(1) < 0.05
    assert on_map.mean() > 0.9  # the middle is map, not axes or text
    tops, ground = np.mean(level[on_map] > 0.6), np.mean(level[on_map] < 0.1)
    assert 0.01 < tops < 0.2 and ground > 0.6, (tops, ground)


def test_the_long_silent_commands_show_their_walks_progress(capsys):
    """chen2019 (and zhao2018-mjx, zhao2018-perception, which share the bar) used to be silent from "compiling" to
    the table; each walk now shows a bar over its control steps."""
    assert main(["experiment", "chen2019", "--batch", "1", "--duration", "0.5"]) == 0
    err = capsys.readouterr().err
    for name in ("planned", "fixed_h8cm", "fixed_h13cm"):
        assert f"chen2019 {name}: 1 patches, 0.5 s" in err, err[-2000:]
    assert "step/s" in err
    # yu2019-step walks its six rows as one rollout: a bar over its control steps, not over rows that all end at
    # once (90 s of walking at 1,024 terrains a row is most of an hour on 2 CPU cores)
    assert main(["experiment", "yu2019-step", "--batch", "1", "--duration", "0.5", "--engine", "c"]) == 0
    err = capsys.readouterr().err
    assert "yu2019-step: 6 rows x 1 envs, 0.5 s" in err and "step/s" in err, err[-2000:]
