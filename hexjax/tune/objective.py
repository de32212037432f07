"""The tuning objective and the problem both tuners share: controllers, terrains, the smooth training and the
hard held-out rollouts (docs/tuning.md).

Objective (per env, in metres; `configs/tune/*.yaml` sets the weights w):

    J = sqrt(w_dx dx^2 + w_dy dy^2) + w_dalpha |dalpha| + w_fall fell + w_energy E

with dx, dy, dalpha the positional errors at the goal of Luneckas 2020 Sect. 2.5 (a straight walk of
`distance` m along the start heading, errors in the start frame), `fell` 1 for a fall or a non-finite
state, E the joint energy (J). The batch objective is the mean over envs. With w_dx = w_dy = 1 the first
term is the paper's goal error (its "relative error" times the distance).

Two forms of the same rollout:
- training ("smooth"): sigmoid gates (the tactile switch, the CPG's FSM), or with `gates: straight_through`
  the hard gates in value and the sigmoids' derivatives in reverse mode (`hexjax.control.gates`: the training
  rollout is then the held-out kind of rollout on the training terrains), the same physics as evaluation
  with a reverse-mode path through MJX's constraint solve (`RolloutConfig.solver_grad`: its Newton iterations
  traced as a scan, or implicit differentiation at the solution), a per-step bound on
  the backward flow through the physics (`RolloutConfig.grad_clip`), and truncated windows
  (`RolloutConfig.grad_window`): the gradient of the travel is the sum over windows of its gradient with
  the window's start state held fixed. The fall indicator has no pathwise gradient; it counts in the
  value only.
- held-out evaluation ("hard"): the controller's step-function gates, unseen terrain seeds. This is the
  number the tuning is judged by.

Why truncated windows: over a whole walk the rollout is chaotic in its parameters. Over 1 m the exact
gradient of the advance reaches 1e13-1e14 (docs/tuning.md); over windows of a fraction of a
second it matches central differences (tests/test_tune.py). The windowed gradient is biased (it ignores
how a change in one window moves the next window's start), in exchange for a variance that does not
explode with the horizon.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Dict, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from hexjax.control.reflex import ReflexController, ReflexParams
from hexjax.control.registry import CONTROLLERS, make_controller
from hexjax.sim.compiled import arrays_digest
from hexjax.sim.config import PhysicsConfig, RolloutConfig, physics_for
from hexjax.sim.metrics import error_stats, travel_errors
from hexjax.sim.rollout import rollout_function
from hexjax.sim.windows import windowed_value_and_grad
from hexjax.tune.config import TuneConfig
from hexjax.tune.space import SPACES, ParamSpace, load_values, with_values
from hexjax.world.presets import get_robot
from hexjax.world.terrain import pad_terrain, sample



def per_env_objective(summary, distance: float, weights: Dict[str, float]):
    """J per env (B,), see the module docstring. Envs that went non-finite count as fallen."""
    w = lambda k: float(weights.get(k, 0.0))
    dx, dy, da = travel_errors(summary, distance)
    # the 1e-8 m^2 keeps the square root's derivative finite at a perfect landing
    j = jnp.sqrt(w("dx") * dx * dx + w("dy") * dy * dy + 1e-8)
    j = j + w("dalpha") * jnp.abs(da) + w("energy") * summary.energy
    bad = (summary.fell | summary.nan).astype(j.dtype)
    return jnp.where(summary.nan, 0.0, j) + w("fall") * bad


@dataclasses.dataclass
class Problem:
    """Everything a tuning run evaluates, built once from a validated `TuneConfig`."""

    cfg: TuneConfig
    space: ParamSpace
    robot: Any
    train_ctrl: Any
    eval_ctrl: Any
    params0: Any
    eval_params0: Any  # the same numbers for the hard form (the CPG's `smooth` param is 0 there)
    duration: float
    specs: Tuple[Any, ...]  # the terrain families (`TuneConfig.terrain`), each batch split evenly among them

    @classmethod
    def build(cls, cfg: TuneConfig) -> "Problem":
        cfg.validate()
        robot = get_robot(CONTROLLERS[cfg.controller].robot)
        train_ctrl, params0, duration = _controller(cfg, robot, smooth=True)
        eval_ctrl, eval_params0, _ = _controller(cfg, robot, smooth=False)
        space = cfg.space()
        space.validate(params0)
        specs = tuple(cfg.terrain_spec(t) for t in cfg.terrains)
        return cls(cfg, space, robot, train_ctrl, eval_ctrl, params0, eval_params0, duration, specs)

    # terrains: training batches are drawn fresh every step; held-out terrains come from another key
    def _keys(self):
        root = jax.random.PRNGKey(self.cfg.seed)
        return jax.random.split(root, 4)  # train terrains, train headings, held-out, validation

    def terrain_batch(self, key, n: int):
        """n terrains from `key`, split evenly among the config's families (the first ones get the remainder)
        and padded to one box count; one family draws all n from `key` itself."""
        m = max(s.max_boxes for s in self.specs)
        if len(self.specs) == 1:
            return pad_terrain(sample(self.specs[0], key, n), m)
        parts = [pad_terrain(sample(s, jax.random.fold_in(key, i), sl.stop - sl.start), m)
                 for i, (s, sl) in enumerate(zip(self.specs, family_slices(n, len(self.specs))))]
        return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), *parts)

    def train_batch(self, step: int, n: Optional[int] = None):
        k_t, k_h = self._keys()[:2]
        n = n or self.cfg.train_batch
        keys = jax.random.split(jax.random.fold_in(k_h, step), n)
        return self.terrain_batch(jax.random.fold_in(k_t, step), n), keys

    def eval_batch(self, which: str = "held_out"):
        """The fixed terrains of the held-out test set (judges the tuning) or of the validation set (picks
        which iterate a run returns); neither is ever trained on."""
        k_e = self._keys()[2 if which == "held_out" else 3]
        n = self.cfg.held_out_batch if which == "held_out" else self.cfg.validation_batch
        return self.terrain_batch(k_e, n), jax.random.split(jax.random.fold_in(k_e, 1), n)

    def train_rollout(self, grad: bool, params_batched: bool = False, duration: Optional[float] = None,
                      settle_time: Optional[float] = None):
        """(model, fn) of the smooth rollout; `grad` adds the truncation, bound and remat. `duration`,
        `settle_time` (s): instead of the config's walk and RolloutConfig's settling (scripts/profile_grad.py)."""
        rc = self._rollout_config(grad, settle_time)
        return rollout_function(self.robot, self.train_ctrl, self.duration if duration is None else duration,
                                physics=self.physics(), config=rc, params_batched=params_batched)

    def _rollout_config(self, grad: bool, settle_time: Optional[float] = None) -> RolloutConfig:
        """The training rollout's config; `grad` adds the truncation, bound and remat (no remat with `backward:
        forward`, whose rollout carries its tangents forward: `RolloutConfig.grad_mode`)."""
        rc = RolloutConfig()
        if grad:
            window = max(1, int(round(self.cfg.window / self.train_ctrl.dt)))
            forward = self.cfg.backward == "forward"
            rc = RolloutConfig(grad_clip=self.cfg.grad_clip, grad_window=window, remat=not forward,
                               solver_grad=self.cfg.solver_grad, unroll_substeps=self.cfg.unroll_substeps,
                               grad_mode="forward" if forward else "reverse")
        return rc if settle_time is None else dataclasses.replace(rc, settle_time=settle_time)

    def hard_rollout(self, params_batched: bool = False):
        """(model, fn) of the hard form as a pure jitted function (for CMA-ES on the evaluated objective,
        `TuneConfig.es_objective: hard`); use with `eval_params0`."""
        return rollout_function(self.robot, self.eval_ctrl, self.duration, physics=self.physics(),
                                params_batched=params_batched)

    def eval_rollout(self):
        """(model, fn) of the hard evaluation rollout on `eval_physics()` on the judge's engine (`TuneConfig.judge`):
        MJX's, compiled once per machine (a kept program); an engine whose programs are not kept (the certified
        ones, `eval_engine: certified`) through `certified_rollout` (model None)."""
        if not self.cfg.judge().engine.keeps_programs:
            return None, lambda model, params, terr, keys: self.certified_rollout(params, terr, keys)
        return rollout_function(self.robot, self.eval_ctrl, self.duration, physics=self.eval_physics(), kept=True)

    def certified_rollout(self, params, terr, keys, params_batched: bool = False, limits: Optional[list] = None):
        """The hard rollout of `params` (the eval form's, shared or batched over the envs) on `eval_physics`, on the
        fastest engine certified for it on this host (`hexjax.sim.physics.pick`: MuJoCo Warp on a GPU, MuJoCo C
        on a CPU): the evaluation every command judges by. Returns the `Summary`. With `limits` (a list) MuJoCo
        Warp's limit counts are appended to it instead of printed."""
        from hexjax.sim.physics import pick, shared_config
        from hexjax.sim.rollout import rollout
        phys = pick(self.cfg.eval_physics)  # the engine and the settings certified on it
        out = rollout(self.robot, terr, self.eval_ctrl, params, self.duration, keys,
                      physics=shared_config(phys, self.specs), engine=phys.engine.name, params_batched=params_batched,
                      stats=limits is not None, say_limits=limits is None)
        if limits is None:
            return out
        limits.append(out[1].overflow)
        return out[0]

    def static(self, role: str, digest: str) -> tuple:
        """What a tuner's compiled function is made from, to key its kept program (`hexjax.sim.compiled`): the
        config's digest, and the robot, controllers, physics and start params resolved from its preset names
        (a preset file edited since changes the key)."""
        return (role, digest, self.robot, self.train_ctrl, self.eval_ctrl, self.physics(), self.eval_physics(),
                arrays_digest(self.params0, self.eval_params0), self.duration)

    def eval_physics(self) -> PhysicsConfig:
        """The held-out and validation evaluations' physics: the `eval_physics` preset (default `validated`) on
        the training terrains' kinds and slot counts, so what a tuning reports is converged physics."""
        return self._preset_physics(self.cfg.eval_physics)

    def _preset_physics(self, name: str) -> PhysicsConfig:
        """A physics preset's solver on the config's terrain kinds and slot counts."""
        from hexjax.sim.physics import get_physics, shared_config
        return shared_config(get_physics(name), self.specs)

    def physics(self) -> PhysicsConfig:
        """The training rollouts' physics (and CMA-ES's hard objective's): the terrain's, with `solver_iterations`
        Newton iterations where the config sets them (MJX's pyramidal cone).
        The reported figures are judged on `eval_physics()`. With `train_physics` set: that preset's solver."""
        if self.cfg.train_physics is not None:
            return self._preset_physics(self.cfg.train_physics)
        base = PhysicsConfig()
        if self.cfg.solver_iterations is not None:
            base = dataclasses.replace(base, iterations=self.cfg.solver_iterations)
        kinds = {s.kind for s in self.specs}
        return physics_for(kinds.pop() if len(kinds) == 1 else "mixed", base)

    def loss_fn(self, fn, model):
        """loss(u, terrain, keys) -> (mean J, per-env J) for unconstrained params u."""
        def loss(u, terrain, keys):
            s = fn(model, self.space.apply(u, self.params0), terrain, keys)
            j = per_env_objective(s, self.cfg.distance, self.cfg.objective)
            return jnp.mean(j), j
        return loss

    def value_and_grad(self, fn, model):
        """f(u, terrain, keys) -> ((mean J, per-env J), d mean J / du) through the gradient rollout (fn, model) of
        `train_rollout(grad=True)`, with `grad_clip` bounding each env's own cotangent (`mean_value_and_grad`)."""
        return mean_value_and_grad(self.loss_fn(fn, model))

    def check_gradient_fits(self, batch: int, flag: str = "train_batch", duration: Optional[float] = None) -> None:
        """One ValueError line naming the largest batch that fits, when `batch` envs of the gradient program
        cannot fit on this host's accelerators (the walk's control steps at the gradient engine's measured bytes
        an env and control step, `hexjax.sim.memory`), before anything is traced. `flag`: the setting named."""
        from hexjax.sim.engines import get_engine
        from hexjax.sim.memory import HEADROOM, check_fits
        from hexjax.sim.config import control_steps
        engine = get_engine("mjx")  # the one engine the rollout's gradient runs (`rollout_function`)
        n_ctrl = control_steps(self.duration if duration is None else duration, self.train_ctrl.dt)
        per_env = int(HEADROOM * engine.grad_bytes_per_env_step * n_ctrl)
        check_fits(flag, batch, per_env, f"the value and gradient of a {n_ctrl}-control-step walk on {engine.title}")

    def gradient_program(self, duration: Optional[float] = None, settle_time: Optional[float] = None):
        """The function a first-order tuning step jits, f(u, terrain, keys) -> ((mean J, per-env J), d mean J / du),
        with its backward pass as `backward` says: reverse mode through the rollout's scan (`value_and_grad`),
        the windows side by side (`parallel_value_and_grad`), or no backward pass: forward mode
        (`forward_value_and_grad`). `duration`, `settle_time` as `train_rollout`'s."""
        if self.cfg.backward == "parallel":
            return self.parallel_value_and_grad(duration, settle_time)
        if self.cfg.backward == "forward":
            return self.forward_value_and_grad(duration, settle_time)
        model, fn = self.train_rollout(grad=True, duration=duration, settle_time=settle_time)
        return self.value_and_grad(fn, model)

    def parallel_value_and_grad(self, duration: Optional[float] = None, settle_time: Optional[float] = None):
        """The same f(u, terrain, keys) as `value_and_grad`, its gradient taken with the windows' backward passes
        side by side (`hexjax.sim.windows`): the gradient of sum J over the batch, divided by its size."""
        rc = self._rollout_config(True, settle_time)
        loss = lambda s: per_env_objective(s, self.cfg.distance, self.cfg.objective)
        walk = self.duration if duration is None else duration
        model, vg = windowed_value_and_grad(self.robot, self.train_ctrl, walk, loss, physics=self.physics(), config=rc)

        def f(u, terrain, keys):
            p, back = jax.vjp(lambda x: self.space.apply(x, self.params0), u)
            (_, j), gp = vg(model, p, terrain, keys)
            n = j.shape[0]
            return (jnp.mean(j), j), jax.tree_util.tree_map(lambda x: x / n, back(gp)[0])

        return f

    def forward_value_and_grad(self, duration: Optional[float] = None, settle_time: Optional[float] = None):
        """The same f(u, terrain, keys) as `value_and_grad`, its gradient taken in forward mode: `jax.jacfwd` of
        sum J over the batch, one tangent per unconstrained number side by side, through the gradient rollout
        without remat and with forward mode's rule for MJX's solve (`RolloutConfig.grad_mode='forward'`,
        `hexjax.sim.internals.forward_mode`). The windows cut the tangents at their starts, so it is the windowed
        gradient of reverse mode without a bound (the config's grad_clip must be null)."""
        model, fn = self.train_rollout(grad=True, duration=duration, settle_time=settle_time)
        loss = self.loss_fn(fn, model)

        def f(u, terrain, keys):
            x, unravel = ravel_pytree(u)

            def total(y):
                _, j = loss(unravel(y), terrain, keys)
                return jnp.sum(j), j

            g, j = jax.jacfwd(total, has_aux=True)(x)
            return (jnp.mean(j), j), unravel(g / j.shape[0])

        return f


def mean_value_and_grad(loss):
    """value_and_grad of the batch mean of `loss(u, ...) -> (mean J, J per env)`, taken as the gradient of the sum
    of J divided by the batch size. Differentiating the mean itself would hand each env the cotangent 1/B, so a
    bound on the backward flow per control step (`RolloutConfig.grad_clip`, applied per env under vmap) would
    act on J_e / B: a bound of grad_clip x B in units of one env's objective, looser with every larger batch.
    Through the sum every env starts from cotangent 1 and is bounded at grad_clip whatever the batch, as the
    hybrid estimator's per-env gradients are (`hexjax.tune.hybrid.per_env_gradients`). Where no bound binds
    the two are the same gradient, to float32 rounding."""
    def total(u, *args):
        _, j = loss(u, *args)
        return jnp.sum(j), j

    vg = jax.value_and_grad(total, has_aux=True)

    def f(u, *args):
        (_, j), g = vg(u, *args)
        n = j.shape[0]
        return (jnp.mean(j), j), jax.tree_util.tree_map(lambda x: x / n, g)

    return f


def _controller(cfg: TuneConfig, robot, smooth: bool):
    """(controller, starting params = the papers' hand rules or `cfg.start`'s values, rollout seconds)."""
    c, p0, dur = _hand_rules(cfg, robot, smooth)
    if cfg.start is None:
        return c, p0, dur
    p = with_values(p0, load_values(cfg.start), source=f"tune.start={cfg.start}")
    c.validate_params(p)
    period = CONTROLLERS[cfg.controller].period
    if period is not None and period not in cfg.space().names:  # a slower started gait needs the longer walk
        dur = dur * float(getattr(p, period)) / float(getattr(p0, period))
    return c, p, dur


def _hand_rules(cfg: TuneConfig, robot, smooth: bool):
    entry = CONTROLLERS[cfg.controller]
    base = entry.base
    if base is not None:  # a learned reflex layer over the base's hand-ruled controller, untrained
        c, p, dur = _hand_rules(dataclasses.replace(cfg, controller=base, params={}), robot, smooth)
        layer = ReflexController(c)
        return layer, ReflexParams(base=p, net=layer.init_net()), dur
    # a controller with gates (its entry names their temperature) has a smooth form; an open-loop gait has none
    gates = {} if entry.temperature is None else dict(smooth=smooth, straight_through=smooth and
                                                      cfg.gates == "straight_through")
    c = make_controller(cfg.controller, robot, gait=cfg.gait, **gates,
                        **{f: getattr(cfg, f) for f in entry.tune_fields})
    dur = cfg.horizon
    if entry.stops:  # a walk with a planned stop walks `distance`
        c, dur = c.for_distance(cfg.distance)
    p = c.default_params()
    if cfg.temperature is not None:
        p = p.replace(**{entry.temperature: jnp.float32(cfg.temperature)})
    tuned = cfg.space().names if cfg.controller in SPACES else ()  # a reflex layer's base may have no space
    if entry.period is not None and entry.period in tuned:
        hi = dict(cfg.space().bounds)[entry.period].hi  # the rollout must cover the slowest walk the bounds allow
        dur = dur * hi / float(getattr(p, entry.period))
    return c, p, dur


def evaluate_held_out(problem: Problem, u, fn=None, model=None, which: str = "held_out",
                      per_env: bool = False) -> Dict[str, Any]:
    """Hard-mode objective and goal errors of params u on the held-out (or validation) terrains; with
    `per_env`, each terrain's objective too (an array, for paired comparisons on the same terrains)."""
    if fn is None:
        model, fn = problem.eval_rollout()
    terr, keys = problem.eval_batch(which)
    params = problem.space.apply(u, problem.eval_params0)
    if not problem.cfg.judge().engine.keeps_programs:  # `rollout` checks the params as a user's: an iterate out of the
        try:  # controller's domain (one the space's per-field bounds allow) is judged the worst, and says why
            problem.eval_ctrl.validate_params(params)
        except ValueError as err:
            return {"objective": float("inf"), "objective_se": float("nan"), "goal_error_cm": float("nan"),
                    "fall_pct": float("nan"), "infeasible": str(err).split(":")[0]}
    s = fn(model, params, terr, keys)
    j = np.asarray(per_env_objective(s, problem.cfg.distance, problem.cfg.objective))
    dx, dy, da = (np.asarray(x) for x in travel_errors(s, problem.cfg.distance))
    fell = np.asarray(s.fell)
    d = problem.cfg.distance
    out = {"objective": float(j.mean()), **error_stats(dx, dy, da, d), "fall_pct": 100 * float(fell.mean()),
           "nan_envs": int(np.asarray(s.nan).sum()),
           # its standard error, and each terrain's J: iterates of two runs of one config walk the same terrains,
           # so their difference has a paired standard error (`hexjax.experiments.commands.tuning`)
           "objective_se": float(j.std(ddof=1) / np.sqrt(j.size)) if j.size > 1 else float("nan"),
           "per_env_objective": [round(float(x), 6) for x in j]}
    if len(problem.specs) > 1:  # the batch is split among the terrain families in blocks (`terrain_batch`)
        out["by_terrain"] = {name: {"n": int(sl.stop - sl.start), "objective": float(j[sl].mean()),
                                    "goal_error_cm": error_stats(dx[sl], dy[sl], da[sl], d)["goal_error_cm"],
                                    "fall_pct": 100 * float(fell[sl].mean())}
                             for name, sl in zip(problem.cfg.terrains, family_slices(len(j), len(problem.specs)))}
    if per_env:
        out["per_env"] = j
    return out


def family_slices(n: int, k: int):
    """The env slices of k terrain families in a batch of n, as `Problem.terrain_batch` lays them out (the
    first n % k families one env more)."""
    sizes = [n // k + (i < n % k) for i in range(k)]
    ends = np.cumsum(sizes)
    return [slice(int(e - z), int(e)) for e, z in zip(ends, sizes)]
