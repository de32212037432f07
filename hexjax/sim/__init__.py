"""The simulator: from specs to a batched rollout (docs/architecture.md).

config    PhysicsConfig, SensorConfig, RolloutConfig (static, hashable)
mjcf      the robot's MJCF with terrain slots and contact pairs
model     MjModel / mjx.Model, per-env terrain slots, sensor readings (Obs)
step      THE control step: env view, controller, physics substeps, summary accumulators
grad      gradient truncation and bounds of the control step
compiled  ahead-of-time compiled rollouts and their compile time
rollout   rollout(): scan, vmap, jit, sharding; backends
backends  mujoco_c: the same control step with MuJoCo C physics on host threads
"""
