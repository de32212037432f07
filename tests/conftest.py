import os

# Two host devices so the sharded-rollout test has a real mesh to split over; set before jax loads.
os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
os.environ.setdefault("JAX_PLATFORMS", "cpu")


import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_rollouts():
    """Each module's compiled rollouts are dropped after it. One pytest process compiles ~100 MJX programs;
    kept alive in `_compiled`'s cache and JAX's, they only grow the process (a full run once died with a
    segfault inside XLA's compiler late in the run; the same test passed alone)."""
    yield
    import jax

    from hexjax.sim import rollout
    rollout._compiled.cache_clear()
    jax.clear_caches()


def pytest_terminal_summary(terminalreporter):
    import resource
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2
    terminalreporter.write_line(f"peak resident memory of the test process: {rss:.1f} GiB")
