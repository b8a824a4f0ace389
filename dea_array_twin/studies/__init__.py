"""The paper's studies: coupled curves, coupling indices (eqs. 13-16), parameter sweeps, figures.

Holds the study tasks and their evaluation (:mod:`.tasks`) and the figures
(:mod:`.plots`, matplotlib imported when it draws); the executors that run the tasks
serially, on local processes or on a Dask cluster are :mod:`dea_array_twin.parallel`
(re-exported here).  May import the model, the config file reader and the executors;
not ROS, bags, replay, calibration or the ROM tools.
"""

from ..parallel import ExecutorError, run_tasks
from .tasks import (
    SWEEPS,
    CouplingIndices,
    CurveFailure,
    CurveResult,
    CurveTask,
    coupling_indices,
    coupling_tasks,
    curves_tasks,
    index_rows,
    run_curve,
    sweep_tasks,
    try_curve,
)

__all__ = ["SWEEPS", "CouplingIndices", "CurveFailure", "CurveResult", "CurveTask", "ExecutorError",
           "coupling_indices", "coupling_tasks", "curves_tasks", "index_rows", "run_curve", "run_tasks",
           "sweep_tasks", "try_curve"]
