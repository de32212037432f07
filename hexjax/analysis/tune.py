"""Tuning controller numbers over batches of randomised terrains: gradients through MJX with optax, and an
evolution-strategy baseline from evosax on the same objective (issue 5).

Objective (per env, in metres; `configs/tune/*.yaml` sets the weights w):

    J = sqrt(w_dx dx^2 + w_dy dy^2) + w_dalpha |dalpha| + w_fall fell + w_energy E

with dx, dy, dalpha the positional errors at the goal of Luneckas 2020 Sect. 2.5 (a straight walk of
`distance` m along the start heading, errors in the start frame), `fell` 1 for a fall or a non-finite
state, E the joint energy (J). The batch objective is the mean over envs. With w_dx = w_dy = 1 the first
term is the paper's goal error (its "relative error" times the distance).

Two forms of the same rollout:
- training ("smooth"): sigmoid gates (the tactile switch, the CPG's FSM), the same physics as evaluation
  with MJX's Newton iterations traced as a scan (`RolloutConfig.reversible_solver`), a per-step bound on
  the backward flow through the physics (`RolloutConfig.grad_clip`), and truncated windows
  (`RolloutConfig.grad_window`): the gradient of the travel is the sum over windows of its gradient with
  the window's start state held fixed. The fall indicator has no pathwise gradient; it counts in the
  value only.
- held-out evaluation ("hard"): the controller's step-function gates, unseen terrain seeds. This is the
  number the tuning is judged by.

Why truncated windows: over a whole walk the rollout is chaotic in its parameters. Over 1 m the exact
gradient of the advance reaches 1e13-1e14 (scripts/fd_noise_tactile.py); over windows of a fraction of a
second it matches central differences (tests/test_tune.py). The windowed gradient is biased (it ignores
how a change in one window moves the next window's start), in exchange for a variance that does not
explode with the horizon.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import time
from typing import Any, Dict, Optional

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from hexjax.analysis.evaluate import pad_terrain
from hexjax.analysis.space import ParamSpace
from hexjax.analysis.tune_config import TuneConfig
from hexjax.mjcf import PhysicsConfig, physics_for
from hexjax.robot import get_robot
from hexjax.sim.rollout import RolloutConfig, rollout_function
from hexjax.terrain import get_terrain, sample

ROBOTS = {"tactile": "luneckas2020", "cpg": "yu2019"}


# --------------------------------------------------------------------------------------------------
# objective

def travel_errors(summary, distance: float):
    """(dx, dy, dalpha) per env from `Summary.travel` (differentiable, truncated at window boundaries) in
    the start frame of each env: dx = distance - advance (> 0: short), dy lateral (> 0: left)."""
    yaw0 = summary.start_pose[:, 2]
    c, s = jnp.cos(yaw0), jnp.sin(yaw0)
    tx, ty, tyaw = summary.travel[:, 0], summary.travel[:, 1], summary.travel[:, 2]
    return distance - (c * tx + s * ty), -s * tx + c * ty, tyaw


def per_env_objective(summary, distance: float, weights: Dict[str, float]):
    """J per env (B,), see the module docstring. Envs that went non-finite count as fallen."""
    w = lambda k: float(weights.get(k, 0.0))
    dx, dy, da = travel_errors(summary, distance)
    # the 1e-8 m^2 keeps the square root's derivative finite at a perfect landing
    j = jnp.sqrt(w("dx") * dx * dx + w("dy") * dy * dy + 1e-8)
    j = j + w("dalpha") * jnp.abs(da) + w("energy") * summary.energy
    bad = (summary.fell | summary.nan).astype(j.dtype)
    return jnp.where(summary.nan, 0.0, j) + w("fall") * bad


# --------------------------------------------------------------------------------------------------
# problem: controllers, terrains, compiled functions

@dataclasses.dataclass
class Problem:
    """Everything a tuning run evaluates, built once from a validated `TuneConfig`."""

    cfg: TuneConfig
    space: ParamSpace
    robot: Any
    train_ctrl: Any
    eval_ctrl: Any
    params0: Any
    duration: float
    spec: Any

    @classmethod
    def build(cls, cfg: TuneConfig) -> "Problem":
        cfg.validate()
        robot = get_robot(ROBOTS[cfg.controller])
        train_ctrl, params0, duration = _controller(cfg, robot, smooth=True)
        eval_ctrl, _, _ = _controller(cfg, robot, smooth=False)
        space = cfg.space()
        space.validate(params0)
        spec = get_terrain(cfg.terrain, length=cfg.distance + 0.3)
        return cls(cfg, space, robot, train_ctrl, eval_ctrl, params0, duration, spec)

    # terrains: training batches are drawn fresh every step; held-out terrains come from another key
    def _keys(self):
        root = jax.random.PRNGKey(self.cfg.seed)
        return jax.random.split(root, 4)  # train terrains, train headings, held-out, validation

    def train_batch(self, step: int, n: Optional[int] = None):
        k_t, k_h = self._keys()[:2]
        n = n or self.cfg.train_batch
        terr = pad_terrain(sample(self.spec, jax.random.fold_in(k_t, step), n), self.spec.max_boxes)
        return terr, jax.random.split(jax.random.fold_in(k_h, step), n)

    def eval_batch(self, which: str = "held_out"):
        """The fixed terrains of the held-out test set (judges the tuning) or of the validation set (picks
        which iterate a run returns); neither is ever trained on."""
        k_e = self._keys()[2 if which == "held_out" else 3]
        n = self.cfg.held_out_batch if which == "held_out" else self.cfg.validation_batch
        terr = pad_terrain(sample(self.spec, k_e, n), self.spec.max_boxes)
        return terr, jax.random.split(jax.random.fold_in(k_e, 1), n)

    def train_rollout(self, grad: bool, params_batched: bool = False):
        """(model, fn) of the smooth rollout; `grad` adds the truncation, bound and remat."""
        window = max(1, int(round(self.cfg.window / self.train_ctrl.dt)))
        rc = RolloutConfig(grad_clip=self.cfg.grad_clip, grad_window=window, remat=True,
                           reversible_solver=True) if grad else RolloutConfig()
        return rollout_function(self.robot, self.train_ctrl, self.duration, physics=self.physics(),
                                config=rc, params_batched=params_batched)

    def eval_rollout(self):
        return rollout_function(self.robot, self.eval_ctrl, self.duration, physics=self.physics())

    def physics(self) -> PhysicsConfig:
        """The terrain's physics, with `solver_iterations` Newton iterations where the config sets them;
        training and evaluation share it, so the gradient is of the physics the result is judged on."""
        base = PhysicsConfig()
        if self.cfg.solver_iterations is not None:
            base = dataclasses.replace(base, iterations=self.cfg.solver_iterations)
        return physics_for(self.spec.kind, base)

    def loss_fn(self, fn, model):
        """loss(u, terrain, keys) -> (mean J, per-env J) for unconstrained params u."""
        def loss(u, terrain, keys):
            s = fn(model, self.space.apply(u, self.params0), terrain, keys)
            j = per_env_objective(s, self.cfg.distance, self.cfg.objective)
            return jnp.mean(j), j
        return loss


def _controller(cfg: TuneConfig, robot, smooth: bool):
    """(controller, starting params = the papers' hand rules, rollout seconds)."""
    if cfg.controller == "tactile":
        from hexjax.control.tactile import TactileGaitController
        c = TactileGaitController(robot, gait=cfg.gait, max_obstacle_height=cfg.max_obstacle_height, smooth=smooth)
        ncyc, dur = c.duration_for(cfg.distance)
        c = dataclasses.replace(c, n_cycles=ncyc)
        p = c.default_params()
        if cfg.temperature is not None:
            p = p.replace(temperature=jnp.float32(cfg.temperature))
        if "swing_time" in cfg.space().names:  # the rollout must cover the slowest walk the bounds allow
            hi = dict(cfg.space().bounds)["swing_time"].hi
            dur = dur * hi / float(p.swing_time)
        return c, p, dur
    from hexjax.control.cpg import CPGController
    c = CPGController(robot, gait=cfg.gait, smooth=smooth)
    p = c.default_params()
    if cfg.temperature is not None:
        p = p.replace(temp_force=jnp.float32(cfg.temperature))
    return c, p, cfg.horizon


def _finite(tree) -> bool:
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(tree))


def _flat(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


def evaluate_held_out(problem: Problem, u, fn=None, model=None, which: str = "held_out") -> Dict[str, float]:
    """Hard-mode objective and goal errors of params u on the held-out (or validation) terrains."""
    if fn is None:
        model, fn = problem.eval_rollout()
    terr, keys = problem.eval_batch(which)
    s = fn(model, problem.space.apply(u, problem.params0), terr, keys)
    j = np.asarray(per_env_objective(s, problem.cfg.distance, problem.cfg.objective))
    dx, dy, da = (np.asarray(x) for x in travel_errors(s, problem.cfg.distance))
    err = np.hypot(dx, dy)
    return {"objective": float(j.mean()), "goal_error_cm": 100 * float(err.mean()),
            "rel_error_pct": 100 * float(err.mean()) / problem.cfg.distance, "dx_cm": 100 * float(dx.mean()),
            "dy_cm": 100 * float(dy.mean()), "abs_dalpha_deg": math.degrees(float(np.abs(da).mean())),
            "fall_pct": 100 * float(np.asarray(s.fell).mean()), "nan_envs": int(np.asarray(s.nan).sum())}


# --------------------------------------------------------------------------------------------------
# checkpoints

def _config_digest(cfg: TuneConfig, method: str) -> str:
    """Identifies what a checkpoint continues: the config less the step count and evaluation period (a run
    may be extended) and less the other method's settings."""
    d = dataclasses.asdict(cfg)
    drop = ["steps", "eval_every"] + (["optimizer", "window", "grad_clip"] if method != "grad" else
                                      ["es_population", "es_sigma"])
    for k in drop:
        d.pop(k)
    return hashlib.sha256(json.dumps([method, d], sort_keys=True, default=str).encode()).hexdigest()[:16]


_COMPILED: Dict[str, Any] = {}


def _cached(key: str, make):
    """One compiled function per (config digest, role) in this process (jit caches by function identity,
    and every `tune` call builds new closures)."""
    if key not in _COMPILED:
        _COMPILED[key] = make()
    return _COMPILED[key]


def save_checkpoint(path: str, state, step: int, log: list, digest: str) -> None:
    """Params, optimiser state (any pytree), step and log, written atomically."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    leaves = _flat(state)
    tmp = path + ".tmp.npz"
    np.savez(tmp, *leaves, meta=np.frombuffer(json.dumps({"step": step, "log": log, "digest": digest}).encode(), np.uint8))
    os.replace(tmp, path)


def load_checkpoint(path: str, like, digest: str):
    """(state, step, log) from `path`, shaped like the pytree `like`; refuses a checkpoint of another config."""
    with np.load(path) as z:
        meta = json.loads(bytes(z["meta"]).decode())
        if meta["digest"] != digest:
            raise ValueError(f"{path}: checkpoint was written by a different config or method; "
                             "use another --out directory or delete it")
        n = len(jax.tree_util.tree_leaves(like))
        leaves = [jnp.asarray(z[f"arr_{i}"]) for i in range(n)]
    return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(like), leaves), meta["step"], meta["log"]


# --------------------------------------------------------------------------------------------------
# gradient tuning

def make_optimizer(cfg: TuneConfig):
    """Adam or SGD at `learning_rate`, cosine-decayed to `decay_to` x that over `steps` when set, after an
    optional global-norm clip."""
    o = dict(cfg.optimizer)
    lr = float(o.get("learning_rate", 0.05))
    if o.get("decay_to"):
        lr = optax.cosine_decay_schedule(lr, cfg.steps, alpha=float(o["decay_to"]))
    opt = optax.adam(lr) if o.get("name", "adam") == "adam" else optax.sgd(lr)
    if o.get("clip_norm"):
        opt = optax.chain(optax.clip_by_global_norm(float(o["clip_norm"])), opt)
    return opt


def tune(cfg: TuneConfig, out_dir: str, resume: bool = True, progress: bool = True,
         time_limit: Optional[float] = None) -> Dict[str, Any]:
    """Adam (or SGD) on the unconstrained params. Every step draws `train_batch` fresh terrains and takes
    one windowed gradient of the smooth objective; every `eval_every` steps (and at step 0 and the end) the
    hard held-out objective is measured. Params, optimiser state and the log are checkpointed to
    out_dir/checkpoint.npz after every step (a rerun resumes); the log goes to out_dir/log.json and a plot
    to out_dir/tune.png. `time_limit` (s) stops early, at a step boundary."""
    t_start = time.perf_counter()
    problem = Problem.build(cfg)
    iterations = problem.physics().iterations
    if cfg.controller == "cpg" and iterations < 4:
        print(f"note: the CPG on yu2019 needs solver_iterations >= 4 for gradients that agree with finite "
              f"differences (docs/tuning.md); this config runs {iterations}")
    u0 = problem.space.init(problem.params0)
    opt = make_optimizer(cfg)
    digest = _config_digest(cfg, "grad")
    model, fn = problem.train_rollout(grad=True)
    vg = _cached(digest + "/vg", lambda: jax.jit(jax.value_and_grad(problem.loss_fn(fn, model), has_aux=True)))

    def advance(state, step):
        u, opt_state = state
        terr, keys = problem.train_batch(step)
        (loss, _), g = vg(u, terr, keys)
        ok = _finite(g) and math.isfinite(float(loss))
        if ok:
            upd, opt_state = opt.update(g, opt_state, u)
            u = optax.apply_updates(u, upd)
        return (u, opt_state), {"train_objective": float(loss), "grad_finite": ok,
                                "grad_norm": float(optax.global_norm(g)) if ok else None}

    return _drive(problem, out_dir, "grad", digest, (u0, opt.init(u0)), lambda st: st[0], advance, cfg.steps,
                  cfg.train_batch, lambda step: step % cfg.eval_every == 0, resume, progress, time_limit, t_start)


def _drive(problem: Problem, out_dir: str, method: str, digest: str, state, params_of, advance, n_steps: int,
           rollouts_per_step: int, should_eval, resume: bool, progress: bool, time_limit, t_start: float):
    """The loop both methods share: resume from out_dir/checkpoint.npz, evaluate the start, then `advance`
    (state, step) -> (state, log fields) up to `n_steps` times or until `time_limit`, evaluating where
    `should_eval(step)` and at the end, checkpointing after every step. `params_of(state)` gives the
    unconstrained params to evaluate."""
    ckpt = os.path.join(out_dir, "checkpoint.npz")
    step, log = 0, []
    if resume and os.path.exists(ckpt):
        state, step, log = load_checkpoint(ckpt, state, digest)
        print(f"resumed from {ckpt} at step {step}")
    em, efn = problem.eval_rollout()
    bar = tqdm(total=n_steps, initial=step, desc=f"tune ({method})", unit="step", disable=not progress)
    if step == 0:
        u = params_of(state)
        log.append({"step": 0, "rollouts": 0, "wall_s": 0.0, **_evaluate(problem, u, efn, em),
                    "params": _jsonable(problem.space.physical(u))})
    while step < n_steps:
        if time_limit is not None and time.perf_counter() - t_start > time_limit:
            print(f"time limit {time_limit:.0f} s reached at step {step}")
            break
        state, fields = advance(state, step)
        step += 1
        u = params_of(state)
        entry = {"step": step, "rollouts": step * rollouts_per_step, "wall_s": time.perf_counter() - t_start,
                 **fields, "params": _jsonable(problem.space.physical(u))}
        if should_eval(step) or step == n_steps:
            entry.update(_evaluate(problem, u, efn, em))
        log.append(entry)
        save_checkpoint(ckpt, state, step, log, digest)
        bar.set_postfix(train=f"{fields['train_objective']:.3f}", held=f"{_last_held(log):.3f}")
        bar.update(1)
    bar.close()
    if "held_out" not in log[-1]:
        log[-1].update(_evaluate(problem, params_of(state), efn, em))
        save_checkpoint(ckpt, state, step, log, digest)
    return _finish(problem, log, out_dir, method)


def _evaluate(problem: Problem, u, fn, model) -> Dict[str, Any]:
    out = {"held_out": evaluate_held_out(problem, u, fn, model)}
    if problem.cfg.validation_batch:
        out["validation"] = evaluate_held_out(problem, u, fn, model, "validation")
    return out


def _last_held(log) -> float:
    for e in reversed(log):
        if "held_out" in e:
            return e["held_out"]["objective"]
    return math.nan


def _jsonable(d):
    return {k: np.asarray(v).tolist() for k, v in d.items()}


def _finish(problem: Problem, log, out_dir: str, method: str) -> Dict[str, Any]:
    """The run's result: `final` is the evaluated iterate with the lowest validation objective (the last
    one without a validation set), reported on the held-out set; `last` is the last iterate."""
    evaluated = [e for e in log if "held_out" in e]
    key = "validation" if problem.cfg.validation_batch else None
    pick = min(evaluated, key=lambda e: e[key]["objective"]) if key else evaluated[-1]
    start = log[0]["held_out"]
    res = {"method": method, "config": dataclasses.asdict(problem.cfg), "log": log,
           "start": {"held_out": start, "params": log[0]["params"]},
           "final": {"step": pick["step"], "rollouts": pick["rollouts"], "held_out": pick["held_out"],
                     "validation": pick.get("validation"), "params": pick["params"]},
           "last": {"step": log[-1]["step"], "held_out": log[-1]["held_out"], "params": log[-1]["params"]},
           "improvement_pct": 100 * (start["objective"] - pick["held_out"]["objective"]) / start["objective"]}
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "log.json"), "w") as f:
        json.dump(res, f, indent=2, default=float)
    plot_log(res, os.path.join(out_dir, "tune.png"))
    return res


def plot_log(res: Dict[str, Any], path: str) -> None:
    """Training objective per step and held-out objective at each evaluation, against rollouts used."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    log = res["log"]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    tr = [(e["rollouts"], e["train_objective"]) for e in log if "train_objective" in e]
    if tr:
        ax.plot(*zip(*tr), ".-", alpha=0.5, label="training batch (smooth)")
    he = [(e["rollouts"], e["held_out"]["objective"]) for e in log if "held_out" in e]
    ax.plot(*zip(*he), "o-", label="held-out (hard)")
    ax.set_xlabel("rollouts used")
    ax.set_ylabel("objective J (m)")
    ax.set_title(f"{res['method']}: {res['config']['controller']} {res['config']['gait']} on {res['config']['terrain']}")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------------------------------
# evolution-strategy baseline

def tune_es(cfg: TuneConfig, out_dir: str, rollouts: int, resume: bool = True, progress: bool = True,
            time_limit: Optional[float] = None) -> Dict[str, Any]:
    """CMA-ES (evosax) on the same unconstrained params and the same smooth training objective, with the
    same terrain stream: generation k evaluates every member of its population on the `train_batch`
    terrains of step k. It stops after `rollouts` rollouts (population x train_batch per generation), so it
    can be given exactly the gradient run's budget. Its starting mean is the hand rules; its step size is
    `cfg.es_sigma` on the unconstrained scale. Held-out evaluations of the mean as for `tune`."""
    from evosax.algorithms import CMA_ES
    t_start = time.perf_counter()
    problem = Problem.build(cfg)
    u0 = problem.space.init(problem.params0)
    pop = cfg.es_population
    es = CMA_ES(population_size=pop, solution=u0)
    es_params = es.default_params.replace(std_init=jnp.float32(cfg.es_sigma))
    key = jax.random.PRNGKey(cfg.seed + 7)
    digest = _config_digest(cfg, f"es{pop}")
    model, fn = problem.train_rollout(grad=False, params_batched=True)
    B = cfg.train_batch

    # every member on the same terrains: params batched over pop x B envs
    def population_loss(pop_u, terr, keys):
        tile = lambda x: jnp.tile(x, (pop,) + (1,) * (x.ndim - 1))
        flat_p = jax.vmap(lambda uu: problem.space.apply(uu, problem.params0))(pop_u)
        params = jax.tree_util.tree_map(lambda x: jnp.repeat(x, B, axis=0), flat_p)
        s = fn(model, params, jax.tree_util.tree_map(tile, terr), tile(keys))
        j = per_env_objective(s, cfg.distance, cfg.objective)
        return j.reshape(pop, B).mean(1)

    pop_loss = _cached(digest + "/pop", lambda: jax.jit(population_loss))

    def advance(state, gen):
        k_ask, k_tell = jax.random.split(jax.random.fold_in(key, gen))
        pop_u, state = es.ask(k_ask, state, es_params)
        terr, keys = problem.train_batch(gen)
        fit = pop_loss(pop_u, terr, keys)
        fit = jnp.where(jnp.isfinite(fit), fit, jnp.max(jnp.where(jnp.isfinite(fit), fit, 0.0)) + 1.0)
        state, _ = es.tell(k_tell, pop_u, fit, state, es_params)
        return state, {"train_objective": float(jnp.mean(fit)), "best_in_generation": float(jnp.min(fit))}

    # evaluate whenever the rollouts used cross a multiple of the gradient run's evaluation period
    should_eval = lambda gen: (gen * pop) // cfg.eval_every > ((gen - 1) * pop) // cfg.eval_every
    return _drive(problem, out_dir, f"cma-es (pop {pop})", digest, es.init(key, u0, es_params), es.get_mean,
                  advance, max(1, rollouts // (pop * B)), pop * B, should_eval, resume, progress, time_limit, t_start)


def compare_plot(rows, path: str) -> None:
    """Held-out objective against rollouts used, one line per method (rows as in scripts/tune_cpu.py)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 3.6))
    for r in rows:
        ax.plot(*zip(*r["curve"]), "o-", label=r["method"])
    ax.set_xscale("symlog", linthresh=8)
    ax.set_xlabel("rollouts used")
    ax.set_ylabel("held-out objective J (m, hard mode)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
