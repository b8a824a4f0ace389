"""The FE behind a reduced twin: the latest command re-solved by the FE in a background thread.

With ``model: rom`` the node's solver thread runs a
:class:`~dea_array_twin.model.reduced_twin.ReducedTwin`; :class:`FeCheck` takes the
latest reduced result (:meth:`FeCheck.post`, called after each update), and at most
``rate`` times a second solves the same command with its own
:class:`~dea_array_twin.model.twin.ArrayTwin` (warm from its previous check), and
records the difference: the largest force difference over each unit's force reference
(the ROM's ``force_reference``) and the largest relative capacitance difference.  A
difference above the ROM's tolerance hands the FE result to ``resync`` (the reduced
twin restarts from the FE state projected on its basis at its next update, see
:meth:`~dea_array_twin.model.reduced_twin.ReducedTwin.request_resync`); the node
publishes the numbers in ``/diagnostics``.  Results the FE itself answered (a
fallback) are not checked, nor states in motion (a time step with a velocity: not a
quasi-static equilibrium the FE could re-solve).  Biased units are re-solved with the
result's external forces.  No rclpy here.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from ..model.config import ArrayConfig
from ..model.solver import ConvergenceError, NewtonSettings
from ..model.twin import ArrayTwin, TwinResult


@dataclass(frozen=True)
class CheckStats:
    """What the FE check found (differences relative: force over its reference, capacitance over C).

    ``last_*`` are of the latest check, ``max_*`` over all checks; NaN before the first.
    """

    checks: int = 0
    resyncs: int = 0
    failures: int = 0
    last_force_difference: float = math.nan
    last_capacitance_difference: float = math.nan
    max_force_difference: float = math.nan
    max_capacitance_difference: float = math.nan
    last_check_ms: float = math.nan
    last_error: str = ""


class FeCheck:
    """Re-solves the latest reduced result's command with the FE, at most ``rate`` times a second.

    Parameters
    ----------
    config : ArrayConfig
        The array (the FE twin of the check is built from it).
    force_reference : ndarray
        Full scale of each unit's force [N] (the ROM's ``force_reference``).
    tolerance : float
        Relative difference above which ``resync`` is called.
    rate : float
        Checks per second (> 0).
    resync : callable
        ``resync(fe_result)`` when the difference exceeds ``tolerance`` (on this thread).
    log : callable
        ``log(key, text)`` for warnings.
    """

    def __init__(self, config: ArrayConfig, force_reference: np.ndarray, tolerance: float, rate: float,
                 resync: Callable[[TwinResult], None], log: Callable[[str, str], None]):
        if not rate > 0:
            raise ValueError(f"FE check rate must be > 0, got {rate}")
        self.fe = ArrayTwin(config, NewtonSettings(check_stability=False))
        self.force_reference = np.asarray(force_reference, float)
        self.tolerance, self.period = float(tolerance), 1.0 / rate
        self._resync, self._log = resync, log
        self._cond = threading.Condition()
        self._latest: TwinResult | None = None
        self._idle = False  # the thread waits for a result (not for the next check time): post wakes it
        self._config = config
        self._stopping = False
        self._stats = CheckStats()
        self._thread = threading.Thread(target=self._run, name="fe-check", daemon=True)

    def start(self) -> None:
        """Start the check thread."""
        self._thread.start()

    def stop(self) -> None:
        """Stop the check thread (waits for a check under way)."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        if self._thread.is_alive():
            self._thread.join()

    def set_config(self, cfg: ArrayConfig) -> None:
        """The run-time command limits changed (the FE of the check uses them from its next solve)."""
        with self._cond:
            self._config = cfg

    def post(self, result: TwinResult) -> None:
        """The newest result of the reduced twin (replaces one not yet checked).

        Wakes the check thread only when it waits for a result: one that waits for the
        time of its next check takes the newest result then (at 1 kHz, a wake-up per post
        cost the solver thread a thread switch and a GIL hand-over per update)."""
        if getattr(result, "fallback", "") or np.any(result.velocity):
            return  # the FE answered it already, or it is a state in motion
        with self._cond:
            self._latest = result
            if self._idle:
                self._cond.notify_all()

    def stats(self) -> CheckStats:
        """A copy of the counters and differences."""
        with self._cond:
            return self._stats

    def _run(self) -> None:
        next_check = time.monotonic()
        while True:
            with self._cond:
                while not self._stopping and (self._latest is None or time.monotonic() < next_check):
                    self._idle = self._latest is None
                    self._cond.wait(timeout=None if self._idle else max(0.0, next_check - time.monotonic()))
                self._idle = False
                if self._stopping:
                    return
                result, self._latest = self._latest, None
                self.fe.config = self._config
            next_check = time.monotonic() + self.period
            self._check(result)

    def _check(self, result: TwinResult) -> None:
        tic = time.perf_counter()
        try:
            fe = self.fe.solve(result.displacement, result.voltage, result.modes, force=result.external_force)
        except (ConvergenceError, ValueError) as exc:
            with self._cond:
                self._stats = replace(self._stats, failures=self._stats.failures + 1, last_error=str(exc))
            self._log("fe_check", f"FE check failed: {exc}")
            return
        force = float(np.max(np.abs(result.force - fe.force) / self.force_reference))
        cap = float(np.max(np.abs(result.capacitance - fe.capacitance) / fe.capacitance))
        resync = max(force, cap) > self.tolerance
        with self._cond:
            s = self._stats
            self._stats = replace(
                s, checks=s.checks + 1, resyncs=s.resyncs + int(resync), last_force_difference=force,
                last_capacitance_difference=cap, last_check_ms=1e3 * (time.perf_counter() - tic), last_error="",
                max_force_difference=np.fmax(force, s.max_force_difference),
                max_capacitance_difference=np.fmax(cap, s.max_capacitance_difference))
        if resync:
            self._log("fe_check", f"reduced twin differs from the FE by {force:.3%} (force) / {cap:.3%} "
                                  f"(capacitance), above its tolerance {self.tolerance:.3%}: resynchronising")
            self._resync(fe)
