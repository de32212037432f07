"""The one controller table (`hexjax.control.registry`): every name builds its controller, each controller
carries its own walk-length rule, and the commands' choices name only registered controllers."""
import math

import pytest

from hexjax.control.registry import CONTROLLERS, make_controller
from hexjax.world.files import read_yaml, resolve
from hexjax.world.presets import get_robot


@pytest.mark.parametrize("name", sorted(CONTROLLERS))
def test_each_name_builds_its_controller_with_a_walk_length_rule(name):
    entry = CONTROLLERS[name]
    robot = get_robot(entry.robot)
    if entry.gaits:
        ctrl = make_controller(name, robot, gait="wave")
        assert ctrl.robot is robot and ctrl.gait == "wave"
    else:  # it plans its own steps: no gait to give
        ctrl = make_controller(name, robot)
        assert ctrl.robot is robot and not hasattr(ctrl, "gait")
        with pytest.raises(ValueError, match=f"gait='tripod': the {name} controller plans its own steps"):
            make_controller(name, robot, gait="tripod")
    walk, seconds = ctrl.for_distance(1.0)
    assert type(walk) is type(ctrl) and math.isfinite(seconds) and seconds > 0
    # a longer walk takes longer
    assert ctrl.for_distance(2.0)[1] > seconds


def test_the_walk_length_rules_by_hand():
    """The gait stops after the cycles that cover the distance; the CPG (no stop) walks it at one stroke a
    leader period plus a period to start; the avoiding gait gets room for a detour of twice the distance."""
    lun, yu = get_robot("luneckas2020"), get_robot("yu2019")
    gait = make_controller("gait", lun)
    p = gait.default_params()
    walk, seconds = gait.for_distance(1.0)
    # tripod: 2 swing slots a cycle; the ramps cost a cycle's advance, so n cycles advance (n - 1) x 2 l
    advance = float(p.step_length) * 2 / (2 - 1)
    n = max(2, round(1.0 / advance) + 1)
    assert walk.n_cycles == n and seconds == pytest.approx(n * float(p.swing_time) * 2 + 0.5)

    cpg = make_controller("cpg", yu)
    q = cpg.default_params()
    period = 2 * math.pi / float(q.net.omega[0])
    walk, seconds = cpg.for_distance(0.6)
    assert walk is cpg and seconds == pytest.approx(0.6 / (float(q.step_length) / period) + period)

    avoid = make_controller("avoid", lun)
    g = avoid.default_params().gait  # the fast gait: l = 6 cm, 0.25 s swing
    walk, seconds = avoid.for_distance(1.0)
    cycle = float(g.swing_time) * 2
    assert walk is avoid and seconds == pytest.approx((math.ceil(2 * 1.0 / (0.06 * 2)) + 2) * cycle)


def test_an_unknown_controller_is_refused_naming_the_choices():
    with pytest.raises(ValueError, match=r"controller='walker': use one of gait, tactile, cpg, avoid, perceive, "
                                         r"support, perceive-support, cpg-reflex, gait-reflex"):
        make_controller("walker", get_robot("luneckas2020"))


def test_the_registry_gaits_are_the_controllers_own():
    """The entries list gaits without importing the controllers (configs are checked before JAX loads): they must
    be the gait tables the controllers check against, and a reflex layer walks its base's."""
    from hexjax.control.cpg.params import CPG_GAITS
    from hexjax.control.gait import GAITS
    own = {"gait": GAITS, "tactile": GAITS, "avoid": GAITS, "perceive": GAITS, "cpg": CPG_GAITS}
    for name, table in own.items():
        assert set(CONTROLLERS[name].gaits) == set(table), name
    for name, e in CONTROLLERS.items():
        if e.base:
            assert e.gaits == CONTROLLERS[e.base].gaits, name
        for g in (set(GAITS) | set(CPG_GAITS)) - set(e.gaits):  # a gait not listed is refused by the controller
            if e.gaits:
                with pytest.raises(ValueError, match="gait"):
                    make_controller(name, get_robot(e.robot), gait=g)


def test_the_commands_offer_only_registered_controllers():
    """The command-line choices are written in YAML (parsed before JAX is imported); they must stay a subset
    of the registry's controllers that can serve them (render: those that walk alone)."""
    from hexjax.experiments.commands.robustness import SWEEPABLE
    from hexjax.render import RENDERABLE
    choices = read_yaml(resolve("commands", "bench"))["options"]["controller"]["choices"]
    assert set(choices) <= set(CONTROLLERS), choices
    choices = read_yaml(resolve("commands", "render"))["options"]["controller"]["choices"]
    assert set(choices) <= set(RENDERABLE), choices
    assert {"gait", "tactile", "cpg", "avoid"} <= set(SWEEPABLE) <= set(CONTROLLERS)
    assert not {"perceive", "support"} & set(SWEEPABLE)  # their params come from a sensor or a DEM, not a rule


def test_the_cell_rules_by_hand():
    """The tactile gait's h_k on a cell is its highest obstacle + 2 cm (Luneckas 2020 Eq. 7) where something
    stands in the way, its own H + 2 cm elsewhere; the avoiding gait's obstacles are the cell's boxes, per env."""
    import jax
    import numpy as np

    from hexjax.world.presets import get_terrain
    from hexjax.world.terrain import sample
    lun = get_robot("luneckas2020")
    tactile = make_controller("tactile", lun)
    rule = CONTROLLERS["tactile"].cell_params
    boxes = get_terrain("boxes")
    p, batched = rule(tactile, boxes, None, 0.5)
    assert not batched and float(p.overcome_height) == pytest.approx(boxes.height_range[1] + 0.02)
    p, _ = rule(tactile, get_terrain("slope-up"), None, 0.5)
    assert float(p.overcome_height) == pytest.approx(tactile.max_obstacle_height + 0.02)
    avoid = make_controller("avoid", lun)
    terr = sample(boxes, jax.random.PRNGKey(0), 3)
    p, batched = CONTROLLERS["avoid"].cell_params(avoid, boxes, terr, 0.5)
    assert batched and np.asarray(p.target).shape == (3, 2) and np.allclose(np.asarray(p.target)[:, 0], 0.5)
    assert np.asarray(p.valid).any()  # some box stands clear of the start and the target
    p, _ = CONTROLLERS["avoid"].cell_params(avoid, get_terrain("stairs-up"), sample(get_terrain("stairs-up"),
                                            jax.random.PRNGKey(0), 3), 0.5)
    assert not np.asarray(p.valid).any()  # a stair is ground, not an obstacle to walk round


def test_every_seed_flag_is_bounded_below_the_keys_that_alias():
    """A seed of 2**32 or more gives the PRNG key of a smaller seed (jax.random.PRNGKey keeps 32 bits of it),
    so every command's --seed stops at 2**31 - 1, leaving room for the offsets the code adds to it."""
    from hexjax.cli import main
    from hexjax.experiments.registry import commands, experiments
    entries = list(commands().values()) + list(experiments().values())
    seeds = [o for e in entries for o in e.options if o.name == "seed"]
    assert len(seeds) >= 15 and all(o.check_value(2**31 - 1) == 2**31 - 1 for o in seeds)
    for o in seeds:
        with pytest.raises(ValueError, match="must be in"):
            o.check_value(2**31)
    with pytest.raises(SystemExit):
        main(["evaluate", "--seed", "99999999999999999999"])


def test_ctrl_c_ends_a_command_at_once_in_one_line(tmp_path):
    """Ctrl-C while a command compiles: exit status 130 within 2 s, and one line on what was kept."""
    import os
    import signal
    import subprocess
    import sys
    import time
    env = dict(os.environ, HEXJAX_CACHE_DIR=str(tmp_path / "cache"))  # a compile long enough to interrupt
    # SIGINT back to its default first: a test run started in the background inherits it ignored
    start = ("import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
             "os.execv(sys.executable, [sys.executable, '-m', 'hexjax.cli', 'evaluate', '--batch', '1', "
             "'--categories', 'flat'])")
    p = subprocess.Popen([sys.executable, "-c", start], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env=env)
    header = p.stdout.readline()  # the physics line: JAX is loaded and the run has begun
    assert header.startswith("physics:"), header
    time.sleep(1.0)
    t0 = time.perf_counter()
    p.send_signal(signal.SIGINT)
    rc = p.wait(timeout=30)
    took = time.perf_counter() - t0
    out, err = p.communicate()  # reads and closes both pipes
    err = [ln for ln in err.splitlines() if ln.strip() and "%|" not in ln]
    assert rc == 130 and took < 2.0, (rc, took)
    assert err[-1] == "hexjax evaluate: interrupted; nothing of this run was kept on disk", err
    assert not any("Traceback" in ln for ln in err)


def test_no_code_outside_the_controllers_branches_on_a_controller_name():
    """What differs between controllers lives in their registry entries: no line of the package (outside
    hexjax/control/) or of scripts/ compares a string with a registered controller's name."""
    import os
    import re
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    names = "|".join(re.escape(n) for n in sorted(CONTROLLERS, key=len, reverse=True))
    lit = rf"""['"]({names})['"]"""
    compare = re.compile(rf"""(==|!=|\bin|\bnot in)\s*[(\[{{]?\s*{lit}|{lit}\s*(==|!=|\bin\b|\bnot in\b)""")
    hits = []
    for folder in ("hexjax", "scripts"):
        for dirpath, _, files in os.walk(os.path.join(root, folder)):
            if os.path.join("hexjax", "control") in dirpath:
                continue
            for f in files:
                if f.endswith(".py"):
                    path = os.path.join(dirpath, f)
                    with open(path) as fh:
                        hits += [f"{os.path.relpath(path, root)}:{i}: {ln.strip()}"
                                 for i, ln in enumerate(fh, 1) if compare.search(ln)]
    assert not hits, "\n".join(hits)
