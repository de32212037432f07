"""The controllers by name: one table that every command, experiment, the tuner and the scripts build from.

    make_controller("tactile", robot, gait="wave")      -> TactileGaitController(robot, gait="wave")
    ctrl, seconds = ctrl.for_distance(1.0)               the controller's own rule for a walk of 1 m

Each entry names the factory, the robot preset it was written for (the paper's robot) and one line on what it
is. The walk-length rule lives on the controller (`Controller.for_distance`), so a new controller brings its
own and no caller keeps a chain of `isinstance` tests.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Dict, Optional

from hexjax.control.base import Controller


@dataclasses.dataclass(frozen=True)
class ControllerEntry:
    make: Callable[..., Controller]  # make(robot, gait=..., **fields) -> controller
    robot: str  # the robot preset the controller was written for
    about: str
    base: Optional[str] = None  # a learned reflex layer's controller: the entry it is laid over


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


def _reflex(base: str):
    """A factory of `base` under a learned reflex layer: the layer's fields (hidden, max_offset, seed) go to the
    layer, the others to the base controller."""
    def make(robot, gait="tripod", hidden=(32,), max_offset=0.3, seed=0, **kw):
        from hexjax.control.reflex import ReflexController
        return ReflexController(CONTROLLERS[base].make(robot, gait=gait, **kw), hidden=tuple(hidden),
                                max_offset=max_offset, seed=seed)
    return make


CONTROLLERS: Dict[str, ControllerEntry] = {
    "gait": ControllerEntry(_gait, "luneckas2020", "the Luneckas 2020 open-loop gait (Eqs. 2-4)"),
    "tactile": ControllerEntry(_tactile, "luneckas2020", "the gait with Luneckas 2020's tactile obstacle "
                               "overcoming (Eqs. 5-7)"),
    "cpg": ControllerEntry(_cpg, "yu2019", "the Yu 2019 CPG with its elevator and searching reflexes"),
    "avoid": ControllerEntry(_avoid, "luneckas2020", "the gait steered by the Zhao 2018 avoidance planner round "
                             "the terrain's boxes"),
    "perceive": ControllerEntry(_perceive, "luneckas2020", "the avoiding gait steered by what a range sensor "
                                "perceives (Kinect V1 preset: scan, grid map, RANSAC, circles)"),
    "cpg-reflex": ControllerEntry(_reflex("cpg"), "yu2019", "the Yu 2019 CPG under a learned reflex layer "
                                  "(joint-target offsets from the senses, zero at the start)", base="cpg"),
    "gait-reflex": ControllerEntry(_reflex("gait"), "luneckas2020", "the Luneckas 2020 gait under a learned reflex "
                                   "layer (joint-target offsets from the senses, zero at the start)", base="gait"),
}


def make_controller(name: str, robot, gait: str = "tripod", **fields) -> Controller:
    """The controller `name` of `CONTROLLERS` for `robot` (a `RobotSpec`), with its other fields set."""
    if name not in CONTROLLERS:
        raise ValueError(f"controller={name!r}: use one of {', '.join(CONTROLLERS)}")
    return CONTROLLERS[name].make(robot, gait=gait, **fields)


def paper_controller(name: str) -> str:
    """The paper's controller a registered controller runs: the one a reflex layer is laid over, or itself."""
    return CONTROLLERS[name].base or name if name in CONTROLLERS else name
