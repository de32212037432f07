from hexjax.control.base import Controller
from hexjax.control.gait import GAITS, GaitController, GaitParams, GaitState, leg_trajectory
from hexjax.control.tactile import TactileGaitController, TactileParams, TactileState

__all__ = ["Controller", "GAITS", "GaitController", "GaitParams", "GaitState", "leg_trajectory",
           "TactileGaitController", "TactileParams", "TactileState"]
