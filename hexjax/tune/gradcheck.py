"""Autodiff against central finite differences, per parameter group."""

from __future__ import annotations

from typing import Callable, Dict, List, Mapping, Optional

import jax
import jax.numpy as jnp
import numpy as np

from hexjax.control.registry import make_controller
from hexjax.sim.compiled import Compiled
from hexjax.world.terrain import sample


def tactile_check_setting(robot):
    """(controller, params) of the tactile gradient check (tests/test_tune.py, tests/test_implicit.py,
    scripts/fd_probe.py): the smooth Luneckas 2020 tactile tripod with a fast gait (0.2 s swing slots) and a pad
    threshold inside the gate's width, so that one 0.4 s window holds a lift-off where every group (basic step,
    overcoming step, threshold) acts."""
    ctrl = make_controller("tactile", robot, smooth=True)
    return ctrl, ctrl.default_params().replace(swing_time=jnp.float32(0.2), tactile_threshold=jnp.float32(0.1),
                                               temperature=jnp.float32(0.1))


def check_batch(spec, n: int):
    """(terrains, env keys) of n envs on terrain spec `spec`, as the gradient checks draw them (tests/test_tune.py,
    tests/test_implicit.py, scripts/fd_probe.py): terrains from PRNG key 0, env keys split from key 1."""
    return sample(spec, jax.random.PRNGKey(0), n), jax.random.split(jax.random.PRNGKey(1), n)


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


def travel_objective(fn, model, space, params, terrain, keys):
    """obj(u) -> the mean travel x + 0.3 y + 0.1 yaw of a batch: the smooth objective the gradient checks use
    (tests/test_tune.py, scripts/fd_probe.py). fn, model: `rollout_function`'s; space: the `ParamSpace` of
    the unconstrained params u; params: the rest of the controller's params."""
    def obj(u):
        s = fn(model, space.apply(u, params), terrain, keys)
        return jnp.mean(s.travel[:, 0]) + 0.3 * jnp.mean(s.travel[:, 1]) + 0.1 * jnp.mean(s.travel[:, 2])
    return obj


def check(obj: Callable, u0: Mapping[str, jax.Array], groups: Mapping[str, List[str]], eps=(1e-3,),
          static: Optional[tuple] = None, one_program: bool = False):
    """Per central-difference step in `eps`: {group: (cosine, autodiff vector, FD vector)}, with the jitted
    autodiff gradient of `obj` at `u0` taken once. Returns (objective at u0, {eps: results}).
    static: what obj is made from (its arrays through `arrays_digest`), to keep its compiled programs on
    disk (`hexjax.sim.compiled`): a second run skips tracing them (20-40 s each on 2 cores).
    one_program: take the differences from the value that the value_and_grad program returns instead of a
    forward program of their own: one compile instead of two (a rollout's forward costs 15-40 s of XLA
    compile on 2 cores), each of the 2 x (number of params) evaluations then costing a gradient. Measured on
    2 cores, 4 envs, 0.5 s walks with the unrolled solver: a gradient call of the tactile check costs about
    0.32 s more than a forward one, of the CPG check 0.46 s against 0.035 s. So it pays with few params and
    a program compiled once (the tactile check, 12 differences), not with many (the CPG check's 36)."""
    vg = jax.jit(jax.value_and_grad(obj))
    if static is not None:
        vg = Compiled(vg, static=("gradcheck/value_and_grad",) + tuple(static))
    if one_program:
        f = lambda u: vg(u)[0]
    else:
        f = jax.jit(obj)
        if static is not None:
            f = Compiled(f, static=("gradcheck/value",) + tuple(static))
    value, grad = vg(u0)
    return float(value), {e: group_cosines(grad, central_differences(f, u0, e), groups) for e in eps}
