"""What every engine is: a name, what it can do, and one way to roll out a batch.

An engine steps the physics of a rollout; the control step around it (controller, sensors, summary,
`hexjax.sim.step`) is the same for all. Callers ask an engine what it can do (`Engine.can`) and never compare
its name: a job that needs gradients asks for `GRADIENTS`, one that records foot traces for `TRACES`, and
`hexjax.sim.physics.pick` keeps only the engines that can.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
from typing import FrozenSet, Optional, Tuple

# What a job may need of an engine (`Engine.can`)
GRADIENTS = "gradients"  # reverse and forward mode through the physics (`hexjax.sim.rollout.rollout_function`)
MESH = "device mesh"  # envs sharded over several devices (`rollout(mesh=...)`)
RANGE_SENSORS = "range sensors"  # a controller that casts rays at the terrain in its control step
TRACES = "traces"  # every per-step trace (feet, controller, joints, forces), not the torso's alone
CAPABILITIES = (GRADIENTS, MESH, RANGE_SENSORS, TRACES)


def host_cores() -> int:
    """The CPU cores this process may run on: its affinity mask, capped by a cgroup's CPU quota (a container
    sees the whole machine's cores in `os.cpu_count()`, and a pool of that many threads on a 16-core share
    spends its time switching)."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    for path, parse in (("/sys/fs/cgroup/cpu.max", lambda s: s.split()),  # cgroup v2: "quota period"
                        ("/sys/fs/cgroup/cpu/cpu.cfs_quota_us", lambda s: [s.strip(), None])):  # v1
        try:
            with open(path) as f:
                quota, period = parse(f.read())
            if quota in ("max", "-1"):
                break
            if period is None:
                with open("/sys/fs/cgroup/cpu/cpu.cfs_period_us") as f:
                    period = f.read().strip()
            n = min(n, max(1, int(int(quota) // int(period))))
            break
        except (OSError, ValueError):
            continue
    return max(1, n)


@dataclasses.dataclass(frozen=True)
class Engine:
    """One engine (`hexjax.sim.engines.ENGINES`). name: its word on the command line and in JSONs; title: its
    full name; precision: of its state; can: what it can do (`CAPABILITIES`); hosts: the platforms it runs on
    ('cpu', 'gpu'); package: the module it needs beyond hexjax's own dependencies, with `install` saying how to
    get it; culls: whether it collides each leg with a few terrain-box slots (MJX's fixed pair list) rather
    than every box (a broadphase); bytes_per_env: the memory one env of a forward rollout holds where the engine
    runs (accelerator memory, or the host's for MuJoCo C), as measured on the tactile gait over `high-large` at
    `validated`'s settings (`hexjax.experiments.runner.check_batch_memory` sizes a batch by it);
    grad_bytes_per_env_step: for an engine with `GRADIENTS`, the memory of the windowed value-and-gradient
    program per env and control step, as measured by `hexjax bench --grad` (a gradient batch is sized by it
    before anything compiles: `hexjax.sim.memory`); keeps_programs: whether its compiled rollouts export and are
    kept on disk (`hexjax.sim.compiled`), so that a caller may hold one as a pure function."""

    name: str
    title: str
    precision: str
    can: FrozenSet[str]
    hosts: Tuple[str, ...]
    culls: bool
    bytes_per_env: int = 512 * 1024
    grad_bytes_per_env_step: Optional[int] = None
    package: Optional[str] = None
    install: str = ""
    keeps_programs: bool = False

    @property
    def host_only(self) -> bool:
        """Whether it steps on the host's cores alone (its controller steps then stay on the host too)."""
        return "gpu" not in self.hosts

    def available(self) -> bool:
        """Whether this process can step physics on this engine (its package is importable)."""
        return self.package is None or importlib.util.find_spec(self.package) is not None

    def lacks(self, needs) -> Tuple[str, ...]:
        """Which of `needs` (capabilities) this engine cannot do, in `CAPABILITIES` order."""
        return tuple(n for n in CAPABILITIES if n in set(needs) and n not in self.can)

    def settings(self, physics) -> str:
        """What a header says of the settings this engine runs (`physics`: a `PhysicsConfig`, slots unresolved
        or not)."""
        own = lambda v: "the terrain's own" if v is None else v
        boxes = (f"{own(physics.slots_per_leg)} box slots a leg, {own(physics.torso_slots)} for the torso"
                 if self.culls else "every terrain box a geom")
        return (f"{self.precision}, {physics.iterations} Newton iterations (tolerance {physics.tolerance:g}), "
                f"{physics.ls_iterations} line-search steps, {physics.cone} cone, impratio {physics.impratio:g}, "
                f"timestep {1e3 * physics.timestep:g} ms, {boxes}")

    def prepare(self, robot, physics) -> None:
        """Build what a rollout of `robot` under `physics` (a `PhysicsConfig`) needs ahead of it, so that no timed
        rollout includes it (the MJX family's device model; MuJoCo C's are made per call)."""

    def rollout(self, robot, terrain, controller, params, n_ctrl: int, keys, *, physics, sensors, config,
                params_batched: bool, mesh, nthread, perturbation):
        """(Summary, seconds compiling, where the program came from: 'compiled', 'disk' or 'process') of a
        batch checked by `hexjax.sim.rollout.rollout`."""
        raise NotImplementedError
