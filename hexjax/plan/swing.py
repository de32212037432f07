"""Swing planning as an optimisation (Chen 2019, Sect. 2.3), solved in JAX and batched.

The paper optimises each swing leg as a three-axis manipulator with terrain-clearance, initial/final and
physical-limit constraints, by a Gauss pseudospectral method, with an objective from animal locomotion
(its ref. [21], not in the text). Here:

* Decision variables: the joint angles at `knots` interior path points; the trajectory is the clamped
  cubic spline (Eqs. 4-5) through [q_start, knots, q_end] at equal times, so the initial/final constraint
  (positions, and zero velocities at both ends) holds by construction.
* Objective: the integral of squared joint acceleration over the swing (smooth, low-effort motion: our
  choice in place of ref. [21]'s criterion).
* Terrain clearance: the foot's surface must stay above the terrain profile under it by a margin that
  grows from 0 at lift-off and touchdown to `clearance` mid-swing (clearance x sin(pi t / T)); joint limits: the robot's ranges. Both are quadratic penalties with weight `penalty`, raised
  tenfold in each of `rounds` rounds (a penalty method; the paper's GPM is a collocation method, ours is
  first order: optax Adam).
* Start: inverse kinematics of a semi-ellipse over the highest terrain under the chord.

`optimise_swing` plans one leg; `jax.vmap` plans a batch (e.g. every swing leg of every env) in one call.
The terrain is a height profile (M,) sampled at equal steps along the horizontal chord from start to end,
in the leg frame's z (a heightmap lookup gives it, e.g. `hexjax.terrain.heightmap`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import optax

from hexjax.plan.support import clamped_spline
from hexjax.world.robot import RobotSpec, leg_fk, leg_ik


@dataclasses.dataclass(frozen=True)
class SwingConfig:
    knots: int = 4
    samples: int = 48  # time samples for the objective and the constraints
    steps: int = 400  # Adam steps per round
    rounds: int = 4
    learning_rate: float = 0.01
    clearance: float = 0.01  # m between the foot's surface and the terrain
    penalty: float = 1e3
    duration: float = 1.0  # s (scales the acceleration only)

    def validate(self) -> None:
        for f in ("knots", "samples", "steps", "rounds"):
            v = getattr(self, f)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"swing.{f}={v!r}: must be an integer >= 1")
        for f in ("learning_rate", "penalty", "duration"):
            if not getattr(self, f) > 0:
                raise ValueError(f"swing.{f}={getattr(self, f)!r}: must be > 0")
        if self.clearance < 0:
            raise ValueError(f"swing.clearance={self.clearance!r}: must be >= 0")


def _terrain_under(foot, start, end, profile):
    """Terrain height (leg-frame z) under foot positions (S, 3): the profile sampled along the chord, read at
    each foot's projection onto it (clamped to the chord's ends)."""
    chord = (end - start)[:2]
    t = jnp.clip((foot[:, :2] - start[:2]) @ chord / jnp.maximum(chord @ chord, 1e-12), 0.0, 1.0)
    grid = jnp.linspace(0.0, 1.0, profile.shape[0])
    return jnp.interp(t, grid, profile)


def _trajectory(cfg, q0, q1, inner):
    ts = jnp.linspace(0.0, cfg.duration, cfg.knots + 2)
    s = clamped_spline(ts, jnp.concatenate([q0[None], inner, q1[None]], 0))
    tq = jnp.linspace(0.0, cfg.duration, cfg.samples)
    return tq, s


def swing_costs(robot: RobotSpec, cfg: SwingConfig, start, end, profile, inner):
    """(effort, clearance violation (S,), limit violation (S, 3), foot path (S, 3)) of knot angles inner."""
    q0, _ = leg_ik(robot, start)
    q1, _ = leg_ik(robot, end)
    tq, s = _trajectory(cfg, q0, q1, inner)
    q = s(tq)
    dt = tq[1] - tq[0]
    acc = (q[2:] - 2 * q[1:-1] + q[:-2]) / dt ** 2
    effort = jnp.sum(acc ** 2) * dt
    foot = leg_fk(robot, q)
    # the margin grows from 0 at lift-off and touchdown (the feet start and end on the terrain) to
    # `clearance` mid-swing
    margin = cfg.clearance * jnp.sin(jnp.pi * tq / cfg.duration)
    need = _terrain_under(foot, start, end, profile) + robot.foot_radius + margin
    gap = jnp.maximum(need - foot[:, 2], 0.0)
    lo = jnp.array([robot.coxa_range[0], robot.femur_range[0], robot.tibia_range[0]])
    hi = jnp.array([robot.coxa_range[1], robot.femur_range[1], robot.tibia_range[1]])
    lim = jnp.maximum(lo - q, 0.0) + jnp.maximum(q - hi, 0.0)
    return effort, gap, lim, foot


def optimise_swing(robot: RobotSpec, cfg: SwingConfig, start, end, profile):
    """One leg's swing from foot centre `start` (3,) to `end` (3,) (leg frame, m) over terrain `profile` (M,).
    Returns dict: knots (K, 3) rad; foot path (S, 3); violation (m): the largest shortfall of the clearance
    constraint; min_clearance (m): foot surface to terrain (0 at the ends); limit_violation (rad); effort;
    and start_effort, start_violation of the semi-ellipse start."""
    top = jnp.max(profile)
    s = jnp.linspace(0.0, 1.0, cfg.knots + 2)[1:-1]
    lift = jnp.maximum(top + cfg.clearance + robot.foot_radius + 0.02 - jnp.maximum(start[2], end[2]), 0.02)
    guess_pts = (start + (end - start) * 0.5 * (1 - jnp.cos(jnp.pi * s))[:, None]
                 + jnp.array([0.0, 0.0, 1.0]) * lift * jnp.sin(jnp.pi * s)[:, None])
    inner0, _ = leg_ik(robot, guess_pts)

    def loss(inner, w):
        effort, gap, lim, _ = swing_costs(robot, cfg, start, end, profile, inner)
        return effort + w * (jnp.sum(gap ** 2) + jnp.sum(lim ** 2)) * 1e3

    opt = optax.adam(cfg.learning_rate)

    def run_round(carry, w):
        inner, state = carry

        def step(c, _):
            x, st = c
            g = jax.grad(loss)(x, w)
            upd, st = opt.update(g, st, x)
            return (optax.apply_updates(x, upd), st), None

        (inner, state), _ = jax.lax.scan(step, (inner, state), None, length=cfg.steps)
        return (inner, state), None

    weights = cfg.penalty * 10.0 ** jnp.arange(cfg.rounds)
    (inner, _), _ = jax.lax.scan(run_round, (inner0, opt.init(inner0)), weights)

    def report(x):
        effort, gap, lim, foot = swing_costs(robot, cfg, start, end, profile, x)
        return {"effort": effort, "violation": jnp.max(gap), "limit_violation": jnp.max(lim), "foot": foot,
                "min_clearance": jnp.min(foot[:, 2] - robot.foot_radius - _terrain_under(foot, start, end, profile))}

    out, start_out = report(inner), report(inner0)
    return {"knots": inner, **out, "start_effort": start_out["effort"], "start_violation": start_out["violation"]}
