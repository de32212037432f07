import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.cache import cache_dir
from hexjax.control.base import Controller
from hexjax.control.gait import GaitController
from hexjax.sim.metrics import goal_errors
from hexjax.sim.compiled import Compiled
from hexjax.sim.config import PhysicsConfig, RolloutConfig, SensorConfig, control_steps
from hexjax.sim.engines import get_engine
from hexjax.sim.engines.mjx import compiled_rollout
from hexjax.sim.internals.contacts import contact_geoms
from hexjax.sim.model import SimModel, mjx
from hexjax.sim.rollout import make_mesh, rollout
from hexjax.world.presets import get_terrain, luneckas2020
from hexjax.world.terrain import sample

FLAT = PhysicsConfig(slots_per_leg=0, torso_slots=0)


@pytest.mark.cost(65)
@pytest.mark.parametrize("gait", ["tripod", "wave"])
def test_flat_walk_straight_1m(gait):
    """Acceptance: 1 m on flat ground, 16 envs with random initial yaw, both gaits: |dx|, |dy| within a few
    cm (Luneckas 2020 Table 1 calibration: (1-3, 1-6) cm), no falls, no NaN."""
    spec = luneckas2020()
    c = GaitController(spec, gait=gait)
    p = c.default_params()
    n, dur = c.duration_for(1.0, p)
    c = dataclasses.replace(c, n_cycles=n)
    terr = sample(get_terrain("flat"), jax.random.PRNGKey(0), 16)
    s = rollout(spec, terr, c, p, dur, jax.random.PRNGKey(1), physics=FLAT, config=RolloutConfig(yaw_noise=0.05))
    e = goal_errors(s, 1.0)
    yaw0 = np.asarray(s.start_pose[:, 2])
    assert np.ptp(yaw0) > 0.03  # the initial headings really were randomised
    assert not np.asarray(s.nan).any() and not np.asarray(s.fell).any()
    assert np.abs(np.asarray(e.dx)).max() < 0.04, np.asarray(e.dx)  # m
    assert np.abs(np.asarray(e.dy)).max() < 0.04, np.asarray(e.dy)
    assert np.degrees(np.abs(np.asarray(e.dalpha))).max() < 3.0
    assert np.asarray(e.success).all()


@dataclasses.dataclass(frozen=True)
class _NanAfter(Controller):
    """A controller that commands NaN joint targets after `t_bad` s: the rollout must flag, not spread, it."""

    base: GaitController
    t_bad: float

    @property
    def dt(self):
        return self.base.dt

    def params_defaults(self):
        return self.base.default_params()

    def init(self, params, key):
        return self.base.init(params, key)

    def step(self, params, state, obs):
        st, a = self.base.step(params, state, obs)
        bad = state.t > self.t_bad
        return st, jnp.where(bad, jnp.nan, a)


def test_nan_is_flagged_and_contained():
    spec = luneckas2020()
    c = _NanAfter(GaitController(spec), 0.5)
    terr = sample(get_terrain("flat"), jax.random.PRNGKey(0), 2)
    s = rollout(spec, terr, c, c.default_params(), 1.0, jax.random.PRNGKey(1), physics=FLAT)
    assert np.asarray(s.nan).all()
    assert np.all(np.isfinite(np.asarray(s.end_pose))) and np.all(np.isfinite(np.asarray(s.energy)))


@pytest.mark.cost(85)
def test_sharded_rollout_matches_unsharded():
    devs = jax.devices()
    assert len(devs) >= 2, "conftest asks XLA for two host devices"
    spec = luneckas2020()
    c = GaitController(spec)
    p = c.default_params()
    terr = sample(get_terrain("flat"), jax.random.PRNGKey(4), 4)
    a = rollout(spec, terr, c, p, 1.0, jax.random.PRNGKey(5), physics=FLAT)
    mesh = make_mesh(devs[:2])
    b = rollout(spec, terr, c, p, 1.0, jax.random.PRNGKey(5), physics=FLAT, mesh=mesh)
    assert len(b.end_pose.sharding.device_set) == 2
    np.testing.assert_allclose(np.asarray(a.end_pose), np.asarray(b.end_pose), atol=1e-4)
    # each device steps its own envs: no collective in the program (automatic partitioning of the vmapped
    # rollout all-reduced the solver's stopping flag over the devices in every Newton iteration)
    _, fn = compiled_rollout(get_engine("mjx"), spec, FLAT, SensorConfig(), c, RolloutConfig(), control_steps(1.0, c.dt),
                             False, False, mesh)
    (exe,) = fn.executables.values()
    hlo = exe.as_text()
    assert "while" in hlo and not re.search(r"\b(all-reduce|all-gather|collective-permute|all-to-all)", hlo)
    # kept on disk as a one-device program is: a new `Compiled`, as in a later process, loads it instead of
    # tracing it (the sharded program is partitioned by Shardy, which can call an exported program back)
    if cache_dir() is not None:
        compiled_rollout.cache_clear()
        again, st = rollout(spec, terr, c, p, 1.0, jax.random.PRNGKey(5), physics=FLAT, mesh=mesh, stats=True)
        assert st.compiled == "disk"
        np.testing.assert_array_equal(np.asarray(again.end_pose), np.asarray(b.end_pose))


def test_per_env_keys_are_used_env_for_env():
    """A stack of B keys gives env i the i-th key: the split of one key reproduces the one-key rollout, and the
    same keys reversed give each env the heading draw of its mirror (flat ground: envs differ only by keys)."""
    spec = luneckas2020()
    c = GaitController(spec)
    p = c.default_params()
    terr = sample(get_terrain("flat"), jax.random.PRNGKey(4), 4)
    a = rollout(spec, terr, c, p, 1.0, jax.random.PRNGKey(5), physics=FLAT)
    keys = jax.random.split(jax.random.PRNGKey(5), 4)
    b = rollout(spec, terr, c, p, 1.0, keys, physics=FLAT)
    np.testing.assert_array_equal(np.asarray(b.end_pose), np.asarray(a.end_pose))
    r = rollout(spec, terr, c, p, 1.0, keys[::-1], physics=FLAT)
    np.testing.assert_array_equal(np.asarray(r.start_pose), np.asarray(a.start_pose)[::-1])
    assert np.ptp(np.asarray(a.start_pose[:, 2])) > 0  # the draws differ, so the reversal is seen


def test_contact_map_matches_mjx_forward():
    sm = SimModel(luneckas2020(), PhysicsConfig(slots_per_leg=1, torso_slots=1), get_engine("mjx"))
    d = mjx.make_data(sm.mj_model)
    # kept on disk: a plain `jax.jit`'s persistent-cache key can change with what the worker traced before
    fwd = Compiled(jax.jit(mjx.forward), static=("test_rollout/forward", sm.robot, sm.physics))
    ref = np.asarray(fwd(sm.mjx_model, d)._impl.contact.geom)
    np.testing.assert_array_equal(contact_geoms(sm.mjx_model, d), ref)


def test_invalid_rollout_inputs_raise_before_tracing():
    spec = luneckas2020()
    c = GaitController(spec)
    p = c.default_params()
    terr = sample(get_terrain("flat"), jax.random.PRNGKey(0), 2)
    with pytest.raises(ValueError, match="duration"):
        rollout(spec, terr, c, p, -1.0, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="batched Terrain"):
        rollout(spec, jax.tree_util.tree_map(lambda x: x[0], terr), c, p, 1.0, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="step_height"):
        rollout(spec, terr, c, p.replace(step_height=jnp.asarray(0.5)), 1.0, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="multiple"):
        rollout(spec, sample(get_terrain("flat"), jax.random.PRNGKey(0), 3), c, p, 1.0, jax.random.PRNGKey(0),
                physics=FLAT, mesh=make_mesh(jax.devices()[:2]))
    with pytest.raises(ValueError, match="timestep"):
        rollout(spec, terr, c, p, 1.0, jax.random.PRNGKey(0), physics=PhysicsConfig(timestep=0.03))
    with pytest.raises(ValueError, match="derive it from hexjax.control.Controller"):
        rollout(spec, terr, object(), p, 1.0, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match=r"duration=1000000000.0: 200,000,000,060 physics steps, more than a rollout"):
        rollout(spec, terr, c, p, 1e9, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match=r"key: got ArrayImpl of shape \(3,\)"):
        rollout(spec, terr, c, p, 1.0, jnp.zeros(3))
    with pytest.raises(ValueError, match=r"key: got int"):
        rollout(spec, terr, c, p, 1.0, 0)
    with pytest.raises(ValueError, match=r"key: got ArrayImpl of shape \(3, 2\).*or 2 of them stacked"):
        rollout(spec, terr, c, p, 1.0, jnp.zeros((3, 2), jnp.uint32))
    with pytest.raises(ValueError, match=r"params\.step_length: shape \(\); params_batched=True needs a leading "
                                         r"axis of the terrain's 2 envs"):
        rollout(spec, terr, c, p, 1.0, jax.random.PRNGKey(0), params_batched=True)
    three = jax.tree_util.tree_map(lambda v: jnp.stack([v] * 3), p)
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        rollout(spec, terr, c, three, 1.0, jax.random.PRNGKey(0), params_batched=True)
