"""The numerical core: the membrane model of section 4 of the paper and the twin built on it.

Holds the typed configuration (:mod:`.config`), the reference geometry and gmsh mesh
(:mod:`.geometry`, :mod:`.mesh`), the Yeoh plus electrostatic material
(:mod:`.material`), elements and vectorised assembly (:mod:`.elements`,
:mod:`.assembly`), the boundary conditions and outputs of one array
(:mod:`.membrane`), the Newton solver (:mod:`.solver`), the twin with its warm state
(:mod:`.twin`), the FIT metric (:mod:`.metrics`), the reduced-order model
(:mod:`.reduced`, :mod:`.rom_build`, :mod:`.ecsw`, :mod:`.rom_kernels`) with its twin
(:mod:`.reduced_twin`), and actuator mode: bias laws (:mod:`.bias`), biased heights
bordering Newton (:mod:`.indenters`), snap-through (:mod:`.snap`), what pushes an
indenter (:mod:`.actuator`), Newmark dynamics (:mod:`.dynamics`), stroke and time
response (:mod:`.response`).  Arrays in, arrays out: it
imports numpy, scipy and gmsh only, never rclpy, mcap, matplotlib, dask or YAML, and
reads or writes no files, so a designer can use it from a notebook and every layer
above is a thin adapter.
"""

from .config import ArrayConfig, ConfigError
from .membrane import BIASED, DRIVEN, FREE, MembraneModel, check_modes
from .reduced import Envelope, ReducedModel, RomMismatchError
from .reduced_twin import ReducedResult, ReducedTwin
from .response import simulate, stroke
from .solver import ConvergenceError, NewtonSettings, SolveCancelled
from .twin import ArrayTwin, TwinResult, command_error

__all__ = ["ArrayConfig", "ArrayTwin", "BIASED", "ConfigError", "ConvergenceError", "DRIVEN", "Envelope", "FREE",
           "MembraneModel", "NewtonSettings", "ReducedModel", "ReducedResult", "ReducedTwin", "RomMismatchError",
           "SolveCancelled", "TwinResult", "check_modes", "command_error", "simulate", "stroke"]
