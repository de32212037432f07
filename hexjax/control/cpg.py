"""CPG locomotion with elevator and searching reflexes: Yu, Gao, Deng 2019 (seed 003) as a hexjax controller.

Per leg (Sect. 3): a Van der Pol leader-follower network (`hexjax.control.vdp`, Eq. 5) integrated by
RK4 at the control rate, and a linear converter joint = g x + h (Eq. 6) with swing and stance coefficient
sets worked out from the leg's inverse kinematics (Sect. 3.2). Sensory neurons turn the toe force into
lambda_ob and lambda_td (Eqs. 7-9). The elevator reflex (Eqs. 10-11) and the searching reflex
(Eqs. 12-15) switch the network and the converter; an event finite-state machine with swing/stance
prolong states (Table 2) keeps the legs in step. Tripod, tetrapod and wave gaits come from the
time-varying leader frequency of Eq. 16.

Every discrete decision is written once as a gate in [0, 1] (`_gate`): a step function in the hard
form, a sigmoid with a temperature in the smooth form (`CPGController.smooth`). The FSM state is kept
as numbers in [0, 1] (swing, hold, search, ...) and updated by convex combinations, so in the hard form
they stay 0 or 1 and the controller is the paper's switching system, while the smooth form is
differentiable in every threshold.

Readings where the paper is silent or ambiguous (each repeated in docs/cpg.md):
  * Eq. 8 as printed drops the max( ) from its second term and adds two binary signals; we read it as
    the OR of the two threshold tests, which is what "lambda_ob is binary" requires.
  * Eq. 16 sets only omega_1; the followers keep omega_2 = omega_3 = 2 omega_1 so they stay locked.
  * Eq. 10 sets y_1 = -1 for omega_1 = 0.4 pi; for other leader frequencies we scale it with omega_1.
    After every reset of the leader (Eq. 10, the swing->stance switch, a found foothold) the followers'
    rates are put on the locked curve y_i = -4 x_1 y_1 (`follower_reset`): with Table 1's k = 0.1 the
    network otherwise needs ~40 s to re-lock (measured, docs/cpg.md), longer than a whole 5 s step.
  * Eq. 14's signs depend on the paper's joint conventions (Fig. 2, not available); we apply it so that
    the search moves the foot from the AEP back towards the PEP (alpha) and down (beta, gamma), with the
    deepest dips near the AEP where mu = sigma (Eq. 15).
  * "Multi-step searching" (Fig. 9b, the 40 mm ditch) deepens the search: each further period of the
    slowed leader lowers the centre of the beta/gamma oscillation by one more amplitude, for at most
    `search_periods` periods; then the leg returns to its AEP (Fig. 9c) and waits.
  * "Retains the current posture": a leg in swing- or stance-prolong holds its last joint command. After
    a foothold found by a search the converter continues from that posture: the difference is a joint
    offset carried through the stance and the next lift-off and faded over the next descent, which is how
    a changed AEP is "corrected in the next swing phase" (Sect. 6.1.2).
  * Body height per leg (Sect. 3.2 sets the converter from the body height over the ground): a touchdown
    well above the other feet (a step top) records that leg's foothold `level`, measured along gravity
    against the stance feet. Its stance moves to the converter's posture at that level by mid-stance and
    its next swing descends to the same level, so a leg on a step top keeps full strides and the torso
    stays level; where the top ends, the searching reflex takes the foot down.
  * ATD is "all legs get footholds" (no leg swinging, searching or given up), not six toe forces above
    F_contact-z; at ATD the next swing slot lifts off (aTD); while any leg runs a reflex every stance leg
    freezes (Sect. 5.2); the elevator reflex fires once per swing.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Tuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hexjax.control.vdp import NetworkParams, locked_state, network_rhs, rk4_step
from hexjax.robot import N_LEGS, RobotSpec, forward_sign, leg_fk, leg_ik, leg_to_body

# Gait indicator gamma of Eq. 16 and each leg's swing slot (legs LF, LM, LH, RF, RM, RH = the paper's
# Leg1..Leg6; slot 0 swings first). Tripod: legs 1, 3, 5 start at [-1, 0] (swing), 2, 4, 6 at [1, 0]
# (Sect. 5.1). Tetrapod and wave: back-to-front waves on each side.
CPG_GAITS = {
    "tripod": (2, (0, 1, 0, 1, 0, 1)),
    "tetrapod": (3, (2, 1, 0, 0, 2, 1)),
    "wave": (6, (5, 4, 3, 2, 1, 0)),
}

# Leg groups of the tripod (Table 2's "alien group").
TRIPOD_GROUP = np.array([0, 1, 0, 1, 0, 1])

MODE_NAMES = ("stance", "swing", "stance-prolong", "swing-prolong", "search", "search-failed")


@struct.dataclass
class CPGParams:
    """Tunable numbers of the CPG controller (traced: `jax.grad` and `vmap` reach all of them). SI units.

    net            NetworkParams, Yu 2019 Table 1 (omega set for the tripod; Eq. 16 rescales omega_1)
    duty ()        gait indicator gamma of Eq. 16 (2 tripod, 3 tetrapod, 6 wave)
    leg_slot (6,)  swing slot of each leg (0 .. gamma - 1)
    step_length () m, clearance () m (h_max), elevated_clearance () m (regenerated h_max of Sect. 6.1.1),
    body_height () m: hip above the ground; these fix the converter coefficients through leg IK
    lc_trim (2, 2, 3) rad: added to [swing, stance] x [g, h] x [alpha, beta, gamma] coefficients
    f_contact (3,) N: F_contact-x (lateral), -y (forward), -z (vertical), Eqs. 8-9
    ramp_time () s: T_s of Eq. 11
    elevator_y1 (): the value y_1 is set to by Eq. 10 (at omega_1 = 0.4 pi)
    elevator_window (): the elevator reflex can fire once the swinging leader x_1 is past this value
    search_amp (3,) rad: delta alpha, beta, gamma of Eq. 14
    search_sigma (): sigma of Eq. 15
    search_freq (3,): factors on omega_1..3 while searching, Eq. 12
    raised_tolerance () m: a touchdown this far above the stance feet is a raised foothold kept in stance
    temp_force () N, temp_phase (), temp_height () m: temperatures of the smooth gates (unused when hard)
    """

    net: NetworkParams
    duty: jax.Array
    leg_slot: jax.Array
    step_length: jax.Array
    clearance: jax.Array
    elevated_clearance: jax.Array
    body_height: jax.Array
    lc_trim: jax.Array
    f_contact: jax.Array
    ramp_time: jax.Array
    elevator_y1: jax.Array
    elevator_window: jax.Array
    search_amp: jax.Array
    search_sigma: jax.Array
    search_freq: jax.Array
    raised_tolerance: jax.Array
    temp_force: jax.Array
    temp_height: jax.Array
    temp_phase: jax.Array


@struct.dataclass
class CPGState:
    """Memory of the controller for one robot. Per-leg arrays are (6,) or (6, 3).

    z (6, 3, 2)    network states
    swing          1 in swing (swing converter), 0 in stance
    hold           1 in swing- or stance-prolong: network frozen, joints held at hold_q
    elev_on, elev  elevator reflex active; its ramp min(1, (t - t_ob) / T_s) of Eq. 11
    search         searching reflex active; search_n: search periods completed
    failed         no foothold found in range: leg back at its AEP, waiting (Fig. 9c)
    q_ref          joints when the search began (alpha, beta, gamma (t_td^-) of Eq. 14)
    hold_q, offset held posture; converter offset after a release
    kept           1 while a leg holds a foothold found by a search (its posture becomes the offset)
    level          m: height of each leg's raised foothold above the ground datum of the stance feet (0 on
                   level ground, +0.04 on a 40 mm step top); its stance holds the foot there and its next
                   swing descends to it
    searched       1 while a leg stands on a foothold found by a search: its stance holds the found posture
    paused         1 for a stance leg frozen mid-stance while another leg runs a reflex
    lam_ob         lambda_ob of the previous step (the reflex fires on its rising edge)
    q_cmd, q_meas  last joint command; joint angles measured at the last step
    counters: n_elev, n_search, n_found, n_fail (6,) events per leg; depth (6,) m deepest foothold
    found by a search below the nominal AEP; wait_steps (6,) control steps spent in stance-prolong while
    another leg searched; t () s
    """

    z: jax.Array
    swing: jax.Array
    hold: jax.Array
    elev_on: jax.Array
    elev: jax.Array
    search: jax.Array
    search_n: jax.Array
    failed: jax.Array
    q_ref: jax.Array
    hold_q: jax.Array
    offset: jax.Array
    lam_ob: jax.Array
    q_cmd: jax.Array
    q_meas: jax.Array
    kept: jax.Array
    level: jax.Array
    searched: jax.Array
    paused: jax.Array
    n_elev: jax.Array
    n_search: jax.Array
    n_found: jax.Array
    n_fail: jax.Array
    depth: jax.Array
    wait_steps: jax.Array
    t: jax.Array


def _quat_to_body(q, v):
    """Rotate world vectors v (..., 3) into the frame of unit quaternion q = (w, x, y, z): R^T v."""
    w, u = q[0], jnp.broadcast_to(q[1:], v.shape)
    uv = jnp.cross(u, v)
    return v - 2.0 * w * uv + 2.0 * jnp.cross(u, uv)


@dataclasses.dataclass(frozen=True)
class LinearConverter:
    """Converter coefficients of Eq. 6 for one parameter set: each (6, 3), joints (alpha, beta, gamma).

    g_sw, h_sw / g_st, h_st: swing / stance sets for the nominal clearance; dg_sw, dh_sw: the Eq. 11
    increments to the elevated clearance; z_aep () m: nominal foot-centre height in the leg frame;
    aep, q_aep (6, 3): the nominal AEP foot centres (leg frames, m) and their joints (rad), untrimmed."""

    g_sw: jax.Array
    h_sw: jax.Array
    g_st: jax.Array
    h_st: jax.Array
    dg_sw: jax.Array
    dh_sw: jax.Array
    z_aep: jax.Array
    aep: jax.Array
    q_aep: jax.Array


def converter_points(robot: RobotSpec, step_length, clearance, body_height, stance_radial):
    """Leg-frame foot centres (6, 4, 3) at AEP, PEP, stance midpoint and swing apex (Sect. 3.2).

    Each foot walks on a line parallel to the body axis at `stance_radial` m from its coxa joint (along
    the leg frame's x axis); AEP and PEP are step_length / 2 ahead of and behind the midpoint, the apex
    is `clearance` above it."""
    fs = jnp.asarray(forward_sign(), jnp.float32)
    r0 = jnp.full(N_LEGS, 1.0) * stance_radial
    zf = -(body_height - robot.foot_radius) * jnp.ones(N_LEGS)
    half = 0.5 * step_length * fs
    aep = jnp.stack([r0, half, zf], -1)
    pep = jnp.stack([r0, -half, zf], -1)
    mid = jnp.stack([r0, jnp.zeros(N_LEGS), zf], -1)
    apex = jnp.stack([r0, jnp.zeros(N_LEGS), zf + clearance], -1)
    return jnp.stack([aep, pep, mid, apex], axis=1)


def linear_converter(robot: RobotSpec, p: CPGParams, stance_radial: float) -> LinearConverter:
    """Coefficients of Eq. 6 from leg IK at AEP, PEP, stance midpoint and apex (Sect. 3.2).

    The leader x_1 runs from -1 (PEP) to +1 (AEP) in swing and back in stance, so alpha = g x_1 + h
    with g = (alpha_AEP - alpha_PEP) / 2. On the locked cycle the followers are -1 at AEP and PEP and
    +1 mid-way, so the swing set maps -1 -> AEP, +1 -> apex and the stance set -1 -> AEP, +1 -> stance
    midpoint (the midpoint is closer to the coxa, so the leg must bend there to keep the foot on a
    straight line)."""
    def sets(clearance):
        pts = converter_points(robot, p.step_length, clearance, p.body_height, stance_radial)
        q, _ = leg_ik(robot, pts)
        aep, pep, mid, apex = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
        end = 0.5 * (aep + pep)
        g_a, h_a = 0.5 * (aep[:, 0] - pep[:, 0]), 0.5 * (aep[:, 0] + pep[:, 0])
        g_sw = jnp.concatenate([g_a[:, None], 0.5 * (apex[:, 1:] - end[:, 1:])], -1)
        h_sw = jnp.concatenate([h_a[:, None], 0.5 * (apex[:, 1:] + end[:, 1:])], -1)
        g_st = jnp.concatenate([g_a[:, None], 0.5 * (mid[:, 1:] - end[:, 1:])], -1)
        h_st = jnp.concatenate([h_a[:, None], 0.5 * (mid[:, 1:] + end[:, 1:])], -1)
        return g_sw, h_sw, g_st, h_st, pts[:, 0], aep

    g_sw, h_sw, g_st, h_st, aep_pt, aep_q = sets(p.clearance)
    g_hi, h_hi, _, _, _, _ = sets(p.elevated_clearance)
    t = p.lc_trim
    return LinearConverter(g_sw=g_sw + t[0, 0], h_sw=h_sw + t[0, 1], g_st=g_st + t[1, 0], h_st=h_st + t[1, 1],
                           dg_sw=g_hi - g_sw, dh_sw=h_hi - h_sw,
                           z_aep=-(p.body_height - robot.foot_radius), aep=aep_pt, q_aep=aep_q)


@dataclasses.dataclass(frozen=True)
class CPGController:
    """The Yu 2019 controller (see the module docstring). Static configuration only; numbers are in
    `CPGParams` (`default_params`).

    robot: RobotSpec (the paper's is `yu2019`); gait: 'tripod', 'tetrapod' or 'wave' (sets the default
    params; the gait itself is traced, so gaits share one compiled rollout); dt: control period, s (the
    network is integrated with one RK4 step per period); feedback: False runs the bare network and
    converter blind (no FSM, no reflexes); elevator / searching: enable each reflex; smooth: sigmoid gates
    instead of step functions; search_periods: how many slowed leader periods a search lasts before the
    leg gives up (4 reach 50 mm below the AEP on `yu2019`; the first alone 21 mm); follower_reset: see the
    module docstring. step_length, clearance (h_max), elevated_clearance (m) set the default params: 40 and
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
        if self.search_periods < 1:
            raise ValueError(f"cpg.search_periods={self.search_periods!r}: must be >= 1")
        if not (math.isfinite(self.stance_radial) and self.stance_radial > 0):
            raise ValueError(f"cpg.stance_radial={self.stance_radial!r}: must be a finite number > 0")

    # Parameters ---------------------------------------------------------------------------------
    def default_params(self, gait: str | None = None) -> CPGParams:
        duty, slots = CPG_GAITS[gait or self.gait]
        return CPGParams(
            net=NetworkParams.table1(), duty=jnp.asarray(float(duty)),
            leg_slot=jnp.asarray(slots, jnp.float32), step_length=jnp.asarray(self.step_length),
            clearance=jnp.asarray(self.clearance), elevated_clearance=jnp.asarray(self.elevated_clearance),
            body_height=jnp.asarray(self.robot.hip_height), lc_trim=jnp.zeros((2, 2, 3)),
            f_contact=jnp.array([10.0, 10.0, 2.0]), ramp_time=jnp.asarray(0.5),
            elevator_y1=jnp.asarray(-1.0), elevator_window=jnp.asarray(-0.5), search_amp=jnp.radians(jnp.array([7.5, 4.0, 2.5])),
            search_sigma=jnp.asarray(1.2), search_freq=jnp.array([0.5, 1.5, 1.5]),
            raised_tolerance=jnp.asarray(0.015),
            temp_force=jnp.asarray(1.0), temp_phase=jnp.asarray(0.05), temp_height=jnp.asarray(0.002))

    def validate_params(self, p: CPGParams) -> None:
        """Host-side checks on concrete params, before tracing; names the field and value."""
        def arr(name):
            obj = p
            for part in name.split("."):
                obj = getattr(obj, part)
            return np.asarray(obj, dtype=float)

        positive = ("net.eps", "net.b", "net.omega", "step_length", "clearance", "elevated_clearance",
                    "body_height", "ramp_time", "search_sigma", "search_freq", "temp_force", "temp_phase",
                    "temp_height", "raised_tolerance")
        for f in positive:
            v = arr(f)
            if not np.all(np.isfinite(v)) or np.any(v <= 0):
                raise ValueError(f"cpg.{f}={v.tolist()!r}: must be finite and > 0")
        for f in ("net.k", "f_contact", "search_amp"):
            v = arr(f)
            if not np.all(np.isfinite(v)) or np.any(v < 0):
                raise ValueError(f"cpg.{f}={v.tolist()!r}: must be finite and >= 0")
        duty = arr("duty")
        if np.any(duty < 2):
            raise ValueError(f"cpg.duty={duty.tolist()!r}: gait indicator gamma must be >= 2 (Eq. 16)")
        slot = arr("leg_slot")
        if slot.shape[-1] != N_LEGS or np.any(slot < 0) or np.any(slot > np.asarray(duty)[..., None] - 1):
            raise ValueError(f"cpg.leg_slot={slot.tolist()!r}: six slots in [0, duty - 1]")
        if np.any(arr("search_sigma") < 1):
            raise ValueError(f"cpg.search_sigma={arr('search_sigma').tolist()!r}: must be >= 1 (Eq. 15)")
        if np.any(arr("elevated_clearance") < arr("clearance")):
            raise ValueError(f"cpg.elevated_clearance={arr('elevated_clearance').tolist()!r}: must be >= "
                             f"clearance={arr('clearance').tolist()!r}")
        trim = arr("lc_trim")
        if trim.shape[-3:] != (2, 2, 3) or not np.all(np.isfinite(trim)):
            raise ValueError(f"cpg.lc_trim shape={trim.shape!r}: must be finite with shape (2, 2, 3)")
        # every converter point, at both clearances, must be reachable (batched params: each member)
        cols = np.broadcast_arrays(*(arr(f) for f in ("step_length", "clearance", "elevated_clearance",
                                                       "body_height")))
        for sl, h, he, bh in set(zip(*(c.reshape(-1).tolist() for c in cols))):
            for name, cl in (("clearance", h), ("elevated_clearance", he)):
                _, ok = leg_ik(self.robot, converter_points(self.robot, sl, cl, bh, self.stance_radial))
                if not bool(np.all(np.asarray(ok))):
                    raise ValueError(
                        f"cpg.step_length={sl!r}, cpg.{name}={cl!r}, cpg.body_height={bh!r}: the converter's "
                        f"AEP/PEP/apex are out of reach of robot {self.robot.name!r}")

    # Gates ----------------------------------------------------------------------------------------
    def _gate(self, x, temp):
        """1 where x > 0: a step in the hard form, sigmoid(x / temp) in the smooth one."""
        if self.smooth:
            return jax.nn.sigmoid(x / temp)
        return (x > 0).astype(x.dtype)

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
        q0 = self._converter_output(p, lc, z, swing, zeros, zeros3, zeros3, zeros)
        return CPGState(z=z, swing=swing, hold=zeros, elev_on=zeros, elev=zeros, search=zeros, search_n=zeros,
                        failed=zeros, q_ref=q0, hold_q=q0, offset=zeros3, lam_ob=zeros, q_cmd=q0, q_meas=q0, kept=zeros, level=zeros, searched=zeros, paused=zeros,
                        n_elev=zeros, n_search=zeros, n_found=zeros, n_fail=zeros, depth=zeros,
                        wait_steps=zeros, t=jnp.asarray(0.0))

    def initial_action(self, p: CPGParams):
        """(18,) joint targets of the first control step: the robot settles in this posture."""
        return self.init(p, None).q_cmd.reshape(-1)

    # Converter (Eqs. 6, 11, 14) --------------------------------------------------------------------
    @staticmethod
    def _converter_output(p, lc: LinearConverter, z, swing, elev, offset, dq_level, searched):
        x = z[..., 0]
        q_sw = (lc.g_sw + elev[:, None] * lc.dg_sw) * x + lc.h_sw + elev[:, None] * lc.dh_sw
        q_st = lc.g_st * x + lc.h_st
        s = swing[:, None]
        # An offset is kept through lift-off and the apex and faded over the descent (x_1 from 0 to 1), so a
        # foot leaving a step top still clears its clearance above it. Over the same descent the foot moves
        # to the level of the foothold it left (dq_level, zero on level ground): on a step top it lands
        # on the top at its AEP with a full stride; where the top ends the foot meets no ground at the AEP
        # and the searching reflex takes it down.
        fall = jnp.clip(1.0 - x[:, :1], 0.0, 1.0)
        q_swing = q_sw + fall * offset + (1.0 - fall) * dq_level
        # In stance the touchdown offset hands over to the level posture by mid-stance (x_1 from 1 to 0):
        # the torso returns to its nominal height and attitude over feet at their recorded levels, where
        # the raw touchdown posture would keep any tilt the torso had at the touchdown. A foothold found by
        # a search is held as found through the stance (the next swing aims for the nominal AEP again, so
        # searches do not chain below the search range).
        w = searched[:, None] + (1.0 - searched[:, None]) * jnp.clip(x[:, :1], 0.0, 1.0)
        q_stance = q_st + dq_level + w * (offset - dq_level)
        return s * q_swing + (1.0 - s) * q_stance

    def _search_output(self, p, lc: LinearConverter, z, q_ref, search_n):
        """Eq. 14 with mu of Eq. 15, around the joints q_ref where the search began (see module notes)."""
        x = z[..., 0]
        x1 = x[:, 0]
        amp = p.search_amp
        mu = 0.5 * (p.search_sigma - 1.0) * x1 + 0.5 * (p.search_sigma + 1.0)
        back = -jnp.sign(lc.g_sw[:, 0])  # alpha direction from AEP towards PEP
        alpha = q_ref[:, 0] + back * amp[0] * (1.0 - x1)
        # The femur goes down (our beta > 0 lifts) and the knee opens (gamma up), which pushes the foot
        # back out as the lowered femur pulls it in: the foot digs nearly straight down.
        deeper = 1.0 + search_n
        beta = q_ref[:, 1] - amp[1] * (deeper + mu * x[:, 1])
        gamma = q_ref[:, 2] + amp[2] * (deeper + mu * x[:, 2])
        return jnp.stack([alpha, beta, gamma], -1)

    # One control step ------------------------------------------------------------------------------
    def step(self, p: CPGParams, s: CPGState, obs) -> Tuple[CPGState, jax.Array]:
        g = self._gate
        tf, tp = p.temp_force, p.temp_phase
        lc = linear_converter(self.robot, p, self.stance_radial)
        z = s.z

        # Sensory neurons, Eqs. 7-9: toe force in the torso frame (x forward, y lateral, z up).
        f = _quat_to_body(obs.torso_quat, obs.foot_force)
        if self.feedback:
            lam_ob = 1.0 - (1.0 - g(jnp.abs(f[:, 1]) - p.f_contact[0], tf)) * (1.0 - g(jnp.abs(f[:, 0]) - p.f_contact[1], tf))
            lam_td = g(jnp.abs(f[:, 2]) - p.f_contact[2], tf)
        else:
            lam_ob, lam_td = jnp.zeros(N_LEGS), jnp.ones(N_LEGS)
        swing, hold, search, failed = s.swing, s.hold, s.search, s.failed
        # Table 2 ATD, "all legs get footholds" (Sect. 5.2): no leg is in the air. A leg is airborne while it
        # swings, searches or has given up; a stance leg, or a swing leg that stopped on a touchdown (sTD),
        # has its foothold. Counting feet above F_contact-z instead would stall the gait whenever the
        # statically indeterminate load leaves one stance foot lightly loaded.
        airborne = swing * (1.0 - hold) + search + failed
        atd = jnp.prod(1.0 - jnp.clip(airborne, 0.0, 1.0))

        elev_on, elev, offset, hold_q, q_ref = s.elev_on, s.elev, s.offset, s.hold_q, s.q_ref
        level, searched = s.level, s.searched
        search_n = s.search_n
        n_elev, n_search, n_found, n_fail, depth = s.n_elev, s.n_search, s.n_found, s.n_fail, s.depth
        one = jnp.ones(N_LEGS)

        if self.feedback:
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
            elev_on, elev = elev_on * (1.0 - to_stance), elev * (1.0 - to_stance)
            zero3 = jnp.zeros((N_LEGS, 3))
            q_new = self._converter_output(p, lc, z, swing, elev, zero3, zero3, searched)  # the bare converter
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

            # (3) Elevator reflex, Eqs. 10-11: rising edge of lambda_ob while the leg sweeps forward.
            if self.elevator:
                rise = lam_ob * (1.0 - s.lam_ob)
                # "halfway of the swing": once the leader is past `elevator_window`; at lift-off the foot
                # still carries its stance load and friction alone can exceed F_contact-x/y.
                # Once per swing: a regenerated swing that meets the face again goes on and lands in front
                # of it (the next swing then meets the face earlier and clears it), instead of retracting
                # again and again against a face near its AEP.
                ert = (swing * (1.0 - hold) * (1.0 - search) * (1.0 - elev_on) * g(z[:, 0, 1], tp)
                       * g(z[:, 0, 0] - p.elevator_window, tp) * rise)
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
            reflex = 1.0 - jnp.prod(1.0 - jnp.clip(elev_on + search + failed, 0.0, 1.0))
            pz = reflex * (1.0 - swing) * (1.0 - hold)
            hold_q = hold_q + pz[:, None] * (s.q_cmd - hold_q)
            hold = hold + pz * (1.0 - hold)
            paused = paused + pz * (1.0 - paused)

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
        q_lc = self._converter_output(p, lc, z, swing, elev, offset, dq_level, searched)
        q_search = self._search_output(p, lc, z, q_ref, search_n)

        if self.feedback:
            # (6) End of swing: touchdown -> swing-prolong; none -> searching reflex (SRT, Eqs. 12-15).
            end_sw = swing * (1.0 - hold) * (1.0 - search) * cross_fwd_end
            srt = end_sw * (1.0 - lam_td) if self.searching else jnp.zeros(N_LEGS)
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
            more = self._gate(self.search_periods - 1.5 - search_n, tp)
            search_n = search_n + period * more
            give_up = period * (1.0 - more)
            failed = failed + give_up * (1.0 - failed)
            hold_q = hold_q + give_up[:, None] * (q_ref - hold_q)
            hold = hold + give_up * (1.0 - hold)
            search = search * (1.0 - give_up)
            n_fail = n_fail + give_up
            q_search = self._search_output(p, lc, z, q_ref, search_n)
        else:
            swing = (z[:, 0, 1] > 0).astype(jnp.float32) if not self.smooth else jax.nn.sigmoid(z[:, 0, 1] / tp)
            q_lc = self._converter_output(p, lc, z, swing, elev, offset, dq_level, searched)

        q_free = search[:, None] * q_search + (1.0 - search[:, None]) * q_lc
        q = hold[:, None] * hold_q + (1.0 - hold[:, None]) * q_free
        any_search = 1.0 - jnp.prod(1.0 - search)
        wait = hold * (1.0 - swing) * any_search
        new = CPGState(z=z, swing=swing, hold=hold, elev_on=elev_on, elev=elev, search=search, search_n=search_n,
                       failed=failed, q_ref=q_ref, hold_q=hold_q, offset=offset, lam_ob=lam_ob, q_cmd=q,
                       q_meas=obs.qpos.reshape(N_LEGS, 3),
                       kept=kept if self.feedback else s.kept, level=level, searched=searched, paused=paused if self.feedback else s.paused,
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
        up = _quat_to_body(obs.torso_quat, up_world[None, :])[0]  # world up in the torso frame
        z_cmd = leg_to_body(self.robot, leg_fk(self.robot, q_cmd)) @ up
        z_meas = leg_to_body(self.robot, leg_fk(self.robot, obs.qpos.reshape(N_LEGS, 3))) @ up
        # Each stance foot's own level is taken off: against the plain mean, a foot landing on a step top
        # next to a stance foot already up there looked only 2/3 of the step height up.
        w = 1.0 - swing
        z_ref = jnp.sum(w * (z_meas - level)) / jnp.maximum(jnp.sum(w), 1e-6)
        return z_cmd - z_ref

    def _reset_followers(self, z, w):
        """Put the followers' rates on the locked curve y_i = -4 x_1 y_1 where w = 1 (module notes)."""
        if not self.follower_reset:
            return z
        target = -4.0 * z[:, 0, 0] * z[:, 0, 1]
        yf = z[:, 1:, 1] + w[:, None] * (target[:, None] - z[:, 1:, 1])
        return z.at[:, 1:, 1].set(yf)

    # Introspection ------------------------------------------------------------------------------
    @staticmethod
    def mode(s: CPGState):
        """(..., 6) int mode per leg, indices into MODE_NAMES (hard form; smooth values are rounded)."""
        sw, hd, se, fl = (jnp.round(a) for a in (s.swing, s.hold, s.search, s.failed))
        m = jnp.where(sw > 0, 1, 0)
        m = jnp.where(hd > 0, jnp.where(sw > 0, 3, 2), m)
        m = jnp.where(se > 0, 4, m)
        return jnp.where(fl > 0, 5, m)

    def trace(self, s: CPGState, obs):
        """Per-step record for plots: neuron outputs x (6, 3), leader rate y1 (6,), mode (6,), joint command
        (6, 3), lambda_ob (6,), elevator ramp (6,), toe force in the torso frame (6, 3) N."""
        return dict(x=s.z[..., 0], y1=s.z[:, 0, 1], mode=self.mode(s), q_cmd=s.q_cmd, lam_ob=s.lam_ob, elev=s.elev,
                    force=_quat_to_body(obs.torso_quat, obs.foot_force), quat=obs.torso_quat)
