"""Finite-element digital twin of soft arrays of dielectric-elastomer transducers.

The public API is flat and needs only numpy, scipy and gmsh::

    from dea_array_twin import ArrayConfig, ArrayTwin
    twin = ArrayTwin(ArrayConfig(prestretch=1.2))
    res = twin.solve(displacement=[0, 0.015, 0], modes=["free", "driven", "free"])
    res.force, res.capacitance            # N, F per unit

and actuator mode (biased units: voltages in, stroke and capacitance out)::

    cfg = ArrayConfig(unit_modes=["free", "biased", "free"],
                      bias=[{"type": "linear", "stiffness": 40.0, "free_position": 0.020}])
    curve = stroke(ArrayTwin(cfg), [0.0, 2730.0])   # quasi-static, per level
    curve.stroke, curve.capacitance, curve.stable, curve.snap

The subpackages, lowest layer first (each may import only those below it; checked by
``lint-imports``, contracts in ``.importlinter``):

* :mod:`.model`: the numerical core (config, mesh, material, FE assembly, solver, twin);
* :mod:`.configfile`, :mod:`.romfile`, :mod:`.parallel`, :mod:`.blasthreads`: the config
  from YAML files, reduced models as ``.npz`` files, running independent tasks (here,
  processes, Dask), holding the process's BLAS to one thread (the ROM node);
* :mod:`.bag`: ROS 2-profile MCAP files: writing, reading, recovery, time series;
* :mod:`.ros`: the ROS 2 node, its recorder, the test harness, example controllers;
* :mod:`.replay`, :mod:`.studies`, :mod:`.calibration`, :mod:`.rom`: re-simulating
  bags, the paper's studies, fitting the material model, training reduced models
  (independent of each other);
* :mod:`.cli`: the ``dea-twin`` command.
"""

from .configfile import load_config
from .model import (
    BIASED,
    DRIVEN,
    FREE,
    ArrayConfig,
    ArrayTwin,
    ConfigError,
    ConvergenceError,
    NewtonSettings,
    ReducedTwin,
    SolveCancelled,
    TwinResult,
    simulate,
    stroke,
)
from .romfile import load_rom, save_rom

__all__ = ["ArrayConfig", "ArrayTwin", "BIASED", "ConfigError", "ConvergenceError", "DRIVEN", "FREE", "NewtonSettings",
           "ReducedTwin", "SolveCancelled", "TwinResult", "load_config", "load_rom", "save_rom", "simulate", "stroke"]
