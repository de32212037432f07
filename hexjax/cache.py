"""Compile once per machine: JAX's persistent compilation cache, on by default for the library and the CLI.

A rollout's XLA compile costs 20-50 s on 2 CPU cores and 50-185 s on a GPU; with the cache a later process
loads the executable instead (docs/benchmarks.md has the figures). Where it lives:

    HEXJAX_CACHE_DIR unset      $XDG_CACHE_HOME/hexjax (default ~/.cache/hexjax)
    HEXJAX_CACHE_DIR=/some/dir  there
    HEXJAX_CACHE_DIR=off        no cache (also: 0, false, no)

`enable()` runs when `hexjax` is imported. It sets JAX's options through their environment variables when
JAX is not imported yet (so nothing of JAX loads for `hexjax --help`), or through `jax.config` when it is;
options the user set already are left alone. The first time a cache folder is made it says where, once.

A cold compile also pays for tracing, which is Python: `rare_collections` keeps Python's garbage collector
from sweeping the growing heap over and over while a large program is traced (`hexjax.sim.compiled` uses it).
"""

from __future__ import annotations

import contextlib
import gc
import os
import sys
from pathlib import Path
from typing import Optional

ENV = "HEXJAX_CACHE_DIR"
OFF = ("off", "0", "false", "no", "none")
# JAX's own options (and their environment variables): where, and which programs are worth keeping. Every
# program is kept, however quick its compile: a process also compiles hundreds of small programs of eager
# operations (model building, terrain sampling, metrics; about 4,500 in a warm run of the test suite, 15-20 ms
# each on 2 cores), and loading them costs less than compiling them. Measured on 2 cores, six test modules warm
# (65 tests, pytest -n 2): 49-54 s keeping every program against 70-71 s keeping those of >= 0.5 s; ~2,000
# more entries, 9 MB.
_OPTIONS = {"jax_persistent_cache_min_compile_time_secs": 0.0, "jax_persistent_cache_min_entry_size_bytes": 0}


def switched_off(name: str) -> bool:
    """Whether environment variable `name` holds one of the `OFF` words (any case, spaces around ignored)."""
    return os.environ.get(name, "").strip().lower() in OFF


def cache_dir() -> Optional[Path]:
    """The cache folder the environment asks for, or None when it is turned off."""
    if switched_off(ENV):
        return None
    v = os.environ.get(ENV, "").strip()
    if v:
        return Path(v).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "hexjax"


def enable(quiet: bool = False) -> Optional[Path]:
    """Point JAX's persistent compilation cache at `cache_dir()/jax` (see the module docstring); returns the
    folder, or None when off or when it cannot be made."""
    d = cache_dir()
    if d is None:
        return None
    xla = d / "jax"
    new = not xla.exists()
    try:
        xla.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        if not quiet:
            print(f"hexjax: no compilation cache ({ENV}={d}: {err.strerror})", file=sys.stderr)
        return None
    values = dict(_OPTIONS, jax_compilation_cache_dir=str(xla))
    if "jax" in sys.modules:
        import jax
        own = jax.config.jax_compilation_cache_dir
        if own:
            return Path(own)  # the user's own cache wins
        for k, v in values.items():
            jax.config.update(k, v)
    else:
        for k, v in values.items():
            os.environ.setdefault(k.upper(), str(v))
    if new and not quiet:
        print(f"hexjax: compiled programs are cached in {xla} (set {ENV} to move it, {ENV}=off to turn it off)",
              file=sys.stderr)
    return xla


def every_cpu_process_writes() -> bool:
    """In a multi-process run (`jax.distributed`), let every process keep the CPU programs it compiles.

    JAX writes persistent-cache entries from process 0 only (so that processes do not contend for one file on a
    shared file system). On XLA:CPU a program's cache key includes the topology as the process sees it, so the
    key of process k > 0 differs from process 0's: nobody writes it, and process k compiles every program again
    on every run (the 2-process robustness sweep's rollout: 16 s on 2 cores, while process 0, which loads its own
    entry in 1 s, waits for it at the first collective). Each process's key is its own, so its writes contend
    with no one. Returns False where JAX's internals for this have moved (then nothing changes)."""
    try:
        from jax._src import compiler, distributed
        write = compiler._cache_write
        if getattr(write, "_hexjax_every_process", False):
            return True

        def cache_write(cache_key, compile_time_secs, module_name, backend, executable):
            pid = distributed.global_state.process_id
            if pid == 0 or getattr(backend, "platform", "") != "cpu":
                return write(cache_key, compile_time_secs, module_name, backend, executable)
            distributed.global_state.process_id = 0  # JAX's own check, for this write only
            try:
                return write(cache_key, compile_time_secs, module_name, backend, executable)
            finally:
                distributed.global_state.process_id = pid

        cache_write._hexjax_every_process = True
        compiler._cache_write = cache_write
        return True
    except (ImportError, AttributeError):
        return False


# Python's garbage-collector thresholds while a program is traced and lowered (`rare_collections`). A trace builds
# millions of objects that live until it ends (jaxpr equations, tracers, MLIR ops), so under Python's defaults
# (700, 10, 10) the collector runs full collections over a growing heap again and again: 9 of them while the
# tactile gradient program (8 envs) is traced, none with these thresholds. Measured on 2 cores, fresh processes,
# tracing and lowering that program: 26.1-26.3 s at the defaults (two runs), 19.1-21.9 s with these (four), the
# same module (its hash equal); the forward program 8.0-8.6 s against 7.4-8.6 s; peak memory 924 and 926 MB. In
# the test suite's long-lived workers the gain is about half that.
TRACE_GC_THRESHOLD = (100_000, 50, 1_000)


@contextlib.contextmanager
def rare_collections():
    """Raise Python's garbage-collector thresholds to at least `TRACE_GC_THRESHOLD` while the block runs (tracing
    and lowering a large program), then put the caller's back. Objects still in reach are unaffected; cyclic
    garbage made inside the block is freed by a later collection."""
    old = gc.get_threshold()
    gc.set_threshold(*(max(a, b) for a, b in zip(old, TRACE_GC_THRESHOLD)))
    try:
        yield
    finally:
        gc.set_threshold(*old)
