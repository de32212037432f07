from hexjax.control.base import Controller
from hexjax.control.gait import GAITS, GaitController, GaitParams, GaitState, leg_trajectory

__all__ = ["Controller", "GAITS", "GaitController", "GaitParams", "GaitState", "leg_trajectory"]
