"""The actuator's answers to voltages: quasi-static stroke and time response of biased units.

Stroke (paper section 2): the position of a biased unit at voltage V minus its position
at 0 V.  :func:`rest_state` brings a twin to the 0 V equilibrium of its biased units,
:func:`stroke` then steps through voltage levels quasi-statically (reporting stability
and snap-through at each), :func:`simulate` integrates the dynamics under piecewise
constant voltage and force schedules.  Library functions: ``dea-twin stroke`` and
``dea-twin simulate`` are thin layers over them, and bias design builds on them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from .config import BIASED, DRIVEN
from .twin import ArrayTwin, TwinResult

__all__ = ["Schedule", "Simulation", "StrokeCurve", "rest_state", "simulate", "stroke"]


def rest_state(twin: ArrayTwin, displacement: Sequence[float] | float = 0.0, start: float = 0.0,
               force: Sequence[float] | float = 0.0) -> TwinResult:
    """The 0 V equilibrium of the config's units, reached the way an array is assembled.

    From the flat membrane (:meth:`ArrayTwin.reset`) every biased unit's indenter is
    first held at ``start`` [m] while the driven units move to ``displacement`` [m];
    then the biased units are released onto their bias elements (and the external
    ``force`` [N]) and settle where membrane and bias balance.  With a bistable bias
    ``start`` chooses the branch.  Stability is checked.
    """
    twin.reset()
    modes = twin.config.modes
    hold = np.where(np.array(modes) == BIASED, start, displacement)
    holding = tuple(DRIVEN if m == BIASED else m for m in modes)
    twin.solve(hold, 0.0, holding, check_stability=False)
    return twin.solve(hold, 0.0, modes, check_stability=True, force=force)


@dataclass(frozen=True)
class StrokeCurve:
    """Quasi-static equilibria at a sequence of voltage levels (SI units).

    Attributes
    ----------
    voltage : ndarray, shape (levels,)
        The level applied [V].
    position, force, capacitance : ndarray, shape (levels, n_units)
        Unit positions [m], membrane forces [N] (eq. 10) and capacitances [F].
    stable : ndarray of bool, shape (levels,)
        Whether each equilibrium is a stable minimum (bias stiffness included).
    snap : ndarray of bool, shape (levels,)
        Whether some unit snapped through on the way to the level.
    rest : TwinResult
        The 0 V equilibrium the levels start from.
    results : tuple of TwinResult
        Everything else known about each level (snap records, flags).
    """

    voltage: np.ndarray
    position: np.ndarray
    force: np.ndarray
    capacitance: np.ndarray
    stable: np.ndarray
    snap: np.ndarray
    rest: TwinResult
    results: tuple

    @property
    def stroke(self) -> np.ndarray:
        """Position minus the 0 V position [m], shape (levels, n_units)."""
        return self.position - self.rest.position


def stroke(twin: ArrayTwin, voltages: Sequence[float], unit: int | None = None,
           displacement: Sequence[float] | float = 0.0, start: float = 0.0,
           on_level: Callable[[float, TwinResult], None] | None = None) -> StrokeCurve:
    """Stroke of biased units: the quasi-static equilibrium at each voltage level in turn.

    Parameters
    ----------
    twin : ArrayTwin
        Its config says which units are biased and with which bias.
    voltages : sequence of float
        Levels [V], applied one after the other, each reached quasi-statically from
        the previous equilibrium (the first from the 0 V state of :func:`rest_state`).
    unit : int, optional
        The biased unit (0-based) that gets the voltage; default: every biased unit.
        Other units stay at 0 V.
    displacement : sequence of float or float
        Where the driven units are held [m].
    start : float
        Height [m] the biased indenters are released from (:func:`rest_state`).
    on_level : callable, optional
        Called with each level and its result (progress, warnings).

    Raises
    ------
    ValueError
        No biased unit, or ``unit`` is not biased.
    ConvergenceError
        A level has no equilibrium the twin can reach.
    """
    modes = twin.config.modes
    biased = [k for k, m in enumerate(modes) if m == BIASED]
    if not biased:
        raise ValueError(f"stroke needs a biased unit: the config's unit_modes are {list(modes)}")
    if unit is not None and modes[unit] != BIASED:
        raise ValueError(f"unit {unit + 1} is {modes[unit]}, not biased (unit_modes {list(modes)})")
    targets = [unit] if unit is not None else biased
    rest = rest_state(twin, displacement, start)
    results = []
    for level in voltages:
        voltage = np.zeros(twin.n_units)
        voltage[targets] = level
        res = twin.solve(voltage=voltage, check_stability=True)
        results.append(res)
        if on_level is not None:
            on_level(float(level), res)
    return StrokeCurve(
        voltage=np.asarray(voltages, dtype=float), position=np.array([r.position for r in results]),
        force=np.array([r.force for r in results]), capacitance=np.array([r.capacitance for r in results]),
        stable=np.array([bool(r.stable) for r in results]), snap=np.array([bool(r.snaps) for r in results]),
        rest=rest, results=tuple(results))


@dataclass(frozen=True)
class Schedule:
    """Piecewise-constant per-unit commands: from ``times[i]`` on, ``values[i]`` (SI units).

    Before the first time the command is ``initial``.
    """

    times: tuple[float, ...]
    values: tuple[tuple[float, ...], ...]
    initial: float = 0.0

    def __post_init__(self) -> None:
        if any(b <= a for a, b in zip(self.times, self.times[1:])) or any(t < 0 for t in self.times):
            raise ValueError(f"schedule times must be >= 0 and increasing, got {list(self.times)}")

    def at(self, time_s: float, n_units: int) -> np.ndarray:
        """The command in force at ``time_s`` [s], one value per unit."""
        index = np.searchsorted(self.times, time_s, side="right") - 1
        if index < 0:
            return np.full(n_units, self.initial)
        values = self.values[index]
        return np.full(n_units, values[0]) if len(values) == 1 else np.asarray(values, dtype=float)


@dataclass(frozen=True)
class Simulation:
    """A time response (SI units): one row per time.

    Attributes
    ----------
    time : ndarray, shape (k,)
        [s], from 0 (the rest state) in steps of ``dt``.
    position, velocity, force, capacitance, voltage, external_force : ndarray, shape (k, n_units)
        Unit positions [m], velocities [m/s], membrane forces [N], capacitances [F],
        applied voltages [V] and external forces [N].
    results : tuple of TwinResult
    """

    time: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    force: np.ndarray
    capacitance: np.ndarray
    voltage: np.ndarray
    external_force: np.ndarray
    results: tuple


def simulate(twin: ArrayTwin, voltage: Schedule, force: Schedule | None, duration: float, dt: float,
             displacement: Sequence[float] | float = 0.0, start: float = 0.0,
             on_step: Callable[[float, TwinResult], None] | None = None) -> Simulation:
    """Time response of the array from its 0 V rest state (:func:`rest_state`) under command schedules.

    Each step of ``dt`` [s] applies the commands in force at its end and calls
    :meth:`ArrayTwin.step`; ``duration`` [s] is rounded to whole steps.  Biased units
    with ``mass`` 0 are quasi-static.
    """
    if not (duration > 0 and dt > 0 and np.isfinite(duration) and np.isfinite(dt)):
        raise ValueError(f"duration and dt must be > 0 s, got {duration} and {dt}")
    n = twin.n_units
    force = force or Schedule((), ())
    results = [rest_state(twin, displacement, start)]
    times = [0.0]
    for i in range(1, int(round(duration / dt)) + 1):
        t = i * dt
        res = twin.step(dt, voltage=voltage.at(t, n), force=force.at(t, n))
        results.append(res)
        times.append(t)
        if on_step is not None:
            on_step(t, res)
    return Simulation(
        time=np.array(times), position=np.array([r.position for r in results]),
        velocity=np.array([r.velocity for r in results]), force=np.array([r.force for r in results]),
        capacitance=np.array([r.capacitance for r in results]), voltage=np.array([r.voltage for r in results]),
        external_force=np.array([r.external_force for r in results]), results=tuple(results))
