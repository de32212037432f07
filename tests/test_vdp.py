"""Van der Pol neuron and leader-follower network (Yu 2019 Eqs. 1-5, Table 1, Table 6), jitted, seeded."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.control.vdp import NetworkParams, integrate, locked_state, network_rhs, phase_amplitude, rk4_step, vdp_rhs

DT = 0.01


_integrate = jax.jit(integrate, static_argnums=(2, 3))  # one program per (shape, length), shared by the tests
CHUNK = 500  # steps per call of `_integrate`


def _run(z0, net, seconds):
    """`integrate` over `seconds`, CHUNK steps per call, each call going on from the last state. One call of all
    the steps computes the same; chunks keep the suite's XLA option (tests/conftest.py, older fusion emitters)
    from copying the stacked trajectory at every step: 120 s of the network took 15.8 s in one call, 0.03 s with
    XLA's default emitters (a scan's stacked output costs steps^2 with the older ones)."""
    n = int(round(seconds / DT))
    parts, z = [z0[None]], z0
    for k in range(0, n, CHUNK):
        zs = _integrate(z, net, DT, min(CHUNK, n - k))[1:]
        parts.append(zs)
        z = zs[-1]
    return jnp.concatenate(parts)


def _lock_errors(zs, net):
    """Follower phase error against the locked relation phi_i = 2 phi_1 + pi (x_i = -cos 2 theta_1), rad,
    and follower frequency ratio over the window. zs (T, B, 3, 2)."""
    ph, amp = phase_amplitude(zs, net.omega)
    err = jnp.angle(jnp.exp(1j * (ph[..., 1:] - 2.0 * ph[..., :1] - math.pi)))
    return np.asarray(err), np.asarray(amp), np.asarray(ph)


def _frequency(ph, dt):
    """Mean angular frequency from unwrapped phase, rad/s (phase decreases: x = A cos(phase) with
    y = -A w sin(phase) runs phase forwards)."""
    un = np.unwrap(ph, axis=0)
    return (un[-1] - un[0]) / (dt * (len(un) - 1))


def _random_states(key, b):
    return jax.random.uniform(key, (b, 3, 2), minval=-1.5, maxval=1.5)


def test_rk4_matches_harmonic_oscillator():
    # eps = 0 makes Eq. 2 a harmonic oscillator with the exact solution cos(w t); RK4 at dt = 0.01 is
    # accurate to ~1e-9 over 10 s.
    w = 0.8 * math.pi
    z = jnp.array([1.0, 0.0])
    f = lambda s: vdp_rhs(s, w, 0.0, 4.0)
    step = jax.jit(lambda s: jax.lax.fori_loop(0, 1000, lambda i, a: rk4_step(f, a, DT), s))
    z = step(z)
    assert abs(float(z[0]) - math.cos(w * 10.0)) < 1e-6


def _lock_times(err, tol=0.15):
    """(B,) s after which both followers stay within tol of the locked phase."""
    bad = np.abs(err).max(-1) > tol
    return np.array([(np.nonzero(bad[:, i])[0].max() + 1) * DT if bad[:, i].any() else 0.0
                     for i in range(bad.shape[1])])


def test_table1_network_phase_locks_and_reaches_unit_amplitude():
    """Table 1 parameters from 64 random states in [-1.5, 1.5]^6: the followers end at twice the leader's
    frequency and a lag of pi/2 in leader phase (x_i = -cos 2 theta_1), amplitudes at 2 / sqrt(b) = 1
    (Eq. 4). Tolerances: phase 0.15 rad, frequency ratio 2 +- 0.02, amplitude 1 +- 0.05.

    Fig. 3 of the paper shows the lock "after roughly 2 s". With Table 1's k = 0.1 we measure a median
    of ~39 s (90 % by ~59 s, all by ~71 s): the coupling acts at a rate of about k / 2 and the leader's
    amplitude relaxes at rate eps. The test pins that down; see docs/cpg.md."""
    net = NetworkParams.table1()
    zs = _run(_random_states(jax.random.PRNGKey(1), 64), net, 120.0)
    err, amp, ph = _lock_errors(zs, net)
    tail = slice(int(90 / DT), None)
    assert np.max(np.abs(err[tail])) < 0.15
    ratio = _frequency(ph[tail, :, 1], DT) / _frequency(ph[tail, :, 0], DT)
    np.testing.assert_allclose(ratio, 2.0, atol=0.02)
    np.testing.assert_allclose(amp[tail].mean(0), 2.0 / math.sqrt(4.0), atol=0.05)
    t_lock = _lock_times(err)
    assert 20.0 < np.median(t_lock) < 60.0 and t_lock.max() < 90.0


def test_strong_coupling_locks_within_a_few_seconds():
    """With k = 1 (ten times Table 1) the same starts lock in seconds, the paper's Fig. 3 time scale:
    median ~3.6 s, all within 10 s."""
    net = NetworkParams.table1().replace(k=jnp.full(4, 1.0))
    zs = _run(_random_states(jax.random.PRNGKey(1), 64), net, 15.0)
    t_lock = _lock_times(_lock_errors(zs, net)[0])
    assert np.median(t_lock) < 5.0 and t_lock.max() < 10.0


@pytest.mark.parametrize("b", [1.0, 4.0, 9.0])
def test_steady_amplitude_is_two_over_sqrt_b(b):
    """Eq. 4: the isolated neuron's limit cycle has amplitude 2 / sqrt(b) (within 2 %, eps = 0.1)."""
    w = 0.4 * math.pi
    f = lambda s: vdp_rhs(s, w, 0.1, b)
    z0 = jnp.array([[0.3, 0.0], [3.0, 0.0]])
    run = jax.jit(lambda s: jax.lax.scan(lambda a, _: (rk4_step(f, a, DT), a[..., 0]), s, None, length=20000)[1])
    xs = np.asarray(run(z0))[-2000:]  # last 20 s = 4 periods
    np.testing.assert_allclose(np.abs(xs).max(0), 2.0 / math.sqrt(b), rtol=0.02)


def test_network_returns_to_limit_cycle_after_kick_but_sinusoid_does_not():
    """Table 6, robustness to state disturbance: kick all three neurons off the locked cycle. The network
    rejoins it (amplitude within 0.1 of 1 and follower lock within 0.15 rad after 80 s). Plain sinusoids
    -- the same three signals from uncoupled harmonic oscillators (eps = 0, k = 0), which is what
    "explicit sinusoidal functions" are as a dynamical system -- keep the kicked amplitude and phase."""
    net = NetworkParams.table1()
    sine = net.replace(eps=jnp.zeros(3), k=jnp.zeros(4))
    z0 = locked_state(jnp.asarray(math.pi), net.omega[0])[None]
    kick = jnp.array([[[0.4, -0.5], [-0.6, 0.8], [0.5, 0.3]]])
    late = slice(int(80 / DT), None)
    err_n, amp_n, _ = _lock_errors(_run(z0 + kick, net, 100.0), net)
    assert np.max(np.abs(amp_n[late] - 1.0)) < 0.1
    assert np.max(np.abs(err_n[late])) < 0.15
    err_s, amp_s, _ = _lock_errors(_run(z0 + kick, sine, 100.0), sine)
    assert np.min(np.abs(amp_s[late] - 1.0).max(-1)) > 0.2
    assert np.min(np.abs(err_s[late]).max(-1)) > 0.3
    # unkicked, the sinusoids do sit on the locked cycle: the difference is the kick's, not the model's
    err_0, amp_0, _ = _lock_errors(_run(z0, sine, 100.0), sine)
    assert np.max(np.abs(err_0[late])) < 0.05 and np.max(np.abs(amp_0[late] - 1.0)) < 0.02


def test_locked_state_is_a_fixed_relation_of_eq5():
    """On locked_state the follower rate equals the drive -4 x1 y1, so the k-coupling terms vanish."""
    net = NetworkParams.table1()
    th = jnp.linspace(0, 2 * math.pi, 13)
    z = locked_state(th, net.omega[0])
    d = network_rhs(z, net.omega, net.eps, net.b, net.k)
    drive = -4.0 * z[:, 0, 0] * z[:, 0, 1]
    np.testing.assert_allclose(np.asarray(z[:, 1, 1]), np.asarray(drive), atol=1e-5)
    np.testing.assert_allclose(np.asarray(z[:, 1, 0]), np.asarray(1 - 2 * z[:, 0, 0] ** 2), atol=1e-5)
    assert np.all(np.isfinite(np.asarray(d)))
    # the coupling terms k12 (drive - y2), k13 (drive - y3), k23 (y2 - y3), k32 (y3 - y2) are zero there:
    # the right-hand side is the same with strong coupling as with none ...
    for k in (jnp.full(4, 5.0), jnp.array([0.3, 2.0, 0.0, 7.0])):
        np.testing.assert_allclose(np.asarray(network_rhs(z, net.omega, net.eps, net.b, k)),
                                   np.asarray(network_rhs(z, net.omega, net.eps, net.b, jnp.zeros(4))), atol=1e-4)
    # ... and off the locked cycle the coupling does act (so the check above can fail)
    off = z.at[:, 1, 1].add(0.3)
    gap = network_rhs(off, net.omega, net.eps, net.b, jnp.full(4, 5.0)) - network_rhs(off, net.omega, net.eps, net.b,
                                                                                       jnp.zeros(4))
    assert np.abs(np.asarray(gap)[:, 1:, 1]).min() > 1.0
