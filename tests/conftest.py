import os

# Two host devices so the sharded-rollout test has a real mesh to split over; set before jax loads.
os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
os.environ.setdefault("JAX_PLATFORMS", "cpu")


import pytest  # noqa: E402

_PEAKS = []

# The slowest tests on 2 cores with a cold cache (compile-bound), slowest first: handed out first, they
# keep the two workers busy to the end instead of leaving one of them a long test at the finish.
SLOW_FIRST = ("test_cpg_gradient_matches_central_differences", "test_families_walkable_at_zero_and_harder_with_difficulty",
              "test_tuning_is_deterministic_and_resumes", "test_two_processes_give_the_per_env_numbers_of_one",
              "test_brax_ppo_trains", "test_gradient_matches_central_differences_per_group",
              "test_es_baseline_improves", "test_smooth_rollout_tends_to_hard_rollout",
              "test_evaluate_obstacles_lose_distance", "test_sharded_rollout_matches_unsharded",
              "test_planner_steers_the_mjx_robot", "test_planned_motion_crosses_the_patch",
              "test_tripod_tetrapod_wave_walk", "test_flat_walk_straight_1m", "test_a_compiled_rollout_is_kept",
              "test_toe_forces_point_up", "test_mjx_pad_touch", "test_warp_backend_walks_like_mjx",
              "test_mujoco_c_backend_walks_like_mjx")


def pytest_collection_modifyitems(items):
    def rank(item):
        hit = [i for i, name in enumerate(SLOW_FIRST) if name in item.nodeid]
        return hit[0] if hit else len(SLOW_FIRST)
    items.sort(key=rank)  # stable: the rest keep their order


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
