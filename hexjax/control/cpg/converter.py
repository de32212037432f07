"""The linear converter of Yu 2019 Eq. 6 (joint = g x + h), its coefficients from leg inverse kinematics
(Sect. 3.2), the elevated swing of Eq. 11, the search motion of Eqs. 14-15, and the contact neurons of Eqs. 8-9
that read the toe forces."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from hexjax.control.cpg.params import CPGParams
from hexjax.world.robot import N_LEGS, RobotSpec, forward_sign, leg_ik


def quat_to_body(q, v):
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

    g_sw, h_sw, g_st, h_st, aep_pt, aep_q = sets(p.clearance + p.leg_clearance)
    g_hi, h_hi, _, _, _, _ = sets(p.elevated_clearance + p.leg_clearance)
    t = p.lc_trim + p.leg_trim  # (6, 2, 2, 3): the shared trim and each leg's own
    return LinearConverter(g_sw=g_sw + t[:, 0, 0], h_sw=h_sw + t[:, 0, 1], g_st=g_st + t[:, 1, 0],
                           h_st=h_st + t[:, 1, 1],
                           dg_sw=g_hi - g_sw, dh_sw=h_hi - h_sw,
                           z_aep=-(p.body_height - robot.foot_radius), aep=aep_pt, q_aep=aep_q)


def contact_neurons(p: CPGParams, f, gate):
    """Eqs. 8-9: (lambda_ob, lambda_td) (6,) of the toe forces f (6, 3) in the torso frame (x forward, y lateral,
    z up) against each leg's thresholds, F_contact x leg_f_scale; `gate` is the controller's hard or smooth step."""
    fc = p.f_contact * p.leg_f_scale  # (6, 3): each leg's F_contact-x (lateral), -y (forward), -z
    lam_ob = 1.0 - (1.0 - gate(jnp.abs(f[:, 1]) - fc[:, 0])) * (1.0 - gate(jnp.abs(f[:, 0]) - fc[:, 1]))
    return lam_ob, gate(jnp.abs(f[:, 2]) - fc[:, 2])


def converter_output(p, lc: LinearConverter, z, swing, elev, offset, dq_level, searched):
    """Joint commands (6, 3) of Eq. 6 (the swing set with the Eq. 11 increment, or the stance set) from the
    neurons' x, with the touchdown `offset` and the foothold level `dq_level` blended in (readings in
    `hexjax.control.cpg`)."""
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

def search_output(p, lc: LinearConverter, z, q_ref, search_n):
    """Eq. 14 with mu of Eq. 15, around the joints q_ref where the search began (readings in
    `hexjax.control.cpg`)."""
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
