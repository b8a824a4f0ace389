"""Fitting the Yeoh coefficients to measured force curves (paper section 5.2; no I/O).

The paper identifies ``c10, c20, c30`` of eq. 4 with COMSOL's Nelder-Mead optimiser,
minimising the deviation of simulated from measured force-displacement curves.  Here
the same simplex search (:func:`scipy.optimize.minimize`, ``method="Nelder-Mead"``)
runs the twin on every :class:`~.measured.MeasuredCurve` at each trial point and
minimises

    cost = sum_j ||F_j - Fm_j||^2 / ||F_j - mean(F_j)||^2 = sum_j (1 - FIT_j / 100)^2,

with ``F_j`` the force measured on curve j's unit, ``Fm_j`` the twin's force there and
FIT the paper's eq. 12, so curves of different magnitude weigh equally.  Each curve
keeps its own geometry and pre-stretch; only the three coefficients change.

After the search, a Gauss-Newton estimate says how well the curves determine each
coefficient: with ``J`` the central finite-difference Jacobian of the stacked
normalised residuals ``r = (Fm - F) / ||F - mean F||`` with respect to
``(c10, c20, c30)`` and ``N`` residuals in all,

    cov = s^2 (J^T J)^-1,   s^2 = SSR / (N - 3),

whose diagonal gives a standard error per coefficient and whose normalised form the
correlation matrix.  It is a local, linearised hint, not a guarantee.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from ..model.config import ArrayConfig, ConfigError
from ..model.metrics import fit
from ..model.solver import ConvergenceError
from ..model.twin import ArrayTwin
from .measured import MeasuredCurve, simulate

__all__ = ["PARAMETERS", "POORLY_DETERMINED", "YeohFit", "fit_yeoh", "gauss_newton_errors"]

#: Fitted config fields, in order.
PARAMETERS = ("c10", "c20", "c30")
#: A coefficient whose standard error exceeds this fraction of its value is "poorly determined".
POORLY_DETERMINED = 0.25
#: Cost given to a trial point where the twin cannot be built (c10 <= 0) or does not converge.
FAILED_COST = 1e6
#: Edge of the initial simplex in scaled units (a tenth of the starting c10 in every coefficient).
SIMPLEX_STEP = 0.1
#: Finite-difference step of the confidence Jacobian in scaled units.
JACOBIAN_STEP = 1e-3

#: ``progress(n_evaluations, cost, best_cost)``, called after each cost evaluation.
Progress = Callable[[int, float, float], None]


@dataclass(frozen=True)
class YeohFit:
    """Result of :func:`fit_yeoh` (coefficients in Pa, FIT in %).

    Attributes
    ----------
    c10, c20, c30 : float
        Fitted Yeoh coefficients [Pa].
    start : ndarray, shape (3,)
        Starting coefficients [Pa].
    stderr : ndarray, shape (3,)
        Gauss-Newton standard error of each coefficient [Pa]; ``inf`` when the curves
        cannot determine it (singular ``J^T J``, or no more residuals than 3).
    correlation : ndarray, shape (3, 3)
        Correlation matrix of the estimates (``nan`` where undefined).
    fit, initial_fit : ndarray, shape (n_curves,)
        FIT [%] of each curve's force with the fitted and with the starting coefficients.
    cost, initial_cost : float
        ``sum (1 - FIT/100)^2`` at the optimum and at the start.
    n_evaluations : int
        Cost evaluations of the Nelder-Mead search (the confidence Jacobian costs 6 more).
    failed_evaluations : int
        Of those, points with ``c10 <= 0`` or without equilibrium (cost ``FAILED_COST``).
    converged : bool
        The simplex met the tolerances before ``max_evaluations``.
    message : str
        The optimiser's message.
    model_force, initial_model_force : tuple of ndarray, shape (k_j,)
        The twin's force on each curve's measured unit at the optimum and at the start [N].
    """

    c10: float
    c20: float
    c30: float
    start: np.ndarray
    stderr: np.ndarray
    correlation: np.ndarray
    fit: np.ndarray
    initial_fit: np.ndarray
    cost: float
    initial_cost: float
    n_evaluations: int
    failed_evaluations: int
    converged: bool
    message: str
    model_force: tuple[np.ndarray, ...]
    initial_model_force: tuple[np.ndarray, ...]

    @property
    def values(self) -> np.ndarray:
        """``(c10, c20, c30)`` [Pa]."""
        return np.array([self.c10, self.c20, self.c30])

    @property
    def poorly_determined(self) -> tuple[str, ...]:
        """Coefficients whose standard error exceeds ``POORLY_DETERMINED`` times their magnitude."""
        return tuple(name for name, value, err in zip(PARAMETERS, self.values, self.stderr)
                     if not err <= POORLY_DETERMINED * abs(value))

    def config(self, base: ArrayConfig) -> ArrayConfig:
        """``base`` with the fitted coefficients."""
        return base.replace(c10=self.c10, c20=self.c20, c30=self.c30)


class _Objective:
    """The twin on every curve for given coefficients; counts evaluations, keeps the best.

    Raises ConvergenceError if the twin fails at ``start`` (no usable reference point).
    """

    def __init__(self, curves: Sequence[MeasuredCurve], start: np.ndarray, progress: Progress | None):
        self.curves = list(curves)
        self.spread = [float(np.linalg.norm(c.force - c.force.mean())) for c in self.curves]
        self.progress = progress
        self.evaluations = 0
        self.failures = 0
        model = self.model_forces(start)
        self.initial = (float(np.sum(self.residuals(model) ** 2)), model)
        self.best = (self.initial[0], start, model)

    def model_forces(self, coefficients: np.ndarray) -> list[np.ndarray]:
        """The twin's force on each curve's measured unit [N].

        Curves sharing a config (after the coefficients are replaced) share one twin.

        Raises
        ------
        ConfigError
            ``c10 <= 0`` or a coefficient not finite.
        ConvergenceError
            A sample has no equilibrium.
        """
        changes = dict(zip(PARAMETERS, map(float, coefficients)))
        twins: dict[ArrayConfig, ArrayTwin] = {}
        out = []
        for curve in self.curves:
            cfg = curve.config.replace(**changes)
            if cfg not in twins:
                twins[cfg] = ArrayTwin(cfg)
            out.append(simulate(twins[cfg], curve)[0][:, curve.unit])
        return out

    def residuals(self, model: list[np.ndarray]) -> np.ndarray:
        """Stacked ``(Fm - F) / ||F - mean F||`` of every curve."""
        return np.concatenate([(m - c.force) / s for c, m, s in zip(self.curves, model, self.spread)])

    def __call__(self, x: np.ndarray, scale: float) -> float:
        """Cost at scaled coefficients ``x`` (``FAILED_COST`` where the twin fails)."""
        coefficients = np.asarray(x, dtype=float) * scale
        self.evaluations += 1
        try:
            model = self.model_forces(coefficients)
            cost = float(np.sum(self.residuals(model) ** 2))
        except (ConfigError, ConvergenceError):
            self.failures += 1
            cost = FAILED_COST
        else:
            if cost < self.best[0]:
                self.best = (cost, coefficients, model)
        if self.progress is not None:
            self.progress(self.evaluations, cost, self.best[0])
        return cost


def gauss_newton_errors(jacobian: np.ndarray, residuals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Standard errors and correlations of least-squares estimates, ``cov = s^2 (J^T J)^-1``.

    Parameters
    ----------
    jacobian : ndarray, shape (N, p)
        Derivatives of the residuals with respect to the parameters.
    residuals : ndarray, shape (N,)
        Residuals at the optimum; ``s^2 = SSR / (N - p)``.

    Returns
    -------
    stderr : ndarray, shape (p,)
        In the parameters' units; all ``inf`` when ``N <= p``, a column is zero or not
        finite, or ``J^T J`` is singular (condition number above 1e12 once the columns
        are scaled to unit length): the data cannot separate the parameters.
    correlation : ndarray, shape (p, p)
        ``cov_ij / (sigma_i sigma_j)``; ``nan`` off the diagonal when undefined.
    """
    n, p = jacobian.shape
    stderr = np.full(p, math.inf)
    correlation = np.full((p, p), math.nan)
    np.fill_diagonal(correlation, 1.0)
    norms = np.linalg.norm(jacobian, axis=0)
    if n <= p or not np.all(np.isfinite(jacobian)) or not np.all(norms > 0):
        return stderr, correlation
    unit = jacobian / norms
    normal = unit.T @ unit
    if np.linalg.cond(normal) > 1e12:
        return stderr, correlation
    s2 = float(residuals @ residuals) / (n - p)
    cov = np.linalg.inv(normal)  # of the unit-column problem; correlations do not depend on s2
    sigma = np.sqrt(np.diag(cov))
    return np.sqrt(s2) * sigma / norms, cov / np.outer(sigma, sigma)


def _jacobian(objective: _Objective, coefficients: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Central differences of the residuals w.r.t. the coefficients; all ``nan`` if a point fails."""
    n = sum(c.n_samples for c in objective.curves)
    columns = []
    for i, h in enumerate(step):
        delta = np.zeros(3)
        delta[i] = h
        try:
            plus = objective.residuals(objective.model_forces(coefficients + delta))
            minus = objective.residuals(objective.model_forces(coefficients - delta))
        except (ConfigError, ConvergenceError):
            return np.full((n, 3), math.nan)
        columns.append((plus - minus) / (2.0 * h))
    return np.column_stack(columns)


def _check_curves(curves: Sequence[MeasuredCurve]) -> None:
    if not curves:
        raise ValueError("no curves to fit")
    for curve in curves:
        if curve.force is None:
            raise ValueError(f"{curve.name}: no measured force (calibration fits forces)")
        if not np.all(np.isfinite(curve.force)):
            raise ValueError(f"{curve.name}: measured force has NaN or inf")
        if not np.ptp(curve.force) > 0:
            raise ValueError(f"{curve.name}: measured force is constant, so its FIT is undefined")


def fit_yeoh(curves: Sequence[MeasuredCurve], start: Sequence[float] | None = None, *,
             max_evaluations: int = 400, tol: float = 1e-3, progress: Progress | None = None) -> YeohFit:
    """Fit ``c10, c20, c30`` to measured force curves with Nelder-Mead.

    The search runs on scaled coefficients ``x = (c10, c20, c30) / s`` with one scale
    ``s`` = the starting c10.  One scale suits all three because the stress depends on
    them through the Yeoh slope ``Y' = c10 + 2 c20 (I-3) + 3 c30 (I-3)^2`` and under an
    indenter at 10-20 % pre-stretch ``I - 3`` reaches 0.3-0.7, so ``2 (I-3)`` and
    ``3 (I-3)^2`` are of order one: a pascal of any coefficient moves the force by a
    comparable amount (on the paper's array, 0-15 mm: within a factor of 2.5 at
    lp = 1.1 and of 1.4 at lp = 1.2).  The initial simplex adds ``SIMPLEX_STEP`` (10 %
    of the starting c10) to each coefficient in turn.

    Parameters
    ----------
    curves : sequence of MeasuredCurve
        Each with a measured, non-constant ``force`` [N].  A curve keeps its own config
        (geometry, pre-stretch, mesh); only the coefficients are replaced.
    start : sequence of 3 float, optional
        Starting ``(c10, c20, c30)`` [Pa]; default: those of ``curves[0]~dea_array_twin.model.config``.
    max_evaluations : int
        Largest number of cost evaluations of the search.
    tol : float
        Convergence tolerance: simplex size in scaled units (``xatol``, i.e. ``tol`` times
        the starting c10 in Pa) and spread of its costs (``fatol = tol^2``).
    progress : callable, optional
        ``progress(n_evaluations, cost, best_cost)`` after each cost evaluation.

    Returns
    -------
    YeohFit

    Raises
    ------
    ValueError
        No curves, or a curve without a usable force.
    ConfigError
        The start has ``c10 <= 0``.
    ConvergenceError
        The twin finds no equilibrium at the start: choose another start.
    """
    _check_curves(curves)
    p0 = np.array(start if start is not None else [getattr(curves[0].config, p) for p in PARAMETERS], dtype=float)
    if p0.shape != (3,) or not np.all(np.isfinite(p0)) or not p0[0] > 0:
        raise ConfigError(f"start must be 3 finite coefficients (c10, c20, c30) with c10 > 0 Pa, got {p0.tolist()}")
    scale = float(p0[0])
    objective = _Objective(curves, p0, progress)
    x0 = p0 / scale
    simplex = np.vstack([x0, x0 + SIMPLEX_STEP * np.eye(3)])
    result = minimize(objective, x0, args=(scale,), method="Nelder-Mead",
                      options={"maxfev": max_evaluations, "xatol": tol, "fatol": tol**2, "initial_simplex": simplex})
    cost, best, model = objective.best
    initial_cost, initial_model = objective.initial
    jacobian = _jacobian(objective, best, np.full(3, JACOBIAN_STEP * scale))
    stderr, correlation = gauss_newton_errors(jacobian, objective.residuals(model))
    return YeohFit(
        c10=float(best[0]), c20=float(best[1]), c30=float(best[2]), start=p0, stderr=stderr, correlation=correlation,
        fit=np.array([fit(c.force, m) for c, m in zip(curves, model)]),
        initial_fit=np.array([fit(c.force, m) for c, m in zip(curves, initial_model)]),
        cost=cost, initial_cost=initial_cost,
        n_evaluations=objective.evaluations, failed_evaluations=objective.failures,
        converged=bool(result.success), message=str(result.message),
        model_force=tuple(model), initial_model_force=tuple(initial_model))
