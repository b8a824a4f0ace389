"""Fitting the model to measurements: the Yeoh coefficients and the slip table of eq. 11.

Holds measured curves and the twin's answers to them (:mod:`.measured`), the
Nelder-Mead fit of ``c10, c20, c30`` (:mod:`.yeoh`), the fit of the slip table
(:mod:`.slip`) and the readers of measured data from CSV files and bags
(:mod:`.data`).  The fits do no I/O; only :mod:`.data` reads files.  May import the
model, the config file reader and the bag layer; not ROS, replay, studies or the CLI.
"""

from .measured import MeasuredCurve, simulate
from .slip import SlipFit, fit_slip
from .yeoh import YeohFit, fit_yeoh

__all__ = ["MeasuredCurve", "SlipFit", "YeohFit", "fit_slip", "fit_yeoh", "simulate"]
