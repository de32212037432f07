"""jaxlib's CPU runtime under concurrent batched LAPACK calls: with jaxlib 0.10.x (hexjax's pin until the sixth
session of issue 19) they could wait on each other forever on a machine with few cores; the pinned jaxlib must
not (hexjax/__init__.py). The XLA:CPU flag that `import hexjax` sets. The test scheduler survives a crashed
worker."""

import os
import subprocess
import sys

import pytest

# four independent batched Cholesky factorisations in one program: XLA:CPU may run them at once, and jaxlib
# 0.10.x split each batch over the intra-op pool and blocked until its parts were done; with the default pool of
# a 2-core machine this program hung in its first call
_CONCURRENT_CHOLESKY = """
import hexjax, jax, jax.numpy as jnp, numpy as np
a = np.random.default_rng(0).normal(size=(4, 256, 24, 24)).astype(np.float32)
h = a @ a.transpose(0, 1, 3, 2) + 24 * np.eye(24, dtype=np.float32)
f = jax.jit(lambda h: [jnp.linalg.cholesky(h[i] * (i + 1)) for i in range(4)])
for _ in range(20):
    out = jax.block_until_ready(f(h))
ref = np.linalg.cholesky(h[2].astype(np.float64) * 3)
print(float(np.abs(np.asarray(out[2]) - ref).max()))
"""


def test_concurrent_batched_lapack_calls_finish():
    # jaxlib's own pool size (one thread per core), as a user's process gets it
    env = {k: v for k, v in os.environ.items() if k not in ("PJRT_NPROC", "NPROC")}
    env["HEXJAX_CACHE_DIR"] = "off"
    try:
        r = subprocess.run([sys.executable, "-c", _CONCURRENT_CHOLESKY], capture_output=True, text=True, timeout=150,
                           env=env)
    except subprocess.TimeoutExpired:
        pytest.fail("four concurrent batched Cholesky calls did not finish in 150 s (the LAPACK pool deadlock)")
    assert r.returncode == 0, r.stderr[-2000:]
    assert float(r.stdout.split()[-1]) < 1e-3  # the factors are right, not only returned


_FLAGS = "import os, hexjax; print(os.environ.get('XLA_FLAGS', ''))"


_SCHED = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
_YNN = "--xla_cpu_experimental_ynn_fusion_type=-reduce"


@pytest.mark.parametrize("given,keep,expect", [
    ("", "", [_SCHED, _YNN]),
    ("--xla_force_host_platform_device_count=2", "", ["--xla_force_host_platform_device_count=2", _SCHED, _YNN]),
    ("--xla_cpu_enable_concurrency_optimized_scheduler=true", "",
     ["--xla_cpu_enable_concurrency_optimized_scheduler=true", _YNN]),
    ("--xla_cpu_experimental_ynn_fusion_type=-dot", "", ["--xla_cpu_experimental_ynn_fusion_type=-dot", _SCHED]),
    ("--xla_force_host_platform_device_count=2", "1", ["--xla_force_host_platform_device_count=2"]),
])
def test_import_adds_its_xla_flags_unless_told_not_to(given, keep, expect):
    """`import hexjax` adds its XLA:CPU settings (the scheduler, YNNPACK's reductions off; hexjax/__init__.py,
    docs/modelling.md) to the user's XLA_FLAGS, keeps a user's own choice of either, and leaves XLA_FLAGS alone
    with HEXJAX_KEEP_XLA_FLAGS=1."""
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "HEXJAX_KEEP_XLA_FLAGS")}
    env.update(XLA_FLAGS=given, HEXJAX_CACHE_DIR="off")
    if keep:
        env["HEXJAX_KEEP_XLA_FLAGS"] = keep
    r = subprocess.run([sys.executable, "-c", _FLAGS], capture_output=True, text=True, timeout=60, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(r.stdout.split()) == sorted(expect)


# A toy suite run under tests/conftest.py's scheduler with two workers, in which two tests kill their worker: the
# first test of a class (a unit the scheduler hands out whole) and the last quick test; the costliest test is
# marked so, and handed out first.
_CRASHING_SUITE = '''
import os, time

import pytest

def _crash_once(name):
    mark = os.path.join(os.environ["CRASH_DIR"], name)
    if not os.path.exists(mark):
        open(mark, "w").close()
        os.abort()

class TestGroup:
    def test_first(self):
        _crash_once("group")

    def test_second(self):
        time.sleep(0.2)

@pytest.mark.cost(3)
def test_slow():
    time.sleep(3)

def test_quick_0():
    time.sleep(0.3)

def test_quick_1():
    time.sleep(0.3)

def test_quick_2():
    time.sleep(0.3)

def test_quick_3():
    time.sleep(0.3)
    _crash_once("last")
'''


def test_a_crashed_worker_fails_its_test_and_the_run_goes_on(tmp_path):
    """A test that kills its worker (a segfault in XLA, say) fails, and every other test runs once and the run
    ends: with xdist 3.8's own bookkeeping the replacement worker was handed finished work and the run waited
    forever (tests/conftest.py, `remove_node`)."""
    import shutil
    shutil.copy(os.path.join(os.path.dirname(__file__), "conftest.py"), tmp_path / "conftest.py")
    (tmp_path / "test_toy.py").write_text(_CRASHING_SUITE)
    (tmp_path / "marks").mkdir()
    env = dict(os.environ, CRASH_DIR=str(tmp_path / "marks"))
    try:
        r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rA", "-n", "2", "-p", "no:cacheprovider",
                            "test_toy.py"], cwd=tmp_path, capture_output=True, text=True, timeout=120, env=env)
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"the run did not end in 120 s after a worker crashed:\n{(e.stdout or b'')[-2000:]}")
    out = r.stdout
    assert r.returncode == 1, out[-3000:]
    assert sorted(os.listdir(tmp_path / "marks")) == ["group", "last"], out[-3000:]  # both crashes happened
    for name in ("TestGroup::test_first", "test_quick_3"):
        assert out.count(f"FAILED test_toy.py::{name}") == 1 and f"crashed while running 'test_toy.py::{name}'" in out
    for name in ("TestGroup::test_second", "test_slow", "test_quick_0", "test_quick_1", "test_quick_2"):
        assert out.count(f"PASSED test_toy.py::{name}") == 1, (name, out[-3000:])
    assert "2 failed, 5 passed" in out, out[-3000:]


def test_the_costliest_test_goes_first_and_a_class_to_one_worker(tmp_path):
    """The toy suite without its crashes: `cost`-marked tests are collected first, the rest keep their order and a
    class's tests stay together; run on two workers, the class's tests run on one of them."""
    import re
    import shutil
    shutil.copy(os.path.join(os.path.dirname(__file__), "conftest.py"), tmp_path / "conftest.py")
    (tmp_path / "test_toy.py").write_text(_CRASHING_SUITE)
    (tmp_path / "marks").mkdir()
    for name in ("group", "last"):
        (tmp_path / "marks" / name).touch()  # crashed already: nothing crashes now
    env = dict(os.environ, CRASH_DIR=str(tmp_path / "marks"))
    run = lambda *a: subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", *a, "test_toy.py"],
                                    cwd=tmp_path, capture_output=True, text=True, timeout=120, env=env).stdout
    order = [line for line in run("--collect-only", "-q").splitlines() if line.startswith("test_toy.py::")]
    assert [o.split("::", 1)[1] for o in order] == ["test_slow", "TestGroup::test_first", "TestGroup::test_second",
                                                    "test_quick_0", "test_quick_1", "test_quick_2", "test_quick_3"]
    out = run("-v", "-n", "2")
    worker = dict((name, gw) for gw, name in re.findall(r"\[(gw\d)\] \[ *\d+%\] PASSED test_toy.py::(\S+)", out))
    assert len(worker) == 7 and worker["TestGroup::test_first"] == worker["TestGroup::test_second"], out[-3000:]
