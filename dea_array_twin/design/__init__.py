"""Bias design for the whole array: each unit's bias element for the largest guaranteed stroke.

The design (:func:`.bias_design.design_bias`) chooses bias parameters from a family
(:mod:`.families`) that maximise the smallest stroke over operating scenarios
(:mod:`.scenarios`), on an inner model built from the twin's swept force curves
(:mod:`.inner`), optimised by :mod:`.optimise` and verified with full biased solves
(:mod:`.solves`); reports and figures are :mod:`.report` and :mod:`.plots`.  May import
the model, the config file reader and the executors; not ROS, bags, replay, studies,
calibration or the ROM tools.
"""

from .bias_design import BiasDesign, DesignSettings, design_bias
from .families import FAMILIES, Ranges
from .scenarios import Scenario, scenarios

__all__ = ["FAMILIES", "BiasDesign", "DesignSettings", "Ranges", "Scenario", "design_bias", "scenarios"]
