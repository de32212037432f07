"""A `Perturbation` (`hexjax.world.randomization`) applied inside one env's control step: to its model
(friction, torso mass and payload, servo gains, torque limits, damping, a limp leg), to what its sensors read
(noise, bias, dropout, a dead leg) and to the action that reaches the servos (latency, a locked leg).

All of it is `jnp.where` and arithmetic on traced arrays, so a neutral draw (scales 1, offsets 0, no fault)
computes the unperturbed values, and the float fields carry gradients on the MJX path. The carry it adds to a
control step is a `PerturbState`: the last `MAX_LATENCY` actions and a locked leg's held angles.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hexjax.sim.config import SensorConfig
from hexjax.world.randomization import FAULT_KINDS, MAX_LATENCY

LOCKED, LIMP, SENSOR_DEAD = (FAULT_KINDS.index(k) for k in ("locked", "limp", "sensor_dead"))
MIN_FRICTION = 1e-5  # mujoco.mjMINMU
# actuators and joints come in leg order, three per leg (coxa, femur, tibia)
_ACT_LEG = np.repeat(np.arange(6), 3)


@struct.dataclass
class PerturbState:
    """actions (MAX_LATENCY + 1, 18): the controller's last outputs, newest first; held (18,): the joint angles a
    locked leg keeps (tracking the joints until the fault starts)."""

    actions: jax.Array
    held: jax.Array


def init_state(ctrl0) -> PerturbState:
    return PerturbState(actions=jnp.tile(ctrl0[None], (MAX_LATENCY + 1, 1)), held=ctrl0)


def _fault_on(p, t, kind: int):
    """(18,) bool: actuators of the leg with a fault of `kind` that has started by time t (s of walking)."""
    return (p.fault_kind == kind) & (t >= p.fault_time) & (jnp.asarray(_ACT_LEG) == p.fault_leg)


def pair_friction_with(pair_friction, mu):
    """The contact pairs' friction (npair, 5) with the sliding coefficient of both tangent directions set to `mu`
    (Coulomb's mu, an absolute value: what "friction" means throughout hexjax), the torsional and rolling ones
    kept. MuJoCo's C code raises every friction coefficient to mjMINMU (1e-5); MJX does not, and a zero
    coefficient gives NaN in its cone, so `mu` is raised to it here."""
    f = jnp.maximum(mu, MIN_FRICTION)
    return pair_friction.at[:, 0].set(f).at[:, 1].set(f)


def model(sm, m, p, t):
    """One env's mjx.Model `m` with the draw `p` applied at walking time t (s; a limp leg acts from its onset)."""
    b = sm.torso_body
    pair_friction = pair_friction_with(m.pair_friction,
                                       jnp.where(p.friction >= 0.0, p.friction, m.pair_friction[:, 0]))
    # torso scaled, payload a point mass at its offset; the body's frame of inertia is the torso's (identity
    # body_iquat, built so in hexjax.sim.mjcf), the payload's off-diagonal inertia dropped
    total, ipos, inertia = torso_with_payload(m.body_mass[b], m.body_ipos[b], m.body_inertia[b], p)
    limp = _fault_on(p, t, LIMP)
    gain = jnp.where(limp, 0.0, p.kp_scale)
    return m.replace(
        pair_friction=pair_friction,
        body_mass=m.body_mass.at[b].set(total),
        body_ipos=m.body_ipos.at[b].set(ipos),
        body_inertia=m.body_inertia.at[b].set(inertia),
        actuator_gainprm=m.actuator_gainprm.at[:, 0].multiply(gain),
        actuator_biasprm=m.actuator_biasprm.at[:, 1:3].multiply(gain[:, None]),
        actuator_forcerange=m.actuator_forcerange * p.torque_scale,
        dof_damping=m.dof_damping.at[6:].multiply(p.damping_scale),
    )


def torso_with_payload(mass, ipos0, inertia0, p, xp=jnp):
    """(mass, centre of mass, diagonal inertia) of the torso scaled by the draw `p` with its payload, a point
    mass at its offset (the payload's off-diagonal inertia dropped); `xp`: jnp (MJX) or np (MuJoCo C)."""
    mt = mass * p.torso_mass_scale
    total = mt + p.payload_kg
    ipos = ipos0 + p.payload_kg * p.payload_offset / total
    r_t, r_p = ipos0 - ipos, ipos0 + p.payload_offset - ipos
    point = lambda r: xp.stack([r[1] ** 2 + r[2] ** 2, r[0] ** 2 + r[2] ** 2, r[0] ** 2 + r[1] ** 2])
    return total, ipos, inertia0 * p.torso_mass_scale + mt * point(r_t) + p.payload_kg * point(r_p)


def observe(obs, p, i, t, sensors: SensorConfig):
    """What the controller reads at control step i (walking time t s): each leg's foot force and pad force
    with the draw's bias, fresh Gaussian noise and dropout; a dead leg reads zero. A lost or dead foot
    reading also reports no contact; the pad's on/off follows its perturbed force."""
    k_fd, k_fn, k_td, k_tn = jax.random.split(jax.random.fold_in(p.key, i), 4)
    dead = (p.fault_kind == SENSOR_DEAD) & (t >= p.fault_time) & (jnp.arange(6) == p.fault_leg)
    keep_f = (jax.random.uniform(k_fd, (6,)) >= p.force_dropout) & ~dead
    keep_t = (jax.random.uniform(k_td, (6,)) >= p.tactile_dropout) & ~dead
    foot = (obs.foot_force + p.force_bias + p.force_noise * jax.random.normal(k_fn, (6, 3))) * keep_f[:, None]
    pad = (obs.tactile_force + p.tactile_bias + p.tactile_noise * jax.random.normal(k_tn, (6,))) * keep_t
    return obs.replace(foot_force=foot, foot_contact=obs.foot_contact & keep_f, tactile_force=pad,
                       tactile=pad > sensors.tactile_threshold)


def act(state: PerturbState, action, qpos_joints, p, t):
    """(new state, the targets the servos get): the action `p.latency` control steps old; a locked leg's
    targets held at the angles its joints had when the fault started."""
    actions = jnp.concatenate([action[None], state.actions[:-1]])
    delayed = actions[jnp.clip(p.latency, 0, MAX_LATENCY)]
    locked = _fault_on(p, t, LOCKED)
    held = jnp.where(locked, state.held, qpos_joints)
    return PerturbState(actions=actions, held=held), jnp.where(locked, held, delayed)
