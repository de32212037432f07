"""Issue 19's tuning additions, without compiling a rollout: the hybrid estimator's fit and its plumbing
(antithetic pairs on the same terrain and noise key, the flat parameter order), tuning on several terrain
presets at once, CMA-ES on the hard objective, tuned params handed to an experiment, and the key under which the
tuners keep their compiled programs."""

import json
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.control.tactile import TactileGaitController
from hexjax.sim.grad import clip_cotangent
from hexjax.tune.config import load_tune_config
from hexjax.tune.driver import config_digest, program_digest
from hexjax.tune.hybrid import combine, per_env_estimates
from hexjax.tune.objective import Problem, mean_value_and_grad, per_env_objective
from hexjax.tune.space import load_values, make_space, with_values
from hexjax.world.presets import luneckas2020

FIELDS = ("overcome_height", "step_height", "step_length")  # sorted: ravel_pytree's order of the dict u


def test_fit_recovers_a_linear_gradient_and_leans_on_the_prior_as_asked():
    """With noise-free directional derivatives d = eps . g_true, a small prior gives g_true whatever the
    windowed gradients say; a prior of 1e9 pairs gives their mean; numpy and jax agree."""
    rng = np.random.default_rng(0)
    B, K, P = 8, 4, 5
    g_true = rng.normal(size=P)
    eps = rng.normal(size=(B, K, P))
    d = eps @ g_true
    g_fo = g_true + rng.normal(size=(B, P))  # biased and noisy per env
    np.testing.assert_allclose(combine(g_fo, eps, d, 1e-9, np), g_true, atol=1e-6)
    np.testing.assert_allclose(combine(g_fo, eps, d, 1e9, np), g_fo.mean(0), atol=1e-6)
    mid = combine(g_fo, eps, d, 1.0, np)
    assert np.linalg.norm(mid - g_true) < 0.1 * np.linalg.norm(g_fo.mean(0) - g_true)
    np.testing.assert_allclose(np.asarray(combine(*(jnp.asarray(x, jnp.float32) for x in (g_fo, eps, d)), 1.0)),
                               mid, rtol=1e-4, atol=1e-5)


def _fake_problem(weights):
    """A stand-in for `Problem` whose 'rollout' is algebra: the travel is `weights` . (three tactile params)
    plus an offset drawn from each env's noise key and one from its terrain, so only a pairing that keeps
    both per env cancels them in the differences."""
    params0 = TactileGaitController(luneckas2020(), gait="tripod").default_params()
    problem = types.SimpleNamespace(space=make_space("tactile", only=list(FIELDS)), params0=params0,
                                    cfg=types.SimpleNamespace(distance=1.0, objective={"dx": 1.0}))

    def fn(model, params, terrain, keys):
        x = jnp.stack([params.overcome_height, params.step_height, params.step_length], -1) @ weights
        x = x + 0.05 * jax.vmap(jax.random.uniform)(keys) + terrain
        n = x.shape[0]
        zeros = jnp.zeros(n)
        return types.SimpleNamespace(travel=jnp.stack([x, zeros, zeros], -1), start_pose=jnp.zeros((n, 3)),
                                     energy=zeros, fell=zeros > 1, nan=zeros > 1)
    return problem, fn


def test_grad_clip_bounds_each_env_whatever_the_batch():
    """The first-order tuner's gradient (`mean_value_and_grad`) is the mean of the envs' own gradients, each with
    `RolloutConfig.grad_clip`'s per-step bound acting on that env's cotangent: the same at any batch size, and the
    same per-env bound as the hybrid's (a batch of one). A toy 'rollout' per env: x = a u, bounded at 1 on the
    way back, J = x^2. Differentiating the mean instead bounds each env at B, so its gradient changes with B."""
    bound = 1.0

    def per_env(u, a):
        x = clip_cotangent(a * u, bound)
        return jnp.sum(x ** 2)

    loss = lambda u, a: (lambda j: (jnp.mean(j), j))(jax.vmap(per_env, (None, 0))(u, a))
    u = jnp.array([0.3, -0.2])
    a = jnp.array([2.0, 0.1, 5.0])  # the cotangent 2x = 2 a u exceeds the bound for the first and third
    own = np.stack([np.asarray(jax.grad(per_env)(u, ai)) for ai in a])  # each env alone, bounded at 1
    assert np.linalg.norm(2 * np.asarray(a[0] * u)) > bound  # the bound does bind for env 0
    vg = jax.jit(mean_value_and_grad(loss))
    for reps in (1, 2, 8):
        (m, j), g = vg(u, jnp.tile(a, reps))
        np.testing.assert_allclose(np.asarray(g), own.mean(0), rtol=1e-6)
        np.testing.assert_allclose(float(m), float(np.mean(j)), rtol=1e-6)
    naive = [np.asarray(jax.grad(lambda u, a: loss(u, a)[0])(u, jnp.tile(a, r))) for r in (1, 8)]
    assert np.linalg.norm(naive[1] - naive[0]) > 0.1 * np.linalg.norm(naive[0])


def test_estimates_pair_each_env_with_itself_and_fit_the_whole_walk():
    """The per-env windowed gradients are those of each env's objective; the directional derivatives, taken
    on each env's own terrain and key, equal eps . (true gradient) to O(sigma^2); fitted with a prior that
    misses one parameter's effect (a window too short for it), the estimate recovers it."""
    w_true = jnp.array([0.5, 2.0, 3.0])
    problem, fn_true = _fake_problem(w_true)
    _, fn_window = _fake_problem(w_true * jnp.array([1.0, 0.0, 1.0]))  # blind to step_height
    B, K = 6, 4
    terrain = jnp.linspace(0.0, 0.1, B)
    keys = jax.random.split(jax.random.PRNGKey(1), B)
    u0 = problem.space.init(problem.params0)
    est = per_env_estimates(problem, (None, fn_window), (None, fn_true), K, 1e-2)
    j, g, eps, d = (np.asarray(x) for x in jax.jit(est)(u0, terrain, keys, jax.random.PRNGKey(2)))
    assert j.shape == (B,) and g.shape == (B, 3) and eps.shape == (B, K, 3) and d.shape == (B, K)

    def j_env(flat, e, fn):  # env e's objective at flat params
        params = jax.tree_util.tree_map(lambda x: x[None], problem.space.apply(
            dict(zip(FIELDS, flat)), problem.params0))
        return per_env_objective(fn(None, params, terrain[e:e + 1], keys[e:e + 1]), 1.0, {"dx": 1.0})[0]

    flat0 = jnp.stack([u0[f] for f in FIELDS])
    true = np.stack([np.asarray(jax.grad(j_env)(flat0, e, fn_true)) for e in range(B)])
    window = np.stack([np.asarray(jax.grad(j_env)(flat0, e, fn_window)) for e in range(B)])
    np.testing.assert_allclose(g, window, rtol=1e-4, atol=1e-7)
    assert np.all(window[:, 1] == 0) and np.all(np.abs(true[:, 1]) > 1e-3)
    np.testing.assert_allclose(d, np.einsum("bkp,bp->bk", eps, true), rtol=2e-2, atol=1e-4)
    hybrid = combine(g, eps, d, 1.0, np)
    np.testing.assert_allclose(hybrid, true.mean(0), rtol=0.05, atol=1e-4)
    assert abs(g.mean(0)[1]) < 1e-9 < abs(hybrid[1])


def test_several_terrains_split_each_batch_and_share_one_box_count():
    """A config over two presets draws its batches half from each, padded to one box count; the digest of
    a single-terrain config is unchanged by the new keys; bad lists fail in one line naming the key."""
    cfg = load_tune_config("cpg_tripod", {"terrain": ["step40", "ditch40"], "train_batch": 5, "held_out_batch": 4})
    problem = Problem.build(cfg)
    terr, keys = problem.train_batch(0)
    z = np.asarray(terr.ground_z)
    assert keys.shape == (5, 2) and terr.box_pos.shape[:2] == (5, max(s.max_boxes for s in problem.specs))
    assert np.sum(z == 0) == 3 and np.sum(np.isclose(z, -0.04)) == 2  # step40 has its ground at 0
    held, _ = problem.eval_batch()
    assert np.sum(np.isclose(np.asarray(held.ground_z), -0.04)) == 2
    # one preset: the same draws as before several were allowed, and the same checkpoint digest
    one = load_tune_config("tactile_tripod", {"eval_physics": "fast"})
    assert config_digest(one, "grad") == "4d04f9060ae31df0" and config_digest(one, "es8") == "66f3d75331aa77e1"
    # evaluated on `validated` (the default) it continues no checkpoint evaluated on the training physics
    assert config_digest(load_tune_config("tactile_tripod"), "grad") != "4d04f9060ae31df0"
    for bad, msg in [({"terrain": []}, "tune.terrain=\\[\\]: must be a terrain preset name"),
                     ({"terrain": ["step40", "step40"]}, "listed twice"),
                     ({"terrain": ["step40", "stepp40"]}, "tune.terrain='stepp40'"),
                     ({"terrain": ["step40", "ditch40", "ditch80"], "train_batch": 2}, "tune.train_batch=2: needs"),
                     ({"terrain_overrides": {"start_xx": 0.1}}, "tune.terrain_overrides: .*start_xx"),
                     ({"estimator": "second_order"}, "tune.estimator='second_order'"),
                     ({"zo_pairs": 0}, "tune.zo_pairs=0"), ({"zo_prior": 0.0}, "tune.zo_prior=0.0"),
                     ({"es_objective": "soft"}, "tune.es_objective='soft'")]:
        with pytest.raises(ValueError, match=msg):
            load_tune_config("cpg_tripod", bad)


def test_tuned_values_load_from_a_log_and_are_checked(tmp_path):
    """A tuning log's picked params (or a plain mapping) set the CPG's fields; a wrong name or shape fails
    in one line naming it."""
    from hexjax.control.cpg import CPGController
    from hexjax.world.presets import yu2019
    p0 = CPGController(yu2019()).default_params()
    log = {"final": {"params": {"f_contact": [12.0, 11.0, 1.5], "clearance": 0.05}}}
    (tmp_path / "log.json").write_text(json.dumps(log))
    p = with_values(p0, load_values(str(tmp_path / "log.json")))
    np.testing.assert_allclose(np.asarray(p.f_contact), [12.0, 11.0, 1.5])
    assert float(p.clearance) == pytest.approx(0.05) and float(p.ramp_time) == float(p0.ramp_time)
    with pytest.raises(ValueError, match="f_contact=\\[1.0, 2.0\\]: must be finite with shape \\(3,\\)"):
        with_values(p0, {"f_contact": [1.0, 2.0]})
    with pytest.raises(ValueError, match="f_contactt: unknown parameter"):
        with_values(p0, {"f_contactt": 1.0})
    with pytest.raises(ValueError, match="clearance='high': must be a number"):
        with_values(p0, {"clearance": "high"})
    (tmp_path / "bad.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match="expected a tuning log.json or a mapping"):
        load_values(str(tmp_path / "bad.json"))


def test_runs_that_differ_only_outside_the_program_share_its_kept_copy():
    """A tuner's compiled program is kept on disk under `program_digest`: another seed, run length, evaluation
    period, held-out or validation batch, optimiser or CMA-ES step size gives the same key (so a seed-1 run
    loads seed 0's program), while a setting traced into the program gives another key. The checkpoint's
    `config_digest` still tells the seeds apart, so a run never resumes another seed's checkpoint."""
    base = load_tune_config("cpg_step_ditch")
    outside = {"seed": 1, "steps": 7, "eval_every": 3, "held_out_batch": 9, "validation_batch": 0,
               "optimizer": {"name": "sgd", "learning_rate": 0.2, "average": 0.7}, "es_sigma": 0.3}
    inside = {"window": 1.0, "grad_clip": 3.0, "gates": "straight_through", "train_batch": 12, "distance": 0.5,
              "train_physics": "fast", "objective": {"dx": 1.0}, "terrain": ["step40", "ditch40"], "es_population": 4,
              "estimator": "hybrid", "es_objective": "smooth"}
    for method in ("grad", "es8"):
        for k, v in outside.items():
            other = load_tune_config("cpg_step_ditch", {k: v})
            assert program_digest(other, method) == program_digest(base, method), (method, k)
        key = program_digest(base, method)
        changed = [k for k, v in inside.items()
                   if program_digest(load_tune_config("cpg_step_ditch", {k: v}), method) != key]
        # CMA-ES's settings stay out of the gradient's key and the gradient's window, clip and estimator out of
        # CMA-ES's (both keep the gates: CMA-ES on the smooth objective runs the training rollout)
        assert set(inside) - set(changed) == ({"es_population", "es_objective"} if method == "grad" else
                                              {"window", "grad_clip", "estimator"}), (method, changed)
    assert config_digest(load_tune_config("cpg_step_ditch", {"seed": 1}), "grad") != config_digest(base, "grad")
