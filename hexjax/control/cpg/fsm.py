"""The Yu 2019 CPG controller's control step (`CPGController.step`), cut along its blocks: the sensory
neurons (Eqs. 7-9), Table 2's events (ATD, aTD, sTD), the elevator reflex (Eqs. 10-11), the network's RK4 step
(Eqs. 1-5) and the searching reflex (Eqs. 12-15). Each block reads and updates the step's working values, a
namespace `v` (the state's fields as they stand, the contact neurons, the gates `g` and the feedback selector
`pick`); the blocks run in the order `CPGController.step` calls them, so the step is the same computation as
one long function."""

from __future__ import annotations

import types

import jax
import jax.numpy as jnp

from hexjax.control.cpg.converter import (contact_neurons, converter_output, linear_converter, quat_to_body,
                                          search_output)
from hexjax.control.vdp import locked_state, network_rhs, rk4_step
from hexjax.world.robot import N_LEGS, leg_fk


class StepBlocks:
    """The blocks of `CPGController.step` (a mixin of `CPGController`: they read its robot, period and helpers)."""

    def _sense(self, p, s, obs) -> types.SimpleNamespace:
        """The step's working values: the state's fields, the contact neurons lambda_ob / lambda_td (Eqs. 7-9)
        and Table 2's ATD (no leg in the air)."""
        v = types.SimpleNamespace()

        def g(x, temp):
            return self._gate(x, temp, p.smooth)

        v.tf, v.tp = p.temp_force, p.temp_phase
        v.lc = linear_converter(self.robot, p, self.stance_radial)
        v.z = s.z

        # Sensory neurons, Eqs. 7-9: toe force in the torso frame (x forward, y lateral, z up).
        f = quat_to_body(obs.torso_quat, obs.foot_force)
        # `feedback`, `elevator`, `searching` are params (0 or 1), so the variants of an experiment share one
        # compiled program: the feedback path is computed and selected (`fb`), the reflexes are gated
        v.fb = p.feedback > 0.5

        def pick(a, b):
            return jax.tree_util.tree_map(lambda x, y: jnp.where(v.fb, x, y), a, b)

        v.lam_ob, v.lam_td = contact_neurons(p, f, lambda x: g(x, v.tf))
        v.lam_ob, v.lam_td = pick((v.lam_ob, v.lam_td), (jnp.zeros(N_LEGS), jnp.ones(N_LEGS)))
        v.swing, v.hold, v.search, v.failed = s.swing, s.hold, s.search, s.failed
        # Table 2 ATD, "all legs get footholds" (Sect. 5.2): no leg is in the air. A leg is airborne while it
        # swings, searches or has given up; a stance leg, or a swing leg that stopped on a touchdown (sTD),
        # has its foothold. Counting feet above F_contact-z instead would stall the gait whenever the
        # statically indeterminate load leaves one stance foot lightly loaded.
        # A leg that gave up a search (`failed`) waits at its AEP posture; unless the gait walks on (`walk_on`),
        # it counts as airborne and as running a reflex, so it holds every other leg for good (Fig. 9c).
        v.waiting = v.failed * (1.0 - p.walk_on)
        airborne = v.swing * (1.0 - v.hold) + v.search + v.waiting
        v.atd = jnp.prod(1.0 - jnp.clip(airborne, 0.0, 1.0))

        v.elev_on, v.elev, v.offset, v.hold_q, v.q_ref = s.elev_on, s.elev, s.offset, s.hold_q, s.q_ref
        v.level, v.searched = s.level, s.searched
        v.search_n = s.search_n
        v.n_elev, v.n_search, v.n_found, v.n_fail, v.depth = s.n_elev, s.n_search, s.n_found, s.n_fail, s.depth
        v.one = jnp.ones(N_LEGS)
        v.kept, v.paused = s.kept, s.paused
        v.g, v.pick = g, pick
        return v

    def _release(self, p, s, obs, v) -> None:
        """(1) ATD releases every prolonged leg; aTD lifts the next swing slot off."""
        g = v.g
        # the feedback path, blocks (1)-(4b); selected by `fb` after it
        # (1) ATD releases every prolonged leg: swing-prolong -> stance, stance-prolong -> swing; a stance
        # leg frozen mid-stance by another leg's reflex (`paused`) resumes its stance.
        toggle = v.hold * v.atd * (1.0 - s.paused)
        to_stance, to_swing = toggle * v.swing, toggle * (1.0 - v.swing)
        # Table 2 aTD: a stance ends when the alien group touches down. Generalised to Eq. 16 gaits: the
        # legs of the swing slot after the one landing now lift off, wherever they are in their stance.
        nxt = jnp.mod(p.leg_slot + 1.0, p.duty)
        # slots are whole numbers: matching them is structure, not a decision, so it is exact in both forms
        follows = (jnp.abs(p.leg_slot[:, None] - nxt[None, :]) < 0.5).astype(jnp.float32)
        forced = (1.0 - v.swing) * (1.0 - toggle) * v.atd * jnp.clip(follows @ to_stance, 0.0, 1.0)
        to_swing = to_swing + forced
        rel = toggle + forced
        # The leader keeps its position and amplitude and moves on in the new direction at the new
        # Eq. 16 frequency (a swing stopped early by a touchdown turns back from where it stopped).
        w_sw, w_st = self._leader_omegas(p)
        y1 = v.z[:, 0, 1]
        y1_st = -jnp.abs(y1) * (w_st / w_sw)
        y1_sw = jnp.abs(y1) * (w_sw / w_st)
        v.z = v.z.at[:, 0, 1].set(y1 + to_stance * (y1_st - y1) + to_swing * (y1_sw - y1))
        v.z = self._reset_followers(v.z, rel)
        v.swing = v.swing + rel * (1.0 - 2.0 * v.swing)
        v.failed = v.failed * (1.0 - rel)  # released with its group (only reached with walk_on: else ATD never comes)
        v.elev_on, v.elev = v.elev_on * (1.0 - to_stance), v.elev * (1.0 - to_stance)
        zero3 = jnp.zeros((N_LEGS, 3))
        q_new = converter_output(p, v.lc, v.z, v.swing, v.elev, zero3, zero3, v.searched)  # the bare converter
        # Offsets carry a searched foothold, or one found more than `raised_tolerance` above the feet in
        # stance (the top of a step), through the next stance, and keep the PEP->swing hand-over continuous.
        # After an ordinary touchdown the stance converter takes over as it is: an offset there would
        # ratchet the body down by every slightly early touchdown.
        above = self._height_above_support(obs, s.q_cmd, s.swing, s.level)
        raised = g(above - p.raised_tolerance, p.temp_height)
        carry = to_swing + to_stance * (1.0 - (1.0 - s.kept) * (1.0 - raised))
        v.offset = v.offset + rel[:, None] * (carry[:, None] * (s.q_cmd - q_new) - v.offset)
        v.kept = s.kept * (1.0 - rel)
        # A leg released into stance records the height of a raised foothold (more than `raised_tolerance`
        # up): measured afresh along gravity against the other feet at every touchdown, so a sagging or
        # tilted torso does not build up in it. A searched foothold is held as found instead.
        v.level = v.level + to_stance * (raised * (1.0 - s.kept) * above - v.level)
        v.searched = s.searched + to_stance * (s.kept - s.searched)
        v.hold = v.hold * (1.0 - v.atd)
        v.paused = s.paused * (1.0 - v.atd)

    def _found(self, p, s, obs, v) -> None:
        """(2) A searching leg that touches down has found its foothold."""
        # (2) A searching leg that touches down has found its foothold: stop, hold the posture, and
        # put the network at the end of swing so the next stance starts in step with the others.
        found = v.search * v.lam_td
        q_meas = obs.qpos.reshape(N_LEGS, 3)
        z_foot = leg_fk(self.robot, q_meas)[:, 2]
        v.depth = jnp.maximum(v.depth, found * (v.lc.z_aep - z_foot))
        v.n_found = v.n_found + found
        z_end = locked_state(jnp.zeros(N_LEGS), self._omegas(p, v.one, jnp.zeros(N_LEGS))[:, 0])
        v.z = v.z + found[:, None, None] * (z_end - v.z)
        v.hold_q = v.hold_q + found[:, None] * (s.q_cmd - v.hold_q)
        # the leg holds the posture it found; at release it becomes the stance offset (`kept`)
        v.hold = v.hold + found * (1.0 - v.hold)
        v.kept = v.kept + found * (1.0 - v.kept)
        v.search = v.search * (1.0 - found)

    def _elevator(self, p, s, obs, v) -> None:
        """(3) The elevator reflex (Eqs. 10-11)."""
        g = v.g
        # (3) Elevator reflex, Eqs. 10-11: rising edge of lambda_ob while the leg sweeps forward (gated by
        # the `elevator` param).
        rise = v.lam_ob * (1.0 - s.lam_ob)
        # "halfway of the swing": once the leader is past `elevator_window`; at lift-off the foot
        # still carries its stance load and friction alone can exceed F_contact-x/y.
        # Once per swing: a regenerated swing that meets the face again goes on and lands in front
        # of it (the next swing then meets the face earlier and clears it), instead of retracting
        # again and again against a face near its AEP.
        ert = (v.swing * (1.0 - v.hold) * (1.0 - v.search) * (1.0 - v.elev_on) * g(v.z[:, 0, 1], v.tp)
               * g(v.z[:, 0, 0] - p.elevator_window, v.tp) * rise) * p.elevator
        scale = self._omegas(p, v.one, jnp.zeros(N_LEGS))[:, 0] / p.net.omega[0]
        target = p.elevator_y1 * scale
        v.z = v.z.at[:, 0, 1].add(ert * (target - v.z[:, 0, 1]))
        v.z = self._reset_followers(v.z, ert)
        v.elev_on = v.elev_on + ert * (1.0 - v.elev_on)
        v.n_elev = v.n_elev + ert

    def _early_touchdown(self, p, s, obs, v) -> None:
        """(4) An early touchdown past the apex aborts the swing (Table 2 sTD)."""
        g = v.g
        # (4) Early touchdown past the apex aborts the swing: swing-prolong (Table 2 sTD).
        # A foot scraping an edge (lambda_ob on) has not landed.
        etd = (v.swing * (1.0 - v.hold) * (1.0 - v.search) * v.lam_td * (1.0 - v.lam_ob)
               * g(v.z[:, 0, 0], v.tp) * g(v.z[:, 0, 1], v.tp))
        v.hold_q = v.hold_q + etd[:, None] * (s.q_cmd - v.hold_q)
        v.hold = v.hold + etd * (1.0 - v.hold)

    def _pause(self, p, s, obs, v) -> None:
        """(4b) While any leg runs a reflex, every stance leg freezes where it is (Sect. 5.2)."""
        # (4b) "The FSM synchronizes the legs by enforcing the leg on the ground come into the Swing/Stance
        # Prolong state until the leg executing local reflex reaches the touchdown state" (Sect. 5.2):
        # while any leg runs a reflex, every stance leg freezes where it is.
        reflex = 1.0 - jnp.prod(1.0 - jnp.clip(v.elev_on + v.search + v.waiting, 0.0, 1.0))
        pz = reflex * (1.0 - v.swing) * (1.0 - v.hold)
        v.hold_q = v.hold_q + pz[:, None] * (s.q_cmd - v.hold_q)
        v.hold = v.hold + pz * (1.0 - v.hold)
        v.paused = v.paused + pz * (1.0 - v.paused)

    def _integrate(self, p, s, obs, v) -> None:
        """(5) The network integrated one control period (RK4); the converter's joint targets."""
        g = v.g
        # (5) Integrate the network one control period (RK4); prolonged legs are frozen.
        omega = self._omegas(p, v.swing, v.search)
        k = p.net.k[None, :] * jnp.concatenate([(1.0 - v.search)[:, None] * jnp.ones((1, 2)),
                                                jnp.ones((N_LEGS, 2))], -1)
        rate = (1.0 - v.hold)[:, None, None]

        def rhs(zz):
            return rate * network_rhs(zz, omega, p.net.eps[None, :], p.net.b[None, :], k)

        z_old = v.z
        v.z = rk4_step(rhs, v.z, self.dt)
        v.elev = jnp.minimum(1.0, v.elev + v.elev_on * self.dt / p.ramp_time)
        y_old, y_new, x_new = z_old[:, 0, 1], v.z[:, 0, 1], v.z[:, 0, 0]
        v.cross_fwd_end = g(y_old, v.tp) * g(-y_new, v.tp) * g(x_new, v.tp)  # leader at its AEP turning point
        v.cross_back_end = g(-y_old, v.tp) * g(y_new, v.tp) * g(-x_new, v.tp)  # leader at its PEP turning point

        v.dq_level = self._level_offset(v.lc, v.level)
        v.q_lc = converter_output(p, v.lc, v.z, v.swing, v.elev, v.offset, v.dq_level, v.searched)
        v.q_search = search_output(p, v.lc, v.z, v.q_ref, v.search_n)

    def _end_of_phase(self, p, s, obs, v) -> None:
        """(6) Ends of swing, stance and search: touchdown, prolong or the searching reflex (Eqs. 12-15); blind:
        the bare converter."""
        g = v.g
        v.blind = (v.hold_q, v.hold, v.q_ref, v.search_n, v.search, v.n_search, v.failed, v.n_fail, v.q_search)
        # the feedback path, block (6); selected by `fb` after it
        # (6) End of swing: touchdown -> swing-prolong; none -> searching reflex (SRT, Eqs. 12-15).
        end_sw = v.swing * (1.0 - v.hold) * (1.0 - v.search) * v.cross_fwd_end
        srt = end_sw * (1.0 - v.lam_td) * p.searching
        stop = end_sw - srt
        v.hold_q = v.hold_q + stop[:, None] * (v.q_lc - v.hold_q)
        v.hold = v.hold + stop * (1.0 - v.hold)
        v.q_ref = v.q_ref + srt[:, None] * (v.q_lc - v.q_ref)
        v.search_n = v.search_n * (1.0 - srt)
        v.search = v.search + srt * (1.0 - v.search)
        v.n_search = v.n_search + srt
        # End of stance -> stance-prolong until ATD (aTD of the alien group is part of ATD).
        end_st = (1.0 - v.swing) * (1.0 - v.hold) * v.cross_back_end
        v.hold_q = v.hold_q + end_st[:, None] * (v.q_lc - v.hold_q)
        v.hold = v.hold + end_st * (1.0 - v.hold)
        # A search period ends when the slowed leader is back at the AEP: search deeper, or give up.
        period = v.search * v.cross_fwd_end * (1.0 - srt)
        more = g(self.search_periods - 1.5 - v.search_n, v.tp)
        v.search_n = v.search_n + period * more
        give_up = period * (1.0 - more)
        v.failed = v.failed + give_up * (1.0 - v.failed)
        v.hold_q = v.hold_q + give_up[:, None] * (v.q_ref - v.hold_q)
        v.hold = v.hold + give_up * (1.0 - v.hold)
        v.search = v.search * (1.0 - give_up)
        v.n_fail = v.n_fail + give_up
        v.q_search = search_output(p, v.lc, v.z, v.q_ref, v.search_n)
        # blind: the swing follows the leader's sign and the converter runs bare
        swing_blind = g(v.z[:, 0, 1], v.tp)
        q_lc_blind = converter_output(p, v.lc, v.z, swing_blind, v.elev, v.offset, v.dq_level, v.searched)
        (v.hold_q, v.hold, v.q_ref, v.search_n, v.search, v.n_search, v.failed, v.n_fail, v.q_search, v.swing,
         v.q_lc) = v.pick((v.hold_q, v.hold, v.q_ref, v.search_n, v.search, v.n_search, v.failed, v.n_fail,
                           v.q_search, v.swing, v.q_lc), v.blind + (swing_blind, q_lc_blind))
