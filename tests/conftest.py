import os

# Two host devices so the sharded-rollout test has a real mesh to split over; set before jax loads.
# XLA:CPU's older LLVM IR fusion emitters (TEST_XLA_FLAGS' second flag) compile the suite's MJX programs in a third
# less time than its default MLIR ones: 1,346 s of compile against 1,968 s, cold runs on one day. Values agree to
# float32 rounding. hexjax itself keeps XLA's default: there the CPU gradient of `hexjax bench --grad` ran 25 %
# slower with the older emitters (docs/modelling.md). They also write a fused
# dynamic-update-slice's whole output, not its slice: a scan of n steps that stacks its outputs (`lax.scan`'s ys)
# costs n^2 (120 s of the Van der Pol network 15.8 s against 0.03 s), and MJX's elliptic-cone solve runs twice as
# long (the perturbed walks: 19.8 s against 9.9 s). Tests that stack thousands of steps split them into chunks
# (tests/test_vdp.py `_run`).
#
# The three checks that walk longest on the elliptic cone, the terrain families', the fidelity matrix's and
# `evaluate` on obstacles, run their command in a process of its own with XLA's default flags, as a user runs it
# (tests/test_terrain.py, tests/test_fidelity.py, tests/test_cli.py): there the solve runs 2-3.4x faster and the
# compile of one program costs little more.
#
# YNNPACK's reductions: the suite runs with hexjax's own setting, the one users get (`import hexjax` adds
# `--xla_cpu_experimental_ynn_fusion_type=-reduce`; hexjax/__init__.py); the warm suite took 5 min 12 s with
# it against 6 min 1 s with XLA's `+reduce` (docs/testing.md).
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

@pytest.fixture
def default_xla_env():
    """The environment for a child process that runs a command as a user runs it: XLA's default flags, not the
    suite's (`TEST_XLA_FLAGS`)."""
    return {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}


_PEAKS = []

# The order and grouping of the tests, from marks on the tests themselves (nothing here names a test):
# - `@pytest.mark.cost(seconds)`: about how long the test takes on 2 cores from a cold cache, compile included.
#   Tests are handed out costliest first, one at a time, so neither worker is left alone with a long test at the
#   end (xdist's default hands each worker a block of consecutive tests: one worker got every slow one, 27 min
#   against 19). Unmarked tests follow in collection order.
# - A test class is one unit of work: its tests go to one worker together, so a module fixture they share (the
#   perturbed walks of tests/test_randomization.py, say) is built once. xdist's own `xdist_group` mark does not
#   group with pytest 9.2 (xdist 3.8 renames `item._nodeid`, which pytest 9 no longer reads).

def pytest_configure(config):
    config.addinivalue_line("markers", "cost(seconds): about how long the test takes on 2 cores from a cold cache "
                                       "(compile included); the costliest are handed out first")


def _scope(nodeid):
    """The unit of work a test belongs to: its class, or the test itself."""
    parts = nodeid.split("::")
    return "::".join(parts[:2]) if len(parts) > 2 else nodeid


def pytest_collection_modifyitems(items):
    cost = {}
    for item in items:
        mark = item.get_closest_marker("cost")
        scope = _scope(item.nodeid)
        cost[scope] = max(cost.get(scope, 0.0), float(mark.args[0]) if mark else 0.0)
    items.sort(key=lambda item: -cost[_scope(item.nodeid)])  # stable: a class stays together, the rest in order


def pytest_xdist_make_scheduler(config, log):
    return CostFirstScheduling(config, log)


class CostFirstScheduling:
    """A pytest-xdist scheduler (its `Scheduling` protocol, xdist/scheduler/protocol.py): the collection's units
    of work (a class, or one test) handed out in collection order (costliest first, above), a unit at a time, each
    worker kept at two or more tests it has not finished (a worker runs a test once it knows the next one, or has
    been told to stop). A worker that crashes fails the test it was running; the tests it had not started go back
    to the front of the queue. (xdist 3.8's own load-scope scheduler re-queued every unit the crashed worker was
    ever given, finished ones too: the replacement worker was handed work with nothing left to run and the run
    waited until CI's limit; tests/test_runtime.py.)"""

    def __init__(self, config, log):
        from xdist.workermanage import parse_tx_spec_config
        self.numnodes = len(parse_tx_spec_config(config))
        self.log = log
        self.collections = {}  # every worker's collection, the ones that left included
        self.collection = None
        self.pending = {}  # worker -> the collection indices it was given and has not finished, in order
        self.queue = []  # units of work not handed out: lists of collection indices

    @property
    def nodes(self):
        return list(self.pending)

    @property
    def collection_is_completed(self):
        return len(self.collections) >= self.numnodes

    @property
    def tests_finished(self):
        return (self.collection_is_completed and not self.queue
                and all(len(p) < 2 for p in self.pending.values()))

    @property
    def has_pending(self):
        return bool(self.queue) or any(self.pending.values())

    def add_node(self, node):
        self.pending[node] = []

    def add_node_collection(self, node, collection):
        if self.collection is not None and list(collection) != self.collection:
            self.log(f"worker {node.gateway.id} collected other tests than the first worker; it gets none")
            return
        self.collections[node] = list(collection)

    def schedule(self):
        if self.collection is None:
            first, *others = self.collections.values()
            if any(c != first for c in others):
                self.log("the workers collected different tests: nothing is run")
                return
            self.collection = first
            units = {}
            for i, nodeid in enumerate(first):
                units.setdefault(_scope(nodeid), []).append(i)
            self.queue = list(units.values())
        for node in self.nodes:
            self._top_up(node)

    def _top_up(self, node):
        if node.shutting_down or node not in self.collections:
            return
        while self.queue and len(self.pending[node]) < 2:
            unit = self.queue.pop(0)
            self.pending[node].extend(unit)
            node.send_runtest_some(unit)
        if not self.queue:
            node.shutdown()

    def mark_test_complete(self, node, item_index, duration=0):
        self.pending[node].remove(item_index)
        self._top_up(node)

    def mark_test_pending(self, item):
        self.queue.insert(0, [self.collection.index(item)])
        for node in self.nodes:
            self._top_up(node)

    def remove_pending_tests_from_node(self, node, indices):
        raise NotImplementedError("work stealing is not used")

    def remove_node(self, node):
        pending = self.pending.pop(node)  # its collection stays counted: replacements are not waited for
        if not pending:
            return None
        crashed, rest = pending[0], pending[1:]  # a worker runs its tests in the order it got them
        if rest:
            self.queue.insert(0, rest)
        for other in self.nodes:
            self._top_up(other)
        return self.collection[crashed]


# JAX's own caches are cleared after a module only when the process holds more than this much memory
_CLEAR_ABOVE_GIB = 4.0


def _rss_gib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1024 ** 3


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_rollouts():
    """Each module's compiled rollouts are dropped after it. One process compiles dozens of MJX programs;
    kept alive in `compiled_rollout`'s cache and JAX's, they only grow the process (a full run once died with a
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
        sys.modules["hexjax.sim.engines.mjx"].compiled_rollout.cache_clear()
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
