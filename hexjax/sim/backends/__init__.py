"""Physics engines besides MJX: MuJoCo C (`mujoco_c`). MJX-Warp runs through `hexjax.sim.model` itself, with its
CPU replay in `hexjax.sim.internals.warp_cpu`."""
