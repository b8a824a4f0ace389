"""Fitting the slip table gamma(d) of eq. 11 to measured capacitance curves (no I/O).

The paper explains the residual capacitance error of its model by the membrane
slipping in the frame clamps while an indenter pulls it, and corrects the frame's
boundary condition along X (eq. 11): ``u = (lp - 1) X gamma(d_k)``.  gamma is a
table over the indenter displacement (:attr:`.ArrayConfig.slip_factor`);
:func:`fit_slip` identifies its values at chosen knots from capacitance curves, as
the paper calibrated it on the two cross curves of its 10 % array (figure 14).

Capacitance depends on kinematics only, and the runs are displacement controlled,
so gamma is identified without touching the Yeoh coefficients; the paper notes
that it barely changes the force curves, and :class:`SlipFit` reports how much it
changed them here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy.optimize import least_squares

from ..model.config import ArrayConfig
from ..model.membrane import DRIVEN
from ..model.metrics import fit
from ..model.solver import NewtonSettings
from ..model.twin import ArrayTwin
from .measured import MeasuredCurve, simulate

__all__ = ["SlipFit", "fit_slip"]

#: Finite-difference step of the Jacobian in gamma: it changes a capacitance by
#: ~2e-4 of itself (dC/C ~ 2 (lp - 1) dgamma), far above the solver's tolerance.
_DIFF_STEP = 1e-3


@dataclass(frozen=True)
class SlipFit:
    """Result of :func:`fit_slip`.

    Attributes
    ----------
    knots : tuple of float
        Table displacements [m, before scaling] (``slip_displacement``).
    factors : tuple of float
        Fitted gamma at each knot [-] (``slip_factor``); the first is 1.
    names : tuple of str
        The curves, in the order of the per-curve arrays below.
    fit_before, fit_after : ndarray
        Capacitance FIT [%] (eq. 12, on ``C - C[0]``) per curve without slip
        (gamma = 1) and with the fitted table.
    force_fit_before, force_fit_after : ndarray
        Force FIT [%] of the measured unit per curve, without and with the table;
        nan for curves without a measured force.
    force_change : ndarray
        Per curve, the largest change of a driven unit's model force caused by the
        table, relative to the largest such force without it [-]; nan when no unit
        is driven.
    model_dc_before, model_dc_after : tuple of ndarray, shape (k_j,)
        The twin's capacitance change of each curve's measured unit from its first
        sample [F], without slip and with the fitted table.
    cost : float
        ``sum over curves of (1 - FIT/100)^2`` with the fitted table.
    n_evaluations : int
        Simulations of the whole set of curves, the gamma = 1 reference included.
    converged : bool
        The optimiser met its tolerances (not stopped by the evaluation budget).
    message : str
        Why the optimiser stopped.
    """

    knots: tuple[float, ...]
    factors: tuple[float, ...]
    names: tuple[str, ...]
    fit_before: np.ndarray
    fit_after: np.ndarray
    force_fit_before: np.ndarray
    force_fit_after: np.ndarray
    force_change: np.ndarray
    model_dc_before: tuple[np.ndarray, ...]
    model_dc_after: tuple[np.ndarray, ...]
    cost: float
    n_evaluations: int
    converged: bool
    message: str

    def config(self, base: ArrayConfig) -> ArrayConfig:
        """``base`` with the fitted slip table."""
        return base.replace(slip_displacement=self.knots, slip_factor=self.factors)


class _BudgetExhausted(Exception):
    """The evaluation budget ran out inside the optimiser."""


def _delta_c(curve: MeasuredCurve, capacitance: np.ndarray) -> np.ndarray:
    """Capacitance change from the first sample [F]: of the measured unit for per-unit (k, n) input."""
    c = capacitance[:, curve.unit] if capacitance.ndim == 2 else capacitance
    return c - c[0]


def _force_change(curve: MeasuredCurve, force: np.ndarray, reference: np.ndarray) -> float:
    """Largest change of a driven unit's force relative to its largest reference force."""
    driven = np.array([m == DRIVEN for m in curve.modes])
    if not driven.any():
        return math.nan
    scale = np.abs(reference[:, driven]).max()
    return float(np.abs(force[:, driven] - reference[:, driven]).max() / scale) if scale > 0 else math.nan


def fit_slip(curves: Sequence[MeasuredCurve], knots: Sequence[float], *, start: Sequence[float] | None = None,
             lower: float = 0.5, max_evaluations: int = 100,
             progress: Callable[[int, tuple[float, ...], float], None] | None = None,
             settings: NewtonSettings | None = None) -> SlipFit:
    """Fit the slip factors gamma at ``knots`` to measured capacitance curves.

    Minimises ``sum_c (1 - FIT_c / 100)^2``, FIT of eq. 12 between the measured
    and the simulated capacitance change of each curve's measured unit from its
    first sample (so offsets of leads and meter cancel).  The same table, in
    metres before scaling, is applied to every curve's own config; gamma at the
    first knot is held at 1 (no slip before the indenter moves), the others vary
    in ``[lower, 1]``.

    Each residual ``(dC - dC_model) / ||dC - mean(dC)||`` makes the cost a plain
    sum of squares, so a bounded trust-region least squares (scipy's ``trf``)
    applies: Gauss-Newton steps on a finite-difference Jacobian converge in a few
    iterations of ``len(knots)`` simulations each, where Nelder-Mead needs tens of
    simulations per parameter, and the bounds keep every trial a valid table.

    Parameters
    ----------
    curves : sequence of MeasuredCurve
        Curves with ``capacitance`` (each varying).  The paper's choice: the
        measured unit driven, and a neighbour driven while the unit is measured.
    knots : sequence of float
        Table displacements [m, before scaling], strictly increasing, >= 0; at
        least two (the first normally 0).
    start : sequence of float, optional
        Initial gamma at ``knots[1:]``; default all 1 (no slip).
    lower : float
        Smallest gamma a trial may take, in (0, 1).
    max_evaluations : int
        Budget of simulations of the whole set of curves (Jacobian columns
        included); the best table seen so far is returned when it runs out.
    progress : callable, optional
        Called after every evaluation with (evaluations so far, the table's
        factors, its cost).
    settings : NewtonSettings, optional
        Solver tolerances of the simulations.

    Returns
    -------
    SlipFit

    Raises
    ------
    ValueError
        No curves, a curve without (or with constant) capacitance, bad knots,
        ``start``, ``lower`` or ``max_evaluations``.
    ConvergenceError
        A sample has no equilibrium for some trial table.
    """
    curves = list(curves)
    knots = tuple(float(k) for k in knots)
    if not curves:
        raise ValueError("fit_slip needs at least one curve")
    if len(knots) < 2:
        raise ValueError(f"fit_slip needs at least two knots (gamma is 1 at the first), got {list(knots)}")
    curves[0].config.replace(slip_displacement=knots, slip_factor=(1.0,) * len(knots))  # validates the knots
    if not 0.0 < lower < 1.0:
        raise ValueError(f"lower must be in (0, 1), got {lower}")
    if max_evaluations < 1:
        raise ValueError(f"max_evaluations must be >= 1, got {max_evaluations}")
    x0 = np.ones(len(knots) - 1) if start is None else np.asarray(start, dtype=float)
    if x0.shape != (len(knots) - 1,) or not np.all((x0 >= lower) & (x0 <= 1.0)):
        raise ValueError(f"start must hold one gamma in [{lower}, 1] per knot after the first "
                         f"({len(knots) - 1}), got {np.asarray(start).tolist()}")
    measured, spread = [], []
    for curve in curves:
        if curve.capacitance is None:
            raise ValueError(f"{curve.name}: no measured capacitance to fit gamma to")
        dc = _delta_c(curve, np.asarray(curve.capacitance, dtype=float))
        norm = float(np.linalg.norm(dc - dc.mean()))
        if not norm > 0.0:
            raise ValueError(f"{curve.name}: the measured capacitance does not change")
        measured.append(dc)
        spread.append(norm)

    runs: dict[tuple[float, ...], list[tuple[np.ndarray, np.ndarray]]] = {}
    best_cost, best_factors = math.inf, ()

    def run(factors: tuple[float, ...]) -> list[tuple[np.ndarray, np.ndarray]]:
        nonlocal best_cost, best_factors
        if factors not in runs:
            if len(runs) >= max_evaluations:
                raise _BudgetExhausted
            runs[factors] = [simulate(ArrayTwin(c.config.replace(slip_displacement=knots, slip_factor=factors),
                                                settings), c) for c in curves]
            cost = float(np.sum(residuals_of(runs[factors]) ** 2))
            if cost < best_cost:
                best_cost, best_factors = cost, factors
            if progress is not None:
                progress(len(runs), factors, cost)
        return runs[factors]

    def residuals_of(outputs: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        return np.concatenate([(dc - _delta_c(c, cap)) / s
                               for c, dc, s, (_, cap) in zip(curves, measured, spread, outputs)])

    def table(free: np.ndarray) -> tuple[float, ...]:
        return (1.0,) + tuple(float(g) for g in free)

    reference = run(table(np.ones(len(knots) - 1)))
    try:
        result = least_squares(lambda p: residuals_of(run(table(p))), x0, bounds=(lower, 1.0), method="trf",
                               diff_step=_DIFF_STEP, xtol=1e-6, ftol=1e-8, max_nfev=max_evaluations)
        factors, converged, message = table(result.x), bool(result.success), str(result.message)
        if best_cost < float(np.sum(result.fun ** 2)):  # never worse than a table already simulated
            factors = best_factors
    except _BudgetExhausted:
        factors, converged = best_factors, False
        message = f"stopped after {max_evaluations} evaluations; best table so far"
    final = runs[factors]

    def cap_fits(outputs: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        return np.array([fit(dc, _delta_c(c, cap)) for c, dc, (_, cap) in zip(curves, measured, outputs)])

    def force_fits(outputs: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        return np.array([math.nan if c.force is None else fit(c.force, force[:, c.unit])
                         for c, (force, _) in zip(curves, outputs)])

    return SlipFit(
        knots=knots, factors=factors, names=tuple(c.name for c in curves),
        fit_before=cap_fits(reference), fit_after=cap_fits(final),
        force_fit_before=force_fits(reference), force_fit_after=force_fits(final),
        force_change=np.array([_force_change(c, f1, f0) for c, (f1, _), (f0, _) in zip(curves, final, reference)]),
        model_dc_before=tuple(_delta_c(c, cap) for c, (_, cap) in zip(curves, reference)),
        model_dc_after=tuple(_delta_c(c, cap) for c, (_, cap) in zip(curves, final)),
        cost=float(np.sum(residuals_of(final) ** 2)), n_evaluations=len(runs), converged=converged,
        message=message)
