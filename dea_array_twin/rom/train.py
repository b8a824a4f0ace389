"""Training a reduced-order model: FE snapshots (in parallel), basis and hyper-reduction, validation.

:func:`train` samples the envelope (Latin hypercube over every driven unit's
displacement and every unit's voltage), solves the FE snapshots with
:func:`dea_array_twin.parallel.run_tasks` (here, on local processes or on Dask), builds
the :class:`~dea_array_twin.model.reduced.ReducedModel`
(:func:`~dea_array_twin.model.rom_build.build_reduced_model`) and validates it on
held-out commands (another sample, solved by the FE the same way) against the FE: the
errors, the indicator and the reduced model's time go into ``rom.validation``.  Before
that, a third sample calibrates the error indicator (:func:`indicator_scale`), so that the
held-out commands check the indicator as it will be used.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..model.config import ArrayConfig
from ..model.reduced import Envelope, ReducedModel
from ..model.reduced_twin import ReducedTwin
from ..model.rom_build import Snapshots, build_reduced_model
from ..model.solver import ConvergenceError
from ..model.twin import ArrayTwin
from ..parallel import run_tasks

#: ``progress(stage, done, total)``: stage is "snapshots", "calibration" or "validation".
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class SnapshotTask:
    """One FE equilibrium to solve from the flat state (picklable, for any executor)."""

    config: ArrayConfig
    modes: tuple
    displacement: tuple
    voltage: tuple


@dataclass(frozen=True)
class SnapshotResult:
    """The FE answer to a :class:`SnapshotTask`; ``error`` is empty when it converged."""

    positions: np.ndarray | None
    force: np.ndarray | None
    capacitance: np.ndarray | None
    seconds: float
    error: str = ""


def solve_snapshot(task: SnapshotTask) -> SnapshotResult:
    """Solve one snapshot with a fresh :class:`ArrayTwin` (cold, from the flat state)."""
    tic = time.perf_counter()
    twin = ArrayTwin(task.config)
    try:
        res = twin.solve(task.displacement, task.voltage, task.modes)
    except ConvergenceError as exc:
        return SnapshotResult(None, None, None, time.perf_counter() - tic, str(exc))
    return SnapshotResult(res.positions.ravel(), res.force, res.capacitance, time.perf_counter() - tic)


def solve_snapshots(cfg: ArrayConfig, modes: tuple, displacement: np.ndarray, voltage: np.ndarray,
                    workers: int = 1, scheduler: str | None = None,
                    progress: Callable[[int], None] | None = None) -> tuple[Snapshots, list[str], float]:
    """FE equilibria at each command; returns the snapshots, a message per failed one, and the CPU seconds.

    Commands whose solve fails (no equilibrium found) are left out of the snapshots.
    """
    tasks = [SnapshotTask(cfg, tuple(modes), tuple(map(float, d)), tuple(map(float, v)))
             for d, v in zip(displacement, voltage)]
    results = run_tasks(solve_snapshot, tasks, workers=workers, scheduler=scheduler, progress=progress)
    ok = [i for i, r in enumerate(results) if not r.error]
    failures = [f"d = {tasks[i].displacement} m, V = {tasks[i].voltage} V: {r.error}"
                for i, r in enumerate(results) if r.error]
    if not ok:
        raise ConvergenceError(f"no snapshot converged; first failure: {failures[0]}")
    snaps = Snapshots(displacement[ok], voltage[ok], np.array([results[i].positions for i in ok]),
                      np.array([results[i].force for i in ok]), np.array([results[i].capacitance for i in ok]))
    return snaps, failures, float(sum(r.seconds for r in results))


@dataclass(frozen=True)
class Validation:
    """The reduced model against the FE on held-out commands (all errors relative).

    Attributes
    ----------
    force_error : ndarray, shape (n, n_units)
        ``|F_rom - F_fe|`` over the unit's force reference (largest training |F|).
    capacitance_error : ndarray, shape (n, n_units)
        ``|C_rom - C_fe| / C_fe``.
    delta_capacitance_error : ndarray, shape (n, n_units)
        ``|C_rom - C_fe|`` over the largest |dC| of the unit in the validation set.
    indicator : ndarray, shape (n,)
        The reduced model's error indicator at each command.
    seconds : ndarray, shape (n,)
        Time of each reduced solve from a reset (a cold start) [s].
    fallbacks : tuple of str
        Why the reduced model handed each of the other commands to the FE
        (``ReducedResult.fallback``, e.g. its Newton did not converge); they are not in the
        arrays above.
    """

    force_error: np.ndarray
    capacitance_error: np.ndarray
    delta_capacitance_error: np.ndarray
    indicator: np.ndarray
    seconds: np.ndarray
    fallbacks: tuple[str, ...] = ()

    def worst(self) -> np.ndarray:
        """Per command, the larger of its force and capacitance errors."""
        return np.maximum(self.force_error.max(axis=1), self.capacitance_error.max(axis=1))

    def table(self, tolerance: float) -> dict:
        """JSON-able summary: max and mean errors, indicator facts, times."""
        worst = self.worst()
        over = worst > tolerance
        flagged = self.indicator > tolerance
        return {
            "commands": int(worst.size) + len(self.fallbacks), "rom_fallbacks": len(self.fallbacks),
            "force_error_max": float(self.force_error.max()), "force_error_mean": float(self.force_error.mean()),
            "capacitance_error_max": float(self.capacitance_error.max()),
            "capacitance_error_mean": float(self.capacitance_error.mean()),
            "delta_capacitance_error_max": float(self.delta_capacitance_error.max()),
            "indicator_max": float(self.indicator.max()),
            "over_tolerance": int(over.sum()), "flagged": int(flagged.sum()),
            "over_tolerance_unflagged": int((over & ~flagged).sum()),
            "cold_solve_ms_median": float(np.median(self.seconds) * 1e3),
        }


#: Errors below this fraction of the tolerance do not enter :func:`indicator_scale`: far below the
#: tolerance the ratio of error to indicator is of no consequence (and noisy: both are tiny).
CALIBRATION_FLOOR = 0.1


def indicator_scale(calibration: Validation, tolerance: float) -> float:
    """What the raw error indicator is multiplied by: the largest ratio of a command's error to its raw
    indicator over the calibration commands whose error is at least ``CALIBRATION_FLOOR`` times the
    tolerance, and at least 1 (an indicator that already exceeds the error is kept as it is).

    The raw indicator estimates the error of the basis along the enrichment vectors; what they
    miss it does not see (on the 4-by-4 it was 0.6-4 times below the error, ``docs/rom.md``).
    Scaled, it flags a command whose error exceeds the tolerance as long as that command's ratio
    is within the calibration's: a statistical answer, checked on the held-out commands
    (``over_tolerance_unflagged`` of the validation table), not a bound.
    """
    worst = calibration.worst()
    used = worst >= CALIBRATION_FLOOR * tolerance
    if not used.any():
        return 1.0
    ratio = worst[used] / np.maximum(calibration.indicator[used], np.finfo(float).tiny)
    return float(max(1.0, ratio.max()))


def validate(twin: ReducedTwin, snaps: Snapshots) -> Validation:
    """Solve each snapshot's command with the reduced model from a reset and compare with the FE.

    ``twin`` should have an infinite tolerance, so that the reduced model answers every
    command it can (the comparison is of the ROM, not of its fallback); a command it hands to
    the FE all the same (its Newton did not converge, a command outside its envelope) is
    counted in :attr:`Validation.fallbacks` with the reason.  Raises RuntimeError when it
    answers none.
    """
    force_ref = twin.rom.force_reference
    dc_ref = np.abs(snaps.capacitance - twin.model.flat_capacitance).max(axis=0)
    fallbacks, fe, ce, dce, ind, sec = [], [], [], [], [], []
    for i in range(snaps.force.shape[0]):
        twin.reset()
        res = twin.solve(snaps.displacement[i], snaps.voltage[i])
        if res.fallback:
            fallbacks.append(res.fallback)
            continue
        fe.append(np.abs(res.force - snaps.force[i]) / force_ref)
        dc = np.abs(res.capacitance - snaps.capacitance[i])
        ce.append(dc / snaps.capacitance[i])
        dce.append(dc / np.where(dc_ref > 0, dc_ref, 1.0))
        ind.append(res.error_indicator)
        sec.append(res.solve_time)
    if not ind:
        raise RuntimeError(f"the reduced model answered none of the {len(fallbacks)} commands: {fallbacks[0]}")
    return Validation(np.array(fe), np.array(ce), np.array(dce), np.array(ind), np.array(sec), tuple(fallbacks))


@dataclass(frozen=True)
class TrainingResult:
    """A trained ROM with its validation and what training cost."""

    rom: ReducedModel
    validation: Validation
    failures: list
    timings: dict


def train(cfg: ArrayConfig, envelope: Envelope, n_snapshots: int = 240, n_modes: int = 30,
          tolerance: float = 1e-3, n_validation: int = 60, seed: int = 0, workers: int = 1,
          scheduler: str | None = None, progress: Progress | None = None,
          say: Callable[[str], None] | None = None, n_calibration: int | None = None,
          edges: float = 0.0) -> TrainingResult:
    """Sample, solve, build and validate a ROM of ``cfg`` over ``envelope`` (see the module docstring).

    Parameters
    ----------
    n_snapshots, n_validation : int
        Training and held-out commands (independent Latin hypercube samples, seeds
        ``seed`` and ``seed + 1``).
    edges : float
        Share of the training commands stretched towards the envelope's bounds
        (:meth:`Envelope.sample`; the calibration and held-out commands stay uniform).
    n_calibration : int, optional
        Commands that calibrate the error indicator (:func:`indicator_scale`; seed
        ``seed + 2``); default ``n_validation``, 0 keeps the raw indicator.
    n_modes : int
        POD modes r.
    tolerance : float
        Relative error the ROM is meant to hold (force over its full scale,
        capacitance over its value); its indicator sends updates above it to the FE.
    workers, scheduler :
        Where the FE snapshots run (:func:`dea_array_twin.parallel.run_tasks`).
    progress : callable, optional
        ``progress(stage, done, total)`` for the FE solves ("snapshots", "calibration", "validation").
    say : callable, optional
        Called with a line of text at each building stage.
    """
    report = progress or (lambda stage, done, total: None)
    timings = {}
    tic = time.perf_counter()
    d, v = envelope.sample(n_snapshots, seed, edges)
    snaps, failures, cpu = solve_snapshots(cfg, envelope.modes, d, v, workers, scheduler,
                                           lambda done: report("snapshots", done, n_snapshots))
    timings.update(snapshots_s=time.perf_counter() - tic, snapshots_cpu_s=cpu)
    tic = time.perf_counter()
    model = ArrayTwin(cfg).model
    rom = build_reduced_model(model, envelope, snaps, min(n_modes, snaps.force.shape[0]), tolerance, progress=say)
    timings["build_s"] = time.perf_counter() - tic
    n_calibration = n_validation if n_calibration is None else n_calibration
    calibration_failures = []
    if n_calibration > 0:
        tic = time.perf_counter()
        dc, vc = envelope.sample(n_calibration, seed + 2)
        calibration, calibration_failures, cpu = solve_snapshots(
            cfg, envelope.modes, dc, vc, workers, scheduler, lambda done: report("calibration", done, n_calibration))
        scale = indicator_scale(validate(ReducedTwin(cfg, rom, tolerance=np.inf), calibration), tolerance)
        rom = dataclasses.replace(rom, indicator_scale=scale)
        timings.update(calibration_s=time.perf_counter() - tic, calibration_fe_cpu_s=cpu)
    tic = time.perf_counter()
    dv, vv = envelope.sample(n_validation, seed + 1)
    held_out, held_failures, cpu = solve_snapshots(cfg, envelope.modes, dv, vv, workers, scheduler,
                                                   lambda done: report("validation", done, n_validation))
    timings.update(validation_fe_s=time.perf_counter() - tic, validation_fe_cpu_s=cpu)
    tic = time.perf_counter()
    twin = ReducedTwin(cfg, rom, tolerance=np.inf)
    validation = validate(twin, held_out)
    timings["validation_rom_s"] = time.perf_counter() - tic
    facts = dict(rom.validation, **validation.table(tolerance), timings=timings,
                 calibration_commands=n_calibration - len(calibration_failures), snapshot_failures=len(failures),
                 validation_failures=len(held_failures) + len(calibration_failures), seed=seed,
                 edges=edges)
    rom = dataclasses.replace(rom, validation=facts)
    return TrainingResult(rom, validation, failures + calibration_failures + held_failures, timings)
