"""The controller protocol: what the rollout, the Brax env and the tuners call on every hexjax controller
(docs/architecture.md).

A controller is a frozen (hashable) dataclass deriving from `Controller`. Its fields are static
configuration (the robot, the gait pattern, the hard or smooth form, the control period `dt`): changing one
recompiles. Everything numeric that may be tuned, batched per env or differentiated lives in a `params`
pytree; everything a controller remembers between steps lives in a `state` pytree:

    default_params(**overrides) -> params      the papers' numbers, fields replaced by `overrides`
    validate_params(params)                    host-side checks before tracing (ValueError naming the field)
    for_distance(distance, params) -> (controller, seconds)   the controller with its stop set and the
                                               rollout seconds for a walk of `distance` m
    init(params, key) -> state                 one env's initial memory
    step(params, state, obs) -> (state, action)   one control period; obs is `hexjax.sim.model.Obs`, action
                                               the (18,) joint position targets, rad
    initial_action(params) -> (18,) or None    the joint targets to settle in (None: the robot's stance)
    trace(state, obs) -> pytree or None        what `RolloutConfig(record=True)` keeps per step
    reflex_phase(params, state) -> (k,)        where the controller is in its cycle, for a learned reflex layer
                                               (`hexjax.control.reflex`); empty by default
    sensor, perceive_every                     a range sensor (`hexjax.perceive.sensors.RangeSensor`) or None
    perceive(params, state, scan, key) -> state   every `perceive_every` control steps of the walk, the
                                               control step casts the sensor's rays against the env's terrain
                                               from the torso's pose and hands the scan over (before `step`)

`init`, `step`, `initial_action`, `trace` and `perceive` are pure JAX on one env; the rollout vmaps them.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np


def shown(v: np.ndarray, bad=None) -> str:
    """A params field's value for a controller's error line: in full when small, else its first offending entry
    (where `bad`, a mask of v's shape, marks one) with its index and the array's shape, so that a batch of params
    (an evolution strategy's population on its terrains) reads in one line."""
    if v.size <= 12:
        return repr(v.tolist())
    flat = np.ravel(np.broadcast_to(bad, v.shape)) if bad is not None else np.zeros(v.size, bool)
    i = np.unravel_index(int(np.argmax(flat)), v.shape)
    return f"{float(v[i]):.6g} at {tuple(int(k) for k in i)} (shape {v.shape})"


def replace_fields(params, overrides: Mapping[str, Any], prefix: str):
    """`params` (a flax struct dataclass) with the named fields replaced. A numeric override takes the
    field's dtype; a pytree override (a nested params struct, a DEM) is put in as it is. An unknown name
    raises ValueError naming `prefix.name` and the fields there are."""
    names = {f.name for f in dataclasses.fields(params)}
    for k in overrides:
        if k not in names:
            raise ValueError(f"{prefix}.{k}: unknown parameter; the fields are {sorted(names)}")

    def conv(k, v):
        if isinstance(v, (int, float, list, tuple)) or hasattr(v, "dtype"):
            return jnp.asarray(v, getattr(getattr(params, k), "dtype", None))
        return v

    return params.replace(**{k: conv(k, v) for k, v in overrides.items()})


class Controller:
    """Base of every hexjax controller (see the module docstring). Subclasses are frozen dataclasses that
    define `dt`, `params_defaults`, `init` and `step`; the other hooks have defaults here."""

    dt: float
    #: prefix of this controller's params in error messages ("gait", "tactile", "cpg", ...)
    params_prefix: str = "params"

    def params_defaults(self) -> Any:
        """The params pytree with the papers' numbers (subclasses)."""
        raise NotImplementedError

    def default_params(self, **overrides) -> Any:
        """`params_defaults()` with the fields named in `overrides` replaced (a float or an array each)."""
        return replace_fields(self.params_defaults(), overrides, self.params_prefix)

    def validate_params(self, params) -> None:
        """Host-side checks on concrete params (shared or batched) before tracing; nothing by default."""

    def init(self, params, key) -> Any:
        raise NotImplementedError

    def step(self, params, state, obs) -> Tuple[Any, jax.Array]:
        raise NotImplementedError

    def initial_action(self, params) -> Optional[jax.Array]:
        """(18,) joint targets to settle in before the first step; None: the robot's neutral stance."""
        return None

    def for_distance(self, distance: float, params=None) -> Tuple["Controller", float]:
        """(this controller with its stop set, rollout seconds) for a walk of `distance` m with `params`
        (default: `default_params()`): each controller's own rule (subclasses)."""
        raise NotImplementedError(f"{type(self).__name__} has no rule for a walk's length: give the rollout "
                                  "its seconds")

    def trace(self, state, obs) -> Any:
        """A pytree recorded per control step with `RolloutConfig(record=True)`; None: nothing."""
        return None

    def reflex_phase(self, params, state) -> jax.Array:
        """(k,) numbers of order one saying where the controller is in its cycle (a learned reflex layer's
        input, `hexjax.control.reflex`); none by default."""
        return jnp.zeros((0,))

    #: a `hexjax.perceive.sensors.RangeSensor` the control step scans the terrain with, or None (no scans)
    sensor: Any = None
    #: control steps between scans (the first at the walk's first step)
    perceive_every: int = 1

    def perceive(self, params, state, scan, key) -> Any:
        """The state after taking in one `hexjax.perceive.raycast.Scan` (world frame); key: for any sampling
        (RANSAC). Called only when `sensor` is set; the default keeps the state."""
        return state
