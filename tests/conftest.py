import os

# Two host devices so the sharded-rollout test has a real mesh to split over; set before jax loads.
# XLA:CPU's older LLVM IR fusion emitters (TEST_XLA_FLAGS' second flag) compile the suite's MJX programs in a third
# less time than its default MLIR ones: 1,346 s of compile against 1,968 s, cold runs on one day. Values agree to
# float32 rounding. hexjax itself keeps XLA's default: there the CPU gradient of `hexjax bench --grad` ran 25 %
# slower with the older emitters (docs/modelling.md, docs/benchmarks.md 2026-11-26). They also write a fused
# dynamic-update-slice's whole output, not its slice: a scan of n steps that stacks its outputs (`lax.scan`'s ys)
# costs n^2 (120 s of the Van der Pol network 15.8 s against 0.03 s), and MJX's elliptic-cone solve runs twice as
# long (the perturbed walks: 19.8 s against 9.9 s). Tests that stack thousands of steps split them into chunks
# (tests/test_vdp.py `_run`).
#
# YNNPACK's reductions: the suite runs with hexjax's own setting, the one users get (`import hexjax` adds
# `--xla_cpu_experimental_ynn_fusion_type=-reduce`; hexjax/__init__.py). Until 2026-11-27 (sixth session) it passed
# `+reduce`, XLA's default, because one chaotic outcome had been set with it (the stones family's drop in
# `test_terrain::test_families_walkable_at_zero_and_harder_with_difficulty`, whose docstring now gives the
# rates measured at 128 envs). With hexjax's setting the warm suite took 5 min 12 s against 6 min 1 s
# (docs/testing.md).
TEST_XLA_FLAGS = ("--xla_force_host_platform_device_count={devices} "
                  "--xla_backend_extra_options=xla_cpu_disable_new_fusion_emitters")
os.environ.setdefault("XLA_FLAGS", TEST_XLA_FLAGS.format(devices=2))
os.environ.setdefault("JAX_PLATFORMS", "cpu")

__import__("hexjax")  # adds hexjax's XLA flags, YNNPACK's included, before any test starts JAX
import gc  # noqa: E402

import pytest  # noqa: E402

from hexjax.cache import TRACE_GC_THRESHOLD  # noqa: E402

# Python's collector runs rarely in the whole test process, not only where `hexjax.sim.compiled` traces a kept
# program: tests also trace gradients, Brax's PPO and jitted helpers of their own. Each module ends with a
# collection of what it made (`_free_compiled_rollouts`), so nothing piles up across the run.
gc.set_threshold(*TRACE_GC_THRESHOLD)

_PEAKS = []

# The slowest tests on 2 cores with a cold cache (compile-bound), slowest first: handed out first, they
# keep the two workers busy to the end instead of leaving one of them a long test at the finish. A test of
# SHARED_FIXTURES takes its group along with it.
SLOW_FIRST = ("test_validated_mjx_meets_the_reference_on_a_paired_matrix", "test_every_backend_honours_the_same_draws", "test_cpg_gradient_matches_central_differences",
              "test_families_walkable_at_zero_and_harder_with_difficulty",
              "test_tuning_is_deterministic_and_resumes", "test_two_processes_give_the_per_env_numbers_of_one",
              "test_brax_ppo_trains", "test_gradient_matches_central_differences_per_group",
              "test_parallel_windows_give_the_scans_gradient", "test_tuner_forward_mode_gives_reverse_modes_gradient",
              "test_forward_mode_gradient_equals_reverse_mode",
              "test_converged_jacobian_matches_unrolled_and_central_differences",
              "test_es_baseline_improves", "test_smooth_rollout_tends_to_hard_rollout",
              "test_evaluate_obstacles_lose_distance",
              "test_a_program_lowers_the_same_whatever_the_process_traced_before",
              "test_sharded_rollout_matches_unsharded",
              "test_planner_steers_the_mjx_robot", "test_planned_motion_crosses_the_patch",
              "test_tripod_tetrapod_wave_walk", "test_flat_walk_straight_1m", "test_a_compiled_rollout_is_kept",
              "test_toe_forces_point_up", "test_mjx_pad_touch", "test_warp_backend_walks_like_mjx",
              "test_mujoco_c_backend_walks_like_mjx")


# Tests that share an expensive module-scoped fixture, by test function name -> the fixture. pytest-xdist hands
# each group to one worker, which runs it in one go, so the fixture is built once (handed out one test at a
# time, as the other tests are, the perturbed walks were built four times: 980 s of a cold run).
# xdist's own `xdist_group` marker has no effect with pytest 9.2 (xdist 3.8 renames `item._nodeid`, which
# pytest 9 no longer reads), hence this list and the scheduler below.
SHARED_FIXTURES = {
    "test_every_backend_honours_the_same_draws": "perturbed_walks",
    "test_same_key_gives_bit_identical_results": "perturbed_walks",
    "test_each_perturbation_does_what_it_should": "perturbed_walks",
    "test_mujoco_c_backend_walks_like_mjx": "mjx_run",
    "test_warp_backend_walks_like_mjx": "mjx_run",
    "test_converged_jacobian_matches_unrolled_and_central_differences": "standing",
    "test_forces_and_acceleration_jacobian_against_central_differences_and_unrolled": "standing",
    "test_integrator_rule_keeps_mjx_values_and_derivative": "standing",
    "test_matrix_free_rows_match_mjx_with_their_derivative": "standing",
}


def pytest_xdist_make_scheduler(config, log):
    """One test per unit of work, slowest first (the collection order), except the groups of SHARED_FIXTURES,
    each one unit; a worker holds at most about three tests it has not started."""
    from xdist.scheduler import LoadScopeScheduling

    class SharedFixtureScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid):
            name = nodeid.split("::")[-1].split("[")[0]
            return SHARED_FIXTURES.get(name, nodeid)

        def remove_node(self, node):
            """A worker left: if it crashed, the test it was running (reported as failed by xdist) and the tests
            it had not started go back in the queue, the crashed test marked done. xdist 3.8 re-queues every
            unit the worker was ever given, finished ones too; a replacement worker handed a finished unit has
            nothing to run, never reports back and is never given the rest, so the run waited at 0 % CPU until
            CI's limit. It also runs the crashed test again, up to 8 times for a crash that repeats."""
            workload = self.assigned_work.pop(node)
            pending = [nid for unit in workload.values() for nid, done in unit.items() if not done]
            if not pending:
                return None
            crashed = pending[0]  # a worker runs its tests in the order it got them
            for scope, unit in workload.items():
                if crashed in unit:
                    unit[crashed] = True
                if not all(unit.values()):
                    self.workqueue[scope] = unit
            for other in self.assigned_work:
                self._reschedule(other)
            return crashed

    return SharedFixtureScheduling(config, log)


def pytest_collection_modifyitems(items):
    def rank(item):
        hit = [i for i, name in enumerate(SLOW_FIRST) if name in item.nodeid]
        return hit[0] if hit else len(SLOW_FIRST)
    items.sort(key=rank)  # stable: the rest keep their order


# JAX's own caches are cleared after a module only when the process holds more than this much memory
_CLEAR_ABOVE_GIB = 4.0


def _rss_gib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1024 ** 3


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_rollouts():
    """Each module's compiled rollouts are dropped after it. One process compiles dozens of MJX programs;
    kept alive in `_compiled`'s cache and JAX's, they only grow the process (a full run once died with a
    segfault inside XLA's compiler late in the run; the same test passed alone). A later module that needs
    the same program again loads it from the persistent compilation cache (`hexjax.cache`).
    JAX's own caches go too, but only once the process holds more than `_CLEAR_ABOVE_GIB`: they also hold the
    small programs of eager operations (one per operation and shape), and clearing them after every module made
    each module compile its eager operations again (half of a warm run's 7,260 compiles, about 80 s of CPU).
    What survives the collection is frozen (`gc.freeze`), so the next module's collection walks only the objects
    made since. Walking every object of a worker (JAX, MJX, Brax and their caches) took 0.9 s at the first module's
    end and up to 2.5 s later: 121 s of CPU over the 76 module ends of a warm run on 2 cores, 7 s frozen. A frozen object that later becomes garbage in a cycle
    (an entry JAX's caches drop) is kept until the memory bound below unfreezes everything for a full collection."""
    yield
    import sys

    if "hexjax.sim.rollout" in sys.modules:
        sys.modules["hexjax.sim.rollout"]._compiled.cache_clear()
    gc.collect()
    if _rss_gib() > _CLEAR_ABOVE_GIB:
        import jax
        gc.unfreeze()
        jax.clear_caches()
        gc.collect()
    gc.freeze()


# Compile time per test, from JAX's monitoring events: tracing, lowering and the backend compile (or the load of
# a program the persistent cache holds), how many programs XLA compiled in a second or more (on a cold cache:
# the compiles that matter), and how many were loaded from the persistent cache. JAX reports a cache hit or miss
# just before the backend step's duration, so a slow load (a large gradient program takes up to 7 s to load on
# 2 cores) is not counted as a compile. A module-scoped fixture counts for the test that builds it. Programs
# compiled in a subprocess are not seen.
_COMPILE = {}
_CURRENT = [None]
_LISTENING = []
_LAST_CACHE_EVENT = [None]
_EVENTS = {"/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration",
           "/jax/core/compile/backend_compile_duration"}


def _listen_once():
    if _LISTENING:
        return
    _LISTENING.append(True)
    from jax import monitoring

    def duration(event, secs, **_):
        if _CURRENT[0] is None or event not in _EVENTS:
            return
        row = _COMPILE[_CURRENT[0]]
        row[0] += secs
        if event.endswith("backend_compile_duration"):
            row[1] += secs >= 1.0 and _LAST_CACHE_EVENT[0] != "hit"
            _LAST_CACHE_EVENT[0] = None

    def count(event, **_):
        if event == "/jax/compilation_cache/cache_hits":
            _LAST_CACHE_EVENT[0] = "hit"
            if _CURRENT[0] is not None:
                _COMPILE[_CURRENT[0]][2] += 1
        elif event == "/jax/compilation_cache/cache_misses":
            _LAST_CACHE_EVENT[0] = "miss"

    monitoring.register_event_duration_secs_listener(duration)
    monitoring.register_event_listener(count)


def _log_programs(path):
    """HEXJAX_TEST_COMPILE_LOG=<folder>: every traced, lowered and compiled program (jax_log_compiles), one line
    each, prefixed with the test that ran it, in <folder>/<worker>.log: which test compiles which program."""
    import logging

    import jax
    jax.config.update("jax_log_compiles", True)
    os.makedirs(path, exist_ok=True)
    handler = logging.FileHandler(os.path.join(path, os.environ.get("PYTEST_XDIST_WORKER", "main") + ".log"))

    class WithTest(logging.Filter):
        def filter(self, record):
            record.test = _CURRENT[0] or "-"
            return True

    handler.addFilter(WithTest())
    handler.setFormatter(logging.Formatter("%(created).1f\t%(test)s\t%(message).400s"))
    for name in ("jax._src.dispatch", "jax._src.interpreters.pxla", "jax._src.compiler"):
        logging.getLogger(name).addHandler(handler)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    if not _LISTENING and os.environ.get("HEXJAX_TEST_COMPILE_LOG"):
        _log_programs(os.environ["HEXJAX_TEST_COMPILE_LOG"])
    _listen_once()
    _CURRENT[0] = item.nodeid
    _COMPILE.setdefault(item.nodeid, [0.0, 0, 0])
    yield
    _CURRENT[0] = None


def _peak_gib() -> float:
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2


def pytest_sessionfinish(session):
    if hasattr(session.config, "workeroutput"):  # a pytest-xdist worker: report to the controller
        session.config.workeroutput["peak_rss_gib"] = _peak_gib()
        session.config.workeroutput["compile"] = _COMPILE


_WORKER_COMPILE = {}


def pytest_testnodedown(node, error):
    out = node.workeroutput if hasattr(node, "workeroutput") else {}
    _PEAKS.append(out.get("peak_rss_gib", 0.0))
    _WORKER_COMPILE.update(out.get("compile", {}))


def pytest_terminal_summary(terminalreporter):
    peaks = _PEAKS or [_peak_gib()]
    terminalreporter.write_line("peak resident memory per test process: " + ", ".join(f"{p:.1f} GiB" for p in peaks))
    comp = _WORKER_COMPILE or _COMPILE
    if comp:
        total = sum(v[0] for v in comp.values())
        missed, loaded = sum(v[1] for v in comp.values()), sum(v[2] for v in comp.values())
        terminalreporter.write_line(
            f"JAX compile (trace + lower + compile or cache load) {total:.0f} s in all; {missed} programs were "
            f"compiled in >= 1 s, {loaded} were loaded from the cache; the most per test:")
        for nodeid, (secs, miss, hit) in sorted(comp.items(), key=lambda kv: -kv[1][0])[:15]:
            if secs < 0.05:
                break
            terminalreporter.write_line(f"  {secs:7.1f} s  {miss:3d} compiled {hit:3d} loaded  {nodeid}")
