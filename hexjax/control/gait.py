"""The leg trajectory of Luneckas et al. 2020 (Eqs. 2-4) and its tripod / wave gaits (Sect. 3.1, Fig. 13),
mapped to joints by inverse kinematics.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Tuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hexjax.control.base import Controller, shown
from hexjax.plan.support import torso_pitch_roll
from hexjax.world.robot import RobotSpec, body_to_leg, leg_ik, neutral_feet_body


@dataclasses.dataclass(frozen=True)
class GaitPattern:
    """Leg phases phi_i and period T, both in units of one swing duration (Luneckas 2020 Fig. 13)."""

    name: str
    period: int  # T: swing slots per gait cycle
    phases: Tuple[int, ...]  # phi_i for LF, LM, LH, RF, RM, RH
    speed: float  # the paper's walking speed, m/s (Sect. 3.3)
    steps_per_m: int  # the paper's steps (gait cycles) per metre (Sect. 3.3)

    @property
    def cycle_advance(self) -> float:
        """Body advance per gait cycle: 1 m / steps per metre, m."""
        return 1.0 / self.steps_per_m

    @property
    def step_length(self) -> float:
        """Stance stroke l giving `cycle_advance` per cycle. Each leg's stance lasts T - 1 swing slots
        and carries the body l, so the body moves l / (T - 1) per slot and l T / (T - 1) per cycle.
        (Reading "steps" as gait cycles: tripod l = 3.85 cm, wave 4.17 cm; reading them as half
        cycles would give a tripod l_k = 2 l_i of 15.4 cm, beyond the robot's l_max of 10 cm.)"""
        return self.cycle_advance * (self.period - 1) / self.period

    @property
    def swing_time(self) -> float:
        """Duration of one swing slot: cycle time (advance / v) divided by T, s."""
        return self.cycle_advance / self.speed / self.period


GAITS = {
    # tripod: LM, RF, RH swing in the first half of the period; LF, LH, RM in the second
    "tripod": GaitPattern("tripod", 2, (1, 0, 1, 0, 1, 0), speed=0.036, steps_per_m=13),
    # wave: one leg at a time, LF, LM, LH, RF, RM, RH
    "wave": GaitPattern("wave", 6, (0, 1, 2, 3, 4, 5), speed=0.013, steps_per_m=20),
}


def leg_trajectory(t, phi, period, l, h, eps):
    """Foot offset from its neutral position, Luneckas 2020 Eqs. 2-4.

    t, phi, period in swing-duration units (the swing of leg i spans phi_i < t <= phi_i + 1, a cycle
    spans T); l step length (m), h step height (m), eps movement direction (rad). Returns (x, y, z) m.

    Reading of the printed equations: as typeset, the stance branches of Eq. 2 do not meet the swing
    branch (at t = phi_i the first gives -l cos(eps), the swing gives 0). We use the continuous form
    they describe (Fig. 5): swing moves the foot linearly from -l/2 to +l/2 along eps while
    z = h sin(pi (t - phi_i)); stance returns it linearly from +l/2 to -l/2 over the other T - 1 units,
    periodic in T. Averaged over a cycle the body advances l per period."""
    s = jnp.mod(t - phi, period)
    swing = s < 1.0
    a = jnp.where(swing, -0.5 * l + l * s, 0.5 * l - l * (s - 1.0) / (period - 1.0))
    z = jnp.where(swing, h * jnp.sin(math.pi * s), 0.0)
    return jnp.cos(eps) * a, jnp.sin(eps) * a, z


@struct.dataclass
class GaitParams:
    """Tunable numbers of the gait (traced; `jax.grad` reaches them). SI units.

    step_length l (m), step_height h (m), swing_time: duration of one swing slot (s),
    direction eps (rad, 0 = forward), body_height_offset: torso raised (+) or lowered (m)."""

    step_length: jax.Array
    step_height: jax.Array
    swing_time: jax.Array
    direction: jax.Array
    body_height_offset: jax.Array


@struct.dataclass
class GaitState:
    t: jax.Array  # time since the gait clock started, s (negative during the ramp-in)


def check_open_ranges(prefix: str, params, checks) -> None:
    """Host-side check that each named field of `params` (scalar or batched) is finite and in (lo, hi];
    `checks`: {field: (lo, hi)}. Raises ValueError naming `prefix.field` and its value."""
    for f, (lo, hi) in checks.items():
        v = np.asarray(getattr(params, f))
        bad = ~np.isfinite(v) | (v <= lo) | (v > hi)
        if np.any(bad):
            raise ValueError(f"{prefix}.{f}={shown(v, bad)}: must be in ({lo}, {hi}]")


class PatternClock(Controller):
    """What the Luneckas 2020 gait controllers share: a gait pattern (Fig. 13), the check of the gait name and
    control period, and the cycle bookkeeping for a walk of a given distance. Mixed into frozen dataclasses
    that define `gait` and `dt`; `default_params()` must return params with `step_length` and `swing_time`
    (scalars, or batched: their mean sets the walk's length)."""

    def _check_gait_and_dt(self) -> None:
        if self.gait not in GAITS:
            raise ValueError(f"gait={self.gait!r}: choose one of {sorted(GAITS)}")
        if not (0 < self.dt <= 0.1):
            raise ValueError(f"controller.dt={self.dt!r}: must be in (0, 0.1] s")

    @property
    def pattern(self) -> GaitPattern:
        return GAITS[self.gait]

    @property
    def cycle_time(self) -> float:
        return self.pattern.swing_time * self.pattern.period

    def cycles_for(self, distance: float, params=None) -> int:
        """Gait cycles (ramps included) whose commanded advance is closest to `distance` m."""
        p = params or self.default_params()
        period = self.pattern.period
        advance = float(np.mean(p.step_length)) * period / (period - 1)
        return max(2, int(round(distance / advance)) + 1)

    def duration_for(self, distance: float, params=None, rest: float = 0.5):
        """(gait cycles, rollout seconds) to walk `distance` m and then stand `rest` s."""
        p = params or self.default_params()
        n = self.cycles_for(distance, p)
        return n, n * float(np.mean(p.swing_time)) * self.pattern.period + rest

    def for_distance(self, distance: float, params=None):
        """This gait stopping after the cycles that cover `distance` m (`duration_for`), and its seconds."""
        n, seconds = self.duration_for(distance, params)
        return dataclasses.replace(self, n_cycles=n), seconds

    def reflex_phase(self, params, state) -> jax.Array:
        """The gait clock's sine and cosine over one cycle (`state.t`, s)."""
        a = 2.0 * jnp.pi * state.t / (params.swing_time * self.pattern.period)
        return jnp.stack([jnp.sin(a), jnp.cos(a)])


@dataclasses.dataclass(frozen=True)
class GaitController(PatternClock):
    """Open-loop Luneckas 2020 gait: feet follow `leg_trajectory`, joints track them through IK.

    Start and stop: the printed trajectory puts half the legs at -l/2 and half at +l/2 at t = 0, a jump
    the servos would slide the feet through. So the horizontal stroke grows linearly from 0 over the
    first gait cycle and, when `n_cycles` is set, shrinks back to 0 over the last one; after that the
    robot stands still in its neutral stance. With both ramps, n cycles advance the body (n - 1) times
    the per-cycle advance (`duration_for` accounts for it)."""

    robot: RobotSpec
    gait: str = "tripod"
    dt: float = 0.02  # control period, s
    step_height: float = 0.03  # h_i, m
    n_cycles: int | None = None  # stop after this many gait cycles (None: walk on)

    def __post_init__(self):
        self._check_gait_and_dt()

    params_prefix = "gait"

    def params_defaults(self) -> GaitParams:
        """The paper's stroke and swing time for the gait (`GaitPattern`), h = `step_height`, forward."""
        p = self.pattern
        return GaitParams(step_length=jnp.asarray(p.step_length), step_height=jnp.asarray(self.step_height),
                          swing_time=jnp.asarray(p.swing_time), direction=jnp.asarray(0.0),
                          body_height_offset=jnp.asarray(0.0))

    def validate_params(self, params: GaitParams) -> None:
        """Host-side checks on concrete params, before tracing."""
        check_open_ranges("gait", params, {"step_length": (0.0, 0.2), "step_height": (0.0, 0.15),
                                           "swing_time": (0.05, 10.0)})

    def init(self, params: GaitParams, key) -> GaitState:
        del params, key
        return GaitState(t=jnp.asarray(0.0))

    def foot_targets(self, params: GaitParams, t):
        """(6, 3) foot centre targets in the torso frame at gait time t (s)."""
        p = self.pattern
        cycle = params.swing_time * p.period
        t_end = jnp.inf if self.n_cycles is None else self.n_cycles * cycle
        tw = jnp.minimum(t, t_end)
        x, y, z = leg_trajectory(tw / params.swing_time, jnp.asarray(p.phases, jnp.float32), p.period,
                                 params.step_length, params.step_height, params.direction)
        ramp = jnp.clip(jnp.minimum(tw, t_end - tw) / cycle, 0.0, 1.0)
        offs = jnp.stack([ramp * x, ramp * y, z], axis=-1)
        neutral = jnp.asarray(neutral_feet_body(self.robot))
        neutral = neutral.at[:, 2].add(-params.body_height_offset)
        return neutral + offs

    def step(self, params: GaitParams, state: GaitState, obs) -> Tuple[GaitState, jax.Array]:
        del obs  # open loop: the Luneckas 2020 baseline walks blind
        feet = self.foot_targets(params, state.t)
        q, _ = leg_ik(self.robot, body_to_leg(self.robot, feet))
        return GaitState(t=state.t + self.dt), q.reshape(-1)

    def trace(self, state: GaitState, obs):
        """Recorded per step: the measured torso pitch and roll (rad), as in Chen 2019 Fig. 6."""
        p, r = torso_pitch_roll(obs.torso_quat)
        return jnp.stack([p, r])
