"""The windows' backward passes side by side (`hexjax.sim.windows`) give the gradient of reverse mode through
the rollout's scan: same value, same gradient to float32 rounding, for a loss that reads every kind of
accumulator (sums, the start pose set once, running extremes) and the end pose."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.sim.compiled import Compiled, arrays_digest
from hexjax.sim.config import RolloutConfig, physics_for
from hexjax.sim.rollout import rollout_function
from hexjax.sim.windows import windowed_value_and_grad
from hexjax.tune.gradcheck import check_batch, tactile_check_setting
from hexjax.world.presets import get_terrain, luneckas2020


def _loss(s):
    """Per env: travel (sums over steps), the start heading (set once, at the end of settling), energy (a sum),
    the largest tilt and the lowest height (running extremes) and the end pose (the last state only)."""
    return (s.travel[:, 0] + 0.3 * s.travel[:, 1] + 0.2 * jnp.sin(s.start_pose[:, 2]) + 0.05 * s.energy
            + 2.0 * s.max_tilt - 3.0 * s.min_height + 0.5 * s.end_pose[:, 1])


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


def test_parallel_backward_refuses_forward_only_settings():
    robot = luneckas2020()
    ctrl, _ = tactile_check_setting(robot)
    with pytest.raises(ValueError, match="record"):
        windowed_value_and_grad(robot, ctrl, 0.4, _loss, physics=physics_for("flat"),
                                config=RolloutConfig(record=True, solver_grad="implicit", grad_window=4))
    with pytest.raises(ValueError, match="solver_grad='none'"):
        windowed_value_and_grad(robot, ctrl, 0.4, _loss, physics=physics_for("flat"),
                                config=RolloutConfig(grad_window=4))
