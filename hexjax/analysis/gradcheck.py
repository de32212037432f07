"""Autodiff against central finite differences, per parameter group (issue 5's gradient check)."""

from __future__ import annotations

from typing import Callable, Dict, List, Mapping

import jax
import jax.numpy as jnp
import numpy as np


def central_differences(f: Callable, u0: Mapping[str, jax.Array], eps: float) -> Dict[str, np.ndarray]:
    """(f(u + eps e_j) - f(u - eps e_j)) / (2 eps) for every entry j of every array in u0 (flattened)."""
    fd = {}
    for k, v in u0.items():
        col = np.zeros(v.size)
        for j in range(v.size):
            d = jnp.zeros(v.size).at[j].set(eps).reshape(v.shape)
            col[j] = (float(f({**u0, k: v + d})) - float(f({**u0, k: v - d}))) / (2 * eps)
        fd[k] = col
    return fd


def group_cosines(grad: Mapping[str, jax.Array], fd: Mapping[str, np.ndarray],
                  groups: Mapping[str, List[str]]) -> Dict[str, tuple]:
    """Per group: (cosine of autodiff with central differences, autodiff vector, FD vector)."""
    out = {}
    for group, names in groups.items():
        a = np.concatenate([np.ravel(np.asarray(grad[n])) for n in names])
        b = np.concatenate([fd[n] for n in names])
        out[group] = (float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-30)), a, b)
    return out
