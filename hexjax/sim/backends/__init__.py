"""Physics engines besides MJX's JAX implementation (MJX-Warp runs through `hexjax.sim.model` itself; `warp_cpu`
replays its recorded calls on a CPU)."""
