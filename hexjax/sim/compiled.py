"""Ahead-of-time compiled rollouts: one executable per input signature, with the seconds its compile took,
kept on disk so that a later process neither traces nor lowers it again.

Compiling a rollout costs 20-50 s on 2 CPU cores and 50-185 s on a GPU; JAX's persistent compilation cache
(`hexjax.cache`) skips XLA's part in a later process, but tracing and lowering the MJX step still take
~7-10 s on 2 cores. So `Compiled` also keeps the traced program (`Compiled` below) under `<cache>/programs/`,
named by a hash of everything that shapes it: the static settings (robot, physics, sensors, controller,
rollout config, step count), the input signature (shapes, dtypes, shardings), the source of hexjax and of
the controller's module, the versions of jax, jaxlib, mujoco and mujoco-mjx, the XLA flags and the devices.
A file that does not load is compiled afresh and replaced.

A program is traced from empty tracing caches (`fresh_trace`), so that the same program gives the same module,
and so the same persistent-cache key, whatever the process traced before it, and with Python's cyclic garbage
collector mostly idle (`hexjax.cache.rare_collections`).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import inspect
import os
import pickle
import re
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import Optional

import jax
import numpy as np

from hexjax import cache

try:  # JAX's two caches of traced functions (`jax.jit` calls inside a traced function): see `fresh_trace`
    from jax._src.interpreters.partial_eval import trace_to_jaxpr as _jaxpr_cache
    from jax._src.pjit import _infer_params_cached as _jit_call_cache
    _TRACE_CACHES = (_jit_call_cache, _jaxpr_cache)
except ImportError:  # another JAX layout: clear every cache instead
    _TRACE_CACHES = ()


@dataclasses.dataclass(frozen=True)
class CompileStats:
    """compile_s: seconds of the call spent tracing, lowering and compiling, or loading a kept executable
    (0.0 when this process had it already); source: 'process', 'disk' or 'compiled'."""

    compile_s: float = 0.0
    source: str = "process"


_SAID = {"compiling": False}


def _say_compiling() -> None:
    """One line, the first time a process compiles a program, so the first minute of a command is not a silent
    0 % bar; a progress bar drawn meanwhile is redrawn below it."""
    if _SAID["compiling"]:
        return
    _SAID["compiling"] = True
    from tqdm.auto import tqdm
    where = cache.cache_dir()
    after = f"cached after, in {where}" if where else "the compilation cache is off"
    tqdm.write(f"hexjax: compiling (about a minute the first time on 2 CPU cores; {after})", file=sys.stderr)


def signature(args):
    """The tree structure, shapes, dtypes and shardings of `args`: what selects an executable."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    return tree, tuple((np.shape(x), str(getattr(x, "dtype", type(x))), str(getattr(x, "sharding", "")))
                       for x in leaves)


def arrays_digest(*trees) -> str:
    """A short hash of the arrays in `trees` (values, shapes, dtypes): for a `static` key of a function that
    closes over arrays, which then are constants of its program."""
    h = hashlib.sha256()
    for x in jax.tree_util.tree_leaves(trees):
        a = np.asarray(x)
        h.update(f"{a.shape}{a.dtype}".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


@functools.lru_cache(maxsize=1)
def _environment() -> str:
    """The code, library versions, XLA flags and devices an executable depends on."""
    h = hashlib.sha256()
    root = Path(__file__).resolve().parents[1]
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode())
        h.update(p.read_bytes())
    versions = []
    for dist in ("jax", "jaxlib", "mujoco", "mujoco-mjx"):
        try:
            versions.append(f"{dist}={metadata.version(dist)}")
        except metadata.PackageNotFoundError:
            versions.append(f"{dist}=none")
    devices = [f"{d.platform}:{getattr(d, 'device_kind', '')}" for d in jax.devices()]
    return "|".join([h.hexdigest(), *versions, sys.version.split()[0], os.environ.get("XLA_FLAGS", ""),
                     jax.default_backend(), *devices])


def _source_of(obj) -> str:
    """The source file of `obj`'s class when it lies outside hexjax (a user's controller): its text."""
    try:
        path = inspect.getsourcefile(type(obj))
    except TypeError:
        return ""
    if not path or Path(path).resolve().is_relative_to(Path(__file__).resolve().parents[1]):
        return ""
    return Path(path).read_text()


def fresh_trace() -> None:
    """Empty JAX's caches of traced functions before a large program is traced, so that the program lowers to
    the same module whatever the process traced before it.

    Each jitted callee of a traced program (`jnp.where`, `jnp.remainder`, MJX's collision functions: about two
    thousand in an MJX gradient program) becomes a private function of the module, one per traced jaxpr, and
    calls share a function only when they share the jaxpr object. Those objects come from JAX's caches of
    traced calls, which outlive a trace: one of them keeps only the 2,048 most recent calls (jax 0.11). So a
    callee traced for an earlier program can come back with the inner jaxprs of that time while a sibling
    call is traced anew, and the module gains a function: the tuning gradient program of `cpg_step_ditch` had
    two more `_where` functions after the two evaluation programs had been traced in the same process (a
    `jnp.remainder` kept from them called an older `_where`) than in a process that loaded those programs from
    disk. The key of JAX's persistent cache is a hash of the module, so that process compiled the program
    again (165 s on an H100).

    Only the two tracing caches are emptied; compiled executables of jitted functions and eager operations
    stay. Where this JAX lays them out otherwise, every cache is cleared."""
    for c in _TRACE_CACHES:
        c.cache_clear()
    if not _TRACE_CACHES:
        jax.clear_caches()


class _FlatExecutable:
    """A kept program's executable, called with the arguments' tree and giving the outputs' tree; `as_text()`:
    the compiled program (as a compiled jitted function's)."""

    def __init__(self, exe, out_tree):
        self.exe, self.out_tree = exe, out_tree

    def __call__(self, *args):
        return jax.tree_util.tree_unflatten(self.out_tree, self.exe(*jax.tree_util.tree_leaves(args)))

    def as_text(self) -> str:
        return self.exe.as_text()

    def memory_analysis(self):
        return self.exe.memory_analysis()


class Compiled:
    """A jitted function compiled ahead of time per input signature. `call(*args)` returns (outputs,
    CompileStats); calling the object returns the outputs alone. `static`: the hashable settings the
    function was made from (their repr names the kept programs; None keeps none: pass None for a function
    that cannot be exported, so that it is not traced twice).

    A kept program is the function exported (`jax.export`) over its flattened arguments, with the tree of its
    outputs: loading it skips tracing and lowering, and its XLA compile is a hit in JAX's persistent cache.
    (A serialised XLA executable would skip even that, but on the CPU one that calls LAPACK, as MJX's solver
    does, crashes when loaded in another process.) A program over several devices, or several processes
    (`jax.distributed`), is kept too: it is exported and called back under Shardy, JAX's default partitioner.
    Programs that do not export (host callbacks, MuJoCo Warp's kernels) are compiled as before."""

    def __init__(self, jitted, static=None):
        self.jitted = jitted
        self.static = static
        self.executables = {}

    def _path(self, sig) -> Optional[Path]:
        d = cache.cache_dir()
        if self.static is None or d is None:
            return None
        # object addresses in the tree's repr (MJX wraps the model's static arrays) differ between processes;
        # those arrays follow from the static settings, which are in the key
        sig_text = re.sub(r" at 0x[0-9a-f]+", "", repr(sig))
        key = "\n".join([repr(self.static), sig_text, _environment(),
                         *(_source_of(x) for x in self.static if not isinstance(x, (int, str, bool)))])
        return d / "programs" / (hashlib.sha256(key.encode()).hexdigest()[:32] + ".bin")

    def memory_bytes(self) -> Optional[int]:
        """The bytes the program compiled last (for its input signature) holds while it runs (arguments, outputs
        and temporaries, less what the outputs alias: XLA's memory analysis), or None before a call or where the
        backend gives no analysis."""
        exe = next(reversed(self.executables.values()), None)
        m = None if exe is None else exe.memory_analysis()
        if m is None:
            return None
        return int(m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes - m.alias_size_in_bytes)

    @staticmethod
    def _flat_executable(exported, out_tree, leaves):
        return _FlatExecutable(jax.jit(exported.call).lower(*leaves).compile(), out_tree)

    def _load(self, path: Path, leaves):
        try:
            with open(path, "rb") as f:
                blob, out_tree = pickle.load(f)
            return self._flat_executable(jax.export.deserialize(blob), out_tree, leaves)
        except Exception:  # written by another setup, or broken: compile afresh and replace it
            return None

    def _export(self, path: Path, args, leaves, in_tree):
        """Export the function over flat arguments, keep it at `path`, and return its executable (None when it
        does not export)."""
        out = {}

        def flat(*ls):
            res = self.jitted(*jax.tree_util.tree_unflatten(in_tree, ls))
            leaves_out, out["tree"] = jax.tree_util.tree_flatten(res)
            return leaves_out

        try:
            fresh_trace()
            exported = jax.export.export(jax.jit(flat))(*leaves)
            exe = self._flat_executable(exported, out["tree"], leaves)
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".tmp{os.getpid()}")
            tmp.write_bytes(pickle.dumps((exported.serialize(), out["tree"])))
            os.replace(tmp, path)
            return exe
        except Exception:  # host callbacks, Warp's FFI kernels: not exportable
            return None

    def call(self, *args):
        sig = signature(args)
        exe = self.executables.get(sig)
        if exe is not None:
            return exe(*args), CompileStats()
        t0 = time.perf_counter()
        leaves, in_tree = jax.tree_util.tree_flatten(args)
        path = self._path(sig)
        exe, source = None, "disk"
        if path is None or not path.exists():
            _say_compiling()
        with cache.rare_collections():
            if path is not None and path.exists():
                exe = self._load(path, leaves)
            if exe is None and path is not None:
                exe, source = self._export(path, args, leaves, in_tree), "compiled"
            if exe is None:
                fresh_trace()
                exe, source = self.jitted.lower(*args).compile(), "compiled"
        self.executables[sig] = exe
        # timed before the first call: on the GPU that call can block until the run ends (MJX's solver loops
        # read their stopping test on the host), which is run time, not compile time
        stats = CompileStats(time.perf_counter() - t0, source)
        return exe(*args), stats

    def __call__(self, *args):
        return self.call(*args)[0]
