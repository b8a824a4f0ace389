"""Finite-element digital twin of soft arrays of dielectric-elastomer transducers.

The numerical core (this package's top level) needs only numpy, scipy and gmsh::

    from dea_array_twin import ArrayConfig, ArrayTwin
    twin = ArrayTwin(ArrayConfig(prestretch=1.2))
    res = twin.solve(displacement=[0, 0.015, 0], modes=["free", "driven", "free"])
    res.force, res.capacitance            # N, F per unit
"""

from .config import ArrayConfig, ConfigError
from .configfile import load_config
from .model import DRIVEN, FREE
from .solver import ConvergenceError, NewtonSettings
from .twin import ArrayTwin, TwinResult

__all__ = ["ArrayConfig", "ArrayTwin", "ConfigError", "ConvergenceError", "DRIVEN", "FREE", "NewtonSettings",
           "TwinResult", "load_config"]
