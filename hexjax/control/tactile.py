"""Tactile obstacle overcoming (Luneckas et al. 2020, Sect. 2.4, Eqs. 5-7, Fig. 7).

Each leg carries a tactile pad on the front of its shin. When the pad of leg i fires, the *next* step of
leg i is an obstacle-overcoming step, longer and higher than the basic one:

    l_k = 2 l_i            (Eq. 6)
    h_k = H + 2 cm         (Eq. 7, H the known maximum obstacle height)

and after it the leg goes back to l_i, h_i unless its pad fired again. The choice is made only at the
start of a step (the lift-off of the leg's swing) and held for the whole step: switching mid-transfer left
the real robot's legs stuck on top of obstacles (Sect. 2.4).

Reading of "step length" for one leg. Eq. 2 with l = l_k for the whole cycle would also sweep that leg's
stance at twice the body's pace, against the other stance legs (they carry the body l_i per cycle), so the
foot would be dragged or slip. Here l_k applies to the transfer: the overcoming swing lands l_k - l_i
further forward than the basic one (a transfer of l_k from the basic lift-off point, the foot reaching
past the obstacle it touched), and every stance moves the foot back at the basic pace. The next basic
swing then starts that much further forward and lands at the basic point, so the pattern is restored
after one step (its transfer is l_i - (l_k - l_i) = 0 relative to the body: the foot is simply lifted and
set down while the body walks on). With l_k = l_i the trajectory is Eq. 2-4 exactly (tested).

Hard and smooth forms: the switch for a step is the gate g in {0, 1} (hard: the largest pad force seen
during the previous step exceeds `tactile_threshold`) or sigmoid((force - threshold) / temperature)
(smooth), or the hard value with the sigmoid's derivative (`straight_through`, `hexjax.control.gates`);
the step's landing point and height are l_i / 2 + g (l_k - l_i) and h_i + g (h_k - h_i). The
params field `enable` multiplies g, so runs with and without the method share one compiled rollout.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Tuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hexjax.control.base import shown
from hexjax.control.gait import PatternClock, check_open_ranges
from hexjax.control.gates import hard_gate, sigmoid_gate
from hexjax.world.robot import N_LEGS, RobotSpec, body_to_leg, leg_ik, neutral_feet_body


@struct.dataclass
class TactileParams:
    """Tunable numbers of the tactile gait (all traced; `jax.grad` and per-env batching reach them). SI.

    step_length l_i (m), step_height h_i (m), swing_time: one transfer slot (s), direction eps (rad),
    overcome_length l_k (m, Eq. 6: 2 l_i), overcome_height h_k (m, Eq. 7: H + 0.02),
    tactile_threshold: pad normal force that counts as a touch (N), temperature: smooth gate width (N),
    enable: 1 to use the method, 0 for the basic gait (the paper's "without the method")."""

    step_length: jax.Array
    step_height: jax.Array
    swing_time: jax.Array
    direction: jax.Array
    overcome_length: jax.Array
    overcome_height: jax.Array
    tactile_threshold: jax.Array
    temperature: jax.Array
    enable: jax.Array


@struct.dataclass
class TactileState:
    t: jax.Array  # gait clock, s
    step_idx: jax.Array  # (6,) int: index of each leg's current step (a step starts at lift-off)
    gate: jax.Array  # (6,) overcoming gate of the current step (0 basic, 1 overcoming)
    gate_prev: jax.Array  # (6,) gate of the previous step (sets where this step's transfer starts)
    seen: jax.Array  # (6,) largest pad force during the current step, N
    n_overcome: jax.Array  # (6,) overcoming steps taken (sum of gates)


def overcome_height(max_obstacle_height):
    """h_k = H + 2 cm (Luneckas 2020 Eq. 7) for the known maximum obstacle height H (m)."""
    return max_obstacle_height + 0.02


@dataclasses.dataclass(frozen=True)
class TactileGaitController(PatternClock):
    """The Luneckas 2020 gait (tripod or wave) with the tactile obstacle-overcoming switch.

    robot: RobotSpec; gait: 'tripod' or 'wave'; max_obstacle_height: H of Eq. 7 (m), the one thing the
    method assumes known; step_height: h_i (m); dt: control period (s); smooth: differentiable gate;
    straight_through: with `smooth`, the gate keeps the hard value and takes the sigmoid's derivative
    (`hexjax.control.gates`); n_cycles: stop after this many gait cycles (None: walk on). Start and stop
    ramps as in `GaitController`: the horizontal stroke grows from 0 over the first cycle and shrinks over the last."""

    robot: RobotSpec
    gait: str = "tripod"
    max_obstacle_height: float = 0.05
    step_height: float = 0.03
    dt: float = 0.02
    smooth: bool = False
    straight_through: bool = False
    n_cycles: int | None = None

    def __post_init__(self):
        self._check_gait_and_dt()
        if self.straight_through and not self.smooth:
            raise ValueError("straight_through=True needs smooth=True: it changes the smooth gate's derivative")
        if not (math.isfinite(self.max_obstacle_height) and 0 <= self.max_obstacle_height <= 0.2):
            raise ValueError(f"max_obstacle_height={self.max_obstacle_height!r}: must be in [0, 0.2] m")
        if not (math.isfinite(self.step_height) and 0 < self.step_height <= 0.15):
            raise ValueError(f"step_height={self.step_height!r}: must be in (0, 0.15] m")

    params_prefix = "tactile"

    def params_defaults(self) -> TactileParams:
        """The paper's hand rules: l_i from the gait's steps per metre, l_k = 2 l_i (Eq. 6), h_k = H + 2 cm
        (Eq. 7) with H = `max_obstacle_height`, the method on (`enable` = 1; 0 for the basic gait)."""
        p = self.pattern
        f = lambda x: jnp.asarray(x, jnp.float32)
        return TactileParams(step_length=f(p.step_length), step_height=f(self.step_height), swing_time=f(p.swing_time),
                             direction=f(0.0), overcome_length=f(2 * p.step_length),
                             overcome_height=f(overcome_height(self.max_obstacle_height)),
                             tactile_threshold=f(0.3), temperature=f(0.05), enable=f(1.0))

    def validate_params(self, params: TactileParams) -> None:
        """Host-side checks on concrete params (shared or batched), before tracing."""
        checks = {"step_length": (0.0, 0.2), "step_height": (0.0, 0.15), "swing_time": (0.05, 10.0),
                  "overcome_length": (0.0, 0.2), "overcome_height": (0.0, 0.2), "tactile_threshold": (0.0, 100.0),
                  "temperature": (0.0, 100.0)}
        check_open_ranges("tactile", params, checks)
        e = np.asarray(params.enable)
        bad = ~((e >= 0) & (e <= 1))
        if np.any(bad):
            raise ValueError(f"tactile.enable={shown(e, bad)}: must be in [0, 1]")

    def commanded_advance(self, params: TactileParams, t):
        """Body advance the gait commands by gait time t (s): the stroke ramps in over the first cycle
        (half a cycle's advance lost) and out over the last. (..., ) m."""
        period = self.pattern.period
        cycle = params.swing_time * period
        per_cycle = params.step_length * period / (period - 1)
        c = t / cycle
        up = jnp.where(c < 1, 0.5 * c * c, c - 0.5)
        if self.n_cycles is None:
            return per_cycle * up
        n = self.n_cycles
        cc = jnp.minimum(c, n)
        full = jnp.where(cc < 1, 0.5 * cc * cc, cc - 0.5)
        down = jnp.maximum(cc - (n - 1), 0.0)
        return per_cycle * (full - 0.5 * down * down)

    # Protocol --------------------------------------------------------------------------------------
    def init(self, params: TactileParams, key) -> TactileState:
        del key
        z = jnp.zeros(N_LEGS)
        return TactileState(t=jnp.asarray(0.0), step_idx=self._step_index(params, jnp.asarray(0.0)),
                            gate=z, gate_prev=z, seen=z, n_overcome=z)

    def _step_index(self, params, t):
        """(6,) index of each leg's current step; step k of leg i starts at its k-th lift-off."""
        p = self.pattern
        u = t / params.swing_time - jnp.asarray(p.phases, jnp.float32)
        return jnp.floor(u / p.period).astype(jnp.int32)

    def _gate(self, params, force):
        x = force - params.tactile_threshold
        g = sigmoid_gate(x, params.temperature, self.straight_through) if self.smooth else hard_gate(x)
        return params.enable * g

    def foot_offsets(self, params: TactileParams, t, gate, gate_prev):
        """(6, 3) foot offsets from the neutral stance in the torso frame at gait time t (s), for the given
        gates of each leg's current and previous step (Luneckas 2020 Eqs. 2-7, read as in the module doc)."""
        p = self.pattern
        period = p.period
        li = params.step_length
        cycle = params.swing_time * period
        t_end = jnp.inf if self.n_cycles is None else self.n_cycles * cycle
        tw = jnp.minimum(t, t_end)
        s = jnp.mod(tw / params.swing_time - jnp.asarray(p.phases, jnp.float32), period)
        swing = s < 1.0
        extra = params.overcome_length - li
        land = 0.5 * li + gate * extra  # this step's landing point
        start = 0.5 * li + gate_prev * extra - li  # where the previous step's stance ended
        a = jnp.where(swing, start + (land - start) * s, land - li * (s - 1.0) / (period - 1.0))
        h = params.step_height + gate * (params.overcome_height - params.step_height)
        z = jnp.where(swing, h * jnp.sin(math.pi * jnp.clip(s, 0.0, 1.0)), 0.0)
        ramp = jnp.clip(jnp.minimum(tw, t_end - tw) / cycle, 0.0, 1.0)
        x = ramp * jnp.cos(params.direction) * a
        y = ramp * jnp.sin(params.direction) * a
        return jnp.stack([x, y, z], axis=-1)

    def step(self, params: TactileParams, state: TactileState, obs) -> Tuple[TactileState, jax.Array]:
        t = state.t
        k = self._step_index(params, t)
        new = k > state.step_idx  # a new step begins for these legs at this control tick
        seen = jnp.maximum(state.seen, obs.tactile_force)  # this tick's reading belongs to the ending step
        g_new = self._gate(params, seen)
        gate = jnp.where(new, g_new, state.gate)
        gate_prev = jnp.where(new, state.gate, state.gate_prev)
        seen = jnp.where(new, 0.0, seen)
        feet = jnp.asarray(neutral_feet_body(self.robot)) + self.foot_offsets(params, t, gate, gate_prev)
        q, _ = leg_ik(self.robot, body_to_leg(self.robot, feet))
        st = TactileState(t=t + self.dt, step_idx=k, gate=gate, gate_prev=gate_prev, seen=seen,
                          n_overcome=state.n_overcome + jnp.where(new, gate, 0.0))
        return st, q.reshape(-1)

    def trace(self, state: TactileState, obs):
        """Per-step record: gate of each leg's current step (6,) and pad force (6,) N."""
        return dict(gate=state.gate, tactile=obs.tactile_force)
