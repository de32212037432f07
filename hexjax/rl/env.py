"""A Brax environment over the hexjax robot and terrain batch, for reinforcement learning (Brax PPO etc.): the
same control step as the rollout (`hexjax.sim.step`: terrain slots, sensors, substeps, the fall test).

`HexapodGoalEnv` follows `brax.envs.base.Env`: `reset(rng)` and `step(state, action)` on one env, vmapped by
Brax's wrappers. Each reset draws its own terrain from a `TerrainSpec` (domain randomisation: terrain, start
heading, goal position, the ground's friction coefficient), places the robot at the origin and a goal ahead of it, and
settles nothing (the robot starts in its stance keyframe). A step runs one control period: terrain slots
assigned to the feet, `n_sub` MJX steps (`hexjax.sim.step.env_view`, `physics`).

Actions: by default a residual on the Luneckas 2020 gait (Luneckas 2020 Eqs. 2-4, `GaitController`, tripod at
l = 6 cm and 0.25 s swings, 0.24 m/s): joint
target = gait IK target + `residual_scale` x clip(action, -1, 1), so a zero policy already walks; with
`residual=False` the action is the joint target offset from the stance keyframe.

Observation (75,): joint angles (18) and rates x 0.1 (18); torso height above the ground plane (1), the
world's up-vector in the torso frame (3), linear and angular velocity in the torso frame (6); each foot's
terrain force in the world frame / body weight (18); each shin's tactile pad on/off (6); the goal in the
torso frame (2) and its distance (1); the gait phase as (sin, cos) (2).

Reward per step: progress towards the goal (m/s) - `action_cost` |a|^2 - `fall_penalty` on falling, and
+ `goal_bonus` on reaching it. Done on a fall (the rollout's test, `hexjax.sim.step.fall_state`), a non-finite
state, or reaching the goal (within 10 cm). Everything episode-specific lives in `pipeline_state`, so Brax's
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
from hexjax.sim.config import PhysicsConfig, RolloutConfig, SensorConfig, physics_for, substeps
from hexjax.sim.engines import sim_model
from hexjax.sim.model import mjx, read_obs
from hexjax.sim.perturb import pair_friction_with
from hexjax.sim.step import env_view, fall_state, physics
from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import Terrain, sample_one


@struct.dataclass
class HexState:
    """What an episode carries: MJX data, its terrain, goal (2,) m, gait time t (s), distance to the goal (m),
    friction coefficient mu (domain randomisation; `hexjax.sim.perturb.pair_friction_with`)."""

    data: mjx.Data
    terrain: Terrain
    goal: jax.Array
    t: jax.Array
    dist: jax.Array
    friction: jax.Array


def _rotate_to_body(quat, v):
    """A world-frame vector v (3,) in the frame of the torso with unit orientation quat (w, x, y, z): v rotated
    by the conjugate quaternion (w, -u), r = 2 (u.v) u + (w^2 - u.u) v - 2 w (u x v)."""
    w, u = quat[0], -quat[1:]
    r = 2 * (jnp.dot(u, v) * u) + (w * w - jnp.dot(u, u)) * v
    return r + 2 * w * jnp.cross(u, v)


class HexapodGoalEnv(Env):
    """Walk to a goal `goal_distance` m ahead (lateral offset U(-goal_spread, goal_spread)) over randomised
    terrain. robot, terrain: a preset name, a .yaml path, or a `RobotSpec` / `TerrainSpec`. See the module
    docstring for observation, action and reward."""

    def __init__(self, robot="luneckas2020", terrain="flat", *, goal_distance: float = 1.0,
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
            raise ValueError(f"friction_range={friction_range!r}: need 0 < lo <= hi (the friction coefficient mu)")
        self.robot = get_robot(robot)
        self.tspec = get_terrain(terrain)
        base = physics or PhysicsConfig(slots_per_leg=self.tspec.slots_per_leg)
        self.physics = physics_for(self.tspec.kind, base)
        self.sm = sim_model(self.robot, self.physics)
        self.gait = GaitController(self.robot, gait=gait)
        # the Luneckas 2020 gait at l = 6 cm, 0.25 s swings: 0.24 m/s (the paper's 0.036 m/s would make a 1 m
        # goal a 30 s episode)
        self.gait_params = self.gait.default_params(step_length=step_length, swing_time=swing_time)
        self.gait.validate_params(self.gait_params)
        self.dt = self.gait.dt
        self.n_sub = substeps(self.physics, self.dt)
        self.fall = RolloutConfig()  # the rollout's fall test: tilt > 60 deg or torso centre below 3 cm
        self.goal_distance, self.goal_spread = goal_distance, goal_spread
        self.residual, self.residual_scale = residual, residual_scale
        self.yaw_noise, self.friction_range = yaw_noise, tuple(friction_range)
        self.action_cost, self.fall_penalty, self.goal_bonus = action_cost, fall_penalty, goal_bonus
        self.weight = self.robot.total_mass * 9.81
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

    def _view(self, hs: HexState, d):
        """(model, data, obs) of the episode at data d; the robot's contacts are explicit <pair>s, whose sliding
        friction is the episode's mu, as a `Perturbation`'s friction sets it."""
        base = self.sm.mjx_model
        base = base.replace(pair_friction=pair_friction_with(base.pair_friction, hs.friction))
        return env_view(self.sm, self.sensors, hs.terrain, d, base=base)

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
        d = mjx.forward(self._view(hs, d)[0], d)
        hs = hs.replace(data=d)
        obs = self._obs(hs, self._view(hs, d)[2])
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
        m, d, _ = self._view(hs, hs.data)
        d = d.replace(ctrl=base + self.residual_scale * a)
        d_new, finite = self.sm.engine.keep_finite(physics(m, d, self.n_sub)[0], d)
        dist = jnp.linalg.norm(hs.goal - d_new.qpos[:2])
        fell = fall_state(self.fall, d_new.qpos, hs.terrain.ground_z)[0] | ~finite
        reached = dist < 0.1
        progress = (hs.dist - dist) / self.dt
        reward = (progress - self.action_cost * jnp.sum(a * a) - self.fall_penalty * fell
                  + self.goal_bonus * reached)
        hs = hs.replace(data=d_new, t=hs.t + self.dt, dist=dist)
        obs = self._obs(hs, read_obs(self.sm, self.sensors, m, d_new))
        done = (fell | reached).astype(jnp.float32)
        metrics = dict(state.metrics)  # keep keys wrappers added (Brax's evaluator adds 'reward')
        metrics.update(progress=progress, distance=dist, reached=reached.astype(jnp.float32),
                       fell=fell.astype(jnp.float32))
        return state.replace(pipeline_state=hs, obs=obs, reward=reward, done=done, metrics=metrics)

    def _obs(self, hs: HexState, o) -> jax.Array:
        """The policy's observation vector (module docstring) from the episode and its sensor readings o."""
        d = hs.data
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
