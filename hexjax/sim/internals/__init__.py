"""MJX's internals, in one place: every file of hexjax that patches or reads MJX's (and MuJoCo Warp's) private
modules is in this package, and a rollout's solve is traced under one context, `solver_context`.

- `rules`: MJX's Newton solve as a fixed-length scan (`reversible_solver`), the rotation and integrator rules,
  and `swapped`, the context that replaces a name in one of MJX's modules while a rollout is traced;
- `implicit`: the implicit-function-theorem backward of the contact solve, and the kept solutions the windowed
  gradient reuses;
- `forward_mode`: forward mode's rule through the same solve;
- `collide`: MuJoCo C's sphere-box and capsule-box contacts in place of MJX's convex routines, and MJX's box-box
  contact with its edge clipping differentiated without NaN (`c_box_contacts`);
- `contacts`: what the simulator reads (contact slot order, contact forces, Warp's overflow flags);
- `warp_cpu`: MuJoCo Warp's calls recorded and replayed on a CPU.

Each was written against the versions pinned in `hexjax.private_reach`; `tests/test_private_reach.py` fails,
naming these files, when another version is installed or a file outside the list reaches into a private module.
"""

from __future__ import annotations

import contextlib

from hexjax.sim.config import PhysicsConfig, RolloutConfig
from hexjax.sim.internals.collide import c_box_contacts
from hexjax.sim.internals.forward_mode import check_model, forward_solver
from hexjax.sim.internals.implicit import REMAT_POLICY, implicit_solver
from hexjax.sim.internals.rules import integrator_rule, reversible_solver, rotation_rule

__all__ = ["REMAT_POLICY", "check_model", "solver_context"]


@contextlib.contextmanager
def solver_context(cfg: RolloutConfig, physics: PhysicsConfig):
    """The context under which MJX's constraint solve is traced as `cfg.solver_grad` says: its Newton iterations
    as a scan ('unrolled'), implicit differentiation ('implicit'), or MJX's own while loop ('none'). The first
    two, which reverse mode goes through, also trace MJX's rotation matrices and its implicit integrator's linear
    solve with cheaper derivatives (`hexjax.sim.internals.rules.rotation_rule`, `integrator_rule`; same values);
    forward-only rollouts ('none') are traced as MJX writes them. With `cfg.grad_mode='forward'` the solve takes
    forward mode's rule instead (`hexjax.sim.internals.forward_mode.forward_solver`). Every rollout's sphere-box
    and capsule-box contacts are MuJoCo C's, and its box-box contacts differentiate without NaN
    (`hexjax.sim.internals.collide`)."""
    with c_box_contacts():
        with _solve_context(cfg, physics):
            yield


@contextlib.contextmanager
def _solve_context(cfg: RolloutConfig, physics: PhysicsConfig):
    if cfg.solver_grad == "none":
        yield
        return
    if cfg.grad_mode == "forward":  # validated: implicit
        solve = forward_solver()
    else:
        solve = reversible_solver(physics.iterations) if cfg.solver_grad == "unrolled" else implicit_solver()
    with rotation_rule(), integrator_rule(), solve:
        yield
