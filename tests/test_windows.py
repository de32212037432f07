"""The windows' backward passes side by side (`hexjax.sim.windows`) give the gradient of reverse mode through
the rollout's scan: same value, same gradient to float32 rounding, for a loss that reads every kind of
accumulator (sums, the start pose set once, running extremes) and the end pose."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.sim.internals import implicit
from hexjax.sim.compiled import Compiled, arrays_digest
from hexjax.sim.config import RolloutConfig, physics_for
from hexjax.sim.engines import sim_model
from hexjax.sim.rollout import rollout_function
from hexjax.sim.step import physics, stop_derived
from hexjax.sim.windows import windowed_value_and_grad
from hexjax.tune.gradcheck import check_batch, tactile_check_setting
from hexjax.world.presets import get_terrain, luneckas2020


def _loss(s):
    """Per env: travel (sums over steps), the start heading (set once, at the end of settling), energy (a sum),
    the largest tilt and the lowest height (running extremes) and the end pose (the last state only)."""
    return (s.travel[:, 0] + 0.3 * s.travel[:, 1] + 0.2 * jnp.sin(s.start_pose[:, 2]) + 0.05 * s.energy
            + 2.0 * s.max_tilt - 3.0 * s.min_height + 0.5 * s.end_pose[:, 1])


@pytest.mark.cost(150)
def test_parallel_windows_give_the_scans_gradient():
    """Tactile tripod (the gradient check's fast setting) on flat ground, 2 envs, 0.4 s after 0.1 s of
    settling: 25 control steps in windows of 4, so 7 windows, the last one padded. Implicit solve, and a per-step
    bound tight enough to bind (`grad_clip` 0.01 per env; the gradient then differs from the unbound one by
    0.87 of its largest derivative). Every float param's derivative agrees with reverse mode through the
    scan within 1e-3 of the largest. Before the rollout gave every env its own copy of every state leaf
    (`hexjax.sim.step.make_env_start`), the scan's bound saw the batch's summed cotangent of the gait clock,
    and this comparison failed."""
    robot = luneckas2020()
    ctrl, p = tactile_check_setting(robot)
    spec = get_terrain("flat")
    terr, keys = check_batch(spec, 2)
    phys = physics_for(spec.kind)
    duration = 0.4
    rc = RolloutConfig(settle_time=0.1, remat=True, solver_grad="implicit", grad_window=4, grad_clip=0.01)
    digest = arrays_digest(p, terr, keys)

    model, fn = rollout_function(robot, ctrl, duration, physics=phys, config=rc)

    def scan_total(params):
        j = _loss(fn(model, params, terr, keys))
        return jnp.sum(j), j

    seq = Compiled(jax.jit(jax.value_and_grad(scan_total, has_aux=True)),
                   static=("test_windows/scan", robot, ctrl, phys, rc, duration, digest))
    (_, j_seq), g_seq = seq(p)

    model_w, vg = windowed_value_and_grad(robot, ctrl, duration, _loss, physics=phys, config=rc)
    par = Compiled(jax.jit(lambda params: vg(model_w, params, terr, keys)),
                   static=("test_windows/parallel", robot, ctrl, phys, rc, duration, digest))
    (summary, j_par), g_par = par(p)
    np.testing.assert_allclose(np.asarray(j_par), np.asarray(j_seq), rtol=1e-5)
    assert np.all(np.isfinite(np.asarray(summary.travel)))

    def flat(g):
        return np.concatenate([np.ravel(np.asarray(x)) for x in jax.tree_util.tree_leaves(g)
                               if x.dtype != jax.dtypes.float0])

    a, b = flat(g_seq), flat(g_par)
    scale = np.max(np.abs(a))
    assert scale > 0.1, a  # the params move the loss: a zero gradient would pass any comparison
    assert np.max(np.abs(a - b)) <= 1e-3 * scale, (a, b)


def _whiles(jaxpr) -> int:
    """`while` loops in a jaxpr, its sub-jaxprs included (MJX's solver is one; its line search is a scan)."""
    n = 0
    for e in jaxpr.eqns:
        n += e.primitive.name == "while"
        for v in e.params.values():
            for x in (v if isinstance(v, (list, tuple)) else [v]):
                sub = getattr(x, "jaxpr", x)
                if hasattr(sub, "eqns"):
                    n += _whiles(sub)
    return n


def test_a_kept_solution_replaces_the_solve():
    """Through `hexjax.sim.internals.implicit.solutions`, a control step's physics keeps each substep's constraint
    solution, and given them back it runs no solver (the windows' backward passes take the forward's solutions,
    so they do not solve a second time) and reaches the same state, to float32 rounding: the two programs are
    compiled apart, and XLA need not round their arithmetic after the solve alike. They came out bit-identical
    on every VM before 2026-11-28's AMD EPYC with AVX2 only, where 7 of the 25 qpos entries differ, by up to
    4.1e-11. A wrong solution, each substep given the one of the substep before, moves the state by 6.9e-6
    there, so the 1e-9 bound still tells a kept solution from a wrong one."""
    robot = luneckas2020()
    phys = physics_for("flat")
    sm = sim_model(robot, phys, "mjx")
    m = sm.mjx_model
    d0 = sm.init_data(jnp.zeros(3))
    d0 = d0.replace(qpos=d0.qpos.at[2].add(-0.005))  # the feet 5 mm into the ground: contact forces push back

    def keep(d):
        with implicit.implicit_solver(), implicit.solutions() as channel:
            d, _ = physics(m, d, 4, detach=stop_derived)
        return d.qpos, channel["kept"]

    def given(d, solved):
        with implicit.implicit_solver(), implicit.solutions(solved):
            d, _ = physics(m, d, 4, detach=stop_derived)
        return d.qpos

    # kept on disk: as plain `jax.jit`s their persistent-cache keys changed with what the worker had traced before
    # (two compiles, 25 s, in one warm run of the suite on 2026-11-29; the same cache had served them an hour before)
    kept = lambda fn, tag: Compiled(jax.jit(fn), static=("test_windows/" + tag, robot, phys))
    qpos, solved = kept(keep, "keep")(d0)
    assert solved[0].shape == (4, m.nv) and float(jnp.max(jnp.abs(solved[1]))) > 1.0  # contact forces act
    assert _whiles(jax.make_jaxpr(keep)(d0).jaxpr) == 1
    assert _whiles(jax.make_jaxpr(given)(d0, solved).jaxpr) == 0
    run_given = kept(given, "given")
    np.testing.assert_allclose(np.asarray(run_given(d0, solved)), np.asarray(qpos), rtol=0, atol=1e-9)
    shifted = jax.tree_util.tree_map(lambda x: jnp.roll(x, 1, axis=0), solved)
    assert float(jnp.max(jnp.abs(run_given(d0, shifted) - qpos))) > 1e-7  # the given solution is what moves it


def test_parallel_backward_refuses_forward_only_settings():
    robot = luneckas2020()
    ctrl, _ = tactile_check_setting(robot)
    with pytest.raises(ValueError, match="record"):
        windowed_value_and_grad(robot, ctrl, 0.4, _loss, physics=physics_for("flat"),
                                config=RolloutConfig(record=True, solver_grad="implicit", grad_window=4))
    with pytest.raises(ValueError, match="solver_grad='none'"):
        windowed_value_and_grad(robot, ctrl, 0.4, _loss, physics=physics_for("flat"),
                                config=RolloutConfig(grad_window=4))


def test_windowed_scan_keeps_the_gradient_and_holds_one_window():
    """`windowed_scan` (the rollout's scan when `remat` meets `grad_window`): the same value and gradient as the
    plain scan, and reverse mode's memory (XLA's temporaries of the gradient program) a fraction of the plain
    scan's, which keeps every step's residuals; with a ragged tail (n not a multiple of the window) too."""
    from hexjax.sim.engines.mjx import windowed_scan
    w = jax.random.normal(jax.random.PRNGKey(0), (64, 64)) * 0.2
    x0 = jnp.linspace(-1.0, 1.0, 64)

    def loss(w, n, window):
        def body(x, i):
            x = jnp.tanh(w @ x + 0.01 * i)
            return x, x[0]
        x, rec = windowed_scan(body, x0, n, window)
        return jnp.sum(x ** 2) + jnp.sum(rec)

    for n in (200, 203):
        plain = jax.jit(jax.value_and_grad(lambda w: loss(w, n, 0)))
        windowed = jax.jit(jax.value_and_grad(lambda w: loss(w, n, 10)))
        (v0, g0), (v1, g1) = plain(w), windowed(w)
        np.testing.assert_allclose(v1, v0, rtol=1e-6)
        np.testing.assert_allclose(g1, g0, rtol=1e-4, atol=1e-5 * float(jnp.abs(g0).max()))  # float32 sums
        temp = lambda f: f.lower(w).compile().memory_analysis().temp_size_in_bytes
        assert temp(windowed) < 0.5 * temp(plain), (temp(windowed), temp(plain))
