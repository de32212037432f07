"""Where hexjax reaches into other packages' private modules (`_src`), and the versions those reaches were
written against. A private module may change in any release, so `tests/test_private_reach.py` fails, naming
the files to re-read, when an installed version differs from the one here, and when a file reaches into a
package's private modules without being listed. The pins in constraints.txt keep `make setup` on these.

MJX's internals are patched at trace time in `hexjax.sim.mjx_rules` (the reversible solver, the rotation and
integrator rules, swapped in by context managers); `hexjax.sim.implicit` and `hexjax.sim.forward_mode` read
MJX's solver and constraint code to differentiate it; `hexjax.sim.model` reads MJX's collision driver and
contact forces; `hexjax.sim.backends.warp_cpu` replays Warp's calls on a CPU.
"""

# package (distribution name) -> the version the reaches were written against
WRITTEN_FOR = {"mujoco-mjx": "3.17.0", "warp-lang": "1.18.0", "jax": "0.11.2"}

# the import prefix of each package's private modules, and the files that reach into them
PRIVATE = {"mujoco-mjx": ("mujoco.mjx._src", "mjx._src", "mujoco_warp._src"),
           "warp-lang": ("warp._src",),
           "jax": ("jax._src",)}
USERS = {
    "mujoco-mjx": ("hexjax/sim/model.py", "hexjax/sim/implicit.py", "hexjax/sim/forward_mode.py",
                   "hexjax/sim/mjx_rules.py", "hexjax/sim/backends/warp_cpu.py", "hexjax/rl/env.py"),
    "warp-lang": ("hexjax/sim/backends/warp_cpu.py",),
    "jax": ("hexjax/sim/compiled.py", "hexjax/sim/implicit.py", "hexjax/rl/ppo.py", "hexjax/cache.py"),
}
