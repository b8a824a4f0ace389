"""The finite-element work of a bias design, as independent tasks any executor runs.

Two kinds of task, each solved by a fresh :class:`~dea_array_twin.model.twin.ArrayTwin`
from the flat state, so the results do not depend on where they ran
(:func:`dea_array_twin.parallel.run_tasks`: here, local processes, Dask):

* :class:`SweepTask` (:func:`run_sweep`): the force curve of one unit, swept over a
  grid of heights while every other held unit stays at a given height and the units
  carry a voltage pattern — the rig's driven curve, plus at every point the membrane's
  condensed stiffness ``dF_i/dw_j`` (:func:`~dea_array_twin.model.stiffness.indenter_stiffness`):
  the inner model's data;
* :class:`PathTask` (:func:`run_path`): full quasi-static biased solves of a design along
  the scenario paths that start from one low voltage pattern (:mod:`.scenarios`): the
  0 V rest state, the low pattern, then for each stroking unit its high pattern and
  back, every voltage change in :data:`PATH_LEVELS` steps with the stability margin
  checked at each.  The verification of a design, and the anchors of the next inner model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.config import BIASED, DRIVEN, FREE, ArrayConfig
from ..model.response import rest_state
from ..model.solver import ConvergenceError
from ..model.stiffness import indenter_stiffness
from ..model.twin import ArrayTwin, TwinResult
from .scenarios import Pattern

#: A return to the low pattern that lands further than this (fraction of D) from the low
#: state marks hysteresis (a snap on the way up that did not snap back).
RETURN_TOL = 1e-4
#: Every voltage change of a scenario path stops at the voltage fractions j / PATH_LEVELS
#: (j = 1 .. PATH_LEVELS) of the change: the path points where the stability margin is
#: checked, here and in the inner model (:mod:`.inner`, its largest voltage step).
PATH_LEVELS = 4


@dataclass(frozen=True)
class SweepTask:
    """Unit ``unit`` swept over ``grid`` with the other held units at ``heights`` (picklable).

    Attributes
    ----------
    config : ArrayConfig
        The array (its unit modes and biases are not used).
    modes : tuple of str
        ``"driven"`` (a held indenter: the design's biased and driven units) or ``"free"``.
    heights : tuple of float
        Height of each held unit [m]; the swept unit's entry is ignored.
    voltage : tuple of float
        Voltage of each unit [V].
    unit : int
        The swept unit, 0-based.
    grid : tuple of float
        The swept unit's heights [m], increasing.
    key : tuple
        Where the sweep belongs (its pattern and unit).
    """

    config: ArrayConfig
    modes: tuple
    heights: tuple
    voltage: tuple
    unit: int
    grid: tuple
    key: tuple = ()


@dataclass(frozen=True)
class Sweep:
    """The curves of a :class:`SweepTask` (SI units).

    Attributes
    ----------
    task : SweepTask
    held : ndarray of int
        The held units (the columns of ``stiffness``).
    force : ndarray, shape (points,)
        ``F`` of the swept unit [N] (eq. 10); NaN from a point without equilibrium on.
    stiffness : ndarray, shape (points, len(held))
        ``dF_unit/dw_j`` [N/m] for each held unit j (the swept unit's own slope included).
    error : str
        Why the sweep stopped early, if it did.
    """

    task: SweepTask
    held: np.ndarray
    force: np.ndarray
    stiffness: np.ndarray
    error: str = ""


def run_sweep(task: SweepTask) -> Sweep:
    """Solve a :class:`SweepTask`: neighbours placed at 0 V, the voltage applied, then the sweep upwards."""
    twin = ArrayTwin(task.config)
    modes = task.modes
    held = np.array([k for k, m in enumerate(modes) if m == DRIVEN], dtype=int)
    column = int(np.searchsorted(held, task.unit))
    heights = np.array(task.heights, dtype=float)
    heights[task.unit] = task.grid[0]
    force = np.full(len(task.grid), np.nan)
    stiffness = np.full((len(task.grid), held.size), np.nan)
    try:
        twin.solve(heights, np.zeros(len(modes)), modes, check_stability=False)
        for i, w in enumerate(task.grid):
            heights[task.unit] = w
            res = twin.solve(heights, task.voltage, modes, check_stability=True)
            force[i] = res.force[task.unit]
            stiffness[i] = indenter_stiffness(twin)[1][column]
    except ConvergenceError as exc:
        return Sweep(task, held, force, stiffness, str(exc))
    return Sweep(task, held, force, stiffness)


@dataclass(frozen=True)
class PathTask:
    """A design's biased solves along the scenarios that start from the low pattern ``low`` (picklable).

    Attributes
    ----------
    config : ArrayConfig
        The array with the design: ``unit_modes`` and ``bias`` per unit.
    low : Pattern
        Which units are at ``voltage`` before the stroke.
    units : tuple of int
        The units that stroke from ``low`` (0-based), one after the other.
    voltage : float
        The actuation voltage V [V].
    start : float
        Height the biased indenters are released from onto their biases [m]
        (:func:`~dea_array_twin.model.response.rest_state`).
    """

    config: ArrayConfig
    low: Pattern
    units: tuple
    voltage: float
    start: float = 0.0


@dataclass(frozen=True)
class State:
    """A biased equilibrium of the array (SI units).

    Attributes
    ----------
    position : ndarray
        Height of each unit [m] (centre deflection of a free unit).
    bias_force : ndarray
        ``B(w)`` of each biased unit [N].
    capacitance : ndarray
        Per unit [F].
    margin : float
        Smallest eigenvalue of the biased units' ``dF/dw - diag(dB/dw)`` [N/m]: the
        stability margin (for one unit ``dF/dw - dB/dw``).
    path_margin : float
        The smallest margin on the way to the state [N/m]: at the state the voltage
        change started from, at each of its :data:`PATH_LEVELS` path points, the state's own.
    stable : bool
        The twin's stability check (the whole tangent positive definite) at the state and
        at every path point on the way.
    snaps : tuple of str
        Snap-throughs on the way to the state.
    """

    position: np.ndarray
    bias_force: np.ndarray
    capacitance: np.ndarray
    margin: float
    path_margin: float
    stable: bool
    snaps: tuple


@dataclass(frozen=True)
class PathResult:
    """The equilibria of a :class:`PathTask`.

    Attributes
    ----------
    task : PathTask
    low : State or None
        The low pattern's state (None: not reached).
    high : tuple of State or None
        Per stroking unit, its high pattern's state.
    hysteresis : tuple of bool
        Per stroking unit, whether removing its voltage again missed the low state.
    errors : tuple of str
        What failed ("" where nothing did), per stroking unit; the low state's failure
        is in every entry.
    """

    task: PathTask
    low: State | None
    high: tuple
    hysteresis: tuple
    errors: tuple


def margin(twin: ArrayTwin, res: TwinResult) -> float:
    """Smallest eigenvalue of ``dF/dw - diag(dB/dw)`` over the biased units at the twin's state [N/m]."""
    units, stiffness = indenter_stiffness(twin)
    laws = twin.config.per_unit("bias")
    biased = [i for i, k in enumerate(units) if res.modes[k] == BIASED]
    if not biased:
        return float("nan")
    s = stiffness[np.ix_(biased, biased)]
    s = s - np.diag([laws[units[i]].slope(res.position[units[i]]) for i in biased])
    return float(np.linalg.eigvalsh(0.5 * (s + s.T)).min())


def change_voltage(twin: ArrayTwin, since: State, before: np.ndarray, after: np.ndarray) -> State:
    """The state after the voltages go from ``before`` to ``after`` [V] in :data:`PATH_LEVELS` full solves.

    ``since`` is the twin's present state (at ``before``); the result's ``path_margin`` and
    ``stable`` cover it and every path point, its ``snaps`` every snap-through on the way."""
    margins, snaps, stable = [since.margin], [], since.stable
    position, bias_force, capacitance = since.position, since.bias_force, since.capacitance
    if np.any(after != before):
        for u in np.arange(1, PATH_LEVELS + 1) / PATH_LEVELS:
            res = twin.solve(voltage=before + u * (after - before), check_stability=True)
            margins.append(margin(twin, res))
            snaps += [s.describe() for s in res.snaps]
            stable = stable and bool(res.stable)
            position, bias_force, capacitance = res.position.copy(), res.bias_force.copy(), res.capacitance.copy()
    return State(position, bias_force, capacitance, margins[-1], float(min(margins)), stable, tuple(snaps))


def run_path(task: PathTask) -> PathResult:
    """Solve a :class:`PathTask` with full quasi-static biased solves (stability checked at every path point)."""
    twin = ArrayTwin(task.config)
    low_voltage = task.voltage * np.array(task.low, dtype=float)
    zero = np.zeros_like(low_voltage)
    tol = RETURN_TOL * twin.config.scaled("electrode_diameter")

    def reach_low() -> State:
        res = rest_state(twin, 0.0, task.start)
        at_rest = margin(twin, res)  # the release from the held start is assembly, not a path: no snaps counted
        rest = State(res.position.copy(), res.bias_force.copy(), res.capacitance.copy(), at_rest, at_rest,
                     bool(res.stable), ())
        return change_voltage(twin, rest, zero, low_voltage)

    try:
        low = reach_low()
    except ConvergenceError as exc:
        message = f"low pattern: {exc}"
        return PathResult(task, None, (None,) * len(task.units), (False,) * len(task.units),
                          (message,) * len(task.units))
    high, hysteresis, errors = [], [], []
    for k in task.units:
        voltage = low_voltage.copy()
        voltage[k] = task.voltage
        try:
            high.append(change_voltage(twin, low, low_voltage, voltage))
            errors.append("")
            back = twin.solve(voltage=low_voltage, check_stability=False)
            hysteresis.append(bool(np.abs(back.position - low.position).max() > tol))
        except ConvergenceError as exc:
            high.append(None)
            hysteresis.append(False)
            errors.append(str(exc))
        if hysteresis[-1] or errors[-1]:  # start the next unit from the low state as reached from rest
            try:
                reach_low()
            except ConvergenceError as exc:
                errors += [f"low pattern: {exc}"] * (len(task.units) - len(errors))
                high += [None] * (len(task.units) - len(high))
                hysteresis += [False] * (len(task.units) - len(hysteresis))
                break
    return PathResult(task, low, tuple(high), tuple(hysteresis), tuple(errors))


def held_modes(config: ArrayConfig) -> tuple[str, ...]:
    """Per unit of a design's config: ``"driven"`` where an indenter is held (biased or driven), else ``"free"``."""
    return tuple(DRIVEN if m in (BIASED, DRIVEN) else FREE for m in config.modes)
