import os

# Two host devices so the sharded-rollout test has a real mesh to split over; set before jax loads.
os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
os.environ.setdefault("JAX_PLATFORMS", "cpu")
