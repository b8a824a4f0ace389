"""Energy-conserving sampling and weighting (ECSW): sparse non-negative quadrature weights.

The reduced model sums its energy over a few quadrature points with weights
``xi >= 0`` instead of over all of them (Farhat, Avery, Chapman, Cortial 2014).  Each
column of ``G`` holds one candidate point's contributions to the reduced gradient
(reduced residual, indenter forces, electrode integrals) at every training state; ``b``
is their sum with all weights 1, the unreduced values.  The weights solve

    min ||xi||_0   subject to   ||G xi - b|| <= tol ||b||,   xi >= 0,

approximately, by the Lawson-Hanson active-set algorithm for non-negative least
squares stopped as soon as the tolerance is met: each outer iteration adds the point
most correlated with the remaining error, so the points are few and chosen greedily.
The least-squares problems on the active set are solved with an updated Cholesky
factor of the (column-normalised) Gram matrix ``G_P^T G_P``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.linalg as sla


@dataclass(frozen=True)
class SparseWeights:
    """The points ECSW kept and their weights.

    Attributes
    ----------
    index : ndarray of int
        Columns of ``G`` with a positive weight, ascending.
    weight : ndarray
        Their weights (> 0); all other points have weight 0.
    relative_error : float
        ``||G xi - b|| / ||b||`` reached.
    """

    index: np.ndarray
    weight: np.ndarray
    relative_error: float


def sparse_nnls(g: np.ndarray, b: np.ndarray, tol: float, max_points: int | None = None,
                progress: Callable[[int, float], None] | None = None) -> SparseWeights:
    """Non-negative ``xi`` with few nonzeros and ``||g xi - b|| <= tol ||b||`` (see the module docstring).

    Parameters
    ----------
    g : ndarray, shape (m, n)
        Contributions of the n candidate points to the m reduced quantities.
    b : ndarray, shape (m,)
        The unreduced sums.
    tol : float
        Relative error at which to stop (> 0).
    max_points : int, optional
        Stop after this many points even if ``tol`` is not met (default: m).
    progress : callable, optional
        Called with (points kept, relative error) after each added point.

    Raises
    ------
    ValueError
        For ``tol <= 0`` or ``b = 0``.
    """
    if not tol > 0:
        raise ValueError(f"tol must be > 0, got {tol}")
    norm_b = float(np.linalg.norm(b))
    if norm_b == 0.0:
        raise ValueError("b is zero: nothing to approximate")
    scale = np.linalg.norm(g, axis=0)
    scale[scale == 0.0] = 1.0
    gs = np.asfortranarray(g / scale)  # column-normalised, so the Gram matrix is better conditioned
    limit = min(max_points or g.shape[0], g.shape[1])
    active: list[int] = []
    gram = np.zeros((limit, limit))  # G_P^T G_P of the active columns, in ``active`` order
    chol = np.zeros((0, 0))
    rhs = np.zeros(0)
    x = np.zeros(0)
    excluded = np.zeros(g.shape[1], dtype=bool)
    residual = b.copy()
    error = 1.0
    while error > tol and len(active) < limit:
        corr = gs.T @ residual
        corr[active] = -np.inf
        corr[excluded] = -np.inf
        j = int(np.argmax(corr))
        if not corr[j] > 0:
            break
        k = len(active)
        cross = gs[:, active].T @ gs[:, j] if k else np.zeros(0)
        grown = _add_column(chol, cross, float(gs[:, j] @ gs[:, j]))
        if grown is None:  # numerically dependent on the active columns
            excluded[j] = True
            continue
        chol = grown
        gram[:k, k] = gram[k, :k] = cross
        gram[k, k] = gs[:, j] @ gs[:, j]
        active.append(j)
        rhs = np.append(rhs, gs[:, j] @ b)
        x = np.append(x, 0.0)
        while True:  # inner loop of Lawson-Hanson: keep the active weights positive
            z = sla.cho_solve((chol, True), rhs)
            if np.all(z > 0):
                x = z
                break
            neg = z <= 0
            alpha = np.min(x[neg] / (x[neg] - z[neg]))
            x = x + alpha * (z - x)
            keep = x > 1e-14 * np.abs(x).max(initial=0.0)  # the blocking weights reach 0
            active = [a for a, kept in zip(active, keep) if kept]
            n_keep = len(active)
            gram[:n_keep, :n_keep] = gram[np.ix_(keep, keep)]
            x, rhs = x[keep], rhs[keep]
            if not active:
                chol = np.zeros((0, 0))
                break
            chol = np.linalg.cholesky(gram[:n_keep, :n_keep])
        residual = b - gs[:, active] @ x
        error = float(np.linalg.norm(residual)) / norm_b
        if progress is not None:
            progress(len(active), error)
    order = np.argsort(active)
    index = np.asarray(active, dtype=np.int64)[order]
    return SparseWeights(index, x[order] / scale[index], error)


def _add_column(chol: np.ndarray, cross: np.ndarray, norm2: float) -> np.ndarray | None:
    """The Cholesky factor of the Gram matrix grown by a column with products ``cross`` and ``|col|^2``.

    None if the column is numerically dependent on the active ones.
    """
    k = cross.size
    if k == 0:
        return np.array([[np.sqrt(norm2)]])
    row = sla.solve_triangular(chol, cross, lower=True)
    pivot = norm2 - float(row @ row)
    if pivot <= 1e-10 * norm2:
        return None
    out = np.zeros((k + 1, k + 1))
    out[:k, :k] = chol
    out[k, :k] = row
    out[k, k] = np.sqrt(pivot)
    return out
