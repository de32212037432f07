"""Ahead-of-time compiled rollouts: one executable per input signature, with the seconds its compile took.

Compiling a rollout costs 20-50 s on 2 CPU cores and 50-185 s on a GPU. JAX's persistent compilation cache
(`hexjax.cache`) keeps XLA's executables on disk, so a second process skips XLA; `Compiled` records how long
each signature's first call spent tracing, lowering and compiling (or loading), which is the figure hexjax
reports as compile time.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import numpy as np


@dataclasses.dataclass(frozen=True)
class CompileStats:
    """compile_s: seconds of the call spent tracing, lowering and compiling (or loading from the cache);
    0.0 when this process had compiled the signature already."""

    compile_s: float = 0.0


def signature(args):
    """The tree structure, shapes, dtypes and shardings of `args`: what selects an executable."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    return tree, tuple((np.shape(x), str(getattr(x, "dtype", type(x))), str(getattr(x, "sharding", "")))
                       for x in leaves)


class Compiled:
    """A jitted function compiled ahead of time per input signature. `call(*args)` returns (outputs,
    CompileStats); calling the object returns the outputs alone."""

    def __init__(self, jitted):
        self.jitted = jitted
        self.executables = {}

    def call(self, *args):
        sig = signature(args)
        exe = self.executables.get(sig)
        compile_s = 0.0
        if exe is None:
            t0 = time.perf_counter()
            exe = self.jitted.lower(*args).compile()
            compile_s = time.perf_counter() - t0
            self.executables[sig] = exe
        return exe(*args), CompileStats(compile_s)

    def __call__(self, *args):
        return self.call(*args)[0]
