"""The controller protocol shared by every hexjax controller (see DESIGN.md).

A controller is a frozen (hashable) object holding static configuration, with two pure methods:
    init(params, key) -> state
    step(params, state, obs) -> (state, action)
`params` is a pytree of traced, tunable numbers (what `jax.grad` reaches); `state` is a pytree of
memory; `obs` is `hexjax.sim.model.Obs`; `action` is (18,) joint position targets, rad. The control
period is part of the static configuration (`dt`), so `step` needs no time argument.
"""

from __future__ import annotations

from typing import Any, Protocol, Tuple

import jax


class Controller(Protocol):
    dt: float

    def default_params(self) -> Any: ...

    def init(self, params: Any, key: jax.Array) -> Any: ...

    def step(self, params: Any, state: Any, obs: Any) -> Tuple[Any, jax.Array]: ...
