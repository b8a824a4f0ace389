"""Sparse ``LDL^T`` factorisations of the free-free tangent ``K_ff``, with symbolic reuse.

Every tangent of one model has the same sparsity pattern, so the fill-reducing
ordering and the elimination tree are computed once per set of free dofs
(:class:`Factoriser`) and each new tangent costs only the numeric factorisation.

The factorisation is ``P K_ff P^T = L D L^T`` with unit lower-triangular ``L`` and
diagonal ``D`` (no pivoting beyond the symmetric ordering).  By Sylvester's law of
inertia ``D`` has as many negative entries as ``K_ff`` has negative eigenvalues, so
the stability check (``K_ff`` positive definite: a stable minimum) is a count of
negative pivots.

Back ends:

* ``"qdldl"`` (the default when the ``qdldl`` package is installed): QDLDL with AMD
  ordering; ``update`` refactors numerically on the stored symbolic analysis, the
  inertia is read from ``D``.
* ``"superlu"`` (scipy, always available; the fallback): SuperLU with a symmetric
  minimum-degree ordering and diagonal pivots (``diag_pivot_thresh = 0``), an
  ``LDL^T`` in disguise whose ``U`` diagonal is ``D``; if it had to pivot off the
  diagonal the inertia is unknown (-1).  No symbolic reuse.
"""

from __future__ import annotations

import functools
import importlib.util

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .assembly import SparsePattern

BACKENDS = ("auto", "qdldl", "superlu")


def resolve_backend(backend: str) -> str:
    """``"qdldl"`` or ``"superlu"`` for a requested back end (``"auto"``: qdldl if installed)."""
    if backend not in BACKENDS:
        raise ValueError(f"linear solver must be one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        return "qdldl" if importlib.util.find_spec("qdldl") is not None else "superlu"
    if backend == "qdldl" and importlib.util.find_spec("qdldl") is None:
        raise ValueError("linear solver 'qdldl' needs the qdldl package: pip install qdldl")
    return backend


class _Slot:
    """One qdldl solver object; ``generation`` counts the factorisations it has held."""

    def __init__(self, solver: object):
        self.solver = solver
        self.generation = 0


class LDLFactor:
    """The numeric factor of one ``K_ff``: ``solve`` and the inertia.

    A qdldl factor lives in a slot that a later factorisation may overwrite; using it
    after that raises instead of silently solving with another matrix.
    """

    def __init__(self, slot: _Slot | None = None, lu: object = None):
        self._slot, self._lu = slot, lu
        self._generation = slot.generation if slot is not None else 0

    def _solver(self) -> object:
        if self._slot.generation != self._generation:
            raise RuntimeError("this factorisation was overwritten by a newer one on the same slot")
        return self._slot.solver

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``K_ff^-1 b``."""
        if self._slot is None:
            return self._lu.solve(b)
        return self._solver().solve(b)

    def negative_pivots(self) -> int:
        """Number of negative entries of ``D`` (negative eigenvalues of ``K_ff``), -1 if unknown."""
        if self._slot is None:
            lu = self._lu
            if not np.array_equal(lu.perm_r, lu.perm_c):
                return -1
            return int(np.count_nonzero(lu.U.diagonal() < 0))
        d = self._solver().factors()[1]
        if not np.all(np.isfinite(d)) or np.any(d == 0.0):  # a zero pivot stopped QDLDL
            return -1
        return int(np.count_nonzero(d < 0))


class Factoriser:
    """Factorisations of ``K_ff`` for one set of free dofs on a fixed pattern.

    Parameters
    ----------
    pattern : SparsePattern
        The global tangent's pattern.
    free : ndarray
        Sorted free dof numbers.
    backend : str
        ``"auto"``, ``"qdldl"`` or ``"superlu"`` (see the module docstring).
    """

    def __init__(self, pattern: SparsePattern, free: np.ndarray, backend: str = "auto"):
        self.backend = resolve_backend(backend)
        self.pattern, self.free = pattern, free
        n = free.size
        index = np.full(pattern.n_dofs, -1)
        index[free] = np.arange(n)
        rows, cols = index[pattern.rows], index[pattern.cols]
        # Upper triangle of K_ff in CSC: column j holds rows i <= j.  The pattern is
        # sorted by (row, col), i.e. the lower triangle's CSC order = upper's CSC order
        # after swapping, so sort the selection by (col, row).
        sel = np.flatnonzero((rows >= 0) & (cols >= 0) & (rows <= cols))
        order = np.lexsort((rows[sel], cols[sel]))
        self._upper = sel[order]
        self._indices = rows[self._upper].astype(np.int64)
        self._indptr = np.concatenate([[0], np.cumsum(np.bincount(cols[self._upper], minlength=n))]).astype(np.int64)
        self._n = n
        self._slots: list[_Slot] = []

    def upper(self, values: np.ndarray) -> sp.csc_matrix:
        """The upper triangle of ``K_ff`` (CSC) from the pattern's nonzeros ``values``."""
        return sp.csc_matrix((values[self._upper], self._indices, self._indptr), shape=(self._n, self._n))

    def factor(self, values: np.ndarray, keep: LDLFactor | None = None) -> LDLFactor:
        """Factor ``K_ff`` of the pattern's nonzeros ``values``.

        A qdldl factor is refactored numerically in a slot other than the one holding
        ``keep`` (the factor still in use, e.g. at the last converged state).
        """
        if self.backend == "superlu":
            return self._superlu(values)
        upper = self.upper(values)
        slot = next((s for s in self._slots if keep is None or keep._slot is not s), None)
        if slot is None:
            try:
                slot = _Slot(_qdldl().Solver(upper, upper=True))
            except RuntimeError:  # QDLDL met an exactly zero pivot: SuperLU may still factor it
                return self._superlu(values)
            self._slots.append(slot)
        else:
            slot.solver.update(upper, upper=True)
            slot.generation += 1
        return LDLFactor(slot)

    def _superlu(self, values: np.ndarray) -> LDLFactor:
        k_ff = self.pattern.block(values, self.free, self.free).tocsc()  # symmetric: CSR data is CSC
        return LDLFactor(lu=spla.splu(k_ff, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                      options={"SymmetricMode": True}))


@functools.cache
def _qdldl():
    import qdldl

    return qdldl
