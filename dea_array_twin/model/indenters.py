"""Heights of biased units' indenters as Newton unknowns: the bordered system and its inertia.

A biased unit's rigid indenter disk sits at ``(lp X, lp Y, w_k)`` (eq. 9 with an unknown
height ``w_k``).  Its disk dofs are counted as prescribed, so the free dofs and ``K_ff``
are exactly those of driven mode, and each height adds one equation

    R_w,k = F_k(x) - G_k(w_k) = 0,      F_k = 1_k^T r_p   (eq. 10),

with ``G_k`` the generalised force pushing the indenter towards +z: ``B_k(w_k) + f_k``
quasi-statically, ``B_k + f_k - m_k a_k(w_k) - c_k v_k(w_k)`` in a Newmark step
(:mod:`.dynamics`).  This is stationarity of ``Pi = Pi_membrane - sum_k int G_k dw_k``,
so Newton's system is symmetric,

    [K_ff  K_fw] [dx_f]     [R_f]        K_fw = K_fp 1_k,
    [K_wf  K_ww] [dw  ] = - [R_w],       K_ww = 1_k^T K_pp 1_j - diag(dG/dw),

and is solved by block elimination with the influence vectors ``Y = K_ff^-1 K_fw``
(cached per factorisation by :meth:`.solver.Factorisation.predict`):

    S = K_ww - K_wf Y,     S dw = -R_w + K_wf K_ff^-1 R_f,     dx_f = -K_ff^-1 R_f - Y dw,

one ``K_ff`` solve per iteration plus a dense ``n_b x n_b`` system.  Inertia
(Haynsworth additivity): ``In(K) = In(K_ff) + In(S)``, so an equilibrium is a stable
minimum when ``K_ff`` has no negative pivot and ``S`` no negative eigenvalue; ``S``
carries the bias stiffness ``-dB/dw``.
"""

from __future__ import annotations

from typing import Protocol, Sequence

import numpy as np

from .bias import BiasRangeError
from .kernels import solve_small


class IndenterLoad(Protocol):
    """The generalised force ``G_k(w_k)`` [N] pushing a biased indenter towards +z."""

    def __call__(self, unit: int, w: float, t: float) -> tuple[float, float]:
        """``(G, dG/dw)`` of ``unit`` at height ``w`` [m] and load-path fraction ``t``.

        Raises :class:`~.bias.BiasRangeError` outside a bias table."""

    def static_slope(self, unit: int, w: float) -> float:
        """``dB/dw`` [N/m] of ``unit`` (no inertial terms): the bias part of the stability check."""


class IndenterBorder:
    """The heights of biased units bordering the membrane's Newton system.

    Build it with :meth:`for_units`.

    Attributes
    ----------
    units : ndarray of int
        The biased units (in contact).
    dofs : list of ndarray
        Global z dofs of each unit's disk.
    groups : list of ndarray
        The same dofs as indices into the partition's prescribed dofs.
    load : IndenterLoad
        ``G_k(w_k)`` and its derivative.
    """

    def __init__(self, units: np.ndarray, dofs: list[np.ndarray], groups: list[np.ndarray], load: IndenterLoad):
        self.units, self.dofs, self.groups, self.load = np.asarray(units, dtype=int), dofs, groups, load
        self._first = np.array([d[0] for d in dofs], dtype=int)  # one z dof per disk: its height
        self._all = np.concatenate(dofs) if dofs else np.zeros(0, dtype=int)
        self._offsets = np.cumsum([0] + [d.size for d in dofs[:-1]])
        self.t = 1.0
        #: The heights [m] the Newton solve since :meth:`begin` starts from (after every
        #: predictor: a time integrator's guess, the load step's linear predictor, a
        #: continuation) and its first step's ``dw``: together the linear prediction of the heights.
        self.start: np.ndarray | None = None
        self.first_dw: np.ndarray | None = None
        #: Why the last trial outside a bias table was refused (for the error message), if any.
        self.outside: str | None = None
        #: Whether the last :meth:`direction` left the free residual alone (no ``K_ff`` solve).
        self.skipped_solve = False
        #: The diagonal of ``S`` the last :meth:`direction` solved with [N/m].
        self.step_stiffness: np.ndarray | None = None
        self._cache: tuple | None = None

    @classmethod
    def for_units(cls, model, units: Sequence[int], prescribed: np.ndarray, load: IndenterLoad) -> "IndenterBorder":
        """The border of ``units`` of ``model`` in the partition with ``prescribed`` dofs (sorted)."""
        dofs = [model.disk_z_dofs(k) for k in units]
        return cls(np.asarray(units, dtype=int), dofs, [np.searchsorted(prescribed, d) for d in dofs], load)

    def begin(self, t: float) -> None:
        """Start a Newton solve at load-path fraction ``t``."""
        self.t = t
        self.start = None
        self.first_dw = None

    def predict(self, fact, x: np.ndarray, t_from: float) -> None:
        """Linear predictor of the heights for the load step from ``t_from`` to ``t``, in ``x``.

        From an equilibrium at ``t_from`` the step changes ``R_w`` by ``-dG = -(G(w, t) -
        G(w, t_from))`` at fixed heights, so ``dw = S^-1 dG`` (no ``K_ff`` solve); the free
        dofs follow through the solver's influence-vector predictor.  Voltage changes are
        not predicted (as for driven units).
        """
        w = self.heights(x)
        try:
            change = self.load_change(w, t_from, self.t)
            if not change.any():
                return
            dw = solve_small(self.schur(fact, w), change)
        except (np.linalg.LinAlgError, BiasRangeError):
            return
        self.move(x, dw)

    def load_change(self, w: np.ndarray, t_from: float, t_to: float) -> np.ndarray:
        """``G(w, t_to) - G(w, t_from)`` [N] per unit at fixed heights ``w`` (the load step's change)."""
        return self.loads(w, t_to)[0] - self.loads(w, t_from)[0]

    def loads(self, w: np.ndarray, t: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(G, dG/dw)`` [N, N/m] per unit at heights ``w`` and path fraction ``t`` (default: the current one).

        Raises :class:`~.bias.BiasRangeError` outside a bias table."""
        t = self.t if t is None else t
        pairs = []
        for k, wk in zip(self.units.tolist(), w.tolist()):
            try:
                pairs.append(self.load(k, wk, t))
            except BiasRangeError as exc:
                raise BiasRangeError(f"unit {k + 1}: {exc}") from None
        return np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])

    def heights(self, x: np.ndarray) -> np.ndarray:
        """The heights ``w_k`` [m] of the disks in ``x``."""
        return x[self._first]

    def membrane_force(self, r: np.ndarray) -> np.ndarray:
        """``F_k = 1_k^T r_p`` [N] (eq. 10) from the internal forces ``r``."""
        return np.add.reduceat(r[self._all], self._offsets)

    def residual(self, r: np.ndarray, x: np.ndarray) -> np.ndarray:
        """``R_w = F - G(w)`` [N]; NaN where ``w`` is outside a bias table (a failed trial)."""
        try:
            g = self.loads(self.heights(x))[0]
        except BiasRangeError as exc:
            self.outside = str(exc)
            return np.full(self.units.size, np.nan)
        return self.membrane_force(r) - g

    def move(self, x: np.ndarray, dw: np.ndarray) -> None:
        """Raise the disks by ``dw`` [m] in ``x``, in place."""
        for d, step in zip(self.dofs, dw):
            x[d] += step

    def _blocks(self, fact) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``Y^T = (K_ff^-1 K_fw)^T`` and ``K_wf`` (both n_b, n_f: a row per unit) and the condensed
        ``K_ww - K_wf Y``, per factorisation."""
        if self._cache is None or self._cache[0] is not fact:
            n_p = fact.prescribed.size
            yt = np.empty((self.units.size, fact.free.size))
            for i, idx in enumerate(self.groups):
                unit_move = np.zeros(n_p)
                unit_move[idx] = 1.0
                yt[i] = -fact.predict(unit_move, [idx])
            kwf = np.vstack([fact.coupling(idx) for idx in self.groups])
            kww = fact.disk_stiffness[np.ix_(self.units, self.units)]
            self._cache = (fact, yt, kwf, kww - kwf @ yt.T)
        return self._cache[1:]

    def membrane_stiffness(self, fact) -> np.ndarray:
        """``dF_i/dw_j = K_ww - K_wf K_ff^-1 K_fw`` [N/m]: the membrane's stiffness condensed onto the heights.

        Symmetric (the membrane force derives from its energy); its diagonal is the slope of
        a unit's driven force curve with the other disks held, the rest the coupling."""
        return self._blocks(fact)[2].copy()

    def schur(self, fact, w: np.ndarray, static: bool = False, t: float | None = None) -> np.ndarray:
        """``S = K_ww - K_wf K_ff^-1 K_fw - dG/dw`` at heights ``w`` (``static``: without inertial terms)
        and path fraction ``t`` (default: the current one)."""
        if static:
            slope = np.array([self.load.static_slope(k, wk) for k, wk in zip(self.units, w)])
        else:
            slope = self.loads(w, t)[1]
        return self._blocks(fact)[2] - np.diag(slope)

    def direction(self, fact, r_f: np.ndarray, r_w: np.ndarray, x: np.ndarray,
                  balanced: float = 0.0) -> tuple[np.ndarray, np.ndarray] | None:
        """The Newton step ``(dx_f, dw)`` by block elimination; None if ``S`` is singular.

        When the free residual is already within ``balanced`` [N] (a converged membrane whose
        indenters' loads changed: a force command, a bias, a time step) the ``K_ff`` solve
        is skipped: the step is then the linear predictor ``dw = -S^-1 R_w, dx_f = -Y dw``.
        """
        yt, kwf, _ = self._blocks(fact)
        self.skipped_solve = max(r_f.max(initial=0.0), -r_f.min(initial=0.0)) <= balanced
        rhs = -r_w
        if not self.skipped_solve:
            z = fact.solve(r_f)
            rhs = rhs + np.sum(kwf * z, axis=1)  # row sums, not BLAS: slow under load (see solver._norm)
        try:
            s = self.schur(fact, self.heights(x))
            dw = solve_small(s, rhs)
        except (np.linalg.LinAlgError, BiasRangeError):
            return None
        self.step_stiffness = np.diagonal(s)
        if self.first_dw is None:
            self.first_dw = dw
        dx = np.zeros(r_f.size) if self.skipped_solve else -z
        for row, step in zip(yt, dw):
            dx -= step * row
        return dx, dw

    def negative_eigenvalues(self, fact, x: np.ndarray, static: bool = True, t: float | None = None) -> int:
        """Negative eigenvalues of ``S`` at ``x`` (``static``: without inertial terms; at path fraction ``t``).

        Add ``K_ff``'s negative pivots for the inertia of the bordered tangent."""
        return int(np.count_nonzero(np.linalg.eigvalsh(self.schur(fact, self.heights(x), static, t)) < 0))

    def without(self, unit: int) -> "IndenterBorder | None":
        """The same border without ``unit`` (held as driven), or None if it was the only one."""
        keep = self.units != unit
        if not keep.any():
            return None
        return IndenterBorder(self.units[keep], [d for d, k in zip(self.dofs, keep) if k],
                              [g for g, k in zip(self.groups, keep) if k], self.load)


def negative_eigenvalues(fact, x: np.ndarray, border: IndenterBorder | None, static: bool = True,
                         t: float | None = None) -> int:
    """Negative eigenvalues of the tangent at ``x``: ``K_ff``'s negative pivots plus the border's.

    Haynsworth: ``In(K) = In(K_ff) + In(S)``.  ``static``: the border without inertial
    terms (the stability of the configuration); ``t``: its path fraction (default: the
    current one).  -1 if the pivots' inertia is unknown.
    """
    if fact.negative_pivots < 0:
        return -1
    if border is None:
        return fact.negative_pivots
    return fact.negative_pivots + border.negative_eigenvalues(fact, x, static, t)
