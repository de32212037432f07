"""The Brax environment (hexjax.rl.env) and a Brax PPO smoke run on it (hexjax.rl.ppo)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hexjax.rl.env import HexapodGoalEnv
from hexjax.rl.ppo import train_ppo
from hexjax.sim.compiled import Compiled


def test_env_zero_policy_walks_the_gait_towards_the_goal():
    settings = dict(terrain="flat")
    env = HexapodGoalEnv(**settings)
    # reset and step kept on disk (hexjax.sim.compiled), keyed by the settings the env was made from (its defaults
    # are hexjax's source, which the key holds too) and the robot and terrain specs (their presets are YAML files,
    # which it does not): as a plain jax.jit the step's persistent-cache key changed with what the worker ran
    # before, and some warm runs compiled it again (7-11 s)
    key = (tuple(sorted(settings.items())), env.robot, env.tspec)
    kept = lambda fn, tag: Compiled(jax.jit(jax.vmap(fn)), static=("test_rl/" + tag,) + key)
    reset, step = kept(env.reset, "env_reset"), kept(env.step, "env_step")
    s = reset(jax.random.split(jax.random.PRNGKey(0), 3))
    assert s.obs.shape == (3, env.observation_size) and env.action_size == 18
    goals = np.asarray(s.pipeline_state.goal)
    assert np.all(goals[:, 0] == 1.0) and len(np.unique(goals[:, 1])) == 3  # randomised per reset
    total = jnp.zeros(3)
    for _ in range(75):  # 1.5 s
        s = step(s, jnp.zeros((3, 18)))
        total = total + s.reward
    x = np.asarray(s.pipeline_state.data.qpos[:, 0])
    assert np.all(x > 0.2)  # the gait alone walks (0.24 m/s after its one-cycle ramp)
    assert bool(jnp.all(jnp.isfinite(s.obs))) and not np.any(np.asarray(s.done))
    # the progress reward telescopes: its sum is (start distance - distance now) / dt
    gained = (np.linalg.norm(goals, axis=1) - np.asarray(s.metrics["distance"])) / env.dt
    np.testing.assert_allclose(np.asarray(total), gained, rtol=1e-3)
    assert np.all(gained * env.dt > 0.15)


def test_env_bad_input():
    with pytest.raises(ValueError, match="goal_distance"):
        HexapodGoalEnv(goal_distance=0.0)
    with pytest.raises(ValueError, match="terrain preset"):
        HexapodGoalEnv(terrain="lava")
    n = jax.device_count()  # 2 in the suite (tests/conftest.py)
    if n > 1:
        with pytest.raises(ValueError, match=f"num_envs={n + 1}: must be a multiple of the {n} devices"):
            train_ppo(HexapodGoalEnv(), num_envs=n + 1)


@pytest.mark.cost(170)
def test_brax_ppo_trains_end_to_end_and_its_reward_improves():
    """40k env steps of Brax PPO: the deterministic evaluations rise at each of the 3 evaluations, by more
    than 5 in all (seeded; measured 1.5 -> 4.6 -> 9.2, where a policy that learns nothing stays near its
    start)."""
    env = HexapodGoalEnv(terrain="flat")
    history, make_policy, params = train_ppo(env, num_timesteps=40_000, num_envs=16, episode_length=50,
                                             num_evals=3, seed=0)
    rewards = [r for _, r in history]
    assert len(rewards) == 3 and all(np.isfinite(rewards))
    assert rewards[0] < rewards[1] < rewards[2] and rewards[2] - rewards[0] > 5.0, rewards
