"""Van der Pol neurons and the per-leg leader-follower network of Yu, Gao, Deng 2019.

Each leg has three coupled neurons z_i = (x_i, y_i): the leader z_1 drives the coxa (alpha) joint,
the followers z_2, z_3 the femur (beta) and tibia (gamma) joints. Arrays are shaped (..., 3, 2) with
the last axis (x, y); leading axes (legs, envs) broadcast.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class NetworkParams:
    """Structure parameters of one three-neuron network (Yu 2019 Table 1 defaults).

    eps (3,): nonlinear damping epsilon_i; b (3,): amplitude parameter b_i (steady amplitude
    2 / sqrt(b_i), Eq. 4); omega (3,) rad/s: natural frequencies omega_i; k (4,): connection weights
    (k12, k13, k23, k32)."""

    eps: jax.Array
    b: jax.Array
    omega: jax.Array
    k: jax.Array

    @staticmethod
    def table1() -> "NetworkParams":
        return NetworkParams(eps=jnp.full(3, 0.1), b=jnp.full(3, 4.0),
                             omega=jnp.array([0.4 * math.pi, 0.8 * math.pi, 0.8 * math.pi]),
                             k=jnp.full(4, 0.1))


def vdp_rhs(z, omega, eps, b):
    """One Van der Pol neuron in state-space form, Yu 2019 Eq. 2: z = (x, y) (..., 2) ->
    (y, eps (1 - b x^2) y - omega^2 x)."""
    x, y = z[..., 0], z[..., 1]
    return jnp.stack([y, eps * (1.0 - b * x * x) * y - omega ** 2 * x], axis=-1)


def network_rhs(z, omega, eps, b, k):
    """Leader-follower network, Yu 2019 Eq. 5 (Eq. 13 when k12 = k13 = 0).

    z (..., 3, 2); omega (..., 3) rad/s; eps, b (..., 3); k (..., 4) = (k12, k13, k23, k32).
    The leader term -4 x_1 y_1 oscillates at twice the leader frequency, so each follower is pulled to
    2 omega_1 and, on the limit cycle, to x_i = 1 - 2 x_1^2 (a phase lag of pi/2 in leader phase);
    k23, k32 couple the two followers to each other."""
    x, y = z[..., 0], z[..., 1]
    own = eps * (1.0 - b * x * x) * y - omega ** 2 * x
    drive = -4.0 * x[..., 0] * y[..., 0]
    k12, k13, k23, k32 = k[..., 0], k[..., 1], k[..., 2], k[..., 3]
    dy1 = own[..., 0]
    dy2 = own[..., 1] + k12 * (drive - y[..., 1]) + k32 * (y[..., 2] - y[..., 1])
    dy3 = own[..., 2] + k13 * (drive - y[..., 2]) + k23 * (y[..., 1] - y[..., 2])
    return jnp.stack([y, jnp.stack([dy1, dy2, dy3], axis=-1)], axis=-1)


def rk4_step(f, z, dt):
    """Classical fourth-order Runge-Kutta step of dz/dt = f(z) over dt (Yu 2019 Table 6: 'RK4 solver')."""
    k1 = f(z)
    k2 = f(z + 0.5 * dt * k1)
    k3 = f(z + 0.5 * dt * k2)
    k4 = f(z + dt * k3)
    return z + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def integrate(z0, net: NetworkParams, dt: float, n_steps: int):
    """RK4 trajectory of the free network from z0 (..., 3, 2): returns (n_steps + 1, ..., 3, 2)."""
    def step(z, _):
        z1 = rk4_step(lambda s: network_rhs(s, net.omega, net.eps, net.b, net.k), z, dt)
        return z1, z1

    _, zs = jax.lax.scan(step, z0, None, length=n_steps)
    return jnp.concatenate([z0[None], zs], axis=0)


def locked_state(theta, omega1, amplitude=1.0):
    """Network state on its phase-locked limit cycle at leader phase theta (rad), for b = 4.

    Leader x_1 = A cos(theta), y_1 = -A omega_1 sin(theta) (Eq. 4); followers on x_i = 1 - 2 x_1^2,
    y_i = -4 x_1 y_1 (the drive term of Eq. 5, which is the rate of that curve). Returns (..., 3, 2)."""
    theta = jnp.asarray(theta)
    x1 = amplitude * jnp.cos(theta)
    y1 = -amplitude * omega1 * jnp.sin(theta)
    xf = -jnp.cos(2.0 * theta)
    yf = -4.0 * jnp.cos(theta) * (-omega1 * jnp.sin(theta))
    leader = jnp.stack([x1, y1], -1)
    follower = jnp.stack([xf, yf], -1)
    return jnp.stack([leader, follower, follower], axis=-2)


def phase_amplitude(z, omega):
    """Phase (rad) and amplitude of each neuron from its state, treating it as x = A cos(phase),
    y = -A omega sin(phase) (exact on the Eq. 4 steady state). z (..., 3, 2), omega (..., 3)."""
    x, y = z[..., 0], z[..., 1]
    v = -y / omega
    return jnp.arctan2(v, x), jnp.sqrt(x * x + v * v)
