"""CPG locomotion with elevator and searching reflexes: Yu, Gao, Deng 2019 as a hexjax controller.

Per leg (Sect. 3): a Van der Pol leader-follower network (`hexjax.control.vdp`, Eq. 5) integrated by
RK4 at the control rate, and a linear converter joint = g x + h (Eq. 6) with swing and stance coefficient
sets worked out from the leg's inverse kinematics (Sect. 3.2). Sensory neurons turn the toe force into
lambda_ob and lambda_td (Eqs. 7-9). The elevator reflex (Eqs. 10-11) and the searching reflex
(Eqs. 12-15) switch the network and the converter; an event finite-state machine with swing/stance
prolong states (Table 2) keeps the legs in step. Tripod, tetrapod and wave gaits come from the
time-varying leader frequency of Eq. 16.

Every discrete decision is written once as a gate in [0, 1] (`_gate`): a step function in the hard
form, a sigmoid with a temperature in the smooth form (the traced `smooth` param, whose default
`CPGController(smooth=True)` sets, so both forms run in one program). The FSM state is kept
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

from hexjax.control.cpg.controller import CPGController
from hexjax.control.cpg.converter import LinearConverter, converter_output, converter_points, linear_converter
from hexjax.control.cpg.params import CPG_GAITS, MODE_NAMES, TRIPOD_GROUP, CPGParams, CPGState, gait_fields

__all__ = ["CPGController", "LinearConverter", "converter_output", "converter_points", "linear_converter", "CPG_GAITS",
           "MODE_NAMES", "TRIPOD_GROUP", "CPGParams", "CPGState", "gait_fields"]
