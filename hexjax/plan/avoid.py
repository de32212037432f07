"""Obstacle avoidance by direction selection: Zhao, Chai, Gao, Qi 2018, Sect. 3.

The robot and the obstacles are circles (Eq. 1). Every plan cycle the planner scores each candidate
walking direction u_i (a fixed fan, plus the direction to the target, Eq. 2) by

    F(u_i) = 1 / (1 + u_i . u_T |w_i|) + sum_r sum_p sum_q c_pq(r)                      (Eqs. 3, 6)

where the second term predicts the robot n_T time-steps ahead along u_i and adds the tanh penalty c_pq(r)
of every robot circle p against every obstacle q at every predicted step r (Eq. 5: 1 at or below d_min,
0 at or beyond d_max). The best direction is walked for n_T time-steps, then the planner runs again, until
the target is reached. Pure JAX: `plan` runs one whole walk as a `lax.scan` over plan cycles, so `vmap`
plans thousands of obstacle fields and start/target pairs in one call.

Readings where the paper is silent (each also in docs/planning.md):
  * Fan: "36 discrete fixed directions evenly spatially distributed (0, 5, ..., 175, 180 deg)" lists 37
    angles; we take the 36 at 0, 5, ..., 175 deg (every angle Table 2's path uses is among them),
    measured in the world frame from +x, with the robot facing +y (90 deg). It walks omnidirectionally
    and does not turn (Sect. 3.2), so its circles keep their offsets. `fan(n, span)` makes others.
  * Walking capacity |w_i| (Fig. 6, not in the text): Table 2's plan cycles fix it. They move 0.749 m
    at 90 deg, 0.675 m at 75 and 105, 0.600 m at 60, 0.525 m at 135, and 0.728 m along the target
    direction 4.5 deg off forward, which is 0.75 m x (1 - |angle off forward| / 150 deg) for every one of
    them. That is the default `capacity`; the target direction gets the value of the same line.
  * Step: a plan cycle of n_T = 5 time-steps of 0.15 m at |w| = 1 (0.75 m, Table 2); the split between
    n_T and the step is not given.
  * Eq. 3's first term is infinite for u_i . u_T |w_i| = -1; the denominator is floored at 1e-6.
  * Eq. 4 is a hard constraint, relaxed by the penalty. Where a candidate's prediction would make a
    robot circle overlap an obstacle (d_pq <= 0), we drop it; if every candidate would, the robot holds
    its place for the cycle (counted as `stuck`). The paper's scores alone can pick an overlapping move
    when the target term outweighs a capped penalty.
  * The walk stops at the target: a time-step is never longer than the distance left to the target, and
    once the robot is within `goal_tol` of it (checked every time-step) it stops and the walk is done.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct


def fan(n: int = 36, span_deg: float = 180.0, start_deg: float = 0.0) -> np.ndarray:
    """(n,) candidate angles, rad, from start_deg in equal steps of span_deg / n (the paper: 36 over 180)."""
    return np.radians(start_deg + span_deg / n * np.arange(n))


def capacity_line(angles, forward=math.pi / 2, per_deg=1.0 / 150.0, floor=0.1):
    """|w| of Fig. 6 as read from Table 2: 1 - |angle off forward| / 150 deg, floored (module notes)."""
    off = jnp.abs(jnp.angle(jnp.exp(1j * (jnp.asarray(angles) - forward))))
    return jnp.maximum(floor, 1.0 - jnp.degrees(off) * per_deg)


@struct.dataclass
class AvoidParams:
    """Traced numbers of the planner (SI units; `vmap` may batch any of them).

    angles (n,) rad: candidate directions (world frame, from +x); capacity (n,): |w_i| of each
    robot_offsets (P, 2) m: robot circle centres relative to the robot's position; robot_radii (P,) m
    d_min, d_max () m: Eq. 5; step () m: distance of one time-step at |w| = 1; goal_tol () m
    """

    angles: jax.Array
    capacity: jax.Array
    robot_offsets: jax.Array
    robot_radii: jax.Array
    d_min: jax.Array
    d_max: jax.Array
    step: jax.Array
    goal_tol: jax.Array


@dataclasses.dataclass(frozen=True)
class AvoidConfig:
    """Static settings: n_T time-steps per plan cycle, the most plan cycles of one walk, and whether the
    target direction joins the candidates (Eq. 3's n + 1-th). `check_substeps`: points per time-step at
    which the executed path is checked for overlap (the planner itself predicts only at whole steps)."""

    n_T: int = 5
    max_cycles: int = 40
    target_candidate: bool = True
    check_substeps: int = 8

    def validate(self) -> None:
        for f in ("n_T", "max_cycles", "check_substeps"):
            v = getattr(self, f)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise ValueError(f"avoid.{f}={v!r}: must be an integer >= 1")


def octopus_params(n_dirs: int = 36, d_min: float = 0.05, d_max: float = 0.2) -> AvoidParams:
    """Octopus-III of Zhao 2018 facing +y, its hexagonal body enveloped by a front and a back circle
    (Fig. 4). Their size is not in the text (the feet span 1.3 m x 0.9 m, Sect. 2). We fit it to Table 2:
    over radii 0.40-0.75 m and offsets 0-0.4 m, circles of 0.6 m radius 0.1 m ahead of and behind the
    centre put the plan cycles closest to the recorded positions (docs/planning.md)."""
    a = fan(n_dirs)
    return AvoidParams(angles=jnp.asarray(a, jnp.float32), capacity=capacity_line(a).astype(jnp.float32),
                       robot_offsets=jnp.array([[0.0, 0.1], [0.0, -0.1]]), robot_radii=jnp.array([0.6, 0.6]),
                       d_min=jnp.float32(d_min), d_max=jnp.float32(d_max), step=jnp.float32(0.15),
                       goal_tol=jnp.float32(0.1))


def _fmt(v) -> str:
    v = np.asarray(v, float)
    return f"{v.item():.6g}" if v.size == 1 else repr(np.round(v, 6).tolist())


def validate_params(p: AvoidParams) -> None:
    """Host-side checks on concrete params, before tracing; names the field and value."""
    a, w = np.asarray(p.angles), np.asarray(p.capacity)
    if a.ndim < 1 or a.shape[-1] == 0:
        raise ValueError(f"avoid.angles shape={a.shape!r}: at least one candidate direction is needed")
    if w.shape != a.shape or not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise ValueError(f"avoid.capacity={_fmt(w)}: one finite value > 0 per angle {a.shape!r}")
    dmin, dmax = np.asarray(p.d_min), np.asarray(p.d_max)
    if np.any(dmin < 0) or np.any(dmin >= dmax):
        raise ValueError(f"avoid.d_min={_fmt(dmin)}, d_max={_fmt(dmax)}: need 0 <= d_min < d_max")
    for f in ("step", "goal_tol"):
        v = np.asarray(getattr(p, f))
        if not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise ValueError(f"avoid.{f}={_fmt(v)}: must be finite and > 0")
    r = np.asarray(p.robot_radii)
    if np.asarray(p.robot_offsets).shape[-2:] != r.shape[-1:] + (2,) or np.any(r <= 0):
        raise ValueError(f"avoid.robot_radii={_fmt(r)}: one radius > 0 per (x, y) offset")


def clearance(pos, p: AvoidParams, centres, radii, valid):
    """Eq. 1 for every robot circle and obstacle: d_pq (..., P, Q) m at robot positions pos (..., 2);
    invalid obstacles are at +inf."""
    c = pos[..., None, :] + p.robot_offsets  # (..., P, 2)
    d = jnp.linalg.norm(c[..., :, None, :] - centres[..., None, :, :], axis=-1) - p.robot_radii[:, None] - radii
    return jnp.where(valid, d, jnp.inf)


def penalty(d, d_min, d_max):
    """Eq. 5: 1 at or below d_min, 0 at or beyond d_max, 0.5 (1 + tanh(1/(d - d_min) + 1/(d - d_max)))
    between (continuous at both ends)."""
    inside = (d > d_min) & (d < d_max)
    ds = jnp.where(inside, d, 0.5 * (d_min + d_max))  # keeps the unused branch finite
    mid = 0.5 * (1.0 + jnp.tanh(1.0 / (ds - d_min) + 1.0 / (ds - d_max)))
    return jnp.where(d <= d_min, 1.0, jnp.where(inside, mid, 0.0))


def _advance(pos, u, dist, target):
    """Move pos (2,) by dist along unit u, but never by more than the distance left to the target (so the
    target direction stops on the target; a sidestep far from it keeps its full length)."""
    return pos + u * jnp.minimum(dist, jnp.linalg.norm(target - pos))


def scores(pos, target, p: AvoidParams, cfg: AvoidConfig, centres, radii, valid):
    """Eq. 6 for each candidate at robot position pos: (F (n + 1,), unit directions (n + 1, 2),
    capacities (n + 1,), overlap (n + 1,) bool: the prediction would make a circle overlap an obstacle)."""
    to_t = target - pos
    u_t = to_t / jnp.maximum(jnp.linalg.norm(to_t), 1e-9)  # Eq. 2
    u = jnp.stack([jnp.cos(p.angles), jnp.sin(p.angles)], -1)
    w = p.capacity
    if cfg.target_candidate:
        ang_t = jnp.arctan2(u_t[1], u_t[0])
        # the target direction's capacity: the capacity of the candidates, interpolated around the circle
        order = jnp.argsort(jnp.mod(p.angles, 2 * jnp.pi))
        a_s, w_s = jnp.mod(p.angles, 2 * jnp.pi)[order], w[order]
        w_t = jnp.interp(jnp.mod(ang_t, 2 * jnp.pi), a_s, w_s, period=2 * jnp.pi)
        u = jnp.concatenate([u, u_t[None]], 0)
        w = jnp.concatenate([w, w_t[None]], 0)
    first = 1.0 / jnp.maximum(1.0 + (u @ u_t) * w, 1e-6)  # Eq. 3

    def predict(ui, wi):
        def one(q, _):
            q = _advance(q, ui, p.step * wi, target)
            return q, clearance(q, p, centres, radii, valid)
        _, d = jax.lax.scan(one, pos, None, length=cfg.n_T)  # (n_T, P, Q)
        return jnp.sum(penalty(d, p.d_min, p.d_max)), jnp.min(d) <= 0.0

    pen, overlap = jax.vmap(predict)(u, w)
    return first + pen, u, w, overlap


@struct.dataclass
class Plan:
    """One walk (or a batch: leading axes). path (C + 1, 2): the robot's position after each plan cycle
    (row 0 the start); chosen (C,) index of the chosen candidate (n = the target direction, -1 none:
    held or done); reached (), cycles () plan cycles used, stuck () cycles held because every candidate
    overlapped, min_clearance () m smallest d_pq along the executed path (checked between steps too),
    length () m walked."""

    path: jax.Array
    chosen: jax.Array
    reached: jax.Array
    cycles: jax.Array
    stuck: jax.Array
    min_clearance: jax.Array
    length: jax.Array


def plan(start, target, centres, radii, valid, p: AvoidParams, cfg: AvoidConfig = AvoidConfig()) -> Plan:
    """Plan one walk from start (2,) to target (2,) among obstacle circles (centres (Q, 2), radii (Q,),
    valid (Q,)): direction selection every n_T time-steps (Sect. 3.2) until the target is within goal_tol
    or max_cycles have run. Pure; `jax.vmap` it over fields, start/target pairs and params."""
    start, target = jnp.asarray(start, jnp.float32), jnp.asarray(target, jnp.float32)
    n_sub = cfg.check_substeps

    def cycle(carry, _):
        pos, done, stuck, dmin, length = carry
        f, u, w, overlap = scores(pos, target, p, cfg, centres, radii, valid)
        f = jnp.where(overlap, jnp.inf, f)
        k = jnp.argmin(f)
        hold = done | jnp.all(overlap)
        ui, wi = u[k], w[k]

        def step(c, _):
            q, dm = c
            arrived = jnp.linalg.norm(target - q) <= p.goal_tol  # a robot at the target stops there
            q1 = jnp.where(hold | arrived, q, _advance(q, ui, p.step * wi, target))
            # the executed segment, checked at n_sub points (the prediction only sees its end)
            s = q + (q1 - q) * (jnp.arange(1, n_sub + 1) / n_sub)[:, None]
            dm = jnp.minimum(dm, jnp.min(clearance(s, p, centres, radii, valid)))
            return (q1, dm), None

        (new, dmin), _ = jax.lax.scan(step, (pos, dmin), None, length=cfg.n_T)
        length = length + jnp.linalg.norm(new - pos)
        stuck = stuck + (~done & jnp.all(overlap)).astype(jnp.int32)
        reached = jnp.linalg.norm(target - new) <= p.goal_tol
        chosen = jnp.where(hold, -1, k)
        return (new, done | reached, stuck, dmin, length), (new, chosen, done)

    d0 = jnp.min(clearance(start[None], p, centres, radii, valid))
    done0 = jnp.linalg.norm(target - start) <= p.goal_tol
    init = (start, done0, jnp.int32(0), d0, jnp.float32(0.0))
    (end, done, stuck, dmin, length), (path, chosen, was_done) = jax.lax.scan(cycle, init, None,
                                                                            length=cfg.max_cycles)
    return Plan(path=jnp.concatenate([start[None], path], 0), chosen=chosen, reached=done,
                cycles=jnp.sum(~was_done).astype(jnp.int32), stuck=stuck, min_clearance=dmin, length=length)


def check_inputs(start, target, centres, radii, valid, p: AvoidParams, cfg: AvoidConfig) -> None:
    """Host-side checks before a batch is traced: shapes, finite numbers, params, and a target inside an
    obstacle (no walk can reach it) named with its field index."""
    cfg.validate()
    validate_params(p)
    s, t = np.asarray(start, float), np.asarray(target, float)
    c, r, v = np.asarray(centres, float), np.asarray(radii, float), np.asarray(valid, bool)
    if s.shape[-1:] != (2,) or t.shape[-1:] != (2,) or c.shape[-1:] != (2,):
        raise ValueError(f"start {s.shape}, target {t.shape}, centres {c.shape}: last axis must be (x, y)")
    if not (np.all(np.isfinite(s)) and np.all(np.isfinite(t)) and np.all(np.isfinite(c[v])) and np.all(np.isfinite(r[v]))):
        raise ValueError("start, target and valid obstacles must be finite")
    if np.any(r[v] <= 0):
        raise ValueError(f"obstacle radii must be > 0 (got min {r[v].min()!r})")
    inside = np.any(v & (np.linalg.norm(c - t[..., None, :], axis=-1) < r), axis=-1)
    if np.any(inside):
        idx = np.argwhere(np.atleast_1d(inside)).ravel()[:5].tolist()
        raise ValueError(f"target inside an obstacle in field(s) {idx}: no walk can reach it")
