"""Physics engines besides MJX's JAX implementation (MJX-Warp runs through `hexjax.sim.model` itself)."""
