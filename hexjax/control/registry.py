"""The controllers by name: one table that every command, experiment, the tuner and the scripts build from.

    make_controller("tactile", robot, gait="wave")      -> TactileGaitController(robot, gait="wave")
    ctrl, seconds = ctrl.for_distance(1.0)               the controller's own rule for a walk of 1 m

Each entry says everything a command needs of its controller: the factory, the robot preset it was written for
(the paper's robot), one line on what it is, the gaits it walks, its smooth gate's temperature field, the params
the tuner scales the walk by, the rule that fits its params to a terrain cell, and whether it walks from its
default params alone (render, robustness sweeps). The walk-length rule lives on the controller
(`Controller.for_distance`). Commands, the tuner and the experiments read these fields and never compare a
controller's name, so adding a controller is one entry here.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Callable, Dict, Optional, Tuple

from hexjax.control import cells  # numpy only: the table is read before JAX loads (a bad name answers at once)

if TYPE_CHECKING:
    from hexjax.control.base import Controller

# the gait patterns of the Luneckas 2020 gait (`hexjax.control.gait.GAITS`) and of the Yu 2019 CPG
# (`hexjax.control.cpg.params.CPG_GAITS`), written here so that configs are checked before JAX loads
LUNECKAS_GAITS = ("tripod", "wave")
CPG_GAITS = ("tripod", "tetrapod", "wave")
# the controller every other's cost is measured against (`hexjax bench`'s overhead column)
OPEN_LOOP = "gait"


@dataclasses.dataclass(frozen=True)
class ControllerEntry:
    """One controller. make(robot, gait=..., **fields) -> controller (no `gait` where `gaits` is empty).

    robot: the robot preset the controller was written for; about: one line; base: a learned reflex layer's
    entry names the controller it is laid over; gaits: the gait patterns it walks (empty: it plans its own steps);
    temperature: its params field that is the smooth gate's temperature (the tuner's `temperature`); period: its
    params field that sets the walk's pace (a tuner that does not tune it scales the walk's seconds by it);
    stops: its walk has a planned stop (the tuner walks `distance`, else `horizon` seconds); tune_fields: the
    tuning config's fields its factory takes; grad_iterations: the fewest solver iterations whose gradients agree
    with finite differences (docs/tuning.md); cell_params(ctrl, spec, terr, distance) -> (params, batched): its
    params for walks over one terrain cell (None: its defaults); family_params(ctrl, specs, batch): per-env params
    over several terrain families in one rollout (None: its defaults); walks_alone: it walks from its default
    params on any terrain (render); blind: the controller it is without its range sensor (the cost of perception
    is measured against it). A reflex entry's tuning fields are its base's (the tuner lays the layer over the base's
    hand-ruled controller)."""

    make: Callable[..., "Controller"]
    robot: str
    about: str
    base: Optional[str] = None
    gaits: Tuple[str, ...] = LUNECKAS_GAITS
    temperature: Optional[str] = None
    period: Optional[str] = None
    stops: bool = False
    tune_fields: Tuple[str, ...] = ()
    grad_iterations: int = 1
    cell_params: Optional[Callable] = None
    family_params: Optional[Callable] = None
    walks_alone: bool = False
    blind: Optional[str] = None

    @property
    def sweeps(self) -> bool:
        """A robustness sweep or the fidelity matrix can walk it: from its defaults or by its cell rule."""
        return self.walks_alone or self.cell_params is not None


def _gait(robot, gait="tripod", **kw):
    from hexjax.control.gait import GaitController
    return GaitController(robot, gait=gait, **kw)


def _tactile(robot, gait="tripod", **kw):
    from hexjax.control.tactile import TactileGaitController
    return TactileGaitController(robot, gait=gait, **kw)


def _cpg(robot, gait="tripod", **kw):
    from hexjax.control.cpg import CPGController
    return CPGController(robot, gait=gait, **kw)


def _avoid(robot, gait="tripod", **kw):
    from hexjax.control.avoid_gait import AvoidGaitController
    return AvoidGaitController(robot, gait=gait, **kw)


def _perceive(robot, gait="tripod", sensor="kinect_v1", **kw):
    from hexjax.control.perceive_gait import PerceivingAvoidGait
    from hexjax.perceive.sensors import get_sensor
    return PerceivingAvoidGait(robot, gait=gait, sensor=get_sensor(sensor) if isinstance(sensor, str) else sensor,
                               **kw)


def _support(robot, **kw):
    from hexjax.control.support_gait import SupportPlanController
    return SupportPlanController(robot, **kw)


def _perceive_support(robot, sensor="kinect_v1", **kw):
    from hexjax.control.perceive_support import PerceivingSupportPlan
    from hexjax.perceive.sensors import get_sensor
    return PerceivingSupportPlan(robot, sensor=get_sensor(sensor) if isinstance(sensor, str) else sensor, **kw)


def _reflex(base: str):
    """A factory of `base` under a learned reflex layer: the layer's fields (hidden, max_offset, seed) go to the
    layer, the others to the base controller."""
    def make(robot, gait="tripod", hidden=(32,), max_offset=0.3, seed=0, **kw):
        from hexjax.control.reflex import ReflexController
        return ReflexController(CONTROLLERS[base].make(robot, gait=gait, **kw), hidden=tuple(hidden),
                                max_offset=max_offset, seed=seed)
    return make


CONTROLLERS: Dict[str, ControllerEntry] = {
    "gait": ControllerEntry(_gait, "luneckas2020", "the Luneckas 2020 open-loop gait (Eqs. 2-4)",
                            period="swing_time", stops=True, walks_alone=True),
    "tactile": ControllerEntry(_tactile, "luneckas2020", "the gait with Luneckas 2020's tactile obstacle "
                               "overcoming (Eqs. 5-7)", temperature="temperature", period="swing_time", stops=True,
                               tune_fields=("max_obstacle_height",), cell_params=cells.tactile_cell,
                               family_params=cells.tactile_families, walks_alone=True),
    "cpg": ControllerEntry(_cpg, "yu2019", "the Yu 2019 CPG with its elevator and searching reflexes",
                           gaits=CPG_GAITS, temperature="temp_force", grad_iterations=4, walks_alone=True),
    "avoid": ControllerEntry(_avoid, "luneckas2020", "the gait steered by the Zhao 2018 avoidance planner round "
                             "the terrain's boxes", cell_params=cells.avoid_cell),
    "perceive": ControllerEntry(_perceive, "luneckas2020", "the avoiding gait steered by what a range sensor "
                                "perceives (Kinect V1 preset: scan, grid map, RANSAC, circles)", blind="avoid"),
    "support": ControllerEntry(_support, "chen2019", "Chen 2019 whole-body support planning on a known DEM "
                               "(footholds, torso height and pose; the params carry the DEM)", gaits=()),
    "perceive-support": ControllerEntry(_perceive_support, "chen2019", "Chen 2019 support planning on the DEM a "
                                        "range sensor perceives (Kinect V1 preset)", gaits=(), blind="support"),
    "cpg-reflex": ControllerEntry(_reflex("cpg"), "yu2019", "the Yu 2019 CPG under a learned reflex layer "
                                  "(joint-target offsets from the senses, zero at the start)", base="cpg",
                                  gaits=CPG_GAITS, walks_alone=True),
    "gait-reflex": ControllerEntry(_reflex("gait"), "luneckas2020", "the Luneckas 2020 gait under a learned reflex "
                                   "layer (joint-target offsets from the senses, zero at the start)", base="gait",
                                   walks_alone=True),
}


def entry(name: str) -> ControllerEntry:
    """The registry's entry `name`; an unknown name is one line naming the choices."""
    if name not in CONTROLLERS:
        raise ValueError(f"controller={name!r}: use one of {', '.join(CONTROLLERS)}")
    return CONTROLLERS[name]


def make_controller(name: str, robot, gait: Optional[str] = None, **fields) -> "Controller":
    """The controller `name` of `CONTROLLERS` for `robot` (a `RobotSpec`), walking `gait` (default: its first; a
    controller that plans its own steps takes none), with its other fields set."""
    e = entry(name)
    if not e.gaits:
        if gait is not None:
            raise ValueError(f"gait={gait!r}: the {name} controller plans its own steps; give no gait")
        return e.make(robot, **fields)
    return e.make(robot, gait=e.gaits[0] if gait is None else gait, **fields)


def paper_controller(name: str) -> str:
    """The paper's controller a registered controller runs: the one a reflex layer is laid over, or itself."""
    return CONTROLLERS[name].base or name if name in CONTROLLERS else name
