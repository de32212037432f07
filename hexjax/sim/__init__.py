"""The simulator: from specs to a batched rollout (docs/architecture.md).

config    PhysicsConfig, SensorConfig, RolloutConfig (static, hashable)
mjcf      the robot's MJCF with terrain slots and contact pairs
model     MjModel / mjx.Model, per-env terrain slots, sensor readings (Obs)
step      THE control step: env view, controller, physics substeps, summary accumulators
grad      gradient truncation and bounds of the control step
compiled  ahead-of-time compiled rollouts and their compile time
physics   presets and the one physics value a command runs (`pick`: settings + engine)
rollout   rollout(): checks a call and dispatches it to its engine
engines   mjx, warp, c: one file an engine behind one protocol, each saying what it can do
"""
