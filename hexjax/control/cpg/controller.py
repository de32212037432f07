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
from hexjax.control.cpg.converter import (LinearConverter, contact_neurons, converter_output, linear_converter,
                                          quat_to_body, search_output)
from hexjax.control.cpg.params import CPG_GAITS, CPGParams, CPGState, gait_fields
from hexjax.control.gates import hard_gate, sigmoid_gate
from hexjax.control.vdp import NetworkParams, locked_state, network_rhs, rk4_step
from hexjax.world.robot import N_LEGS, RobotSpec, leg_fk, leg_ik, leg_to_body


@dataclasses.dataclass(frozen=True)
class CPGController(Controller):
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
        def g(x, temp):
            return self._gate(x, temp, p.smooth)

        tf, tp = p.temp_force, p.temp_phase
        lc = linear_converter(self.robot, p, self.stance_radial)
        z = s.z

        # Sensory neurons, Eqs. 7-9: toe force in the torso frame (x forward, y lateral, z up).
        f = quat_to_body(obs.torso_quat, obs.foot_force)
        # `feedback`, `elevator`, `searching` are params (0 or 1), so the variants of an experiment share one
        # compiled program: the feedback path is computed and selected (`fb`), the reflexes are gated
        fb = p.feedback > 0.5

        def pick(a, b):
            return jax.tree_util.tree_map(lambda x, y: jnp.where(fb, x, y), a, b)

        lam_ob, lam_td = contact_neurons(p, f, lambda x: g(x, tf))
        lam_ob, lam_td = pick((lam_ob, lam_td), (jnp.zeros(N_LEGS), jnp.ones(N_LEGS)))
        swing, hold, search, failed = s.swing, s.hold, s.search, s.failed
        # Table 2 ATD, "all legs get footholds" (Sect. 5.2): no leg is in the air. A leg is airborne while it
        # swings, searches or has given up; a stance leg, or a swing leg that stopped on a touchdown (sTD),
        # has its foothold. Counting feet above F_contact-z instead would stall the gait whenever the
        # statically indeterminate load leaves one stance foot lightly loaded.
        # A leg that gave up a search (`failed`) waits at its AEP posture; unless the gait walks on (`walk_on`),
        # it counts as airborne and as running a reflex, so it holds every other leg for good (Fig. 9c).
        waiting = failed * (1.0 - p.walk_on)
        airborne = swing * (1.0 - hold) + search + waiting
        atd = jnp.prod(1.0 - jnp.clip(airborne, 0.0, 1.0))

        elev_on, elev, offset, hold_q, q_ref = s.elev_on, s.elev, s.offset, s.hold_q, s.q_ref
        level, searched = s.level, s.searched
        search_n = s.search_n
        n_elev, n_search, n_found, n_fail, depth = s.n_elev, s.n_search, s.n_found, s.n_fail, s.depth
        one = jnp.ones(N_LEGS)
        kept, paused = s.kept, s.paused
        before = (z, swing, elev_on, elev, offset, hold, hold_q, kept, level, searched, paused, depth, n_found,
                  search, n_elev)

        # the feedback path, blocks (1)-(4b); selected by `fb` after it
        # (1) ATD releases every prolonged leg: swing-prolong -> stance, stance-prolong -> swing; a stance
        # leg frozen mid-stance by another leg's reflex (`paused`) resumes its stance.
        toggle = hold * atd * (1.0 - s.paused)
        to_stance, to_swing = toggle * swing, toggle * (1.0 - swing)
        # Table 2 aTD: a stance ends when the alien group touches down. Generalised to Eq. 16 gaits: the
        # legs of the swing slot after the one landing now lift off, wherever they are in their stance.
        nxt = jnp.mod(p.leg_slot + 1.0, p.duty)
        # slots are whole numbers: matching them is structure, not a decision, so it is exact in both forms
        follows = (jnp.abs(p.leg_slot[:, None] - nxt[None, :]) < 0.5).astype(jnp.float32)
        forced = (1.0 - swing) * (1.0 - toggle) * atd * jnp.clip(follows @ to_stance, 0.0, 1.0)
        to_swing = to_swing + forced
        rel = toggle + forced
        # The leader keeps its position and amplitude and moves on in the new direction at the new
        # Eq. 16 frequency (a swing stopped early by a touchdown turns back from where it stopped).
        w_sw, w_st = self._leader_omegas(p)
        y1 = z[:, 0, 1]
        y1_st = -jnp.abs(y1) * (w_st / w_sw)
        y1_sw = jnp.abs(y1) * (w_sw / w_st)
        z = z.at[:, 0, 1].set(y1 + to_stance * (y1_st - y1) + to_swing * (y1_sw - y1))
        z = self._reset_followers(z, rel)
        swing = swing + rel * (1.0 - 2.0 * swing)
        failed = failed * (1.0 - rel)  # released with its group (only reached with walk_on: else ATD never comes)
        elev_on, elev = elev_on * (1.0 - to_stance), elev * (1.0 - to_stance)
        zero3 = jnp.zeros((N_LEGS, 3))
        q_new = converter_output(p, lc, z, swing, elev, zero3, zero3, searched)  # the bare converter
        # Offsets carry a searched foothold, or one found more than `raised_tolerance` above the feet in
        # stance (the top of a step), through the next stance, and keep the PEP->swing hand-over continuous.
        # After an ordinary touchdown the stance converter takes over as it is: an offset there would
        # ratchet the body down by every slightly early touchdown.
        above = self._height_above_support(obs, s.q_cmd, s.swing, s.level)
        raised = g(above - p.raised_tolerance, p.temp_height)
        carry = to_swing + to_stance * (1.0 - (1.0 - s.kept) * (1.0 - raised))
        offset = offset + rel[:, None] * (carry[:, None] * (s.q_cmd - q_new) - offset)
        kept = s.kept * (1.0 - rel)
        # A leg released into stance records the height of a raised foothold (more than `raised_tolerance`
        # up): measured afresh along gravity against the other feet at every touchdown, so a sagging or
        # tilted torso does not build up in it. A searched foothold is held as found instead.
        level = level + to_stance * (raised * (1.0 - s.kept) * above - level)
        searched = s.searched + to_stance * (s.kept - s.searched)
        hold = hold * (1.0 - atd)
        paused = s.paused * (1.0 - atd)

        # (2) A searching leg that touches down has found its foothold: stop, hold the posture, and
        # put the network at the end of swing so the next stance starts in step with the others.
        found = search * lam_td
        q_meas = obs.qpos.reshape(N_LEGS, 3)
        z_foot = leg_fk(self.robot, q_meas)[:, 2]
        depth = jnp.maximum(depth, found * (lc.z_aep - z_foot))
        n_found = n_found + found
        z_end = locked_state(jnp.zeros(N_LEGS), self._omegas(p, one, jnp.zeros(N_LEGS))[:, 0])
        z = z + found[:, None, None] * (z_end - z)
        hold_q = hold_q + found[:, None] * (s.q_cmd - hold_q)
        # the leg holds the posture it found; at release it becomes the stance offset (`kept`)
        hold = hold + found * (1.0 - hold)
        kept = kept + found * (1.0 - kept)
        search = search * (1.0 - found)

        # (3) Elevator reflex, Eqs. 10-11: rising edge of lambda_ob while the leg sweeps forward (gated by
        # the `elevator` param).
        rise = lam_ob * (1.0 - s.lam_ob)
        # "halfway of the swing": once the leader is past `elevator_window`; at lift-off the foot
        # still carries its stance load and friction alone can exceed F_contact-x/y.
        # Once per swing: a regenerated swing that meets the face again goes on and lands in front
        # of it (the next swing then meets the face earlier and clears it), instead of retracting
        # again and again against a face near its AEP.
        ert = (swing * (1.0 - hold) * (1.0 - search) * (1.0 - elev_on) * g(z[:, 0, 1], tp)
               * g(z[:, 0, 0] - p.elevator_window, tp) * rise) * p.elevator
        scale = self._omegas(p, one, jnp.zeros(N_LEGS))[:, 0] / p.net.omega[0]
        target = p.elevator_y1 * scale
        z = z.at[:, 0, 1].add(ert * (target - z[:, 0, 1]))
        z = self._reset_followers(z, ert)
        elev_on = elev_on + ert * (1.0 - elev_on)
        n_elev = n_elev + ert

        # (4) Early touchdown past the apex aborts the swing: swing-prolong (Table 2 sTD).
        # A foot scraping an edge (lambda_ob on) has not landed.
        etd = (swing * (1.0 - hold) * (1.0 - search) * lam_td * (1.0 - lam_ob)
               * g(z[:, 0, 0], tp) * g(z[:, 0, 1], tp))
        hold_q = hold_q + etd[:, None] * (s.q_cmd - hold_q)
        hold = hold + etd * (1.0 - hold)

        # (4b) "The FSM synchronizes the legs by enforcing the leg on the ground come into the Swing/Stance
        # Prolong state until the leg executing local reflex reaches the touchdown state" (Sect. 5.2):
        # while any leg runs a reflex, every stance leg freezes where it is.
        reflex = 1.0 - jnp.prod(1.0 - jnp.clip(elev_on + search + waiting, 0.0, 1.0))
        pz = reflex * (1.0 - swing) * (1.0 - hold)
        hold_q = hold_q + pz[:, None] * (s.q_cmd - hold_q)
        hold = hold + pz * (1.0 - hold)
        paused = paused + pz * (1.0 - paused)
        (z, swing, elev_on, elev, offset, hold, hold_q, kept, level, searched, paused, depth, n_found, search,
         n_elev) = pick((z, swing, elev_on, elev, offset, hold, hold_q, kept, level, searched, paused, depth, n_found,
                         search, n_elev), before)

        # (5) Integrate the network one control period (RK4); prolonged legs are frozen.
        omega = self._omegas(p, swing, search)
        k = p.net.k[None, :] * jnp.concatenate([(1.0 - search)[:, None] * jnp.ones((1, 2)), jnp.ones((N_LEGS, 2))], -1)
        rate = (1.0 - hold)[:, None, None]

        def rhs(zz):
            return rate * network_rhs(zz, omega, p.net.eps[None, :], p.net.b[None, :], k)

        z_old = z
        z = rk4_step(rhs, z, self.dt)
        elev = jnp.minimum(1.0, elev + elev_on * self.dt / p.ramp_time)
        y_old, y_new, x_new = z_old[:, 0, 1], z[:, 0, 1], z[:, 0, 0]
        cross_fwd_end = g(y_old, tp) * g(-y_new, tp) * g(x_new, tp)  # leader at its AEP turning point
        cross_back_end = g(-y_old, tp) * g(y_new, tp) * g(-x_new, tp)  # leader at its PEP turning point

        dq_level = self._level_offset(lc, level)
        q_lc = converter_output(p, lc, z, swing, elev, offset, dq_level, searched)
        q_search = search_output(p, lc, z, q_ref, search_n)

        blind = (hold_q, hold, q_ref, search_n, search, n_search, failed, n_fail, q_search)
        # the feedback path, block (6); selected by `fb` after it
        # (6) End of swing: touchdown -> swing-prolong; none -> searching reflex (SRT, Eqs. 12-15).
        end_sw = swing * (1.0 - hold) * (1.0 - search) * cross_fwd_end
        srt = end_sw * (1.0 - lam_td) * p.searching
        stop = end_sw - srt
        hold_q = hold_q + stop[:, None] * (q_lc - hold_q)
        hold = hold + stop * (1.0 - hold)
        q_ref = q_ref + srt[:, None] * (q_lc - q_ref)
        search_n = search_n * (1.0 - srt)
        search = search + srt * (1.0 - search)
        n_search = n_search + srt
        # End of stance -> stance-prolong until ATD (aTD of the alien group is part of ATD).
        end_st = (1.0 - swing) * (1.0 - hold) * cross_back_end
        hold_q = hold_q + end_st[:, None] * (q_lc - hold_q)
        hold = hold + end_st * (1.0 - hold)
        # A search period ends when the slowed leader is back at the AEP: search deeper, or give up.
        period = search * cross_fwd_end * (1.0 - srt)
        more = g(self.search_periods - 1.5 - search_n, tp)
        search_n = search_n + period * more
        give_up = period * (1.0 - more)
        failed = failed + give_up * (1.0 - failed)
        hold_q = hold_q + give_up[:, None] * (q_ref - hold_q)
        hold = hold + give_up * (1.0 - hold)
        search = search * (1.0 - give_up)
        n_fail = n_fail + give_up
        q_search = search_output(p, lc, z, q_ref, search_n)
        # blind: the swing follows the leader's sign and the converter runs bare
        swing_blind = g(z[:, 0, 1], tp)
        q_lc_blind = converter_output(p, lc, z, swing_blind, elev, offset, dq_level, searched)
        (hold_q, hold, q_ref, search_n, search, n_search, failed, n_fail, q_search, swing, q_lc) = pick(
            (hold_q, hold, q_ref, search_n, search, n_search, failed, n_fail, q_search, swing, q_lc),
            blind + (swing_blind, q_lc_blind))

        q_free = search[:, None] * q_search + (1.0 - search[:, None]) * q_lc
        q = hold[:, None] * hold_q + (1.0 - hold[:, None]) * q_free
        any_search = 1.0 - jnp.prod(1.0 - search)
        wait = hold * (1.0 - swing) * any_search
        new = CPGState(z=z, swing=swing, hold=hold, elev_on=elev_on, elev=elev, search=search, search_n=search_n,
                       failed=failed, q_ref=q_ref, hold_q=hold_q, offset=offset, lam_ob=lam_ob, q_cmd=q,
                       q_meas=obs.qpos.reshape(N_LEGS, 3),
                       kept=kept, level=level, searched=searched, paused=paused,
                       n_elev=n_elev, n_search=n_search, n_found=n_found, n_fail=n_fail, depth=depth,
                       wait_steps=s.wait_steps + wait, t=s.t + self.dt)
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
