"""Compile once per machine (hexjax.cache): where the persistent compilation cache goes, that it is told once,
that it can be turned off, and that a compiled program lands in it."""

import os
import subprocess
import sys

import pytest


def _run(code, **env):
    e = {k: v for k, v in os.environ.items() if not k.startswith("JAX_") or k == "JAX_PLATFORMS"}
    e.update(env)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180, env=e)
    assert r.returncode == 0, r.stderr[-2000:]
    return r


def test_cache_folder_is_told_once_and_receives_compiled_programs(tmp_path):
    code = ("import os, hexjax, jax, jax.numpy as jnp\n"
            "print(os.environ['JAX_COMPILATION_CACHE_DIR'])\n"
            "print(jax.jit(lambda x: jnp.sin(x) @ x.T)(jnp.ones((64, 64))).shape)")
    # a program that compiles in milliseconds is kept too (hexjax.cache keeps every program)
    first = _run(code, HEXJAX_CACHE_DIR=str(tmp_path))
    assert first.stdout.splitlines()[0] == str(tmp_path / "jax")
    assert f"compiled programs are cached in {tmp_path / 'jax'}" in first.stderr
    entries = os.listdir(tmp_path / "jax")
    assert entries, "no compiled program was written to the cache"
    second = _run(code, HEXJAX_CACHE_DIR=str(tmp_path))
    assert "compiled programs are cached" not in second.stderr  # said once, when the folder was made
    assert sorted(os.listdir(tmp_path / "jax")) == sorted(entries)  # the second run loaded, wrote nothing new


def test_cache_off_and_jax_imported_first(tmp_path):
    off = _run("import os, hexjax\nprint(os.environ.get('JAX_COMPILATION_CACHE_DIR', 'unset'))", HEXJAX_CACHE_DIR="off")
    assert off.stdout.strip() == "unset" and "cached" not in off.stderr
    # jax imported before hexjax: the cache is set through jax.config instead of the environment
    late = _run("import jax, hexjax\nprint(jax.config.jax_compilation_cache_dir)", HEXJAX_CACHE_DIR=str(tmp_path / "c"))
    assert late.stdout.strip() == str(tmp_path / "c" / "jax")


@pytest.mark.cost(60)
def test_a_compiled_rollout_is_kept_and_reloaded_by_the_next_process(tmp_path):
    """The second process neither traces nor compiles the rollout: it loads the kept program
    (hexjax.sim.compiled) and the persistent XLA cache, and gives the same numbers. (The programs folder is
    new; XLA's cache is the test session's own, so that a warm suite does not compile this rollout again.)"""
    from hexjax import cache
    xla = cache.cache_dir()
    if xla is not None:
        (xla / "jax").mkdir(parents=True, exist_ok=True)
        (tmp_path / "jax").symlink_to(xla / "jax", target_is_directory=True)
    code = ("import jax, numpy as np, hexjax\n"
            "r = hexjax.luneckas2020(); c = hexjax.GaitController(r)\n"
            "t = hexjax.sample(hexjax.get_terrain('flat'), jax.random.PRNGKey(0), 2)\n"
            "s, st = hexjax.rollout(r, t, c, c.default_params(), 0.2, jax.random.PRNGKey(1), "
            "physics=hexjax.PhysicsConfig(slots_per_leg=0, torso_slots=0), stats=True)\n"
            "print(st.compiled, round(st.compile_s, 2), repr(np.asarray(s.end_pose).tolist()))")
    first = _run(code, HEXJAX_CACHE_DIR=str(tmp_path)).stdout.split(" ", 2)
    second = _run(code, HEXJAX_CACHE_DIR=str(tmp_path)).stdout.split(" ", 2)
    assert first[0] == "compiled" and second[0] == "disk"
    assert float(second[1]) < 0.5 * float(first[1])
    assert first[2] == second[2]  # bit-identical end poses
    assert len(os.listdir(tmp_path / "programs")) == 1


def test_every_cpu_process_keeps_the_programs_it_compiles(monkeypatch):
    """In a multi-process run a process other than 0 writes the CPU programs it compiles to the cache: JAX writes
    from process 0 only, and on the CPU each process's key holds its own view of the topology, so process 1's
    entries were never written and it compiled the sweep's rollout on every run (`every_cpu_process_writes`).
    A GPU program of process 1 is still left to process 0's write."""
    import types

    from jax._src import compiler, distributed

    from hexjax import cache
    written = []
    monkeypatch.setattr(compiler.compilation_cache, "put_executable_and_time", lambda key, *a: written.append(key))
    monkeypatch.setattr(compiler, "_cache_write", compiler._cache_write)  # put back after the test
    assert cache.every_cpu_process_writes() and cache.every_cpu_process_writes()  # a second call wraps nothing more
    monkeypatch.setattr(distributed.global_state, "process_id", 1)
    for platform in ("cpu", "gpu"):
        compiler._cache_write(f"key-{platform}", 10.0, "jit_f", types.SimpleNamespace(platform=platform), None)
    assert written == ["key-cpu"] and distributed.global_state.process_id == 1


_LOWER_EVAL = """
import hashlib, jax
from hexjax.tune.config import load_tune_config
from hexjax.tune.objective import Problem
problem = Problem.build(load_tune_config("cpg_step_ditch", {"train_batch": 5}))
model, fn = problem.hard_rollout()

def module(n):
    terr = problem.terrain_batch(jax.random.PRNGKey(0), n)
    keys = jax.random.split(jax.random.PRNGKey(1), n)
    text = jax.jit(fn).lower(model, problem.eval_params0, terr, keys).as_text()
    return hashlib.sha256(text.encode()).hexdigest()
"""


@pytest.mark.cost(90)
def test_a_program_lowers_the_same_whatever_the_process_traced_before():
    """The CPG's evaluation rollout of `cpg_step_ditch` for 5 terrains lowers to another module in a process that
    traced it for 6 terrains first: jitted callees traced for the first program come back from JAX's caches with
    the inner jaxprs of that time, and the module holds different private functions. JAX's persistent cache is
    keyed by the module, so such a process compiled the program again (a tuning run's gradient program, 165 s
    on an H100). `Compiled` empties those caches before it traces (`hexjax.sim.compiled.fresh_trace`): then
    the module is the one a fresh process lowers. Without the call the assert fails (checked with jax 0.11.2:
    the module after the 6-terrain one differed from the fresh process's)."""
    from hexjax.sim.compiled import fresh_trace
    fresh = _run(_LOWER_EVAL + "print(module(5))\n", HEXJAX_CACHE_DIR="off").stdout.split()[-1]
    ns = {}
    exec(_LOWER_EVAL, ns)
    ns["module"](6)
    fresh_trace()
    assert ns["module"](5) == fresh


def test_programs_are_traced_with_rare_collections_and_the_callers_thresholds_come_back():
    """`hexjax.cache.rare_collections` raises Python's collector thresholds to `TRACE_GC_THRESHOLD` (never lowers
    one), puts the caller's back even when the block raises, and `Compiled` traces under it."""
    import gc

    import jax
    import jax.numpy as jnp
    import pytest

    from hexjax.cache import TRACE_GC_THRESHOLD, rare_collections
    from hexjax.sim.compiled import Compiled
    before = gc.get_threshold()
    seen = []
    try:
        gc.set_threshold(700, 10, 10_000)
        with pytest.raises(RuntimeError):
            with rare_collections():
                seen.append(gc.get_threshold())
                raise RuntimeError
        assert seen == [(TRACE_GC_THRESHOLD[0], TRACE_GC_THRESHOLD[1], 10_000)]
        assert gc.get_threshold() == (700, 10, 10_000)

        def f(x):
            seen.append(gc.get_threshold())  # runs while the program is traced
            return jnp.sin(x) * 2

        assert float(Compiled(jax.jit(f))(jnp.float32(0.5))) == pytest.approx(2 * 0.479425538)
        assert seen[-1][:2] == TRACE_GC_THRESHOLD[:2] and gc.get_threshold() == (700, 10, 10_000)
    finally:
        gc.set_threshold(*before)
