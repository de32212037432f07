"""MuJoCo Warp through MJX: MuJoCo's own collision and solver kernels on a CUDA GPU (or a CPU), forward only.

The rollout is the MJX engine's (`mjx.py`); what differs:
- Build: the model declares MuJoCo's contact sensors and is put with `impl='warp'`; one empty Data is made for
  the whole batch, whose contact pool the worlds share (`SimModel.warp_pools`).
- Step: MuJoCo Warp computes the world poses of static geoms once, so moved slots get their `geom_xpos` set
  (`hexjax.sim.model.place_static_geoms`) and their bounding volumes (it culls pairs by them); the sensors are
  MuJoCo's own (`obs_from_sensordata`); a step that goes non-finite restores the state fields alone (the
  contact pool is shared, so a per-env select over the whole Data is not possible).
- Overflow: MuJoCo Warp prints a line from the device each time a world's line search or Newton loop ends at its
  limit. The prints are compiled out (`quiet_overflow`) and each world's flags are read at the end of the walk
  instead: `Summary.overflow`, counted per rollout (`overflow_counts`) and written into results' JSON.
- Quiet: Warp's own messages (a line per module compiled, the CUDA driver's absence on a CPU host) are off
  unless `HEXJAX_WARP_VERBOSE=1`.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from typing import Dict, Optional

import jax
import jax.numpy as jnp
import numpy as np

from hexjax.sim.engines.base import RANGE_SENSORS, TRACES
from hexjax.sim.engines.mjx import MJX, state_finite
from hexjax.sim.model import obs_from_sensordata, place_static_geoms
from hexjax.sim.step import STATE_FIELDS


@dataclasses.dataclass(frozen=True)
class Warp(MJX):
    contact_sensors: bool = True
    keeps_programs: bool = False  # a program holding Warp's kernels does not export
    data_template: bool = True

    def put_model(self, mj_model):
        if not self.available():
            raise RuntimeError(f"the warp engine needs the warp-lang package: {self.install}")
        quiet_warp()
        from mujoco.mjx import warp as mjx_warp
        if not mjx_warp.WARP_INSTALLED:
            raise RuntimeError(f"mujoco-mjx does not find warp-lang: {self.install}")
        from hexjax.sim.internals import warp_cpu
        from hexjax.sim.internals.contacts import quiet_overflow
        from hexjax.sim.internals.rules import mjx
        warp_cpu.enable()  # on a CPU, Warp's calls are recorded once and replayed (internals/warp_cpu.py)
        return quiet_overflow(mjx.put_model(mj_model, impl="warp"))

    def make_data(self, sm, batch: int = 1):
        """An empty mjx.Data whose contact pool the worlds of a vmap of size `batch` share."""
        from hexjax.sim.internals.rules import mjx
        return mjx.make_data(sm.mj_model, impl="warp", **sm.warp_pools(batch))

    def place_slots(self, m, ids, geom_pos, geom_size, slot_size):
        # MuJoCo Warp culls pairs by each geom's bounding sphere and box, compiled for the placeholder slot:
        # they follow the slot's size (a box's bounding box is centred on it, half sizes = its half sizes)
        rbound = m.geom_rbound.at[ids].set(jnp.linalg.norm(slot_size, axis=-1))
        aabb = m.geom_aabb.at[ids, 0].set(0.0).at[ids, 1].set(slot_size)
        return m.replace(geom_pos=geom_pos, geom_size=geom_size, geom_rbound=rbound, geom_aabb=aabb)

    def observe(self, sm, sensors, terrain, m, d, slot_pos):
        d = place_static_geoms(sm, d, terrain, slot_pos)
        return d, obs_from_sensordata(sensors, d.qpos, d.qvel, d.sensordata, d.time)

    def detach(self, d):
        return d  # no gradients

    def keep_finite(self, d_new, d):
        finite = state_finite(d_new)
        return d_new.replace(**{f: jnp.where(finite, getattr(d_new, f), getattr(d, f)) for f in STATE_FIELDS}), finite

    def overflow(self, d):
        from hexjax.sim.internals.contacts import overflow_flags
        return overflow_flags(d)


# bytes_per_env: XLA's buffers of the compiled forward rollout, the Data pools MuJoCo Warp's kernels write
# included, grow by 82,690 bytes an env from B = 32 to 64 (2 CPU cores)
WARP_ENGINE = Warp(name="warp", title="MuJoCo Warp", precision="float32", can=frozenset({RANGE_SENSORS, TRACES}),
                   hosts=("gpu", "cpu"), culls=True, bytes_per_env=82_690, package="warp",
                   install="pip install 'hexjax[warp]' (or make warp), then run again")


def quiet_warp() -> None:
    """Warp's messages off (a line per module it compiles, the CUDA driver's absence on a CPU host) unless
    HEXJAX_WARP_VERBOSE=1; set before Warp initialises, which is when it says the second. That one Warp's C++
    writes to stderr whatever its settings, so on a host where JAX sees no GPU Warp is initialised with stderr
    sent to /dev/null."""
    import warp as wp
    quiet = os.environ.get("HEXJAX_WARP_VERBOSE", "") in ("", "0")
    wp.config.quiet = quiet
    if quiet and hasattr(wp, "LOG_WARNING"):  # a module's load time is logged at the INFO level
        wp.config.log_level = wp.LOG_WARNING
    if quiet and jax.default_backend() == "cpu":  # wp.init() does nothing once Warp is initialised
        sys.stderr.flush()
        saved = os.dup(2)
        try:
            with open(os.devnull, "w") as null:
                os.dup2(null.fileno(), 2)
                wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def overflow_counts(flags, physics) -> Optional[Dict[str, int]]:
    """How many envs of a rollout hit each of MuJoCo Warp's limits at least once, from `Summary.overflow`
    (B,) (None: the engine keeps no flags): the line search's (`physics.ls_iterations` steps), the Newton
    loop's (`physics.iterations`), and any other (contacts or constraint rows beyond the pools)."""
    if flags is None:
        return None
    from hexjax.sim.internals.contacts import OVERFLOW_ITERATIONS, OVERFLOW_LS_ITERATIONS
    f = np.asarray(jax.device_get(flags)).astype(np.int64)
    other = ~(OVERFLOW_ITERATIONS | OVERFLOW_LS_ITERATIONS)
    return dict(envs=int(f.size), line_search_limit=int(np.count_nonzero(f & OVERFLOW_LS_ITERATIONS)),
                iteration_limit=int(np.count_nonzero(f & OVERFLOW_ITERATIONS)),
                other=int(np.count_nonzero(f & other)), ls_iterations=physics.ls_iterations,
                iterations=physics.iterations)


def overflow_line(counts: Dict[str, int]) -> str:
    """One line for a rollout's overflow counts."""
    return (f"MuJoCo Warp: {counts['line_search_limit']:,} of {counts['envs']:,} envs ended a line search at its "
            f"limit ({counts['ls_iterations']} steps) and {counts['iteration_limit']:,} a Newton solve at its limit "
            f"({counts['iterations']} iterations) at least once" + (
                f"; {counts['other']:,} overflowed a contact or row pool" if counts["other"] else ""))
