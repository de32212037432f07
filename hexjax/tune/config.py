"""Tuning configs (configs/tune/*.yaml): every key, its default and its check, raised before anything is
traced. The optimiser loop itself reads a validated `TuneConfig`."""

from __future__ import annotations

import dataclasses
import math
from typing import Dict, Optional

from hexjax.sim.config import GRAD_SOLVERS
from hexjax.tune.space import ParamSpace, make_space
from hexjax.world.files import build, read_yaml, resolve

OBJECTIVE_TERMS = ("dx", "dy", "dalpha", "fall", "energy")
OPTIMIZERS = ("adam", "sgd")


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    controller: str = "tactile"
    gait: str = "tripod"
    terrain: str = "high-small"
    max_obstacle_height: float = 0.05
    train_batch: int = 8
    held_out_batch: int = 16
    validation_batch: int = 16  # terrains that pick the returned iterate (0: return the last one)
    distance: float = 1.0
    horizon: float = 10.0  # s walked by controllers without a planned stop (cpg); the tactile gait walks `distance`
    window: float = 0.2  # s: truncated-gradient window (`RolloutConfig.grad_window`)
    grad_clip: float = 1.0  # bound on the backward flow through each control step (`RolloutConfig.grad_clip`)
    # smooth-gate temperature: the tactile pad gate (N), or the CPG's force gate temp_force (N); None keeps
    # the controller's own default (tactile 0.05, CPG 1 N with temp_phase 0.05 and temp_height 2 mm)
    temperature: Optional[float] = None
    # MJX Newton iterations of both the training and the evaluation physics (None: PhysicsConfig's 2). The
    # CPG on `yu2019` needs 4 for gradients that agree with finite differences (docs/tuning.md)
    solver_iterations: Optional[int] = None
    # how the gradient goes through MJX's constraint solve (`RolloutConfig.solver_grad`): 'unrolled'
    # differentiates every Newton iteration, 'implicit' one linear solve at the solution (docs/tuning.md)
    solver_grad: str = "unrolled"
    params: Dict[str, Dict[str, float]] = dataclasses.field(default_factory=dict)
    optimizer: Dict[str, object] = dataclasses.field(default_factory=lambda: {"name": "adam", "learning_rate": 0.05})
    objective: Dict[str, float] = dataclasses.field(default_factory=lambda: {"dx": 1.0, "dy": 1.0})
    steps: int = 30
    eval_every: int = 10
    seed: int = 0
    es_population: int = 8  # CMA-ES baseline: population size
    es_sigma: float = 0.5  # CMA-ES baseline: initial step size on the unconstrained scale

    def validate(self) -> None:
        try:
            resolve("terrains", self.terrain)
        except ValueError as err:
            raise ValueError(f"tune.terrain={self.terrain!r}: {err}") from None
        if self.controller == "cpg" and self.gait not in ("tripod", "tetrapod", "wave"):
            raise ValueError(f"tune.gait={self.gait!r}: the cpg controller walks 'tripod', 'tetrapod' or 'wave'")
        if self.controller == "tactile" and self.gait not in ("tripod", "wave"):
            raise ValueError(f"tune.gait={self.gait!r}: the tactile gait walks 'tripod' or 'wave'")
        if not (isinstance(self.validation_batch, int) and self.validation_batch >= 0):
            raise ValueError(f"tune.validation_batch={self.validation_batch!r}: must be an integer >= 0")
        for f in ("train_batch", "held_out_batch", "steps", "eval_every", "es_population"):
            v = getattr(self, f)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise ValueError(f"tune.{f}={v!r}: must be an integer >= 1")
        if self.es_population < 2:
            raise ValueError(f"tune.es_population={self.es_population!r}: must be >= 2")
        it = self.solver_iterations
        if it is not None and not (isinstance(it, int) and not isinstance(it, bool) and 1 <= it <= 32):
            raise ValueError(f"tune.solver_iterations={it!r}: must be None or an integer in [1, 32]")
        if self.solver_grad not in GRAD_SOLVERS:
            raise ValueError(f"tune.solver_grad={self.solver_grad!r}: use one of {GRAD_SOLVERS}")
        for f in ("distance", "horizon", "window", "grad_clip", "temperature", "es_sigma"):
            v = getattr(self, f)
            if f == "temperature" and v is None:
                continue
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"tune.{f}={v!r}: must be a finite number > 0")
        if not (0 <= self.max_obstacle_height <= 0.2):
            raise ValueError(f"tune.max_obstacle_height={self.max_obstacle_height!r}: must be in [0, 0.2] m")
        opt = dict(self.optimizer)
        unknown = set(opt) - {"name", "learning_rate", "clip_norm", "decay_to"}
        if unknown:
            raise ValueError(f"tune.optimizer: unknown keys {sorted(unknown)}")
        if opt.get("name", "adam") not in OPTIMIZERS:
            raise ValueError(f"tune.optimizer.name={opt.get('name')!r}: choose one of {OPTIMIZERS}")
        lr = opt.get("learning_rate", 0.05)
        if not (isinstance(lr, (int, float)) and math.isfinite(lr) and lr > 0):
            raise ValueError(f"tune.optimizer.learning_rate={lr!r}: must be a finite number > 0")
        dec = opt.get("decay_to")
        if dec is not None and not (isinstance(dec, (int, float)) and 0 < dec <= 1):
            raise ValueError(f"tune.optimizer.decay_to={dec!r}: must be None or a fraction in (0, 1]")
        clip = opt.get("clip_norm")
        if clip is not None and not (isinstance(clip, (int, float)) and math.isfinite(clip) and clip > 0):
            raise ValueError(f"tune.optimizer.clip_norm={clip!r}: must be None or a finite number > 0")
        for k, w in self.objective.items():
            if k not in OBJECTIVE_TERMS:
                raise ValueError(f"tune.objective.{k}: unknown term; use {OBJECTIVE_TERMS}")
            if not (isinstance(w, (int, float)) and math.isfinite(w) and w >= 0):
                raise ValueError(f"tune.objective.{k}={w!r}: weight must be a finite number >= 0")
        if not any(self.objective.values()):
            raise ValueError("tune.objective: every weight is 0, nothing to minimise")
        self.space()  # unknown controller, unknown parameter, min > max

    def space(self) -> ParamSpace:
        return make_space(self.controller, overrides=self.params, only=list(self.params) or None)


def load_tune_config(name: str, overrides: Optional[Dict] = None, merge: bool = False) -> TuneConfig:
    """Read a tuning config (a preset name in configs/tune/ or a YAML path), apply `overrides` (top-level keys;
    with `merge`, a dict value updates a dict key such as optimizer instead of replacing it), check it, and
    return it. Every error is one line naming the file, the key and the value."""
    path = resolve("tune", name)
    raw = read_yaml(path)
    for k, v in (overrides or {}).items():
        if merge and isinstance(v, dict) and isinstance(raw.get(k), dict):
            raw[k] = {**raw[k], **v}
        else:
            raw[k] = v
    return build(TuneConfig, raw, str(path), "tune")
