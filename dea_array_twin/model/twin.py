"""The array's digital twin: the membrane model plus its current state.

:class:`ArrayTwin` is what users, the ROS node, replay and studies talk to: give it
per-unit displacements [m], voltages [V] and modes, get a :class:`TwinResult` with
per-unit force [N] and capacitance [F].  It keeps the last converged state and the
tangent factorisation there, so a small change of command is a warm update.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from .config import ArrayConfig
from .membrane import DRIVEN, FREE, MembraneModel
from .solver import ConvergenceError, EquilibriumSolver, NewtonSettings, SolveCancelled

__all__ = ["ArrayTwin", "TwinResult", "ConvergenceError", "DRIVEN", "FREE", "SolveCancelled", "command_error"]


@dataclass(frozen=True)
class TwinResult:
    """One equilibrium of the array and everything known about it (SI units).

    Attributes
    ----------
    displacement : ndarray
        Commanded indenter displacement per unit [m] (free units: their centre deflection).
    voltage : ndarray
        Voltage per unit [V].
    modes : tuple of str
        ``"driven"`` or ``"free"`` per unit.
    force : ndarray
        Axial force on each indenter [N], eq. 10; positive when the membrane pulls
        the indenter back towards the plane; 0 for free units.
    capacitance : ndarray
        Capacitance of each unit [F], eq. 7, whole electrode.
    delta_capacitance : ndarray
        ``capacitance`` minus the flat pre-stretched 0 V value [F].
    centre_deflection : ndarray
        Out-of-plane position of each unit centre [m].
    peak_field : ndarray
        Largest true electric field ``V / (t0 l3)`` on each electrode [V/m].
    positions : ndarray, shape (n_nodes, 3)
        Deformed node positions [m].
    energy : float
        Stored energy of the membrane [J].
    min_principal_stress : float
        Smallest in-plane principal Cauchy stress outside held indenter disks [Pa].
    wrinkled : bool
        ``min_principal_stress < 0``: a compressed region, which a real membrane
        relieves by wrinkling and this model does not represent.
    field_exceeded : bool
        Some ``peak_field`` is above the configured ``breakdown_field``.
    stable : bool or None
        The tangent at the state is positive definite (a stable minimum); ``None`` if
        not checked.
    iterations, factorisations, step_cuts : int
        Newton iterations, tangent factorisations and load-step halvings of the solve.
    residual : float
        Largest free residual force at convergence [N].
    solve_time : float
        Wall time of the solve [s].
    """

    displacement: np.ndarray
    voltage: np.ndarray
    modes: tuple
    force: np.ndarray
    capacitance: np.ndarray
    delta_capacitance: np.ndarray
    centre_deflection: np.ndarray
    peak_field: np.ndarray
    positions: np.ndarray
    energy: float
    min_principal_stress: float
    wrinkled: bool
    field_exceeded: bool
    stable: bool | None
    iterations: int
    factorisations: int
    step_cuts: int
    residual: float
    solve_time: float

    @property
    def flags(self) -> tuple[str, ...]:
        """Which of ``"unstable"``, ``"wrinkled"``, ``"field_exceeded"`` apply (for counting)."""
        return tuple(name for name, on in (("unstable", self.stable is False), ("wrinkled", self.wrinkled),
                                           ("field_exceeded", self.field_exceeded)) if on)

    @property
    def warnings(self) -> list[str]:
        """Human-readable list of what is wrong with this state (empty if nothing), one per flag."""
        text = {"unstable": "equilibrium is not a stable minimum (tangent not positive definite)",
                "wrinkled": f"compressive principal stress {self.min_principal_stress:.4g} Pa: membrane would wrinkle",
                "field_exceeded": f"electric field {self.peak_field.max() / 1e6:.4g} V/um exceeds the breakdown limit"}
        return [text[name] for name in self.flags]

    @property
    def ok(self) -> bool:
        """True when no warning applies."""
        return not self.warnings


def command_error(kind: str, values: Sequence[float], cfg: ArrayConfig) -> str | None:
    """Why a command the node or a replay would reject is invalid, or None.

    ``kind`` is "displacement" or "voltage".  Stricter than :meth:`ArrayTwin.solve`
    (which solves any finite command within ``max_displacement``): a voltage must
    also be >= 0 and keep the flat pre-stretched field below ``breakdown_field``."""
    n = cfg.n_units
    if len(values) != n:
        return f"{kind} command has {len(values)} values, expected {n} (one per unit)"
    arr = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(arr)):
        return f"{kind} command contains NaN or inf: {arr.tolist()}"
    if kind == "displacement":
        limit = cfg.scaled("max_displacement")
        if np.any(np.abs(arr) > limit):
            return f"displacement {arr.tolist()} m beyond max_displacement {limit} m"
        return None
    if np.any(arr < 0):
        return f"negative voltage {arr.tolist()} V (the electrodes are driven by one polarity)"
    v_max = cfg.hv_voltage(cfg.breakdown_field)
    if np.any(arr > v_max):
        return (f"voltage {arr.tolist()} V above {v_max:.0f} V, where the flat pre-stretched field "
                f"reaches breakdown_field {cfg.breakdown_field:.4g} V/m")
    return None


class ArrayTwin:
    """A live twin of the array described by ``config``.

    Parameters
    ----------
    config : ArrayConfig, optional
        The array; the paper's 1-by-3 default if omitted.
    settings : NewtonSettings, optional
        Solver tolerances.

    Examples
    --------
    >>> twin = ArrayTwin()
    >>> res = twin.solve(displacement=[0, 0.015, 0], modes=["free", "driven", "free"])
    >>> res.force[1] > 0
    True
    """

    def __init__(self, config: ArrayConfig | None = None, settings: NewtonSettings | None = None):
        self.config = config or ArrayConfig()
        self.model = MembraneModel(self.config)
        self.solver = EquilibriumSolver(self.model, settings)
        self.reset()

    @property
    def n_units(self) -> int:
        """Number of units."""
        return self.model.n_units

    def reset(self) -> None:
        """Return to the flat pre-stretched state at 0 V, all units driven at 0 m."""
        n = self.n_units
        self._x = self.model.flat_state()
        self._modes: tuple[str, ...] = (DRIVEN,) * n
        self._displacement = np.zeros(n)
        self._voltage = np.zeros(n)
        self.solver.factorisation = None
        self.last: TwinResult | None = None

    def _vector(self, name: str, values: Sequence[float] | float | None, default: np.ndarray) -> np.ndarray:
        if values is None:
            return default.copy()
        arr = np.asarray(values, dtype=float)
        if arr.ndim == 0:  # one value for every unit
            arr = np.full(self.n_units, float(arr))
        if arr.shape != (self.n_units,):
            raise ValueError(f"{name} must have one value per unit ({self.n_units}), got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be finite, got {arr.tolist()}")
        return arr

    def solve(self, displacement: Sequence[float] | float | None = None,
              voltage: Sequence[float] | float | None = None,
              modes: Sequence[str] | None = None, check_stability: bool | None = None,
              cancel: Callable[[], bool] | None = None) -> TwinResult:
        """Move the twin to a new command and return the equilibrium there.

        Parameters
        ----------
        displacement : sequence of float, optional
            Indenter displacement d_k per unit [m] (ignored for free units);
            default: the previous command.
        voltage : sequence of float or float, optional
            Voltage per unit [V]; default: the previous one.
        modes : sequence of str, optional
            ``"driven"`` or ``"free"`` per unit; default: the previous modes
            (all driven after :meth:`reset`).
        check_stability : bool, optional
            Factor the tangent at the new state and report whether it is a stable
            minimum (``result.stable``); default: the solver setting.  Costs one
            factorisation (about 7 ms on the default mesh); without it
            ``result.stable`` is None.
        cancel : callable, optional
            Asked with no arguments before every Newton iteration; when it returns
            True the solve is abandoned (e.g. past a time budget, or for a newer
            request).  Called from the thread that runs the solve.

        Raises
        ------
        ConvergenceError
            If no equilibrium is found; the twin keeps its previous state.
        SolveCancelled
            ``cancel()`` returned True; the twin keeps its previous state (positions,
            command, modes; the next solve starts with a fresh tangent there).
        ValueError
            For a command of the wrong length or with NaN/inf.
        """
        tic = time.perf_counter()
        cfg, model = self.config, self.model
        d1 = self._vector("displacement", displacement, self._displacement)
        v1 = self._vector("voltage", voltage, self._voltage)
        modes = model.check_modes(modes if modes is not None else self._modes)
        limit = cfg.scaled("max_displacement")
        if np.any(np.abs(d1) > limit):
            raise ValueError(f"displacement {d1.tolist()} m exceeds max_displacement ({limit} m)")
        centre = self._x.reshape(-1, 3)[model.mesh.centre_nodes, 2]
        # A unit that becomes driven starts from where its centre is now.
        d0 = np.where(np.array(self._modes) == DRIVEN, self._displacement, centre)
        try:
            x, r, point, stats = self.solver.solve(self._x, modes, d0, d1, self._voltage, v1, check_stability, cancel)
        except (ConvergenceError, SolveCancelled):
            # The solver's tangent is now one at a step on the way (and the one at the state
            # kept may have been overwritten in its factor slot): the next solve factors afresh.
            self.solver.factorisation = None
            raise
        self._x, self._modes, self._voltage = x, modes, v1
        out = model.outputs(x, r, point, v1, modes)
        self._displacement = np.where(np.array(modes) == DRIVEN, d1, out.centre_deflection)
        fact = self.solver.factorisation
        stable = None
        if stats.stability_checked and fact is not None and fact.negative_pivots >= 0:
            stable = fact.negative_pivots == 0
        energy = model.energy(point, v1)
        self.last = TwinResult(
            displacement=self._displacement.copy(), voltage=v1, modes=modes, force=out.force,
            capacitance=out.capacitance, delta_capacitance=out.capacitance - model.flat_capacitance,
            centre_deflection=out.centre_deflection, peak_field=out.peak_field,
            positions=x.reshape(-1, 3).copy(), energy=energy, min_principal_stress=out.min_principal_stress,
            wrinkled=out.min_principal_stress < 0, field_exceeded=bool(np.any(out.peak_field > cfg.breakdown_field)),
            stable=stable, iterations=stats.iterations, factorisations=stats.factorisations,
            step_cuts=stats.step_cuts, residual=stats.residual_norm, solve_time=time.perf_counter() - tic)
        return self.last
