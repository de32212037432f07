"""MJX's internals replaced while a rollout is traced: the Newton solve as a fixed-length scan with a safe square
root (`reversible_solver`), the frames' rotation and the implicit integrator's linear solve with cheaper
derivatives (`rotation_rule`, `integrator_rule`), and the context that swaps a module's name (`swapped`). Each
keeps MJX's values; each relies on private names of the pinned mujoco-mjx (3.17.0), said at each."""

from __future__ import annotations

import contextlib
import io

import jax
import jax.numpy as jnp

# mujoco.mjx prints "Failed to import warp" when the optional MuJoCo Warp backend is absent; hexjax uses
# the JAX implementation, so that notice is noise on every command.
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    from mujoco import mjx  # noqa: E402


class _ScanLax:
    """jax.lax with `while_loop` run as a fixed-length scan of `n` iterations (no-ops once done)."""

    def __init__(self, n: int):
        self.n = n

    def __getattr__(self, name):
        return getattr(jax.lax, name)

    def while_loop(self, cond, body, init):
        from mujoco.mjx._src import solver
        return solver._while_loop_scan(cond, body, init, self.n)


class _JaxWithScanLax:
    def __init__(self, n: int):
        self.lax = _ScanLax(n)

    def __getattr__(self, name):
        return getattr(jax, name)


@jax.custom_jvp
def _sqrt(x):
    """jnp.sqrt, with derivative 0 where x <= 0 instead of inf. MJX's elliptic-cone line search takes the square
    root of each contact's tangential force squared, exactly 0 for a contact without friction force (a parked
    slot, a foot in the air); its derivative there is inf, and reverse mode multiplies it by the 0 cotangent of the
    branch that discards it: NaN in every gradient. Values are jnp.sqrt's, bit for bit."""
    return jnp.sqrt(x)


@_sqrt.defjvp
def _sqrt_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    y = jnp.sqrt(x)
    pos = x > 0
    return y, jnp.where(pos, dx / (2 * jnp.where(pos, y, 1.0)), 0.0)


class _NumpySafeSqrt:
    """jax.numpy with `sqrt` replaced by `_sqrt` (for MJX's solver module, as `reversible_solver` traces it)."""
    sqrt = staticmethod(_sqrt)

    def __getattr__(self, name):
        return getattr(jnp, name)


@contextlib.contextmanager
def reversible_solver(iterations: int):
    """While open, MJX's constraint solver traces its Newton iterations as a fixed-length scan instead of a
    lax.while_loop, so reverse-mode gradients go through `iterations` > 1 (MJX already runs its line search
    this way). Same result as the while loop: iterations after convergence are no-ops. Its `jp.sqrt` gets a
    derivative that is finite at 0 (`_sqrt`), so that gradients through the elliptic cone are not NaN. Only
    tracing needs the context; compiled functions keep what they traced. Relies on three private names of
    MJX's solver module (its `jax` and `jp` globals and `_while_loop_scan`), present in the pinned mujoco-mjx
    3.17.0."""
    from mujoco.mjx._src import solver
    if not (hasattr(solver, "_while_loop_scan") and getattr(solver, "jax", None) is not None
            and getattr(solver, "jp", None) is jnp):
        raise RuntimeError("reversible_solver: this mujoco-mjx's solver lacks _while_loop_scan or its jax / jp "
                           "globals; use PhysicsConfig(iterations=1) for gradients instead")
    with swapped(solver, "jax", _JaxWithScanLax(iterations)), swapped(solver, "jp", _NumpySafeSqrt()):
        yield


@contextlib.contextmanager
def swapped(module, name: str, value):
    """While open, `module.name` is `value`; the previous one is put back on exit, also after an exception. This
    is how hexjax traces MJX with one of its internals replaced (`reversible_solver`, `rotation_rule`,
    `hexjax.sim.internals.implicit.implicit_solver`): MJX looks these names up in their module at each call."""
    prev = getattr(module, name)
    setattr(module, name, value)
    try:
        yield
    finally:
        setattr(module, name, prev)


def _rotation(p):
    """The rotation matrix of a unit quaternion (w, x, y, z) from p(i, j), the (i, j) entry of q q^T; given the
    entries of q dq^T + dq q^T instead, the same linear map gives the matrix's tangent."""
    return jnp.array([[p(0, 0) + p(1, 1) - p(2, 2) - p(3, 3), 2 * (p(1, 2) - p(0, 3)), 2 * (p(1, 3) + p(0, 2))],
                      [2 * (p(1, 2) + p(0, 3)), p(0, 0) - p(1, 1) + p(2, 2) - p(3, 3), 2 * (p(2, 3) - p(0, 1))],
                      [2 * (p(1, 3) - p(0, 2)), 2 * (p(2, 3) + p(0, 1)), p(0, 0) - p(1, 1) - p(2, 2) + p(3, 3)]])


_MJX_QUAT_TO_MAT = mjx._src.math.quat_to_mat  # MJX's own, whatever `rotation_rule` patches in later


@jax.custom_jvp
def quat_to_mat(q):
    """MJX's `math.quat_to_mat` with its values, and a derivative written per component. MJX forms q q^T and reads
    its entries 24 times (10 distinct ones); reverse mode turns every read into a zero 4 x 4 array with one entry
    set, and sums them: 24 arrays of the batch's size for each body and geom frame of every physics step. On 2 CPU
    cores those pads and sums took 11.5 % of the windowed gradient's kernel time (B = 64, docs/benchmarks.md
    2026-11-27 fourth session). Here reverse mode slices the 4 components of the tangent once."""
    return _MJX_QUAT_TO_MAT(q)


@quat_to_mat.defjvp
def _quat_to_mat_jvp(primals, tangents):
    (q,), (dq,) = primals, tangents
    qs, ds = [q[i] for i in range(4)], [dq[i] for i in range(4)]
    return _MJX_QUAT_TO_MAT(q), _rotation(lambda i, j: qs[i] * ds[j] + ds[i] * qs[j])


def rotation_rule():
    """While open, MJX's kinematics (bodies', geoms' and sites' frames) call `quat_to_mat` above: the same values,
    a cheaper reverse mode. Only tracing needs the context. Relies on MJX's `smooth` and `support` modules calling
    `math.quat_to_mat` through the module (mujoco-mjx 3.17.0)."""
    return swapped(mjx._src.math, "quat_to_mat", quat_to_mat)


@jax.custom_jvp
def spd_solve(a, b):
    """a^{-1} b for a symmetric positive definite a, computed as MJX's implicit integrator computes it (a Cholesky
    factor of a, then two triangular solves), with the derivative of the solution itself:
    d(a^{-1} b) = a^{-1} (db - da a^{-1} b), one more solve with the same factor for each tangent. JAX's own rule
    differentiates the factor instead (two triangular solves with a matrix right-hand side per tangent, O(n^3)),
    which took 7 % of a forward-mode gradient's GPU time."""
    return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(a), b)


@spd_solve.defjvp
def _spd_solve_jvp(primals, tangents):
    (a, b), (da, db) = primals, tangents
    factor = jax.scipy.linalg.cho_factor(a)
    x = jax.scipy.linalg.cho_solve(factor, b)
    return x, jax.scipy.linalg.cho_solve(factor, db - da @ x)


def _implicit_integrator(m, d):
    """MJX's `forward.implicit` (the implicit and implicitfast integrators, mujoco-mjx 3.17.0) with its linear solve
    as `spd_solve`: the same values, a cheaper derivative."""
    derivative, forward, support = mjx._src.derivative, mjx._src.forward, mjx._src.support
    with jax.named_scope("implicit"):
        qderiv = derivative.deriv_smooth_vel(m, d)
        qacc = d.qacc
        if qderiv is not None:
            qm = support.full_m(m, d) if support.is_sparse(m) else d._impl.M
            qacc = spd_solve(qm - m.opt.timestep * qderiv, d.qfrc_smooth + d.qfrc_constraint)
        return forward._advance(m, d, d.act_dot, qacc)


def integrator_rule():
    """While open, MJX's step integrates with `_implicit_integrator` (same values, the derivative of its linear solve
    by `spd_solve`). Only tracing needs the context. Relies on MJX's `forward.step` calling `implicit` through its
    module (mujoco-mjx 3.17.0)."""
    return swapped(mjx._src.forward, "implicit", _implicit_integrator)
