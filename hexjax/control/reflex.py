"""A learned reflex layer over a paper's controller: a small network from what the robot senses to offsets on the
joint targets the controller commands.

The papers' reflexes are hand-made maps of this kind. Yu 2019 adds two to its CPG: the elevator reflex (Eq. 11:
a swing leg whose foot meets an obstacle, lambda_ob, is lifted over it) and the searching reflex (Eqs. 12-14: a
leg that finds no ground at touchdown reaches down for it); Luneckas 2020 adds one to its gait (Sect. 2.4,
Eqs. 5-7: a shin pad that touches makes the next step longer and higher). `ReflexController` learns such a map
for every leg at once, and keeps the paper's controller under it:

    q = q_base + max_offset * tanh(f_theta(x))

with q_base the base controller's 18 joint targets (its own step, reflexes included) and f_theta a multilayer
perceptron (flax) of the senses x of one env, each scaled to order one:
- each foot's contact force in the torso frame (6 x 3, over the robot's weight) and each shin pad's normal force
  (6, tanh of force / 1 N);
- the joint angles (18, rad) and rates (18, x 0.1 s);
- the world's up direction in the torso frame (3: gravity's, reversed) and its rate of turn between control steps
  (3, x 0.1 s), the torso's tilt and tilting rate;
- the base controller's phase (`Controller.reflex_phase`): the gait clock's sine and cosine (Luneckas 2020), the
  leader oscillator of each leg's network (Yu 2019, 6 x 2).

The last layer starts at zero, so an untrained layer leaves the paper's controller exactly as it is
(tests/test_reflex.py). The network is smooth; the controller's hard and smooth forms are its base controller's
(`make_controller("cpg-reflex", robot, smooth=True)` trains on the CPG's sigmoid gates).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Tuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hexjax.control.base import Controller
from hexjax.control.cpg.converter import quat_to_body

N_JOINTS = 18


class ReflexNet(nn.Module):
    """The perceptron: tanh hidden layers of `hidden` units, then a linear layer to the 18 joints, zero at the
    start."""

    hidden: Tuple[int, ...]

    @nn.compact
    def __call__(self, x):
        for n in self.hidden:
            x = jnp.tanh(nn.Dense(n)(x))
        return nn.Dense(N_JOINTS, kernel_init=nn.initializers.zeros, bias_init=nn.initializers.zeros)(x)


@struct.dataclass
class ReflexParams:
    """base: the base controller's params (tuned alongside or held); net: the layer's weights (flax variables)."""

    base: Any
    net: Any


@struct.dataclass
class ReflexState:
    base: Any  # the base controller's state
    up_prev: jax.Array  # (3,) the world's up direction in the torso frame at the previous step (for its rate)


@dataclasses.dataclass(frozen=True)
class ReflexController(Controller):
    """`base` with a learned reflex layer (module docstring). hidden: units of each hidden layer; max_offset:
    the largest offset a joint gets, rad; seed: of the hidden layers' initial weights."""

    base: Controller
    hidden: Tuple[int, ...] = (32,)
    max_offset: float = 0.3
    seed: int = 0

    params_prefix = "reflex"

    def __post_init__(self):
        if not self.hidden or any(int(n) < 1 for n in self.hidden):
            raise ValueError(f"reflex.hidden={self.hidden!r}: one or more layer widths >= 1")
        if not 0 < self.max_offset <= 1.0:
            raise ValueError(f"reflex.max_offset={self.max_offset!r}: must be in (0, 1] rad")

    # what the rollout and the commands read of a controller
    @property
    def dt(self) -> float:
        return self.base.dt

    @property
    def robot(self):
        return self.base.robot

    @property
    def gait(self) -> str:
        return self.base.gait

    @property
    def net(self) -> ReflexNet:
        return ReflexNet(tuple(int(n) for n in self.hidden))

    def n_inputs(self) -> int:
        return 6 * 3 + 6 + 2 * N_JOINTS + 3 + 3 + self._phase_size()

    def _phase_size(self) -> int:
        base_p = self.base.default_params()
        return int(np.size(jax.eval_shape(lambda: self.base.reflex_phase(base_p, self.base.init(base_p, None)))))

    def init_net(self):
        """The layer's initial weights: the hidden layers drawn from `seed`, the last layer zero."""
        return self.net.init(jax.random.PRNGKey(self.seed), jnp.zeros(self.n_inputs()))

    def default_params(self, **overrides) -> ReflexParams:
        """The base controller's default params (with `overrides`, its fields) and the initial layer."""
        return ReflexParams(base=self.base.default_params(**overrides), net=self.init_net())

    def validate_params(self, params: ReflexParams) -> None:
        self.base.validate_params(params.base)
        bad = [jax.tree_util.keystr(k) for k, v in jax.tree_util.tree_leaves_with_path(params.net)
               if not np.all(np.isfinite(np.asarray(v)))]
        if bad:
            raise ValueError(f"reflex.net{bad[0]}: not finite")

    def n_params(self, params: ReflexParams | None = None) -> int:
        """Numbers in the layer."""
        net = self.init_net() if params is None else params.net
        return int(sum(np.size(x) for x in jax.tree_util.tree_leaves(net)))

    def for_distance(self, distance: float, params: ReflexParams | None = None):
        walk, seconds = self.base.for_distance(distance, None if params is None else params.base)
        return dataclasses.replace(self, base=walk), seconds

    def init(self, params: ReflexParams, key) -> ReflexState:
        return ReflexState(base=self.base.init(params.base, key), up_prev=jnp.array([0.0, 0.0, 1.0]))

    def initial_action(self, params: ReflexParams):
        return self.base.initial_action(params.base)

    def senses(self, params: ReflexParams, state: ReflexState, obs) -> Tuple[jax.Array, jax.Array]:
        """(x, up): the layer's inputs (module docstring) and the world's up direction in the torso frame."""
        weight = float(self.robot.total_mass) * 9.81
        up = quat_to_body(obs.torso_quat, jnp.array([0.0, 0.0, 1.0]))
        x = jnp.concatenate([
            (quat_to_body(obs.torso_quat, obs.foot_force) / weight).reshape(-1),
            jnp.tanh(obs.tactile_force),
            obs.qpos, 0.1 * obs.qvel,
            up, 0.1 * jnp.cross(state.up_prev, up) / self.dt,
            jnp.ravel(self.base.reflex_phase(params.base, state.base)),
        ])
        return x, up

    def step(self, params: ReflexParams, state: ReflexState, obs):
        x, up = self.senses(params, state, obs)
        base_state, q = self.base.step(params.base, state.base, obs)
        dq = self.max_offset * jnp.tanh(self.net.apply(params.net, x))
        return ReflexState(base=base_state, up_prev=up), q + dq

    def trace(self, state: ReflexState, obs):
        return self.base.trace(state.base, obs)
