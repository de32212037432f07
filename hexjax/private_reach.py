"""Where hexjax reaches into other packages' private modules (`_src`), and the versions those reaches were
written against. A private module may change in any release, so `tests/test_private_reach.py` fails, naming
the files to re-read, when an installed version differs from the one here, and when a file reaches into a
package's private modules without being listed. The pins in constraints.txt keep `make setup` on these.

MJX's internals are all in `hexjax.sim.internals` (its package docstring says what each file patches or reads,
and `solver_context` is the one context a rollout's solve is traced under), MuJoCo Warp's CPU replay among them.
JAX's private modules are read by the compiled-program cache, the persistent cache and PPO.
"""

# package (distribution name) -> the version the reaches were written against
WRITTEN_FOR = {"mujoco-mjx": "3.17.0", "warp-lang": "1.18.0", "jax": "0.11.2"}

# the import prefix of each package's private modules, and the files that reach into them
PRIVATE = {"mujoco-mjx": ("mujoco.mjx._src", "mjx._src", "mujoco_warp._src"),
           "warp-lang": ("warp._src",),
           "jax": ("jax._src",)}
USERS = {
    "mujoco-mjx": ("hexjax/sim/internals/collide.py", "hexjax/sim/internals/contacts.py",
                   "hexjax/sim/internals/implicit.py", "hexjax/sim/internals/forward_mode.py",
                   "hexjax/sim/internals/rules.py", "hexjax/sim/internals/warp_cpu.py"),
    "warp-lang": ("hexjax/sim/internals/warp_cpu.py",),
    "jax": ("hexjax/sim/compiled.py", "hexjax/sim/internals/implicit.py", "hexjax/rl/ppo.py", "hexjax/cache.py"),
}
