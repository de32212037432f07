"""The Yu 2019 CPG controller: network, converter, sensory neurons, reflexes and the event FSM in one
control step (the readings behind it: `hexjax.control.cpg`'s docstring, docs/cpg.md)."""

from __future__ import annotations

import dataclasses
import math
from typing import Tuple

import jax
import jax.numpy as jnp

from hexjax.control.base import Controller
from hexjax.control.cpg.checks import check_params
from hexjax.control.cpg.fsm import StepBlocks
from hexjax.control.cpg.converter import (LinearConverter, converter_output, linear_converter,
                                          quat_to_body)
from hexjax.control.cpg.params import CPG_GAITS, CPGParams, CPGState, gait_fields
from hexjax.control.gates import hard_gate, sigmoid_gate
from hexjax.control.vdp import NetworkParams, locked_state
from hexjax.world.robot import N_LEGS, RobotSpec, leg_fk, leg_ik, leg_to_body

# what the event blocks of a step may change; with the `feedback` param off the step keeps them as they were
FEEDBACK_FIELDS = ("z", "swing", "elev_on", "elev", "offset", "hold", "hold_q", "kept", "level", "searched", "paused",
                   "depth", "n_found", "search", "n_elev")


@dataclasses.dataclass(frozen=True)
class CPGController(StepBlocks, Controller):
    """The Yu 2019 controller (its readings of the paper: `hexjax.control.cpg`). Static configuration only;
    numbers are in `CPGParams` (`default_params`).

    robot: RobotSpec (the paper's is `yu2019`); gait: 'tripod', 'tetrapod' or 'wave' (sets the default
    params, `gait_fields`; the gait itself is traced, so gaits share one compiled rollout:
    `default_params(**gait_fields("wave"))`); dt: control period, s (the
    network is integrated with one RK4 step per period); feedback: False runs the bare network and
    converter blind (no FSM, no reflexes); elevator / searching: enable each reflex (these three set the
    default params of the same names, which the step reads: one program serves every variant); smooth: sigmoid
    gates instead of step functions (likewise a param); straight_through: with the smooth param on, each
    gate keeps the step function's value and takes the sigmoid's derivative (`hexjax.control.gates`: the
    hard rollout, differentiable); search_periods: how many slowed leader periods a search lasts before the
    leg gives up (4 reach 50 mm below the AEP on `yu2019`; the first alone 21 mm); follower_reset: see
    `hexjax.control.cpg`. step_length, clearance (h_max), elevated_clearance (m) set the default params: 40 and
    80 mm are Sect. 6.1.1's; the paper gives no stride for its virtual model, 70 mm keeps neighbouring feet
    of the 250 mm body apart. stance_radial (m): coxa joint to the foot's straight walking line; 0.22 m
    puts the femur joint ~0.17 m from the foot so that the paper's search amplitudes dig ~20 mm per
    period (its "0 to 28 mm", Sect. 6.1.2); static because it shapes the posture the robot settles in."""

    robot: RobotSpec
    gait: str = "tripod"
    dt: float = 0.02
    feedback: bool = True
    elevator: bool = True
    searching: bool = True
    smooth: bool = False
    straight_through: bool = False
    follower_reset: bool = True
    search_periods: int = 4
    step_length: float = 0.07
    clearance: float = 0.04
    elevated_clearance: float = 0.08
    stance_radial: float = 0.22

    def __post_init__(self):
        if self.gait not in CPG_GAITS:
            raise ValueError(f"cpg.gait={self.gait!r}: choose one of {sorted(CPG_GAITS)}")
        if not (0 < self.dt <= 0.05):
            raise ValueError(f"cpg.dt={self.dt!r}: must be in (0, 0.05] s")
        if self.straight_through and not self.smooth:
            raise ValueError("cpg.straight_through=True needs smooth=True: it changes the smooth form's derivative")
        if self.search_periods < 1:
            raise ValueError(f"cpg.search_periods={self.search_periods!r}: must be >= 1")
        if not (math.isfinite(self.stance_radial) and self.stance_radial > 0):
            raise ValueError(f"cpg.stance_radial={self.stance_radial!r}: must be a finite number > 0")

    params_prefix = "cpg"

    # Parameters ---------------------------------------------------------------------------------
    def params_defaults(self) -> CPGParams:
        """Table 1's network, the `gait` (Eq. 16), and the converter, threshold and reflex numbers of Sect. 6."""
        g = gait_fields(self.gait)
        return CPGParams(
            net=NetworkParams.table1(), duty=jnp.asarray(g["duty"]),
            leg_slot=jnp.asarray(g["leg_slot"], jnp.float32), step_length=jnp.asarray(self.step_length),
            clearance=jnp.asarray(self.clearance), elevated_clearance=jnp.asarray(self.elevated_clearance),
            body_height=jnp.asarray(self.robot.hip_height), lc_trim=jnp.zeros((2, 2, 3)),
            f_contact=jnp.array([10.0, 10.0, 2.0]), leg_trim=jnp.zeros((N_LEGS, 2, 2, 3)),
            leg_clearance=jnp.zeros(N_LEGS), leg_f_scale=jnp.ones((N_LEGS, 3)), ramp_time=jnp.asarray(0.5),
            elevator_y1=jnp.asarray(-1.0), elevator_window=jnp.asarray(-0.5),
            search_amp=jnp.radians(jnp.array([7.5, 4.0, 2.5])),
            search_sigma=jnp.asarray(1.2), search_freq=jnp.array([0.5, 1.5, 1.5]), raised_tolerance=jnp.asarray(0.015),
            temp_force=jnp.asarray(1.0), temp_phase=jnp.asarray(0.05), temp_height=jnp.asarray(0.002),
            feedback=jnp.asarray(float(self.feedback)), elevator=jnp.asarray(float(self.elevator)),
            searching=jnp.asarray(float(self.searching)), smooth=jnp.asarray(float(self.smooth)),
            walk_on=jnp.asarray(0.0))

    def for_distance(self, distance: float, params=None):
        """No stop (the CPG walks on): `distance` at the nominal speed, one stroke a leader period
        2 pi / omega_1, plus a period to start."""
        p = params or self.default_params()
        period = 2 * math.pi / float(p.net.omega[0])
        return self, distance / (float(p.step_length) / period) + period

    def validate_params(self, p: CPGParams) -> None:
        """Host-side checks on concrete params, before tracing; names the field and value (`checks.py`)."""
        check_params(self.robot, self.stance_radial, p)

    # Gates ----------------------------------------------------------------------------------------
    def _gate(self, x, temp, smooth):
        """1 where x > 0: a step in the hard form (`smooth` param 0), sigmoid(x / temp) in the smooth one (1), or
        with `straight_through` the step in value and the sigmoid in reverse mode (`hexjax.control.gates`)."""
        on = smooth > 0.5
        soft = sigmoid_gate(x, temp, self.straight_through)
        return jnp.where(on, soft, hard_gate(x))

    # Network frequencies (Eqs. 12, 16) ----------------------------------------------------------------
    @staticmethod
    def _leader_omegas(p: CPGParams):
        """Eq. 16: leader frequency in swing, gamma pi / T_g, and in stance, gamma pi / ((gamma - 1) T_g),
        with the gait period T_g = 2 pi / omega_1 of Table 1 (5 s), so the tripod (gamma = 2) keeps omega_1."""
        w_table = p.net.omega[0]
        return p.duty * w_table / 2.0, p.duty * w_table / (2.0 * (p.duty - 1.0))

    @classmethod
    def _omegas(cls, p: CPGParams, swing, search):
        """(6, 3) natural frequencies: Eq. 16 leader (swing / stance), followers at twice it, Eq. 12 in search."""
        w_table = p.net.omega[0]
        w_sw, w_st = cls._leader_omegas(p)
        w1 = swing * w_sw + (1.0 - swing) * w_st
        ratio = p.net.omega / w_table  # (1, 2, 2) in Table 1
        w = w1[:, None] * ratio[None, :]
        factor = 1.0 + search[:, None] * (p.search_freq[None, :] - 1.0)
        return w * factor

    def initial_state_network(self, p: CPGParams):
        """(z (6, 3, 2), swing (6,)): legs in slot 0 at the start of swing (leader at [-1, 0]), the others
        in stance, evenly spaced so that each lifts off one slot after the previous one (Sect. 5.1)."""
        k = p.leg_slot
        stance_left = k / jnp.maximum(p.duty - 1.0, 1.0)
        theta = jnp.where(k < 0.5, math.pi, math.pi * (1.0 - stance_left))
        swing = (k < 0.5).astype(jnp.float32)
        w = self._omegas(p, swing, jnp.zeros(N_LEGS))[:, 0]
        z = locked_state(theta, w)
        # a leg that starts a swing is at the stance->swing turning point: zero rate
        return z, swing

    def init(self, p: CPGParams, key) -> CPGState:
        del key
        z, swing = self.initial_state_network(p)
        lc = linear_converter(self.robot, p, self.stance_radial)
        zeros, zeros3 = jnp.zeros(N_LEGS), jnp.zeros((N_LEGS, 3))
        q0 = converter_output(p, lc, z, swing, zeros, zeros3, zeros3, zeros)
        return CPGState(z=z, swing=swing, hold=zeros, elev_on=zeros, elev=zeros, search=zeros, search_n=zeros,
                        failed=zeros, q_ref=q0, hold_q=q0, offset=zeros3, lam_ob=zeros, q_cmd=q0, q_meas=q0, kept=zeros,
                        level=zeros, searched=zeros, paused=zeros,
                        n_elev=zeros, n_search=zeros, n_found=zeros, n_fail=zeros, depth=zeros,
                        wait_steps=zeros, t=jnp.asarray(0.0))

    def initial_action(self, p: CPGParams):
        """(18,) joint targets of the first control step: the robot settles in this posture."""
        return self.init(p, None).q_cmd.reshape(-1)

    # One control step ------------------------------------------------------------------------------
    def step(self, p: CPGParams, s: CPGState, obs) -> Tuple[CPGState, jax.Array]:
        """One control period: the contact neurons, the event FSM and the reflexes on the feedback path (selected
        by the `feedback` param), the network's RK4 step, the converter; blocks in `hexjax.control.cpg.fsm`."""
        v = self._sense(p, s, obs)
        before = tuple(getattr(v, n) for n in FEEDBACK_FIELDS)
        for block in (self._release, self._found, self._elevator, self._early_touchdown, self._pause):
            block(p, s, obs, v)
        after = v.pick(tuple(getattr(v, n) for n in FEEDBACK_FIELDS), before)  # the feedback path, or none of it
        for n, x in zip(FEEDBACK_FIELDS, after):
            setattr(v, n, x)
        self._integrate(p, s, obs, v)
        self._end_of_phase(p, s, obs, v)
        q_free = v.search[:, None] * v.q_search + (1.0 - v.search[:, None]) * v.q_lc
        q = v.hold[:, None] * v.hold_q + (1.0 - v.hold[:, None]) * q_free
        any_search = 1.0 - jnp.prod(1.0 - v.search)
        wait = v.hold * (1.0 - v.swing) * any_search
        new = CPGState(z=v.z, swing=v.swing, hold=v.hold, elev_on=v.elev_on, elev=v.elev, search=v.search,
                       search_n=v.search_n, failed=v.failed, q_ref=v.q_ref, hold_q=v.hold_q, offset=v.offset,
                       lam_ob=v.lam_ob, q_cmd=q, q_meas=obs.qpos.reshape(N_LEGS, 3), kept=v.kept, level=v.level,
                       searched=v.searched, paused=v.paused, n_elev=v.n_elev, n_search=v.n_search,
                       n_found=v.n_found, n_fail=v.n_fail, depth=v.depth, wait_steps=s.wait_steps + wait,
                       t=s.t + self.dt)
        return new, q.reshape(-1)

    def _level_offset(self, lc: LinearConverter, level):
        """(6, 3) rad: joints that move each leg's nominal AEP up by `level` (6,) m in the leg frame."""
        q1, _ = leg_ik(self.robot, lc.aep.at[:, 2].add(level))
        return q1 - lc.q_aep

    def _height_above_support(self, obs, q_cmd, swing, level):
        """(6,) m: each foot's height (at its commanded joints) above the ground datum of the stance feet:
        the mean over stance feet of their height (at their measured joints) less their own foothold level.
        Along gravity, from leg kinematics and the torso attitude. Blind: no terrain map, no torso height; a
        foot that lands on top of a step stands out, a torso that sags or tilts as a whole does not."""
        up_world = jnp.array([0.0, 0.0, 1.0])
        up = quat_to_body(obs.torso_quat, up_world[None, :])[0]  # world up in the torso frame
        z_cmd = leg_to_body(self.robot, leg_fk(self.robot, q_cmd)) @ up
        z_meas = leg_to_body(self.robot, leg_fk(self.robot, obs.qpos.reshape(N_LEGS, 3))) @ up
        # Each stance foot's own level is taken off: against the plain mean, a foot landing on a step top
        # next to a stance foot already up there looked only 2/3 of the step height up.
        w = 1.0 - swing
        z_ref = jnp.sum(w * (z_meas - level)) / jnp.maximum(jnp.sum(w), 1e-6)
        return z_cmd - z_ref

    def _reset_followers(self, z, w):
        """Put the followers' rates on the locked curve y_i = -4 x_1 y_1 where w = 1 (readings in `hexjax.control.cpg`)."""
        if not self.follower_reset:
            return z
        target = -4.0 * z[:, 0, 0] * z[:, 0, 1]
        yf = z[:, 1:, 1] + w[:, None] * (target[:, None] - z[:, 1:, 1])
        return z.at[:, 1:, 1].set(yf)

    @staticmethod
    def mode(s: CPGState):
        """(..., 6) int mode per leg, indices into MODE_NAMES (hard form; smooth values are rounded)."""
        sw, hd, se, fl = (jnp.round(a) for a in (s.swing, s.hold, s.search, s.failed))
        on = (sw > 0).astype(jnp.int32)
        return jnp.where(fl > 0, 5, jnp.where(se > 0, 4, jnp.where(hd > 0, 2 + on, on)))

    def trace(self, s: CPGState, obs):
        """Per-step record for plots: neuron outputs x (6, 3), leader rate y1 (6,), mode (6,), joint command
        (6, 3), lambda_ob (6,), elevator ramp (6,), toe force in the torso frame (6, 3) N."""
        return dict(x=s.z[..., 0], y1=s.z[:, 0, 1], mode=self.mode(s), q_cmd=s.q_cmd, lam_ob=s.lam_ob, elev=s.elev,
                    force=quat_to_body(obs.torso_quat, obs.foot_force), quat=obs.torso_quat)

    def reflex_phase(self, p: CPGParams, s: CPGState) -> jax.Array:
        """Each leg's leader oscillator, neuron and rate (z[:, 0]: 6 x 2), for a learned reflex layer."""
        return s.z[:, 0].reshape(-1)
