"""Tuning configs (configs/tune/*.yaml): every key, its default and its check, raised before anything is
traced. The optimiser loop itself reads a validated `TuneConfig`."""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any, Dict, Optional, Tuple

from hexjax.sim.config import GRAD_SOLVERS
from hexjax.world.files import build, read_yaml, resolve

if TYPE_CHECKING:
    from hexjax.tune.space import ParamSpace

OBJECTIVE_TERMS = ("dx", "dy", "dalpha", "fall", "energy")
OPTIMIZERS = ("adam", "sgd")
ESTIMATORS = ("first_order", "hybrid")
GATES = ("smooth", "straight_through")
BACKWARDS = ("sequential", "parallel", "forward")
ES_STRATEGIES = ("auto", "cma_es", "sep_cma_es", "snes")
ES_FULL_MAX = 100  # tuned numbers up to which `es_strategy: auto` keeps CMA-ES's full covariance


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    controller: str = "tactile"
    gait: str = "tripod"
    # a terrain preset, or a list of them trained and judged together (each batch split evenly among them)
    terrain: Any = "high-small"
    # TerrainSpec keys set on every one of them (e.g. start_x: put the obstacles nearer for a short horizon)
    terrain_overrides: Dict[str, Any] = dataclasses.field(default_factory=dict)
    max_obstacle_height: float = 0.05
    train_batch: int = 8
    held_out_batch: int = 16
    validation_batch: int = 16  # terrains that pick the returned iterate (0: return the last one)
    distance: float = 1.0
    horizon: float = 10.0  # s walked by controllers without a planned stop (cpg); the tactile gait walks `distance`
    window: float = 0.2  # s: truncated-gradient window (`RolloutConfig.grad_window`)
    # bound on each env's backward flow through each control step (`RolloutConfig.grad_clip`), in units of
    # that env's own objective, whatever train_batch (`objective.mean_value_and_grad`); null: no bound (exact
    # windowed gradients; what `backward: forward` takes)
    grad_clip: Optional[float] = 1.0
    # smooth-gate temperature: the tactile pad gate (N), or the CPG's force gate temp_force (N); None keeps
    # the controller's own default (tactile 0.05, CPG 1 N with temp_phase 0.05 and temp_height 2 mm)
    temperature: Optional[float] = None
    # the training rollout's gates (`hexjax.control.gates`): 'smooth' sigmoids, or 'straight_through': the hard
    # controller that evaluation runs, with the sigmoids' derivatives in reverse mode
    gates: str = "smooth"
    # MJX Newton iterations of both the training and the evaluation physics (None: PhysicsConfig's 2). The
    # CPG on `yu2019` needs 4 for gradients that agree with finite differences (docs/tuning.md)
    solver_iterations: Optional[int] = None
    # a physics preset (name or .yaml, on MJX) for the training rollouts instead of the terrain's default physics
    # with `solver_iterations`: `validated` tunes on the physics the results are reported on (CMA-ES's hard
    # objective; the implicit gradient takes either cone, forward mode the pyramidal one)
    train_physics: Optional[str] = None
    # the physics preset the held-out and validation evaluations run (docs/physics.md): the figures a tuning
    # reports are judged on it, whatever physics the training rollouts take (an MJX preset: mjx or warp)
    eval_physics: str = "validated"
    # how the gradient goes through MJX's constraint solve (`RolloutConfig.solver_grad`): 'unrolled'
    # differentiates every Newton iteration, 'implicit' one linear solve at the solution (docs/tuning.md)
    solver_grad: str = "unrolled"
    # the training rollout's `RolloutConfig.unroll_substeps`: each control step's physics steps traced one after
    # another; the gradient runs faster on a GPU (+28 % on an H100) and compiles about twice as long
    unroll_substeps: bool = False
    # how the windowed gradient's backward pass runs: 'sequential' is reverse mode through the rollout's scan,
    # every control step after the other; 'parallel' runs the windows' backward passes side by side,
    # train_batch x windows of them (`hexjax.sim.windows`): the same gradient, 2.7x faster on an H100 at 256
    # terrains, 5.5 % faster on 2 CPU cores at 64 but holding every step's state in memory (docs/tuning.md).
    # 'forward' takes the same windowed gradient in forward mode, one tangent per tuned number beside the
    # primal (`RolloutConfig.grad_mode`): one loop and no backward pass, the fastest where the tuned numbers are
    # few (5 for the tactile preset: 38 % of the forward's rate on an H100); needs solver_grad: implicit and
    # grad_clip: null (docs/tuning.md, "How the gradient goes through a walk"). First-order estimator only.
    backward: str = "sequential"
    # the gradient estimator of `hexjax.tune.grad` (docs/tuning.md, "Bias and variance of the windowed gradient"): 'first_order'
    # is the windowed pathwise gradient; 'hybrid' fits the whole walk's directional derivatives along
    # `zo_pairs` antithetic perturbations per training terrain (N(0, zo_sigma^2) on the unconstrained scale),
    # with the windowed gradient as a prior worth `zo_prior` pairs
    estimator: str = "first_order"
    zo_pairs: int = 8
    zo_sigma: float = 0.5
    zo_prior: float = 1.0
    params: Dict[str, Dict[str, float]] = dataclasses.field(default_factory=dict)
    # the starting numbers: a params preset (configs/params/<name>.yaml) or a tuning log.json whose values replace
    # the papers' hand rules before tuning (None: the hand rules); its fields need not be among `params`
    start: Optional[str] = None
    optimizer: Dict[str, object] = dataclasses.field(default_factory=lambda: {"name": "adam", "learning_rate": 0.05})
    objective: Dict[str, float] = dataclasses.field(default_factory=lambda: {"dx": 1.0, "dy": 1.0})
    steps: int = 30
    eval_every: int = 10
    seed: int = 0
    es_population: int = 8  # CMA-ES baseline: population size
    es_sigma: float = 0.5  # CMA-ES baseline: initial step size on the unconstrained scale
    # the rollout CMA-ES scores: 'smooth' (the gradient's training objective) or 'hard' (the evaluated one; for
    # a controller whose smooth form walks unlike its hard form, e.g. the CPG at Table 1's rate, docs/tuning.md)
    es_objective: str = "smooth"
    # the evolution strategy (evosax): 'cma_es' (full covariance), 'sep_cma_es' (diagonal), 'snes' (separable
    # natural ES), or 'auto': CMA-ES up to `ES_FULL_MAX` tuned numbers, sep-CMA-ES above
    es_strategy: str = "auto"
    # where the evolution strategy's rollouts run: 'training' (MJX on the training physics, jitted with the
    # population) or 'certified' (the hard form on `eval_physics` on the fastest engine certified for it on this
    # host: MuJoCo Warp on a GPU, MuJoCo C on a CPU; needs es_objective: hard)
    es_rollouts: str = "training"
    # where the held-out and validation evaluations run: 'mjx' (a kept MJX program on `eval_physics`) or
    # 'certified' (the fastest engine certified for `eval_physics` on this host: MuJoCo Warp on a GPU, MuJoCo C
    # on a CPU; what every other command judges on)
    eval_engine: str = "mjx"

    @property
    def terrains(self) -> Tuple[str, ...]:
        """The terrain presets trained and judged on (one or several)."""
        return (self.terrain,) if isinstance(self.terrain, str) else tuple(self.terrain)

    def validate(self) -> None:
        """Every key checked, one concern after another; each error is one line naming `tune.<key>` and its value."""
        self._check_data()
        self._check_physics()
        self._check_estimator()
        self._check_es()
        self._check_optimizer()
        self._check_objective()
        self.space()  # unknown controller, unknown parameter, min > max
        for name in self.terrains:  # a wrong override (checked like the preset file's own keys)
            try:
                self.terrain_spec(name)
            except ValueError as err:
                raise ValueError(f"tune.terrain_overrides: {err}") from None

    def _positive(self, *fields: str, optional: Tuple[str, ...] = ()) -> None:
        """Each of `fields` a finite number > 0 (those in `optional` may be None)."""
        for f in fields:
            v = getattr(self, f)
            if f in optional and v is None:
                continue
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"tune.{f}={v!r}: must be a finite number > 0")

    def _whole(self, *fields: str, least: int = 1) -> None:
        for f in fields:
            v = getattr(self, f)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= least):
                raise ValueError(f"tune.{f}={v!r}: must be an integer >= {least}")

    def _check_data(self) -> None:
        """The walks: controller and gait, terrains, batches, steps, the start, distance and horizon."""
        from hexjax.control.registry import CONTROLLERS, paper_controller
        if self.controller not in CONTROLLERS:
            raise ValueError(f"controller={self.controller!r}: use one of {', '.join(CONTROLLERS)}")
        t = self.terrain
        if not (isinstance(t, str) or (isinstance(t, (list, tuple)) and t and all(isinstance(x, str) for x in t))):
            raise ValueError(f"tune.terrain={t!r}: must be a terrain preset name or a non-empty list of them")
        if len(set(self.terrains)) != len(self.terrains):
            raise ValueError(f"tune.terrain={t!r}: a preset is listed twice")
        for name in self.terrains:
            try:
                resolve("terrains", name)
            except ValueError as err:
                raise ValueError(f"tune.terrain={name!r}: {err}") from None
        for f in ("train_batch", "held_out_batch", "validation_batch"):
            if isinstance(getattr(self, f), int) and 0 < getattr(self, f) < len(self.terrains):
                raise ValueError(f"tune.{f}={getattr(self, f)!r}: needs at least one env per terrain "
                                 f"({len(self.terrains)} terrains)")
        if self.start is not None:
            if not isinstance(self.start, str):
                raise ValueError(f"tune.start={self.start!r}: must be a params preset name or a log.json path")
            try:
                from hexjax.tune.space import load_values
                load_values(self.start)
            except ValueError as err:
                raise ValueError(f"tune.start={self.start!r}: {err}") from None
        if self.temperature is not None and CONTROLLERS[paper_controller(self.controller)].temperature is None:
            raise ValueError(f"tune.temperature={self.temperature!r}: the {self.controller} controller has no smooth "
                             "gate to set it on; leave it out")
        gaits = CONTROLLERS[self.controller].gaits
        if self.gait not in gaits:
            raise ValueError(f"tune.gait={self.gait!r}: the {self.controller} controller walks "
                             + " or ".join(map(repr, gaits)))
        self._whole("validation_batch", least=0)
        self._whole("train_batch", "held_out_batch", "steps", "eval_every")
        self._positive("distance", "horizon")
        if not (0 <= self.max_obstacle_height <= 0.2):
            raise ValueError(f"tune.max_obstacle_height={self.max_obstacle_height!r}: must be in [0, 0.2] m")

    def _check_physics(self) -> None:
        """The training and the evaluation physics, and how the gradient goes through the solve."""
        it = self.solver_iterations
        if it is not None and not (isinstance(it, int) and not isinstance(it, bool) and 1 <= it <= 32):
            raise ValueError(f"tune.solver_iterations={it!r}: must be None or an integer in [1, 32]")
        from hexjax.sim.engines import GRADIENTS, get_engine
        from hexjax.sim.physics import get_physics
        if self.train_physics is not None:
            if it is not None:
                raise ValueError(f"tune.train_physics={self.train_physics!r} with tune.solver_iterations={it!r}: "
                                 "the preset sets the solver; give one or the other")
            if get_engine(get_physics(self.train_physics).engine).lacks({GRADIENTS}):
                raise ValueError(f"tune.train_physics={self.train_physics!r}: training rollouts take gradients; give "
                                 "a preset written for an engine that gives them (validated, fast or a .yaml on mjx)")
        if get_engine(get_physics(self.eval_physics).engine).lacks({GRADIENTS}):
            raise ValueError(f"tune.eval_physics={self.eval_physics!r}: the evaluation is a kept program of the "
                             "gradient's engine; give a preset on mjx (validated, fast or a .yaml of one's own)")
        if self.eval_engine not in ("mjx", "certified"):
            raise ValueError(f"tune.eval_engine={self.eval_engine!r}: use 'mjx' or 'certified'")
        if self.solver_grad not in GRAD_SOLVERS:
            raise ValueError(f"tune.solver_grad={self.solver_grad!r}: use one of {GRAD_SOLVERS}")
        if not isinstance(self.unroll_substeps, bool):
            raise ValueError(f"tune.unroll_substeps={self.unroll_substeps!r}: must be true or false")

    def _check_estimator(self) -> None:
        """The gradient estimator: gates, windows, the bound, the backward pass, the hybrid's pairs."""
        if self.gates not in GATES:
            raise ValueError(f"tune.gates={self.gates!r}: use one of {GATES}")
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"tune.estimator={self.estimator!r}: use one of {ESTIMATORS}")
        self._whole("zo_pairs")
        if self.backward not in BACKWARDS:
            raise ValueError(f"tune.backward={self.backward!r}: use one of {BACKWARDS}")
        if self.backward != "sequential" and self.estimator != "first_order":
            raise ValueError(f"tune.backward={self.backward!r} with tune.estimator={self.estimator!r}: it serves "
                             "the first-order estimator only; use backward: sequential")
        if self.backward == "forward" and self.solver_grad != "implicit":
            raise ValueError(f"tune.backward='forward' with tune.solver_grad={self.solver_grad!r}: forward mode "
                             "goes through the solve by implicit differentiation; set solver_grad: implicit")
        if self.backward == "forward" and self.grad_clip is not None:
            raise ValueError(f"tune.backward='forward' with tune.grad_clip={self.grad_clip!r}: the bound acts on "
                             "reverse mode's cotangents and has no forward-mode counterpart; set grad_clip: null")
        self._positive("window", "grad_clip", "temperature", "zo_sigma", "zo_prior",
                       optional=("grad_clip", "temperature"))

    def _check_es(self) -> None:
        """The evolution strategy: which one, where its rollouts run, its population and step size."""
        if self.es_strategy not in ES_STRATEGIES:
            raise ValueError(f"tune.es_strategy={self.es_strategy!r}: use one of {ES_STRATEGIES}")
        if self.es_objective not in ("smooth", "hard"):
            raise ValueError(f"tune.es_objective={self.es_objective!r}: use 'smooth' or 'hard'")
        if self.es_rollouts not in ("training", "certified"):
            raise ValueError(f"tune.es_rollouts={self.es_rollouts!r}: use 'training' or 'certified'")
        if self.es_rollouts == "certified" and self.es_objective != "hard":
            raise ValueError("tune.es_rollouts='certified' runs the evaluated (hard) rollout: set es_objective: hard")
        self._whole("es_population", least=2)
        self._positive("es_sigma")

    def _check_optimizer(self) -> None:
        opt = dict(self.optimizer)
        unknown = set(opt) - {"name", "learning_rate", "clip_norm", "decay_to", "average"}
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
        avg = opt.get("average")
        if avg is not None and not (isinstance(avg, (int, float)) and 0 <= avg < 1):
            raise ValueError(f"tune.optimizer.average={avg!r}: must be None or a fraction in [0, 1)")
        clip = opt.get("clip_norm")
        if clip is not None and not (isinstance(clip, (int, float)) and math.isfinite(clip) and clip > 0):
            raise ValueError(f"tune.optimizer.clip_norm={clip!r}: must be None or a finite number > 0")

    def _check_objective(self) -> None:
        for k, w in self.objective.items():
            if k not in OBJECTIVE_TERMS:
                raise ValueError(f"tune.objective.{k}: unknown term; use {OBJECTIVE_TERMS}")
            if not (isinstance(w, (int, float)) and math.isfinite(w) and w >= 0):
                raise ValueError(f"tune.objective.{k}={w!r}: weight must be a finite number >= 0")
        if not any(self.objective.values()):
            raise ValueError("tune.objective: every weight is 0, nothing to minimise")

    def terrain_spec(self, name: str):
        """The TerrainSpec of preset `name` as this config trains on it: the corridor covers the walk, and
        `terrain_overrides` apply."""
        from hexjax.world.presets import get_terrain  # JAX loads here: a config's first checks answer without it
        return get_terrain(name, **{"length": self.distance + 0.3, **self.terrain_overrides})

    def judge(self):
        """The `Physics` the held-out and validation terrains are judged on (`eval_engine`): `eval_physics` on MJX,
        the gradient's engine, whose program is kept, or on the fastest engine certified for it on this host."""
        from hexjax.sim.engines import GRADIENTS
        from hexjax.sim.physics import pick
        return pick(self.eval_physics, needs=() if self.eval_engine == "certified" else {GRADIENTS})

    def space(self) -> ParamSpace:
        from hexjax.tune.space import make_space
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
