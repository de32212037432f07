"""jaxlib's CPU runtime under concurrent batched LAPACK calls: with jaxlib 0.10.x (hexjax's pin until the sixth
session of issue 19) they could wait on each other forever on a machine with few cores; the pinned jaxlib must
not (hexjax/__init__.py)."""

import os
import subprocess
import sys

import pytest

# four independent batched Cholesky factorisations in one program: XLA:CPU may run them at once, and jaxlib
# 0.10.x split each batch over the intra-op pool and blocked until its parts were done; with the default pool of
# a 2-core machine this program hung in its first call (docs/benchmarks.md, issue 19, fifth session)
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
