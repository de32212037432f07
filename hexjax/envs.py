"""A Brax environment over the hexjax robot and terrain batch, for reinforcement learning (Brax PPO etc.).

`HexapodGoalEnv` follows `brax.envs.base.Env`: `reset(rng)` and `step(state, action)` on one env, vmapped by
Brax's wrappers. Each reset draws its own terrain from a `TerrainSpec` (domain randomisation: terrain, start
heading, goal position, ground friction scale), places the robot at the origin and a goal ahead of it, and
settles nothing (the robot starts in its stance keyframe). A step runs one control period: terrain slots
assigned to the feet (as in `hexjax.sim.rollout`), `n_sub` MJX steps.

Actions: by default a residual on the seed-000 gait (Luneckas 2020 Eqs. 2-4, `GaitController`, tripod at
l = 6 cm and 0.25 s swings, 0.24 m/s): joint
target = gait IK target + `residual_scale` x clip(action, -1, 1), so a zero policy already walks; with
`residual=False` the action is the joint target offset from the stance keyframe.

Observation (75,): joint angles (18) and rates x 0.1 (18); torso height above the ground plane (1), the
world's up-vector in the torso frame (3), linear and angular velocity in the torso frame (6); each foot's
terrain force in the world frame / body weight (18); each shin's tactile pad on/off (6); the goal in the
torso frame (2) and its distance (1); the gait phase as (sin, cos) (2).

Reward per step: progress towards the goal (m/s) - `action_cost` |a|^2 - `fall_penalty` on falling, and
+ `goal_bonus` on reaching it. Done on a fall (tilt > 60 deg, torso lower than 3 cm), a non-finite state, or
reaching the goal (within 10 cm). Everything episode-specific lives in `pipeline_state`, so Brax's
AutoResetWrapper restores it whole.
"""

from __future__ import annotations

import contextlib
import io
import math

import jax
import jax.numpy as jnp
from flax import struct

with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    from brax.envs.base import Env, State  # noqa: E402 (brax prints warp notices on import)

from hexjax.control.gait import GaitController, GaitState
from hexjax.mjcf import PhysicsConfig, physics_for
from hexjax.robot import get_robot
from hexjax.sim.model import SensorConfig, assign_slots, env_model, mjx, read_obs, sim_model
from hexjax.terrain import Terrain, get_terrain, sample_one
from mujoco.mjx._src import math as mjx_math  # noqa: E402 (after hexjax.sim.model, which silences MJX's import)


@struct.dataclass
class HexState:
    """What an episode carries: MJX data, its terrain, goal (2,) m, gait time t (s), distance to the goal (m),
    friction scale (domain randomisation)."""

    data: mjx.Data
    terrain: Terrain
    goal: jax.Array
    t: jax.Array
    dist: jax.Array
    friction: jax.Array


def _rotate_to_body(quat, v):
    """A world-frame vector v in the frame of the torso with orientation quat (w, x, y, z)."""
    return mjx_math.rotate(v, mjx_math.quat_inv(quat))


class HexapodGoalEnv(Env):
    """Walk to a goal `goal_distance` m ahead (lateral offset U(-goal_spread, goal_spread)) over randomised
    terrain. See the module docstring for observation, action and reward."""

    def __init__(self, robot: str = "luneckas2020", terrain: str = "flat", goal_distance: float = 1.0,
                 goal_spread: float = 0.3, residual: bool = True, residual_scale: float = 0.25, gait: str = "tripod",
                 yaw_noise: float = math.radians(10.0), friction_range=(0.8, 1.2), action_cost: float = 0.01,
                 fall_penalty: float = 1.0, goal_bonus: float = 1.0, physics: PhysicsConfig | None = None,
                 step_length: float = 0.06, swing_time: float = 0.25):
        if not goal_distance > 0:
            raise ValueError(f"goal_distance={goal_distance!r}: must be > 0")
        if not residual_scale > 0:
            raise ValueError(f"residual_scale={residual_scale!r}: must be > 0")
        lo, hi = friction_range
        if not 0 < lo <= hi:
            raise ValueError(f"friction_range={friction_range!r}: need 0 < lo <= hi")
        self.robot = get_robot(robot)
        self.tspec = get_terrain(terrain)
        base = physics or PhysicsConfig(slots_per_leg=self.tspec.slots_per_leg)
        self.physics = physics_for(self.tspec.kind, base)
        self.sm = sim_model(self.robot, self.physics)
        self.gait = GaitController(self.robot, gait=gait)
        # the seed-000 gait at l = 6 cm, 0.25 s swings: 0.24 m/s (the paper's 0.036 m/s would make a 1 m
        # goal a 30 s episode)
        self.gait_params = self.gait.default_params().replace(step_length=jnp.float32(step_length),
                                                              swing_time=jnp.float32(swing_time))
        self.gait.validate_params(self.gait_params)
        self.dt = self.gait.dt
        self.n_sub = int(round(self.dt / self.physics.timestep))
        self.goal_distance, self.goal_spread = goal_distance, goal_spread
        self.residual, self.residual_scale = residual, residual_scale
        self.yaw_noise, self.friction_range = yaw_noise, tuple(friction_range)
        self.action_cost, self.fall_penalty, self.goal_bonus = action_cost, fall_penalty, goal_bonus
        self.weight = self.robot.total_mass * 9.81
        self._foot_sites = jnp.asarray(self.sm.foot_sites)
        self._ctrl0 = jnp.asarray(self.sm.ctrl0)
        self.sensors = SensorConfig()
        self._obs_size = int(jax.eval_shape(self.reset, jax.random.PRNGKey(0)).obs.shape[-1])

    # brax.envs.base.Env ---------------------------------------------------------------------------------
    @property
    def observation_size(self) -> int:
        return self._obs_size

    @property
    def action_size(self) -> int:
        return 18

    @property
    def backend(self) -> str:
        return "mjx"

    def _model(self, hs: HexState, d):
        slot_pos, slot_size = assign_slots(self.sm, hs.terrain, d.site_xpos[self._foot_sites, :2], d.qpos[:2])
        m = env_model(self.sm, hs.terrain, slot_pos, slot_size)
        # the robot's contacts are explicit <pair>s, which carry their own friction
        return m.replace(pair_friction=m.pair_friction * hs.friction)

    def reset(self, rng: jax.Array) -> State:
        k_t, k_yaw, k_goal, k_f = jax.random.split(rng, 4)
        terrain = sample_one(self.tspec, k_t)
        yaw = jax.random.uniform(k_yaw, (), minval=-self.yaw_noise, maxval=self.yaw_noise)
        goal = jnp.stack([jnp.asarray(self.goal_distance, jnp.float32),
                          jax.random.uniform(k_goal, (), minval=-self.goal_spread, maxval=self.goal_spread)])
        friction = jax.random.uniform(k_f, (), minval=self.friction_range[0], maxval=self.friction_range[1])
        d = self.sm.init_data(jnp.stack([0.0, 0.0, yaw]))
        hs = HexState(data=d, terrain=terrain, goal=goal, t=jnp.zeros(()), dist=jnp.linalg.norm(goal),
                      friction=friction)
        d = mjx.forward(self._model(hs, d), d)
        hs = hs.replace(data=d)
        obs = self._obs(hs, self._model(hs, d))
        zero = jnp.zeros(())
        metrics = {"progress": zero, "distance": hs.dist, "reached": zero, "fell": zero}
        return State(pipeline_state=hs, obs=obs, reward=zero, done=zero, metrics=metrics)

    def step(self, state: State, action: jax.Array) -> State:
        hs = state.pipeline_state
        a = jnp.clip(action, -1.0, 1.0)
        if self.residual:
            _, base = self.gait.step(self.gait_params, GaitState(t=hs.t), None)
        else:
            base = self._ctrl0
        d = hs.data.replace(ctrl=base + self.residual_scale * a)
        m = self._model(hs, d)
        d_new = jax.lax.fori_loop(0, self.n_sub, lambda _, dd: mjx.step(m, dd), d)
        finite = jnp.all(jnp.isfinite(d_new.qpos)) & jnp.all(jnp.isfinite(d_new.qvel))
        d_new = jax.tree_util.tree_map(lambda x, y: jnp.where(finite, x, y), d_new, hs.data)
        dist = jnp.linalg.norm(hs.goal - d_new.qpos[:2])
        up = _rotate_to_body(d_new.qpos[3:7], jnp.array([0.0, 0.0, 1.0]))
        height = d_new.qpos[2] - hs.terrain.ground_z
        fell = (up[2] < math.cos(math.radians(60.0))) | (height < 0.03) | ~finite
        reached = dist < 0.1
        progress = (hs.dist - dist) / self.dt
        reward = (progress - self.action_cost * jnp.sum(a * a) - self.fall_penalty * fell
                  + self.goal_bonus * reached)
        hs = hs.replace(data=d_new, t=hs.t + self.dt, dist=dist)
        obs = self._obs(hs, m)
        done = (fell | reached).astype(jnp.float32)
        metrics = dict(state.metrics)  # keep keys wrappers added (Brax's evaluator adds 'reward')
        metrics.update(progress=progress, distance=dist, reached=reached.astype(jnp.float32),
                       fell=fell.astype(jnp.float32))
        return state.replace(pipeline_state=hs, obs=obs, reward=reward, done=done, metrics=metrics)

    def _obs(self, hs: HexState, m) -> jax.Array:
        d = hs.data
        o = read_obs(self.sm, self.sensors, m, d)
        quat = d.qpos[3:7]
        up = _rotate_to_body(quat, jnp.array([0.0, 0.0, 1.0]))
        lin = _rotate_to_body(quat, d.qvel[:3])
        ang = d.qvel[3:6]  # MJX's free-joint angular velocity is already in the body frame
        goal_b = _rotate_to_body(quat, jnp.concatenate([hs.goal - d.qpos[:2], jnp.zeros(1)]))[:2]
        phase = 2 * math.pi * hs.t / (self.gait_params.swing_time * self.gait.pattern.period)
        return jnp.concatenate([
            o.qpos, 0.1 * o.qvel, (d.qpos[2] - hs.terrain.ground_z)[None], up, lin, ang,
            (o.foot_force / self.weight).reshape(-1), o.tactile.astype(jnp.float32), goal_b,
            hs.dist[None], jnp.stack([jnp.sin(phase), jnp.cos(phase)])])


def _device_put_replicated(x, devices):
    """`jax.device_put_replicated`, removed in jax 0.10 but still called by brax 0.14.2's PPO: each leaf stacked
    once per device along a new leading axis, that axis sharded over `devices` (the replacement the JAX pmap
    migration guide gives)."""
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec
    devices = list(devices)
    sharding = NamedSharding(Mesh(np.array(devices), ("d",)), PartitionSpec("d"))
    return jax.tree_util.tree_map(lambda a: jax.device_put(jnp.stack([jnp.asarray(a)] * len(devices)), sharding), x)


def train_ppo(env: HexapodGoalEnv, num_timesteps: int = 60_000, num_envs: int = 16, episode_length: int = 100,
              num_evals: int = 4, seed: int = 0, progress=None, **ppo_kwargs):
    """Brax PPO on `env`. Returns (eval history [(env steps, mean episode reward)], make_policy, params).
    Defaults are a smoke size for a 2-core CPU; raise num_timesteps / num_envs on a GPU."""
    from brax.training.agents.ppo import train as ppo
    if "device_put_replicated" not in vars(jax):  # brax 0.14.2 on jax >= 0.10 (see _device_put_replicated)
        jax.device_put_replicated = _device_put_replicated
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
    make_policy, params, _ = ppo.train(environment=env, **kw)
    return history, make_policy, params
