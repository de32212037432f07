"""hexjax reaches into MJX's, Warp's and JAX's private modules in a few files (`hexjax.private_reach`); a new
release of one of them may change those modules silently. These fail loudly, naming the files to re-read."""
import os
import re
from importlib import metadata

import pytest

from hexjax.private_reach import PRIVATE, USERS, WRITTEN_FOR

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.parametrize("package", sorted(WRITTEN_FOR))
def test_the_installed_package_is_the_one_the_private_reaches_were_written_for(package):
    try:
        have = metadata.version(package)
    except metadata.PackageNotFoundError:
        pytest.skip(f"{package} is not installed")
    assert have == WRITTEN_FOR[package], (
        f"{package} {have} is installed, but {', '.join(USERS[package])} reach into its private modules as of "
        f"{WRITTEN_FOR[package]}: re-read them against {have}'s sources (and the tests that check each rule), "
        "then update hexjax/private_reach.py")


def test_every_file_that_reaches_into_a_private_module_is_listed():
    found = {p: set() for p in PRIVATE}
    for folder, _, files in os.walk(os.path.join(ROOT, "hexjax")):
        for f in files:
            if not f.endswith(".py") or f == "private_reach.py":
                continue
            path = os.path.relpath(os.path.join(folder, f), ROOT)
            code = "\n".join(ln for ln in open(os.path.join(ROOT, path)).read().splitlines()
                             if not ln.lstrip().startswith("#"))
            for package, prefixes in PRIVATE.items():
                if any(re.search(r"\b" + re.escape(px) + r"\b", code) for px in prefixes):
                    found[package].add(path)
    for package in PRIVATE:
        assert found[package] == set(USERS[package]), (
            f"{package}: files reaching into its private modules {sorted(found[package])}, listed in "
            f"hexjax/private_reach.py {sorted(USERS[package])}")


def test_mjx_internals_are_reached_from_one_package_only():
    """Every file that patches or reads MJX's private modules is in hexjax/sim/internals/, and the solve of every
    MJX-family rollout (`hexjax.sim.engines.mjx`) and of the windowed gradient is traced under its one context
    (`solver_context`)."""
    outside = [p for p in USERS["mujoco-mjx"] if not p.startswith("hexjax/sim/internals/")]
    assert not outside, f"reach into MJX's private modules from outside hexjax/sim/internals/: {outside}"
    from hexjax.sim import internals, windows
    from hexjax.sim.engines import mjx
    assert mjx.solver_context is internals.solver_context is windows.solver_context
