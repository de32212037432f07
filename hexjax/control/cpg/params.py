"""The Yu 2019 CPG controller's numbers (`CPGParams`, traced) and memory (`CPGState`), and the gaits of Eq. 16."""

from __future__ import annotations

import jax
import numpy as np
from flax import struct

from hexjax.control.vdp import NetworkParams

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
    leg_trim (6, 2, 2, 3) rad: each leg's own trim, added to lc_trim (zero: the paper's one converter per joint)
    leg_clearance (6,) m: each leg's offset on clearance and elevated_clearance (zero: the paper's one h_max)
    leg_f_scale (6, 3): each leg's factor on f_contact (one: the paper's thresholds for every leg). These three
    make the per-leg space of `hexjax.tune.space` (`PER_LEG`): 96 numbers beside the 16 shared ones
    ramp_time () s: T_s of Eq. 11
    elevator_y1 (): the value y_1 is set to by Eq. 10 (at omega_1 = 0.4 pi)
    elevator_window (): the elevator reflex can fire once the swinging leader x_1 is past this value
    search_amp (3,) rad: delta alpha, beta, gamma of Eq. 14
    search_sigma (): sigma of Eq. 15
    search_freq (3,): factors on omega_1..3 while searching, Eq. 12
    raised_tolerance () m: a touchdown this far above the stance feet is a raised foothold kept in stance
    temp_force () N, temp_phase (), temp_height () m: temperatures of the smooth gates (unused when hard)
    feedback, elevator, searching, smooth (): 1 or 0, the sensory FSM and the two reflexes on or off, and the
    smooth (sigmoid) or hard (step) form of every gate (traced, so the variants of an experiment share one
    compiled program)
    walk_on (): 1 or 0. After a search that found nothing the leg returns to its AEP posture and waits "for
    high-level regulation" (Fig. 9c); with 0 it waits for good (the FSM holds every other leg, as the paper's
    robot does without that regulation), with 1 the regulation is to walk on: the waiting leg no longer holds the
    gait back, joins its group's next stance in the air and swings again from there
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
    leg_trim: jax.Array
    leg_clearance: jax.Array
    leg_f_scale: jax.Array
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
    feedback: jax.Array
    elevator: jax.Array
    searching: jax.Array
    smooth: jax.Array
    walk_on: jax.Array


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



def gait_fields(gait: str) -> dict:
    """The params fields that select an Eq. 16 gait ('tripod', 'tetrapod', 'wave'): {duty, leg_slot}, for
    `CPGController.default_params(**gait_fields(g))` (the gait is traced, so gaits share one program)."""
    if gait not in CPG_GAITS:
        raise ValueError(f"cpg.gait={gait!r}: choose one of {sorted(CPG_GAITS)}")
    duty, slots = CPG_GAITS[gait]
    return {"duty": float(duty), "leg_slot": np.asarray(slots, np.float32)}
