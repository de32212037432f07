"""`hexjax bench --profile`'s trace reader (`hexjax.experiments.commands.profile`) on hand-made traces: device kernels
summed by name, the host's XLA threads read where no device is, and the one-line error where no trace is."""

import gzip
import json

import pytest

from hexjax.experiments.commands.profile import kernel_table


def _trace(path, events):
    path.mkdir(parents=True, exist_ok=True)
    with gzip.open(path / "perfetto_trace.json.gz", "wt", encoding="utf-8") as f:
        json.dump({"traceEvents": events}, f)


def _meta(pid, name, tid=None):
    e = {"ph": "M", "pid": pid, "name": "thread_name" if tid is not None else "process_name", "args": {"name": name}}
    return dict(e, tid=tid) if tid is not None else e


def test_device_kernels_are_summed_by_name_and_the_host_is_left_out(tmp_path):
    ev = [_meta(1, "/host:CPU"), _meta(2, "/device:GPU:0"), _meta(1, "python", tid=7), _meta(2, "stream 3", tid=3),
          {"ph": "X", "pid": 2, "tid": 3, "name": "solve_kernel", "dur": 3000.0},
          {"ph": "X", "pid": 2, "tid": 3, "name": "solve_kernel", "dur": 1000.0},
          {"ph": "X", "pid": 2, "tid": 3, "name": "collide_kernel", "dur": 1000.0},
          {"ph": "X", "pid": 1, "tid": 7, "name": "PjitFunction(rollout)", "dur": 9e6}]
    _trace(tmp_path / "plugins" / "profile" / "run", ev)
    t = kernel_table(str(tmp_path))
    assert t["where"] == "/device:GPU:0" and t["events_ms"] == 5.0
    assert [(r["name"], r["ms"], r["calls"], r["share"]) for r in t["rows"]] == [
        ("solve_kernel", 4.0, 2, 0.8), ("collide_kernel", 1.0, 1, 0.2)]


def test_without_a_device_the_xla_threads_are_read(tmp_path):
    ev = [_meta(1, "/host:CPU"), _meta(1, "python", tid=7), _meta(1, "tf_XLAEigen/1", tid=8),
          {"ph": "X", "pid": 1, "tid": 8, "name": "ynn_fusion", "dur": 2000.0},
          {"ph": "X", "pid": 1, "tid": 7, "name": "$bench.py:141 <lambda>", "dur": 5000.0}]
    _trace(tmp_path, ev)
    t = kernel_table(str(tmp_path), top=1)
    assert t["where"] == "the host's XLA threads" and [r["name"] for r in t["rows"]] == ["ynn_fusion"]


def test_a_folder_without_a_trace_is_one_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no perfetto_trace.json.gz"):
        kernel_table(str(tmp_path))


def test_bench_grad_reads_a_programs_memory_whether_compiled_or_loaded(tmp_path, monkeypatch):
    """`hexjax bench --grad`'s memory column: XLA's analysis of the kept program, the same figure whether the
    program was just compiled or loaded from disk, and at least its arguments and result."""
    import jax
    import jax.numpy as jnp

    from hexjax.sim.compiled import Compiled
    monkeypatch.setenv("HEXJAX_CACHE_DIR", str(tmp_path))
    x = jnp.ones((128, 256))
    sizes = []
    for _ in range(2):  # compiled, then loaded
        p = Compiled(jax.jit(lambda a: a @ a.T), static=("test/memory",))
        p.call(x)
        sizes.append(p.memory_bytes())
    assert sizes[0] == sizes[1] >= x.nbytes + 128 * 128 * 4
