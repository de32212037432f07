"""Static settings of the simulator: physics (MuJoCo solver and terrain slots), sensors, and the rollout.

All three are frozen dataclasses: hashable, so they key compiled programs, and changing one recompiles.
Each checks itself (`validate`) on the host before anything is traced.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional


CONES = ("pyramidal", "elliptic")
INTEGRATORS = ("euler", "implicitfast")
MAX_ITERATIONS = 10_000  # Newton iterations per physics step; MuJoCo's docs: ~5 suffice, rarely more than 20


@dataclasses.dataclass(frozen=True)
class PhysicsConfig:
    """Solver settings of one model, MuJoCo's `<option>` plus hexjax's terrain culling (`hexjax.sim.model`).

    The defaults are the `fast` physics preset (configs/physics/fast.yaml): two Newton iterations, MJX's
    pyramidal cone. Results are reported on the `validated` preset (`hexjax.sim.physics.get_physics`), whose
    every figure is within the fidelity contract of converged MuJoCo C (docs/physics.md). A preset holds its
    settings as one of these (`PhysicsPreset.settings`), where a slot count of None means the terrain's own;
    `PhysicsPreset.config(terrain)` gives the counts a model is built with."""

    timestep: float = 0.005  # s
    iterations: int = 2  # 1 lets six stance feet chatter (measured: torso hops, 1.5 of 6 feet in contact)
    ls_iterations: int = 4
    integrator: str = "implicitfast"
    cone: str = "pyramidal"
    slots_per_leg: Optional[int] = 2  # terrain boxes each leg collides with at a time (MJX engines); None: the terrain's
    torso_slots: Optional[int] = 2  # and the torso
    tolerance: float = 1e-8  # MuJoCo's opt.tolerance: the Newton loop stops once its relative improvement is below
    ls_tolerance: float = 0.01  # MuJoCo's opt.ls_tolerance: the line search's stopping rule
    impratio: float = 1.0  # MuJoCo's opt.impratio: frictional over normal constraint impedance (elliptic cone)

    def validate(self) -> None:
        num = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        whole = lambda v: isinstance(v, int) and not isinstance(v, bool)
        if not (num(self.timestep) and 0 < self.timestep <= 0.02):
            raise ValueError(f"physics.timestep={self.timestep!r}: must be in (0, 0.02] s")
        for f in ("iterations", "ls_iterations"):
            v = getattr(self, f)
            if not (whole(v) and 1 <= v <= MAX_ITERATIONS):
                raise ValueError(f"physics.{f}={v!r}: must be a whole number in [1, {MAX_ITERATIONS}]")
        for f in ("tolerance", "ls_tolerance"):
            v = getattr(self, f)
            if not (num(v) and 0 < v < 1):
                raise ValueError(f"physics.{f}={v!r}: must be a number in (0, 1)")
        if not (num(self.impratio) and 0 < self.impratio <= 1000):
            raise ValueError(f"physics.impratio={self.impratio!r}: must be a number in (0, 1000]")
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"physics.integrator={self.integrator!r}: use one of {INTEGRATORS}")
        if self.cone not in CONES:
            raise ValueError(f"physics.cone={self.cone!r}: use one of {CONES}")
        for f in ("slots_per_leg", "torso_slots"):
            v = getattr(self, f)
            if not (v is None or whole(v) and 0 <= v <= 16):
                raise ValueError(f"physics.{f}={v!r}: must be a whole number in [0, 16] (or null: the terrain's own)")


def physics_for(kind: str, base: "PhysicsConfig | None" = None) -> "PhysicsConfig":
    """The physics settings a terrain kind needs: flat ground has no boxes, so no slots (7 pairs)."""
    base = base or PhysicsConfig()
    if kind == "flat":
        return dataclasses.replace(base, slots_per_leg=0, torso_slots=0)
    return base


@dataclasses.dataclass(frozen=True)
class SensorConfig:
    contact_threshold: float = 0.5  # N
    tactile_threshold: float = 0.3  # N


GRAD_SOLVERS = ("unrolled", "implicit")  # the values of RolloutConfig.solver_grad that reverse mode goes through
SOLVER_GRADS = ("none",) + GRAD_SOLVERS
GRAD_MODES = ("reverse", "forward")  # the values of RolloutConfig.grad_mode


@dataclasses.dataclass(frozen=True)
class RolloutConfig:
    """Static rollout settings (changing one recompiles)."""

    settle_time: float = 0.3  # s of standing before the controller starts; start pose is taken after it
    yaw_noise: float = math.radians(3.0)  # initial heading drawn from U(-yaw_noise, yaw_noise), rad
    fall_tilt: float = math.radians(60.0)  # torso tilt beyond this counts as a fall, rad
    fall_height: float = 0.03  # torso centre closer than this to the ground plane counts as a fall, m
    record: bool = False  # keep a per-control-step torso trace (B, T, 4): x, y, z, yaw
    # Reverse mode only: bound the norm of the gradient flowing back through the physics and controller
    # state at every control step, per env under vmap (None: exact gradients). It bounds the cotangent the env
    # receives: differentiate a sum over envs, not a mean, or the bound loosens with the batch
    # (`hexjax.tune.objective.mean_value_and_grad`). Gradients through stiff contacts grow ~100x per 0.1 s and
    # overflow within a second; a per-step bound keeps them finite and their direction local.
    grad_clip: Optional[float] = None
    # Reverse mode only: truncated gradients. Every `grad_window` control steps the physics and controller
    # state are cut from the gradient (stop_gradient), so the gradient of `Summary.travel` is the sum of the
    # per-window gradients with each window's start state held fixed (truncated backpropagation through
    # time; 0: no cut). Its value is unchanged.
    grad_window: int = 0
    # Recompute each control step in the backward pass instead of storing its internals (jax.checkpoint):
    # memory per env and step drops from every substep's solver residuals to one mjx.Data. With `grad_window`,
    # each window is recomputed too (`hexjax.sim.engines.mjx.windowed_scan`): one mjx.Data per window and one
    # window's steps at a time, so the memory follows the window, not the walk.
    remat: bool = False
    # Trace a control step's physics steps one after another instead of as a loop (values equal to float32
    # rounding: XLA fuses them differently). In reverse mode with `remat`, the loop stacks hundreds of small
    # residual arrays per physics step for the transpose; unrolled, value_and_grad of the tuning objective runs
    # 28 % faster on an H100 (B = 4,096), and XLA takes 2.1x as long to compile it (docs/tuning.md).
    unroll_substeps: bool = False
    # How reverse mode goes through MJX's constraint solve (forward values are the same for all three):
    #   'none'      MJX's lax.while_loop, which JAX cannot reverse: gradients need physics.iterations == 1
    #               (one unconverged Newton step makes the rollout non-smooth in the params: central
    #               differences flip sign with the step size; tests/test_tune.py)
    #   'unrolled'  the Newton iterations traced as a fixed-length scan (`hexjax.sim.internals.rules.reversible_solver`)
    #               and differentiated step by step: the reference
    #   'implicit'  the implicit function theorem at the solution (`hexjax.sim.internals.implicit`): one linear solve
    #               with the Newton Hessian per physics step in the backward pass; exact where the solver
    #               has converged
    solver_grad: str = "none"
    # How the gradient is carried: 'reverse' (jax.grad, the default) or 'forward' (jax.jacfwd, one tangent per
    # tuned number beside the primal; `hexjax.sim.internals.forward_mode` gives MJX's solve its forward-mode
    # rule). Forward mode needs solver_grad='implicit' and has no remat (no backward pass) and no grad_clip (it bounds a
    # cotangent); it pays where the tuned numbers are few (docs/tuning.md, "How the gradient goes through a walk").
    grad_mode: str = "reverse"
    # Every this many control steps the compiled rollout reports its step index to the host (see
    # `progress_to`); 0: never. A host callback costs ~0.1 ms, so a few hundred calls are free.
    progress_every: int = 0

    def validate(self) -> None:
        if self.solver_grad not in SOLVER_GRADS:
            raise ValueError(f"rollout.solver_grad={self.solver_grad!r}: use one of {SOLVER_GRADS}")
        if self.grad_mode not in GRAD_MODES:
            raise ValueError(f"rollout.grad_mode={self.grad_mode!r}: use one of {GRAD_MODES}")
        if self.grad_mode == "forward":
            if self.solver_grad != "implicit":
                raise ValueError(f"rollout.grad_mode='forward' with rollout.solver_grad={self.solver_grad!r}: "
                                 "forward mode goes through the solve by implicit differentiation; use 'implicit'")
            if self.remat:
                raise ValueError("rollout.grad_mode='forward' with rollout.remat=True: remat serves reverse mode's "
                                 "backward pass, which forward mode does not have; set remat=False")
            if self.grad_clip is not None:
                raise ValueError(f"rollout.grad_mode='forward' with rollout.grad_clip={self.grad_clip!r}: the bound "
                                 "acts on reverse mode's cotangents and has no forward-mode counterpart; set None")
        if not (isinstance(self.grad_window, int) and self.grad_window >= 0):
            raise ValueError(f"rollout.grad_window={self.grad_window!r}: must be an integer >= 0")
        if not isinstance(self.unroll_substeps, bool):
            raise ValueError(f"rollout.unroll_substeps={self.unroll_substeps!r}: must be True or False")
        if not (isinstance(self.progress_every, int) and self.progress_every >= 0):
            raise ValueError(f"rollout.progress_every={self.progress_every!r}: must be an integer >= 0")
        if self.settle_time < 0:
            raise ValueError(f"rollout.settle_time={self.settle_time!r}: must be >= 0")
        if not 0 <= self.yaw_noise < math.pi:
            raise ValueError(f"rollout.yaw_noise={self.yaw_noise!r}: must be in [0, pi)")
        if not 0 < self.fall_tilt <= math.pi:
            raise ValueError(f"rollout.fall_tilt={self.fall_tilt!r}: must be in (0, pi]")
        if self.grad_clip is not None and not (math.isfinite(self.grad_clip) and self.grad_clip > 0):
            raise ValueError(f"rollout.grad_clip={self.grad_clip!r}: must be None or a finite number > 0")


# Step counts of a rollout -------------------------------------------------------------------------------------
def substeps(physics: PhysicsConfig, ctrl_dt: float) -> int:
    """Physics steps per control step; the control period must be a whole multiple of the timestep."""
    n = ctrl_dt / physics.timestep
    if abs(n - round(n)) > 1e-6 or round(n) < 1:
        raise ValueError(f"controller.dt={ctrl_dt!r} must be a whole multiple of physics.timestep={physics.timestep!r}")
    return int(round(n))


def settle_steps(cfg: RolloutConfig, ctrl_dt: float) -> int:
    """Control steps of standing still before the controller starts."""
    return int(round(cfg.settle_time / ctrl_dt))


def control_steps(duration: float, ctrl_dt: float) -> int:
    """Control steps after settling for a rollout of `duration` s."""
    return int(math.ceil(duration / ctrl_dt - 1e-9))


def total_physics_steps(cfg: RolloutConfig, physics: PhysicsConfig, ctrl_dt: float, n_ctrl: int) -> int:
    """Physics steps one env takes in a rollout of `n_ctrl` control steps, its settling included."""
    return (settle_steps(cfg, ctrl_dt) + n_ctrl) * substeps(physics, ctrl_dt)
