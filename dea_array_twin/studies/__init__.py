"""The paper's studies: coupled curves, coupling indices (eqs. 13-16), parameter sweeps, figures.

Holds the study tasks and their evaluation (:mod:`.tasks`), the executors that run
them serially, on local processes or on a Dask cluster (:mod:`.parallel`, Dask
imported when asked for) and the figures (:mod:`.plots`, matplotlib imported when it
draws).  May import the model and the config file reader; not ROS, bags, replay or
calibration.
"""

from .parallel import ExecutorError, run_tasks
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
