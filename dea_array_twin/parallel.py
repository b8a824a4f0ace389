"""Run independent tasks in this process, on local worker processes or on a Dask cluster.

Studies (:class:`~dea_array_twin.studies.tasks.CurveTask`) and ROM training snapshots
(:mod:`dea_array_twin.rom.train`) are lists of independent, deterministic tasks, so the
executor only decides where they run: results come back in task order and are
identical whichever executor ran them.  Imports nothing of the package, so every
tool layer can use it.
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from typing import Callable, Iterator, Sequence, TypeVar

T = TypeVar("T")
R = TypeVar("R")

#: BLAS/OpenMP thread variables set to 1 in worker processes: each worker is one core.
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


class ExecutorError(RuntimeError):
    """The executor could not run the tasks (cluster unreachable, worker lacks the package...)."""


@contextmanager
def _single_threaded_children() -> Iterator[None]:
    """Environment for spawned workers: one BLAS thread each (restored afterwards)."""
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update({k: "1" for k in _THREAD_VARS})
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def run_tasks(function: Callable[[T], R], tasks: Sequence[T], workers: int = 1, scheduler: str | None = None,
              progress: Callable[[int], None] | None = None, connect_timeout: float = 10.0) -> list[R]:
    """``[function(t) for t in tasks]``, in task order, on the chosen executor.

    Parameters
    ----------
    function : callable
        A module-level (picklable) function of one task.
    tasks : sequence
        Picklable tasks.
    workers : int
        1: run here, one after the other; N > 1: N local worker processes (spawned,
        one BLAS thread each).  Ignored when ``scheduler`` is given.
    scheduler : str, optional
        Address of a Dask distributed scheduler (``tcp://host:8786``); its workers
        must have ``dea_array_twin`` installed, in the same version.
    progress : callable, optional
        Called with the number of tasks finished so far, after each one.
    connect_timeout : float
        How long to try to reach ``scheduler`` [s].

    Raises
    ------
    ExecutorError
        The scheduler cannot be reached or Dask is not installed.
    Exception
        Whatever a task raised (the first failure, re-raised here).
    """
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    report = progress or (lambda done: None)
    if scheduler is not None:
        return _run_dask(function, tasks, scheduler, report, connect_timeout)
    if workers == 1 or len(tasks) <= 1:
        results = []
        for task in tasks:
            results.append(function(task))
            report(len(results))
        return results
    context = multiprocessing.get_context("spawn")  # no fork of a process holding gmsh/BLAS threads
    with _single_threaded_children(), ProcessPoolExecutor(min(workers, len(tasks)), mp_context=context) as pool:
        futures = {pool.submit(function, task): i for i, task in enumerate(tasks)}
        results: list = [None] * len(tasks)
        for done, future in enumerate(as_completed(futures), start=1):
            results[futures[future]] = future.result()
            report(done)
    return results


def _run_dask(function: Callable[[T], R], tasks: Sequence[T], scheduler: str,
              report: Callable[[int], None], connect_timeout: float) -> list[R]:
    """The Dask branch of :func:`run_tasks`."""
    try:
        from distributed import Client
        from distributed import as_completed as dask_completed
    except ImportError:
        raise ExecutorError("--scheduler needs Dask: pip install 'dask[distributed]' "
                            "(or this package's [cluster] extra)") from None
    try:
        client = Client(scheduler, timeout=connect_timeout)
    except (OSError, TimeoutError) as exc:
        raise ExecutorError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
    with client:
        futures = client.map(function, list(tasks), pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        results: list = [None] * len(tasks)
        for done, future in enumerate(dask_completed(futures), start=1):
            try:
                results[index[future.key]] = future.result()
            except ModuleNotFoundError as exc:
                raise ExecutorError(f"a Dask worker cannot import {exc.name!r}: install dea_array_twin "
                                    "(same version) on every worker") from None
            report(done)
    return results
