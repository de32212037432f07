"""Brax PPO on `HexapodGoalEnv` (`hexjax ppo`): a smoke size for a 2-core CPU by default."""

from __future__ import annotations

import functools
import time
from typing import Dict

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from hexjax.sim.engines import GRADIENTS
from hexjax.rl.env import HexapodGoalEnv

NEEDS = frozenset({GRADIENTS})  # the Brax env steps MJX itself: its state is MJX's Data, a JAX pytree


def _gspmd():
    """Context in which JAX partitions programs over several devices with GSPMD instead of Shardy. Brax's PPO
    runs its `pmap` as a `shard_map` in JAX 0.11, and jaxlib 0.11.2's Shardy pass segfaults compiling it, in a
    canonicalisation pattern for the manual computation's unused inputs (`ManualComputationUnusedInputsPattern`,
    gdb): an empty array among the inputs crashes it (a (0, 3) array summed inside a 2-device `shard_map` on the
    CPU does). GSPMD compiles it. (The sharded rollout keeps empty arrays out of its manual computation instead:
    `hexjax.sim.rollout._shard_map_without_empty_arrays`.)"""
    from jax._src import config as jax_config  # the setting's context manager; jax.config has only `update`
    return jax_config.use_shardy_partitioner(False)


def _device_put_replicated(x, devices):
    """`jax.device_put_replicated`, removed in jax 0.10 but still called by brax 0.14.2's PPO: each leaf stacked
    once per device along a new leading axis, that axis sharded over `devices` (the replacement the JAX pmap
    migration guide gives)."""
    devices = list(devices)
    sharding = NamedSharding(Mesh(np.array(devices), ("d",)), PartitionSpec("d"))
    return jax.tree_util.tree_map(lambda a: jax.device_put(jnp.stack([jnp.asarray(a)] * len(devices)), sharding), x)


def _evaluate_with_fixed_types(run_evaluation):
    """brax 0.14.2's `Evaluator.run_evaluation`, fed inputs of one type. Its first evaluation gets the initial
    normaliser, whose `std_eps` is a weakly typed scalar, and uncommitted arrays; every later one gets
    strongly typed arrays committed to a device (a training step's outputs). JAX traces and compiles the
    evaluation unroll once for each (26-29 s of XLA compile on 2 CPU cores the second time, found with
    JAX_EXPLAIN_CACHE_MISSES). Here every call gets strong types, committed to the device the first of them
    is on, so the first program serves them all."""
    @functools.wraps(run_evaluation)
    def run(self, policy_params, *args, **kwargs):
        device = jax.tree_util.tree_leaves(self._eval_state_to_donate)[0].devices().pop()

        def fixed(x):
            x = jnp.asarray(x)
            return jax.device_put(x.astype(x.dtype), device)
        self._eval_state_to_donate = jax.tree_util.tree_map(fixed, self._eval_state_to_donate)
        return run_evaluation(self, jax.tree_util.tree_map(fixed, policy_params), *args, **kwargs)
    run.fixed_types = True
    return run


def train_ppo(env: HexapodGoalEnv, num_timesteps: int = 60_000, num_envs: int = 16, episode_length: int = 100,
              num_evals: int = 4, seed: int = 0, progress=None, **ppo_kwargs):
    """Brax PPO on `env`. Returns (eval history [(env steps, mean episode reward)], make_policy, params).
    Defaults are a smoke size for a 2-core CPU; raise num_timesteps / num_envs on a GPU."""
    if num_envs % jax.device_count():  # Brax splits the envs evenly over the devices (an assert of its own)
        raise ValueError(f"num_envs={num_envs}: must be a multiple of the {jax.device_count()} devices Brax splits "
                         "the envs over")
    from brax.training.agents.ppo import train as ppo  # brax is the optional `rl` extra
    if "device_put_replicated" not in vars(jax):  # brax 0.14.2 on jax >= 0.10 (see _device_put_replicated)
        jax.device_put_replicated = _device_put_replicated
    from brax.training import acting
    if not getattr(acting.Evaluator.run_evaluation, "fixed_types", False):  # see _evaluate_with_fixed_types
        acting.Evaluator.run_evaluation = _evaluate_with_fixed_types(acting.Evaluator.run_evaluation)
    history = []

    def on_progress(step, metrics):
        history.append((int(step), float(metrics["eval/episode_reward"])))
        if progress is not None:
            progress(step, metrics)

    kw = dict(num_timesteps=num_timesteps, num_envs=num_envs, episode_length=episode_length, num_evals=num_evals,
              batch_size=num_envs, num_minibatches=4, unroll_length=10, num_updates_per_batch=4,
              learning_rate=3e-4, entropy_cost=1e-3, discounting=0.97, normalize_observations=True,
              num_eval_envs=num_envs, seed=seed, progress_fn=on_progress)
    kw.update(ppo_kwargs)
    with _gspmd():  # brax's pmap over the local devices is a shard_map in jax 0.11
        make_policy, params, _ = ppo.train(environment=env, **kw)
    return history, make_policy, params


# The command (configs/commands/ppo.yaml) ------------------------------------------------------------------------
def run(o, entry) -> Dict:
    from hexjax.sim.physics import pick
    from hexjax.world.presets import get_terrain
    preset = pick(o.physics, needs=NEEDS)
    env = HexapodGoalEnv(robot=o.robot, terrain=o.terrain, goal_distance=o.goal,
                         physics=preset.config(get_terrain(o.terrain)))
    t0 = time.perf_counter()
    history, _, _ = train_ppo(env, num_timesteps=o.timesteps, num_envs=o.envs, episode_length=o.episode_length,
                              num_evals=o.evals, seed=o.seed,
                              progress=lambda step, m: print(f"  {int(step):>9,} env steps: eval episode reward "
                                                             f"{float(m['eval/episode_reward']):.3f}", flush=True))
    return {"robot": o.robot, "terrain": o.terrain, "goal_m": o.goal, "timesteps": o.timesteps, "num_envs": o.envs,
            "episode_length": o.episode_length, "seed": o.seed,
            "history": [{"env_steps": s, "eval_episode_reward": r} for s, r in history],
            "wall_s": time.perf_counter() - t0, "device": str(jax.devices()[0].platform)}


def report(res: Dict) -> str:
    h = res["history"]
    return (f"Brax PPO on HexapodGoalEnv ({res['robot']}, {res['terrain']}, goal {res['goal_m']:g} m): eval episode "
            f"reward {h[0]['eval_episode_reward']:.3f} -> {h[-1]['eval_episode_reward']:.3f} over "
            f"{h[-1]['env_steps']:,} env steps in {res['wall_s']:.0f} s")
