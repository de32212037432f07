"""What `import hexjax` sets up for jaxlib's CPU runtime before JAX starts (hexjax/__init__.py): a thread pool
large enough that concurrent batched LAPACK calls cannot wait on each other forever."""

import os
import subprocess
import sys
from importlib.metadata import version

import pytest

import hexjax

# four independent batched Cholesky factorisations in one program: XLA:CPU may run them at once, and jaxlib
# 0.10.x splits each batch over the intra-op pool and blocks until its parts are done; with the default pool of
# a 2-core machine this program hung in its first call (docs/benchmarks.md, issue 19, fifth session)
_CONCURRENT_CHOLESKY = """
import os, hexjax, jax, jax.numpy as jnp, numpy as np
a = np.random.default_rng(0).normal(size=(4, 256, 24, 24)).astype(np.float32)
h = a @ a.transpose(0, 1, 3, 2) + 24 * np.eye(24, dtype=np.float32)
f = jax.jit(lambda h: [jnp.linalg.cholesky(h[i] * (i + 1)) for i in range(4)])
for _ in range(20):
    out = jax.block_until_ready(f(h))
ref = np.linalg.cholesky(h[2].astype(np.float64) * 3)
print(os.environ.get("PJRT_NPROC"), float(np.abs(np.asarray(out[2]) - ref).max()))
"""


def test_concurrent_batched_lapack_calls_finish():
    env = {k: v for k, v in os.environ.items() if k not in ("PJRT_NPROC", "NPROC")}
    env["HEXJAX_CACHE_DIR"] = "off"
    try:
        r = subprocess.run([sys.executable, "-c", _CONCURRENT_CHOLESKY], capture_output=True, text=True, timeout=150,
                           env=env)
    except subprocess.TimeoutExpired:
        pytest.fail("four concurrent batched Cholesky calls did not finish in 150 s (the LAPACK pool deadlock)")
    assert r.returncode == 0, r.stderr[-2000:]
    pool, err = r.stdout.split()
    assert pool == hexjax._lapack_pool_threads({})
    assert float(err) < 1e-3  # the factors are right, not only returned


def test_pool_size_rules():
    assert hexjax._lapack_pool_threads({"PJRT_NPROC": "3"}) is None  # the user's choice stands
    assert hexjax._lapack_pool_threads({"NPROC": "3"}) is None
    affected = (0, 10, 0) <= tuple(int(v) for v in version("jaxlib").split(".")[:3]) < (0, 11, 1)
    size = hexjax._lapack_pool_threads({})
    if affected:
        assert int(size) >= 16 and int(size) >= len(os.sched_getaffinity(0))
    else:
        assert size is None
