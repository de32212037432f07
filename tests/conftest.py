import os

# Two host devices so the sharded-rollout test has a real mesh to split over; set before jax loads.
os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
os.environ.setdefault("JAX_PLATFORMS", "cpu")


import pytest  # noqa: E402

_PEAKS = []


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_rollouts():
    """Each module's compiled rollouts are dropped after it. One process compiles dozens of MJX programs;
    kept alive in `_compiled`'s cache and JAX's, they only grow the process (a full run once died with a
    segfault inside XLA's compiler late in the run; the same test passed alone). A later module that needs
    the same program again loads it from the persistent compilation cache (`hexjax.cache`)."""
    yield
    import sys

    import jax
    if "hexjax.sim.rollout" in sys.modules:
        sys.modules["hexjax.sim.rollout"]._compiled.cache_clear()
    jax.clear_caches()


def _peak_gib() -> float:
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2


def pytest_sessionfinish(session):
    if hasattr(session.config, "workeroutput"):  # a pytest-xdist worker: report to the controller
        session.config.workeroutput["peak_rss_gib"] = _peak_gib()


def pytest_testnodedown(node, error):
    _PEAKS.append(node.workeroutput.get("peak_rss_gib", 0.0) if hasattr(node, "workeroutput") else 0.0)


def pytest_terminal_summary(terminalreporter):
    peaks = _PEAKS or [_peak_gib()]
    terminalreporter.write_line("peak resident memory per test process: " + ", ".join(f"{p:.1f} GiB" for p in peaks))
