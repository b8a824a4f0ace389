"""Newton solver for the membrane's equilibrium, with load stepping and warm starts.

Equilibrium is stationarity of the total energy ``E(x)`` over the free dofs
(paper eq. 3 in weak form): ``r_f(x) = dE/dx_f = 0``.  Each iteration solves
``K_ff dx = -r_f`` with the consistent tangent (material + geometric stiffness,
:mod:`.assembly`) and backtracks on the residual norm when a full step does not
reduce it.  The solver

* moves from the current state to the target along a load path (indenter
  displacements and voltages interpolated linearly, and a frame that is not yet
  where the slip table of eq. 11 puts it moved there gradually), halving the step
  when Newton fails and growing it again after successes;
* predicts each step with the last tangent (``x_f += -K_ff^-1 K_fp dx_p``), factored
  at the start state when there is none yet (a fresh twin: the flat membrane's
  tangent gives the first step's shape, so a 15 mm jump converges in one step);
* when a solve continues the last one (same free dofs and voltage, starting where
  it ended) and the prescribed change is ``s dp + rest`` for the last change ``dp``
  (moving the free dofs by ``dx_f``), predicts ``x_f + s dx_f`` plus the tangent
  response to ``rest`` — or, when the last solve continued the one before it, the
  quadratic through those three states instead of ``s dx_f``; with a tangent at the
  start state itself, the quadratic extrapolation ``x_f + (s + s^2) T dp - s^2 dx_f``
  (``T dp`` the tangent response): along a smooth command path (a curve, a sine, a
  reversal) this leaves a much smaller residual than the tangent of an older state;
* when only biased units' loads change (a force command, a Newmark step) and the solve
  continues the last one, starts the heights and the free dofs on the quadratic through
  the last three states (:class:`PathRecord`); a Newmark step first solves the heights'
  own equation with the membrane force extrapolated the same way (:meth:`EquilibriumSolver._heights_step`);
* scales a step with a stale tangent (not in a checked load step, where it did not pay) by the
  length that minimised the energy along the last full step made with it (:func:`_step_length`);
* may reuse the last factorisation for several iterations (modified Newton) and
  refactors when the residual falls by less than ``contraction`` per iteration
  (unless that iteration converged: a residual at its round-off floor does not contract);
  in a load step that factors the tangent at its end anyway (a stability check), only
  when the iterations the stale tangent still needs at that rate cost more than a
  factorisation (:func:`_iterations_left`, ``factorisation_cost``);
* converges when the residual is below ``residual_tol * force_scale`` and the
  remaining position error, estimated from the last increment and the residual
  reduction ratio ``q`` as ``|dx| q / (1 - q)``, is below
  ``increment_tol * length_scale``; a biased height's row (a force on the rigid disk)
  by the height and membrane force errors it leaves (:func:`_balanced`);
* checks that the equilibrium is a stable minimum from the inertia of the
  ``LDL^T`` factorisation of ``K_ff`` at the converged state (a Cholesky test).

Biased units add their indenter heights as unknowns bordering ``K_ff``
(:mod:`.indenters`); the stability check then adds the negative eigenvalues of the
bordered Schur complement, and a quasi-static path that passes a limit point of a biased
unit (snap-through) is detected and landed on the stable branch it jumps to
(:mod:`.snap`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numba
import numpy as np

from .bias import BiasRangeError
from .indenters import IndenterBorder, IndenterLoad, negative_eigenvalues
from .kernels import JIT, internal_forces, solve_small, tangent_values
from .linsolve import BACKENDS, Factoriser, LDLFactor, factoriser
from .membrane import BIASED, DRIVEN, MembraneModel, held
from .snap import Snap, land_after_snap


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """``np.array_equal``, at once for one array (the model caches the free dofs per unit modes: the
    comparison of two arrays of thousands of dofs runs several times per warm update)."""
    return a is b or np.array_equal(a, b)


def _norm(v: np.ndarray) -> float:
    """Euclidean norm without BLAS: a multithreaded BLAS ``dot`` on a loaded machine can take
    milliseconds for 15k entries (measured: 5 ms per call on the 3-by-3 array at load 5)."""
    return float(np.sqrt(np.sum(v * v)))


class ConvergenceError(RuntimeError):
    """Newton did not reach equilibrium, even after cutting the load step."""


class SolveCancelled(RuntimeError):
    """The caller's ``cancel`` callback stopped the solve (it is asked before every Newton iteration)."""


@dataclass(frozen=True)
class NewtonSettings:
    """Tolerances and limits of the Newton solver.

    Attributes
    ----------
    residual_tol : float
        Max |free residual| relative to the model's force scale ``t0 c10 D``.
    increment_tol : float
        Max |last increment| relative to the model's length scale ``D``.
    max_iterations : int
        Newton iterations per load step before the step counts as failed.
    max_step_cuts : int
        Times a load step may be halved before the solve raises.
    modified_newton : bool
        Reuse a factorisation across iterations while the residual falls by at
        least ``contraction`` per iteration.
    contraction : float
        Required residual reduction factor per modified-Newton iteration.  0.3 is
        the cheapest of 0.02-0.5 over warm updates, curves and cold solves on the
        1-by-3 (one factorisation costs about 10-15 iterations there; see
        ``benchmarks/bench_core.py``); 0.5 kept stale tangents for up to 13 iterations.
    factorisation_cost : float
        What a factorisation with its tangent costs, in Newton iterations (a residual and
        a solve with the factors): on the default 1-by-3 ~6.5 ms against ~0.65 ms.  In a
        load step whose converged state is factored anyway (a stability check), a tangent
        that contracts by less than ``contraction`` is refactored only when the residual
        needs more iterations than this at the rate it falls (:func:`_iterations_left`):
        the refactored tangent would serve that step only, the next one starts from the
        check's.
    check_stability : bool
        Factor the tangent at the converged state and report its inertia.
    unstable_step : float
        A load step longer than this fraction of the path that converges to a
        state whose tangent is not positive definite, starting from a stable one, is
        retried in halves: a long step can land on a spurious (saddle) branch, e.g.
        two indenters pulled 8 mm out of the flat membrane at once.  Shorter steps
        are accepted and their state reported unstable.
    long_jump : float
        A solve whose indenter displacements change by more than this fraction of
        D is checked for stability (and so retried as above) even when
        ``check_stability`` is off: a jump is where a spurious branch is likely,
        and one factorisation is cheap next to its load steps.
    linear_solver : str
        Factorisation of ``K_ff`` (:mod:`.linsolve`): ``"block"`` (compiled multifrontal
        LDL^T on 3x3 node blocks with symbolic reuse, the default), ``"block-uplooking"``
        (the same, one block at a time: the reference) or ``"superlu"`` (scipy).
    factor_threads : int
        Threads of a ``"block"`` factorisation: 2 factors two subtrees of the elimination
        tree at once where that pays (:meth:`.linsolve.Factoriser.factor`; the same factors
        to the last bit), 1 keeps it on the calling thread.
    snap_step : float
        Load-path fraction below which a step of a path with biased units that fails
        to converge, or that moves a height ``jump_tol`` away from its linear
        prediction, is taken for a limit point: the state is continued in that unit's
        height until it lands on the stable branch (:mod:`.snap`).  Longer such steps
        are retried in halves.
    jump_tol : float
        Largest distance (fraction of D) between a biased unit's converged height and
        the linear prediction of its load step before the step counts as a jump to
        another branch.
    snap_reach : float
        Largest move (fraction of D) of a biased height in one quasi-static load step;
        a longer one is retried in halves like a jump (a prediction near a limit point
        can reach past the fold), and at ``snap_step`` counts as a snap.
    snap_march : float
        Height increment (fraction of D) of the continuation that looks for the branch a
        snapping unit lands on.
    """

    residual_tol: float = 1e-8
    increment_tol: float = 1e-7
    max_iterations: int = 30
    max_step_cuts: int = 12
    modified_newton: bool = True
    contraction: float = 0.3
    factorisation_cost: float = 10.0
    check_stability: bool = True
    unstable_step: float = 1.0 / 32.0
    long_jump: float = 0.1
    linear_solver: str = "block"
    factor_threads: int = 2
    snap_step: float = 1.0 / 256.0
    jump_tol: float = 0.01
    snap_reach: float = 0.025
    snap_march: float = 0.02

    def __post_init__(self) -> None:
        if self.linear_solver not in BACKENDS:
            raise ValueError(f"linear_solver must be one of {BACKENDS}, got {self.linear_solver!r}")
        if self.factor_threads not in (1, 2):
            raise ValueError(f"factor_threads must be 1 or 2, got {self.factor_threads!r}")


@dataclass
class Factorisation:
    """An ``LDL^T`` factorisation of ``K_ff`` at one state (:mod:`.linsolve`), with the
    tangent's nonzeros ``values`` it was made of: the ``K_fp`` block and the disks'
    ``K_ww`` are cut from them when asked for (a checked update never needs them).
    """

    factor: LDLFactor
    values: np.ndarray
    model: MembraneModel
    free: np.ndarray
    prescribed: np.ndarray
    state: np.ndarray | None = None  # the converged positions it was computed at, if any
    _influence: dict = field(default_factory=dict)
    _negative: int | None = None
    #: The step length, in Newton steps, that minimised the energy along its last full step
    #: (:func:`_step_length`): what the next step with it, once stale, is scaled by.
    step_length: float = 1.0

    @functools.cached_property
    def k_fp(self):
        """The free-prescribed block ``K_fp`` (CSR)."""
        return self.model.pattern.block(self.values, self.free, self.prescribed)

    @functools.cached_property
    def disk_stiffness(self) -> np.ndarray:
        """:meth:`.membrane.MembraneModel.disk_stiffness`: the ``K_ww`` block of biased units' heights."""
        return self.model.disk_stiffness(self.values)

    def coupling(self, idx: np.ndarray) -> np.ndarray:
        """``K_fp 1_idx``: the free dofs' forces per unit rigid move of the prescribed dofs ``idx``."""
        return self.model.pattern.column_sum(self.values, self.free, self.prescribed[idx])

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``K_ff^-1 b``."""
        return self.factor.solve(b)

    @property
    def negative_pivots(self) -> int:
        """Number of negative eigenvalues of ``K_ff`` (0: a stable minimum), -1 if unknown.

        Read from ``D`` on first access (by Sylvester's law of inertia).
        """
        if self._negative is None:
            self._negative = self.factor.negative_pivots()
        return self._negative

    def influence(self, idx: np.ndarray) -> np.ndarray:
        """``-K_ff^-1 K_fp 1_idx``: the free dofs' response to a unit rigid move of the prescribed dofs
        ``idx`` (one solve, the first time it is asked for)."""
        key = idx.tobytes()
        if key not in self._influence:
            self._influence[key] = -self.solve(self.coupling(idx))
        return self._influence[key]

    def predict(self, dxp: np.ndarray, groups: list[np.ndarray]) -> np.ndarray:
        """Linear response ``-K_ff^-1 K_fp dxp`` of the free dofs to a prescribed change.

        ``groups`` are index sets into the prescribed dofs that usually move together
        (the z dofs of one indenter disk).  A group moved rigidly costs no solve: its
        influence vector ``-K_ff^-1 K_fp 1_group`` is computed once per factorisation.
        Any other change (the frame's X dofs moving with the slip factor of eq. 11)
        costs one solve.
        """
        rest = dxp.copy()
        out = np.zeros(self.free.size)
        for idx in groups:
            amount = dxp[idx]
            if amount[0] != 0.0 and np.all(amount == amount[0]):
                out += amount[0] * self.influence(idx)
                rest[idx] = 0.0
        if np.any(rest):
            out -= self.solve(self.k_fp @ rest)
        return out


@dataclass(frozen=True)
class PathRecord:
    """What the last solve did: what the continuation predictors of the next one extrapolate.

    Attributes
    ----------
    end : ndarray
        The converged positions it ended at.
    dx_f, dp : ndarray
        Its change of the free and of the prescribed dofs.
    free : ndarray
        Its free dofs.
    voltage : ndarray
        The voltage it ended at [V].
    heights_only : bool
        Whether only the biased units' loads changed along it (no voltage, driven
        displacement or frame change): its ``dx_f`` is then the membrane's response to ``dw``.
    load_change : ndarray or None
        Its quasi-static change of the biased units' loads [N] (None: not a loads-only solve).
    units : ndarray or None
        The biased units in contact along it.
    dw : ndarray or None
        Their height change [m].
    membrane_force : ndarray or None
        Their membrane forces ``F_k`` at the end [N].
    force_change : ndarray or None
        Their change along this solve [N] (None: the start's forces are not known).
    before : PathRecord or None
        The heights-only solve that ended where this heights-only one started (its own
        ``before`` dropped: the third state of the quadratic continuation), or the solve
        without biased units that this one continued (:meth:`EquilibriumSolver._secant`), with
        its own ``before`` up to :data:`CONTINUATION_DEGREE` states back in all.
    """

    end: np.ndarray
    dx_f: np.ndarray
    dp: np.ndarray
    free: np.ndarray
    voltage: np.ndarray
    heights_only: bool = False
    load_change: np.ndarray | None = None
    units: np.ndarray | None = None
    dw: np.ndarray | None = None
    membrane_force: np.ndarray | None = None
    force_change: np.ndarray | None = None
    before: PathRecord | None = None

    def continuation(self, scale: float, ratio: float | None) -> tuple[np.ndarray, np.ndarray]:
        """``(dx_f, dw)``: the change of the free dofs and heights at ``scale`` times this path's change.

        :func:`_extrapolate` through this path's and :attr:`before`'s changes (``before``'s
        change being ``ratio`` times this one's; None: the secant ``s dx_n``).
        """
        before = self.before if ratio is not None else None
        return (_extrapolate(scale, ratio, self.dx_f, before.dx_f if before else None),
                _extrapolate(scale, ratio, self.dw, before.dw if before else None))

    def continues(self, x: np.ndarray, free: np.ndarray, voltage: np.ndarray) -> bool:
        """Whether a solve from ``x`` with these ``free`` dofs at ``voltage`` starts where this one ended."""
        return _same(self.end, x) and _same(self.free, free) and np.array_equal(self.voltage, voltage)


def _extrapolate(scale: float, ratio: float | None, last: np.ndarray, before: np.ndarray | None,
                 slope: bool = False) -> np.ndarray:
    """Change of a quantity at ``scale`` times the last path's change ``last``, continuing its path.

    The quadratic through the last three states (:func:`_path_basis`, :func:`_on_path`), with the
    path parameter ``lambda`` running over ``[-1, 0]`` along the last solve and over
    ``[-1 - a, -1]`` along the one before (changing by ``before``, ``a = ratio`` times the last
    one's change of the commands): third-order accurate along a smooth path (the secant
    ``lambda dq_n`` alone: second order), and exact for a reversal (``lambda = -1``).
    ``ratio`` None: the secant.  ``slope``: ``dq / dlambda`` at ``scale`` instead.
    """
    nodes = _quadratic_nodes(ratio)
    coefficients = _path_coefficients(scale, _path_basis(nodes, np.arange(nodes.size)), slope)
    return _on_path(coefficients, [last] if ratio is None else [last, before])


def _quadratic_nodes(ratio: float | None) -> np.ndarray:
    """Path parameters of the last two states (``ratio`` None) or three (:func:`_extrapolate`)."""
    return np.array((0.0, -1.0) if ratio is None else (0.0, -1.0, -1.0 - ratio))


# The continuation's scalar algebra is compiled (:data:`.kernels.JIT`): a few numbers each, where numpy's and
# the interpreter's per-call costs were most of an update's continuation (0.08 of ~1.2 ms, docs/architecture.md).
@numba.njit(**JIT)
def _path_basis(nodes: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """``N`` of the polynomial through states at the path parameters ``nodes`` (``nodes[0] = 0``: the last).

    With the states given by their changes ``c_i = q_i - q_{i+1}`` (the newest first) and
    ``nodes[j]`` the parameter of state ``q_{p_j}``, ``p = positions`` (``0, 1, 2, ...`` unless
    a state that repeats a newer one's command is left out), the polynomial with
    ``P(t_j) = q_{p_j}`` is

        P(lambda) - q_0 = -sum_m lambda^m sum_i N_mi c_i,    m = 1..M,

    where ``N_mi = sum_{j: p_j > i} a_mj``, ``a_mj`` the coefficient of ``lambda^m`` in the
    Lagrange polynomial ``l_j`` of ``t_j`` (``q_p - q_0 = -(c_0 + ... + c_{p-1})``; ``l_j(0) = 0``
    for ``j >= 1``).  Returns ``N``, shape ``(M, p_last)``.
    """
    degree = nodes.size - 1
    lagrange = np.zeros((degree, degree + 1))  # lagrange[j - 1, m]: coefficient of lambda^m in l_j
    poly, product = np.empty(degree + 1), np.empty(degree + 1)
    for j in range(1, degree + 1):
        poly[:] = 0.0
        poly[0] = 1.0
        length = 1
        for i in range(nodes.size):
            if i != j:  # poly *= (lambda - t) / (t_j - t)
                t = nodes[i]
                scale = 1.0 / (nodes[j] - t)
                for m in range(length + 1):
                    product[m] = scale * ((poly[m - 1] if m > 0 else 0.0) - t * (poly[m] if m < length else 0.0))
                length += 1
                poly[:length] = product[:length]
        lagrange[j - 1] = poly
    basis = np.zeros((degree, positions[-1]))
    for m in range(1, degree + 1):
        for i in range(positions[-1]):
            for j in range(1, degree + 1):
                if positions[j] > i:
                    basis[m - 1, i] += lagrange[j - 1, m]
    return basis


@numba.njit(**JIT)
def _path_coefficients(lam: float, basis: np.ndarray, slope: bool = False) -> np.ndarray:
    """``-u(lambda) N`` of :func:`_path_basis` (``slope``: ``-u'(lambda) N``): the polynomial's change
    from the last state (its slope) is ``sum_i c_i changes[i]`` (:func:`_on_path`)."""
    degree, count = basis.shape
    out = np.zeros(count)
    for i in range(count):
        for m in range(degree):
            out[i] -= ((m + 1) * lam**m if slope else lam ** (m + 1)) * basis[m, i]
    return out


def _on_path(coefficients: Sequence[float], changes: Sequence[np.ndarray]) -> np.ndarray:
    """``sum_i c_i changes[i]``: the polynomial's change from the last state (or its slope) with the
    coefficients of :func:`_path_coefficients`, the states given by their changes ``changes[i] =
    q_i - q_{i+1}`` (the last solve's first)."""
    out = coefficients[0] * changes[0]
    for c, change in zip(coefficients[1:], changes[1:]):
        out += c * change
    return out


def compile_continuation() -> None:
    """Compile the continuation's kernels (or load them from numba's on-disk cache) with the types a solve
    gives them, so that no update of a live twin does (:meth:`.twin.ArrayTwin.warm_up`)."""
    changes = [np.array([1.0, 0.0, 0.0]), np.array([0.9, 0.3, 0.0]), np.array([0.7, 0.6, 0.1])]
    _on_command_path(np.array([1.0, 0.2, 0.0]), changes, 1.0)
    _extrapolate(0.5, None, changes[0], None)
    _extrapolate(0.5, 0.8, changes[0], changes[1], slope=True)
    _within_reach(0.5, _quadratic_nodes(0.8))
    _usable(0.8)


@dataclass
class SolveStats:
    """What one solve did."""

    iterations: int = 0
    factorisations: int = 0
    steps: int = 0
    step_cuts: int = 0
    residual_norm: float = float("nan")
    stability_checked: bool = False
    #: Negative eigenvalues of the (bordered) tangent at the end when checked; -1 unknown.
    negative_eigenvalues: int = -1
    #: Snap-throughs on the way: :class:`~.snap.Snap` records.
    snaps: list = field(default_factory=list)


def factorise(model: MembraneModel, ke: np.ndarray, free: np.ndarray, prescribed: np.ndarray,
              backend: str = "block") -> Factorisation:
    """Assemble ``K`` from element matrices ``ke`` and factor its free-free block (no reuse)."""
    values = model.pattern.values(ke)
    return Factorisation(Factoriser(model.pattern, free, backend).factor(values), values, model, free, prescribed)


class EquilibriumSolver:
    """Solves for equilibria of one model, keeping the last factorisation for warm starts."""

    def __init__(self, model: MembraneModel, settings: NewtonSettings | None = None):
        self.model = model
        self.settings = settings or NewtonSettings()
        self.factorisation: Factorisation | None = None
        self._disk_groups: dict[tuple[str, ...], list[np.ndarray]] = {}
        self._last_border: tuple | None = None  # (modes, IndenterBorder)
        #: What the continuation predictors extrapolate.
        self._last_path: PathRecord | None = None
        #: Set by a twin that refreshes its tangent in a worker thread (``background_tangent`` of
        #: :class:`.twin.ArrayTwin`): a tangent that contracts by less than ``contraction`` is then kept,
        #: as in a checked load step, while the iterations it still needs cost less than a factorisation
        #: (a refactorisation here would hold the solve for it).
        self.refresh_elsewhere = False
        #: The largest residual ratio (after / before) of a Newton step on a tangent from an earlier
        #: iterate, over the steps that started above the tolerance, since this was set to 0: how stale the
        #: tangent has gone (the twin refreshes it elsewhere above :data:`.twin.BACKGROUND_CONTRACTION`).
        self.stale_contraction = 0.0

    def disk_groups(self, modes: tuple[str, ...]) -> list[np.ndarray]:
        """Index sets into the prescribed dofs of each driven or biased disk's z dofs (rigid moves)."""
        if modes not in self._disk_groups:
            m = self.model
            prescribed = m.prescribed_dofs(modes)[0]
            self._disk_groups[modes] = [np.flatnonzero(np.isin(prescribed, m.disk_z_dofs(k)))
                                        for k, mode in enumerate(modes) if held(mode)]
        return self._disk_groups[modes]

    def _border(self, modes: tuple[str, ...], prescribed: np.ndarray, load: IndenterLoad) -> IndenterBorder:
        """The biased heights' border of ``modes``, kept across solves with its blocks per factorisation."""
        if self._last_border is None or self._last_border[0] != modes:
            units = [k for k, mode in enumerate(modes) if mode == BIASED]
            self._last_border = (modes, IndenterBorder.for_units(self.model, units, prescribed, load))
        border = self._last_border[1]
        border.load, border.outside = load, None
        return border

    def _tangent(self, x: np.ndarray, maxwell: np.ndarray) -> np.ndarray:
        """Nonzeros of the tangent at ``x`` (:func:`.kernels.tangent_values`)."""
        m = self.model
        return tangent_values(m.disc, m.pattern, x, m.yeoh, maxwell, m.thickness)[1]

    def _factorise(self, values: np.ndarray, free: np.ndarray, prescribed: np.ndarray,
                   threads: int | None = None) -> Factorisation:
        """Factor ``K_ff`` of the tangent nonzeros ``values``, reusing the symbolic analysis of ``free``
        (on ``threads``, default ``settings.factor_threads``)."""
        factor = factoriser(self.model.pattern, free, self.settings.linear_solver).factor(
            values, self.settings.factor_threads if threads is None else threads)
        return Factorisation(factor, values, self.model, free, prescribed)

    def factorise_at(self, x: np.ndarray, maxwell: np.ndarray, free: np.ndarray, prescribed: np.ndarray,
                     stats: SolveStats, threads: int | None = None) -> Factorisation:
        """The factorised tangent at the converged ``x`` (counted in ``stats``; on ``threads``, default
        ``settings.factor_threads``)."""
        fact = self._factorise(self._tangent(x, maxwell), free, prescribed, threads)
        fact.state = x
        stats.factorisations += 1
        return fact

    def background_tangent(self, x: np.ndarray, maxwell: np.ndarray, modes: tuple[str, ...],
                           groups: list[np.ndarray], threads: int) -> Factorisation:
        """:meth:`factorise_at` the converged ``x`` of unit ``modes`` on ``threads``, for a worker thread:
        with the influence vectors of the disk ``groups`` (:meth:`disk_groups`, asked for in the calling
        thread) computed too, which the first update to start from it would otherwise solve for (three
        solves on the 1-by-3, 0.9 ms)."""
        prescribed, free = self.model.prescribed_dofs(modes)
        fact = self.factorise_at(x, maxwell, free, prescribed, SolveStats(), threads)
        for idx in groups:
            fact.influence(idx)
        return fact

    # ------------------------------------------------------------------ one step
    def _newton(self, x: np.ndarray, free: np.ndarray, prescribed: np.ndarray, maxwell: np.ndarray,
                fact: Factorisation | None, stats: SolveStats, cancel: Callable[[], bool] | None = None,
                border: IndenterBorder | None = None, checked: bool = False) -> tuple | None:
        """Newton iterations at fixed prescribed values (and biased heights as unknowns: ``border``).

        ``checked``: the converged state will be factored (a stability check), so a stale
        tangent is refactored only when it would cost more iterations than a factorisation.

        Returns ``(x, r, point_state, factorisation)`` at convergence, None on failure.
        Raises :class:`SolveCancelled` when ``cancel()`` is true before an iteration.
        """
        m, s = self.model, self.settings
        args = (m.yeoh, maxwell, m.thickness)
        r_tol = s.residual_tol * m.force_scale
        x_tol = s.increment_tol * m.length_scale
        if fact is not None and not _same(fact.free, free):
            fact = None
        fresh = False  # whether ``fact`` was computed at the current iterate
        r, point = internal_forces(m.disc, x, *args)
        res = _residual(r, x, free, border)
        norm = _norm(res)
        last_dx, converged = np.inf, False
        for _ in range(s.max_iterations):
            if cancel is not None and cancel():  # the cancel point: between iterations
                raise SolveCancelled(f"solve cancelled after {stats.iterations} Newton iterations")
            if not np.isfinite(norm):
                return None
            if converged:
                stats.residual_norm = float(np.abs(res).max())
                return x, r, point, fact
            if fact is None:
                fact = self._factorise(self._tangent(x, maxwell), free, prescribed)
                stats.factorisations += 1
                fresh = True
            scale = 1.0
            if border is None:
                dx, dw = -fact.solve(res), np.zeros(0)
                if not fresh and not checked:
                    scale = fact.step_length
                    dx *= scale
            else:
                step = border.direction(fact, res[:free.size], res[free.size:], x, r_tol)
                if step is None:  # singular S: at a limit point, or a stale tangent
                    if fresh:
                        return None
                    fact = None
                    continue
                dx, dw = step
            stats.iterations += 1
            for alpha in (1.0, 0.5, 0.25, 0.125, 0.0625):  # backtrack on the residual norm
                trial = x.copy()
                trial[free] += alpha * dx
                if border is not None:
                    border.move(trial, alpha * dw)
                r_trial, point_trial = internal_forces(m.disc, trial, *args)
                res_trial = _residual(r_trial, trial, free, border)
                norm_trial = _norm(res_trial)
                if np.isfinite(norm_trial) and (norm_trial < norm or np.abs(res_trial).max() <= r_tol):
                    break
            else:
                if fresh:
                    return None
                fact = None  # a stale tangent failed: refactor here and retry
                continue
            if border is None and alpha == 1.0:
                fact.step_length = _step_length(dx, res, res_trial, scale, fact.step_length)
            ratio = norm_trial / norm if norm > 0 else 0.0
            if not fresh and norm > r_tol:  # a step from a residual at its round-off floor says nothing
                self.stale_contraction = max(self.stale_contraction, ratio)
            x, r, res, point, norm = trial, r_trial, res_trial, point_trial, norm_trial
            # With contraction ratio q the remaining error is about |dx| q / (1 - q)
            # (a geometric series): that is what is tested against the tolerance.
            step_size = alpha * max(np.abs(dx).max(), np.abs(dw).max(initial=0.0))
            last_dx = step_size * ratio / (1.0 - ratio) if (alpha == 1.0 and ratio < 0.9) else step_size
            # A step that left the free residual alone (only the heights moved) says nothing
            # about how good the tangent is, nor does one that ended converged (the residual
            # at its round-off floor contracts by nothing): the tangent stays for the next solve.
            converged = last_dx <= x_tol and _balanced(res, free.size, r_tol, x_tol, fact, border)
            slow = ratio > s.contraction and not converged
            stale = slow and not ((checked or self.refresh_elsewhere)
                                  and _iterations_left(norm, r_tol, ratio) <= s.factorisation_cost)
            if not s.modified_newton or (stale and not (border is not None and border.skipped_solve)):
                fact = None
            fresh = False
        return None

    # ------------------------------------------------------------------ load path
    def solve(self, x: np.ndarray, modes: tuple[str, ...], start_displacement: np.ndarray,
              displacement: np.ndarray, start_voltage: np.ndarray, voltage: np.ndarray,
              check_stability: bool | None = None, load: IndenterLoad | None = None,
              detect_snaps: bool = True, guess: dict[int, float] | None = None,
              cancel: Callable[[], bool] | None = None) -> tuple:
        """Equilibrium at (``displacement``, ``voltage``) starting from state ``x``.

        ``x`` is a converged state at (``start_displacement``, ``start_voltage``)
        for driven units; it is not modified.  Biased units' disks must be flat in
        ``x`` (:meth:`.membrane.MembraneModel.place_disk`); their heights are unknowns
        pushed by ``load`` (required when a unit is biased), which sees the load-path
        fraction ``t``.  Returns the new positions, the internal forces there, the
        :class:`~.assembly.PointState` there and :class:`SolveStats`.
        ``check_stability`` overrides the setting for this solve; ``detect_snaps``
        turns the snap-through handling of biased paths on (quasi-static) or off (a
        dynamic step).  ``guess`` gives starting heights [m] of biased units for the first
        load step (a time integrator's prediction); the free dofs follow them through the
        linear predictor.  Raises :class:`ConvergenceError`, or :class:`SolveCancelled` as soon
        as ``cancel()`` (asked before every Newton iteration) returns True.
        """
        m, s = self.model, self.settings
        check = s.check_stability if check_stability is None else check_stability
        d0, d1 = np.asarray(start_displacement, float), np.asarray(displacement, float)
        driven = np.array([mode == DRIVEN for mode in modes])  # free units have no indenter to jump
        check = check or bool(np.abs(d1 - d0)[driven].max(initial=0.0) > s.long_jump * m.length_scale)
        prescribed, free = m.prescribed_dofs(modes)
        groups = self.disk_groups(modes)
        biased = [k for k, mode in enumerate(modes) if mode == BIASED]
        if biased and load is None:
            raise ValueError(f"units {[k + 1 for k in biased]} are biased: solve needs their load")
        border = self._border(modes, prescribed, load) if biased else None
        stats = SolveStats()
        v0, v1 = np.asarray(start_voltage, float), np.asarray(voltage, float)
        # With a slip table (eq. 11) the frame of ``x`` may not be where the path starts
        # (after a reset to the gamma = 1 flat state, or when the driven units change):
        # that lag is blended out along the path, so step cuts also shorten a frame jump.
        # Without slip it is exactly zero.
        frame = m.mesh.frame_nodes
        lag = x.reshape(-1, 3)[frame] - m.frame_positions(modes, d0)
        fact = self.factorisation
        if border is not None:
            border.begin(0.0)
        same_free, old, x_start = fact is not None and _same(fact.free, free), fact, x

        @functools.cache
        def start_stable() -> bool:
            """Whether the start state is a stable one (asked only when a step lands on an unstable state)."""
            if same_free:
                return negative_eigenvalues(old, x_start, border, False, 0.0) == 0
            return old is None or old.negative_pivots == 0

        if not same_free:
            # No tangent of this free set yet (a fresh twin, new unit modes): one at the
            # start state gives the linear predictor of the first step.
            fact = self._factorise(self._tangent(x, m.maxwell(v0)), free, prescribed)
            stats.factorisations += 1
            self.factorisation = fact
        secant = (self._secant(x, free, prescribed, d0, d1, v0, v1, modes)
                  if not lag.any() and border is None else None)
        # Only the biased units' loads change (force, bias, a time step's inertia): the heights
        # and the free dofs following them continue the last such solve.
        driven_units = [k for k, md in enumerate(modes) if md == DRIVEN]
        heights_only = (border is not None and not lag.any() and np.array_equal(v0, v1)
                        and np.array_equal(d0[driven_units], d1[driven_units]))
        loads_only = heights_only and not guess  # quasi-static: the load change is the whole change
        load_change = border.load_change(border.heights(x), 0.0, 1.0) if loads_only else None
        last = self._last_path
        continuing = last is not None and last.continues(x, free, v0)
        done, step, cuts, retries, snap_tried = 0.0, 1.0, 0, 0, -1.0
        while done < 1.0:
            t = min(1.0, done + step)
            trial = x.copy()
            m.apply_prescribed(trial, modes, d0 + t * (d1 - d0))
            if lag.any():
                trial.reshape(-1, 3)[frame] += (1.0 - t) * lag
            continuation = None
            if border is not None:
                border.begin(t)
                if t == 1.0 and done == 0.0 and heights_only and continuing:
                    continuation = (self._heights_secant(load_change) if loads_only
                                    else self._heights_step(border, fact, border.heights(x)))
            if guess and done == 0.0 and continuation is None:
                for k, w in guess.items():
                    trial[m.disk_z_dofs(k)] = w
            if border is not None:
                if continuation is not None:  # free dofs and heights move together
                    dx_along, dw_along, dw = continuation
                    trial[free] += dx_along
                    border.move(trial, dw)
                else:
                    border.predict(fact, trial, done)
            change = trial[prescribed] - x[prescribed]
            if continuation is not None:  # the continuation moved the free dofs with dw_along already
                for group, rest in zip(border.groups, dw - dw_along):
                    change[group] = rest
            if t == 1.0 and done == 0.0 and secant is not None:  # the last solve's path, continued
                scale, dx_last, dp_last, dx_along, dp_along = secant
                if fact.state is not None and fact.state is self._last_path.end:  # tangent at x: quadratic
                    trial[free] += (scale + scale**2) * fact.predict(dp_last, groups) - scale**2 * dx_last
                    change = change - scale * dp_last
                else:
                    trial[free] += dx_along
                    change = change - dp_along
            trial[free] += fact.predict(change, groups)  # linear predictor from the last tangent
            maxwell = m.maxwell(v0 + t * (v1 - v0))
            if border is not None:
                border.start = border.heights(trial)
            outcome = self._newton(trial, free, prescribed, maxwell, fact, stats, cancel, border, check)
            if (outcome is not None and border is not None and detect_snaps
                    and self._jumped(border, outcome[0], border.heights(x))):
                if t - done > s.snap_step:  # maybe another branch: retry in halves
                    retries += 1
                    stats.step_cuts = cuts + retries
                    step = 0.5 * (t - done)
                    continue
                outcome = None  # a jump over the shortest step: a limit point, landed below
            if outcome is None:
                # A stalled path of biased units may be a limit point: once the step is short,
                # look for the branch it jumps to (once per point reached), whatever the cuts so far.
                can_snap = border is not None and detect_snaps and snap_tried != done
                if can_snap and t - done <= s.snap_step:
                    snap_tried = done
                    landing = land_after_snap(self, trial, free, prescribed, maxwell, border, stats, cancel)
                    if landing is not None:
                        x_new, r, point, fact, unit = landing
                        stats.snaps.append(Snap(int(unit), float(x[m.disk_z_dofs(unit)[0]]),
                                                float(x_new[m.disk_z_dofs(unit)[0]]), t))
                        x, done, step = x_new, t, s.snap_step
                        stats.steps += 1
                        self.factorisation = fact
                        continue
                    can_snap = False
                cuts += 1
                stats.step_cuts = cuts + retries
                if cuts > s.max_step_cuts and not can_snap:
                    reached_d, reached_v = d0 + done * (d1 - d0), v0 + done * (v1 - v0)
                    raise ConvergenceError(
                        f"Newton failed to converge after {cuts - 1} step cuts: reached {done:.3g} of the load "
                        f"path (displacement {np.round(reached_d, 9).tolist()} m, voltage "
                        f"{np.round(reached_v, 3).tolist()} V) on the way to displacement {d1.tolist()} m, "
                        f"voltage {v1.tolist()} V; beyond it the membrane may have no stable equilibrium "
                        f"(e.g. electromechanical instability at high voltage)"
                        + (f"; the last refused trial: {border.outside}" if border is not None and border.outside
                           else ""))
                step *= 0.5
                fact = self.factorisation if (self.factorisation is not None
                                              and _same(self.factorisation.free, free)) else None
                continue
            x_new, r, point, fact_used = outcome
            if check or fact_used is None:
                fact_new = self.factorise_at(x_new, maxwell, free, prescribed, stats)
                if (t - done > s.unstable_step and negative_eigenvalues(fact_new, x_new, border, static=False) > 0
                        and start_stable()):
                    retries += 1  # a long step onto an unstable state: retry it in halves
                    stats.step_cuts = cuts + retries  # (not a Newton failure: max_step_cuts counts those)
                    step = 0.5 * (t - done)
                    continue
            else:
                fact_new = fact_used
            x, fact, done = x_new, fact_new, t
            stats.steps += 1
            step = min(2.0 * step, 1.0)
            self.factorisation = fact
        stats.stability_checked = check
        if check:
            stats.negative_eigenvalues = negative_eigenvalues(fact, x, border)
        record = dict(end=x, dx_f=x[free] - x_start[free], dp=x[prescribed] - x_start[prescribed], free=free,
                      voltage=v1, heights_only=heights_only, load_change=load_change)
        if border is None and secant is not None:  # it continued the last solve's path
            record.update(before=_truncated(last, CONTINUATION_DEGREE - 1))
        if border is not None:
            before = None
            if heights_only and continuing and last.heights_only and np.array_equal(last.units, border.units):
                before = _truncated(last, 1)
            force = border.membrane_force(r)
            record.update(units=border.units, dw=border.heights(x) - border.heights(x_start), membrane_force=force,
                          before=before, force_change=force - before.membrane_force if before is not None else None)
        self._last_path = PathRecord(**record)
        return x, r, point, stats

    def _jumped(self, border: IndenterBorder, x_new: np.ndarray, w_from: np.ndarray) -> bool:
        """Whether a load step from heights ``w_from`` may have jumped to another branch.

        Either a biased height moved ``jump_tol * D`` away from the step's linear prediction,
        Newton's first iterate ``w_start + dw_1``: the heights it started from (with a time
        integrator's guess ``w + dt v + dt^2 a / 2``, the load step's predictor or a
        continuation) plus its first bordered step, which holds the response of the tangent
        to everything that changed at fixed heights (loads, voltage through the Maxwell term,
        driven units).  A continuous move of the equilibrium converges close to it (the
        distance is second order in the step); a jump to another branch does not.  Or a
        height moved more than ``snap_reach * D`` in the step: near a limit point the
        stiffness ``S`` is small and the prediction ``S^-1 dG`` itself may reach past the
        fold onto the far branch, where Newton then converges without a mismatch (a dome
        bias: a force step from 0 to 5 mN over its 3.5 mN peak landed 1.4 mm up unreported).
        Shorter steps either stay on their branch or show the jump.
        """
        heights = border.heights(x_new)
        if np.abs(heights - w_from).max() > self.settings.snap_reach * self.model.length_scale:
            return True
        if border.first_dw is None or border.start is None:
            return False
        predicted = border.start + border.first_dw
        return bool(np.abs(heights - predicted).max() > self.settings.jump_tol * self.model.length_scale)

    def _secant(self, x: np.ndarray, free: np.ndarray, prescribed: np.ndarray, d0: np.ndarray, d1: np.ndarray,
                v0: np.ndarray, v1: np.ndarray, modes: tuple[str, ...]) -> tuple | None:
        """``(s, dx_f, dp, dx_along, dp_along)`` when this solve continues the last one: same free
        dofs and voltage, starting where it ended, the prescribed change ``dp_along`` (``s dp``, or
        a point of the curve through the last commands) plus a remainder.

        The last solve moved the free dofs by ``dx_f`` for a prescribed change ``dp``; with
        ``s = <dp_new, dp> / <dp, dp>`` the prediction ``x_f + s dx_f + T (dp_new - s dp)``
        (``T`` the tangent predictor) is second-order accurate along a smooth command path
        (a curve, a sine) where the tangent predictor alone is first-order, and exact for a
        reversal (``s = -1``).  When the last solve continued the ones before it
        (:attr:`PathRecord.before`), ``dx_along`` replaces ``s dx_f``: the new command is placed on
        the polynomial through the last commands, up to :data:`CONTINUATION_DEGREE` + 1 of them
        (:func:`_on_command_path`: along one direction that is ``s dp``; units moving with
        different phases, the node's command stream, make a curve), and the states are
        extrapolated to that point of the polynomial through them: order ``degree + 1`` (the
        states of a solve without biased units are a function of the command, so a turn between
        them is no harm as long as they are apart: :func:`_path_nodes`, :func:`_within_reach`).
        Fewer states (the first solves of a path, states too close together, a reach too far)
        lower the degree, down to the secant; a state that repeats a newer one's command is left
        out, so a motion that turned back retraces the states it passed.
        """
        last = self._last_path
        if last is None or not np.array_equal(v0, v1) or not last.continues(x, free, v0):
            return None  # (x: the caller's start state, which a twin keeps as the last end state)
        target = x.copy()
        self.model.apply_prescribed(target, modes, d1)
        dp_new, dp = target[prescribed] - x[prescribed], last.dp
        scale = _along(dp_new, dp, exact=False)
        if scale is None:
            return None
        commands, states, record = [dp], [last.dx_f], last.before
        while record is not None and len(commands) < CONTINUATION_DEGREE and record.dp.shape == dp.shape:
            commands.append(record.dp)
            states.append(record.dx_f)
            record = record.before
        for count in range(len(commands), 1, -1):  # the highest degree the last states allow
            path = _on_command_path(dp_new, commands[:count], scale)
            if path is not None:
                coefficients, dp_along = path
                return scale, last.dx_f, dp, _on_path(coefficients, states[:count]), dp_along
        if abs(scale) > SECANT_REACH:
            return None
        return scale, last.dx_f, dp, scale * last.dx_f, scale * dp

    def _heights_secant(self, load_change: np.ndarray) -> tuple | None:
        """``(dx_f, dw, dw)`` when this solve continues the last one (:meth:`PathRecord.continues`) with
        the biased loads only.

        As :meth:`_secant`, for a change ``dG = s dG_last`` of the biased units' loads
        (force commands, biases) with everything else held: the free dofs and heights
        continue the last solve's path to ``s`` (:meth:`PathRecord.continuation`: quadratic
        through the last two solves' states when they changed the loads along the same
        direction, else ``x_f + s dx_f``, ``w + s dw``) — exact for a reversal, third order
        along a smooth command path.
        """
        last = self._last_path
        if last.load_change is None or last.load_change.shape != load_change.shape:
            return None
        scale = _along(load_change, last.load_change)
        before = last.before
        ratio = _usable(_along(before.load_change, last.load_change)
                        if before is not None and before.load_change is not None
                        and before.load_change.shape == last.load_change.shape else None)
        if scale is None or not _within_reach(scale, _quadratic_nodes(ratio)):
            return None
        dx_f, dw = last.continuation(scale, ratio)
        return dx_f, dw, dw

    def _heights_step(self, border: IndenterBorder, fact: Factorisation, w: np.ndarray) -> tuple | None:
        """``(dx_f, dw_along, dw)``: the heights' step from ``w`` when only their loads change.

        For a solve that changes nothing but the biased units' ``G`` (a Newmark step: the
        inertial force depends on the step) and starts where the last solve ended
        (:meth:`PathRecord.continues`), with the membrane forces ``F`` there:

            S dw = -R_w = G(w, 1) - F,       S = K_ww - K_wf K_ff^-1 K_fw - dG/dw,

        the heights' Newton step with the free dofs condensed out (no ``K_ff`` solve: the
        influence vectors are cached).  The free dofs follow the last solves' path
        continued to ``s = <dw, dw_last> / <dw_last, dw_last>`` (:meth:`PathRecord.continuation`,
        which moves the heights by ``dw_along``), and the tangent's ``-Y (dw - dw_along)`` for
        the rest: along a smooth motion this is third order where ``-Y dw`` alone, with an old
        tangent, is first order.  None when the last solve did not change only the loads of the
        same biased units.
        """
        last = self._last_path
        if not last.heights_only or last.membrane_force is None or not np.array_equal(last.units, border.units):
            return None
        try:
            dw = self._heights_solve(border, fact, w, last)
        except (np.linalg.LinAlgError, BiasRangeError):
            return None
        scale = _along(dw, last.dw, exact=False)
        ratio = _usable(_along(last.before.dw, last.dw) if last.before is not None else None)
        if scale is None or not _within_reach(scale, _quadratic_nodes(ratio)):
            return (np.zeros(last.dx_f.size), np.zeros_like(dw), dw)
        dx_f, dw_along = last.continuation(scale, ratio)
        return dx_f, dw_along, dw

    def _heights_solve(self, border: IndenterBorder, fact: Factorisation, w: np.ndarray,
                       last: PathRecord) -> np.ndarray:
        """``dw`` with ``F(w + dw) = G(w + dw)``, ``F`` the membrane force modelled from the last solves.

        ``F(w + dw) = F + K dw`` with ``K`` the condensed stiffness ``K_ww - K_wf K_ff^-1 K_fw``
        of ``fact`` (an older tangent), corrected along the last height change ``u = dw_last``
        to the path through the last solves' forces: with ``dw = lambda u + r``,
        ``F(w + dw) = F + dF(lambda) + K r`` (:func:`_extrapolate`: the quadratic through the last
        three states, or the secant ``lambda dF_last``: Broyden's update of ``K``).  Newton on this
        small system (``G`` exact, :class:`.indenters.IndenterLoad`), from ``dw = 0``, until a step
        is below 1e-3 of ``dw`` (Newton's next one, ~1e-6 of it, is far below what the membrane's
        Newton iterations resolve).
        """
        stiffness = border.membrane_stiffness(fact)
        u = last.dw
        norm2 = float(u @ u)
        path = last.force_change is not None and norm2 > 0.0
        ratio = None
        if path and last.before is not None and last.before.force_change is not None:
            ratio = _usable(_along(last.before.dw, u))
        before = last.before.force_change if ratio is not None else None
        ku = stiffness @ u
        dw = np.zeros(u.size)
        for _ in range(4):
            load, slope = border.loads(w + dw)
            force, jacobian = stiffness @ dw, stiffness - np.diag(slope)
            if path:
                lam = float(dw @ u) / norm2
                force += _extrapolate(lam, ratio, last.force_change, before) - lam * ku
                jacobian += np.outer(_extrapolate(lam, ratio, last.force_change, before, slope=True) - ku, u) / norm2
            step = solve_small(jacobian, load - last.membrane_force - force)
            dw += step
            if np.abs(step).max() <= 1e-3 * np.abs(dw).max():  # Newton's next step: ~(step / dw)^2 dw
                break
        return dw


#: Range of :func:`_step_length` (a stale tangent's step is up to ~20 % off here; beyond this it is no tangent).
STEP_LENGTHS = (0.5, 1.5)


def _step_length(dx: np.ndarray, r0: np.ndarray, r1: np.ndarray, scale: float, last: float) -> float:
    """The multiple of a Newton step ``n = dx / scale`` that minimises the energy along it.

    ``E(x + alpha n)`` is stationary where ``n . r(x + alpha n) = 0``; with the curvature along
    the step from the residuals before (``r0``) and after (``r1``) the full step ``dx``,
    ``dx . K dx ~ dx . (r1 - r0)``:

        alpha* = -n . r0 / (n . K n) = -scale (dx . r0) / (dx . (r1 - r0)).

    With a stale tangent ``alpha*`` changes little from one step to the next (0.8-1.1 along
    the 1-by-3 curve, whose tangents are softer than the state's), so the next step is scaled by
    it: the 0.1 mm warm updates of ``bench_core.py`` take 1.02 Newton iterations instead of 1.14.
    ``last`` when the curvature is not positive; clipped to :data:`STEP_LENGTHS`.
    """
    curvature = float(np.sum(dx * (r1 - r0)))
    if not curvature > 0.0:
        return last
    return min(max(-scale * float(np.sum(dx * r0)) / curvature, STEP_LENGTHS[0]), STEP_LENGTHS[1])


def _iterations_left(norm: float, tol: float, ratio: float) -> float:
    """Iterations a residual of norm ``norm`` needs to fall below ``tol`` at ``ratio`` per iteration.

    A stale tangent converges linearly, ``|r_{k+n}| ~ ratio^n |r_k|``, so
    ``n = log(tol / |r_k|) / log(ratio)``; infinite when it does not contract.
    """
    if norm <= tol:
        return 0.0
    if ratio >= 1.0:
        return float("inf")
    return float(np.log(tol / norm) / np.log(ratio))


def _on_command_path(dp_new: np.ndarray, changes: Sequence[np.ndarray],
                     scale: float) -> tuple[np.ndarray, np.ndarray] | None:
    """``(c, P(lambda))``: the point of the polynomial through the last commands nearest to the new one,
    with its coefficients ``c`` (:func:`_path_coefficients`) for :func:`_on_path` of the states to it.

    The last prescribed changes ``changes`` (the last solve's first) are chords of a path,
    their commands at the path parameters :func:`_path_nodes`; ``P(lambda) = sum_i c_i(lambda)
    changes[i]`` (:func:`_path_basis`), and ``lambda`` minimises ``|P(lambda) - dp_new|``
    (:func:`_nearest_on_path`).  Along one direction ``P(lambda) = lambda dp`` and ``lambda =
    scale``.  None when the commands are not apart (:func:`_path_nodes`) or ``lambda`` is out of
    reach (:func:`_within_reach`).
    """
    coefficients = _nearest_on_path(np.array(changes), dp_new, scale)
    if coefficients.size == 0:
        return None
    return coefficients, _on_path(coefficients, changes)


@numba.njit(**JIT)
def _nearest_on_path(changes: np.ndarray, dp_new: np.ndarray, scale: float) -> np.ndarray:
    """The coefficients ``c`` of :func:`_on_command_path` (empty: None there), the changes as the rows of
    ``changes``.

    With ``N`` of :func:`_path_basis`, ``P(lambda) = sum_m lambda^m M_m``, ``M = -N C`` the monomial
    coefficients: ``P'.(P - dp_new)`` and ``P'.P'`` are polynomials in ``lambda`` whose coefficients
    come from the dot products of the ``M_m`` with each other and with ``dp_new``; three Gauss-Newton
    steps ``P'.(P - dp_new) / P'.P'`` from the projection ``scale``.
    """
    none = np.empty(0)
    nodes, positions = _path_nodes(changes @ changes.T)
    if nodes.size == 0:
        return none
    basis = _path_basis(nodes, positions)
    k, used = basis.shape
    monomials = -(basis @ changes[:used])
    v_gram, v_dp = monomials @ monomials.T, monomials @ dp_new
    # P'.(P - dp_new) and P'.P' as polynomials in lambda (coefficients of lambda^0, lambda^1, ...)
    along, curvature = np.zeros(2 * k), np.zeros(2 * k - 1)
    for m in range(1, k + 1):
        along[m - 1] -= m * v_dp[m - 1]
        for n in range(1, k + 1):
            along[m + n - 1] += m * v_gram[m - 1, n - 1]
            curvature[m + n - 2] += m * n * v_gram[m - 1, n - 1]
    lam = scale
    for _ in range(3):
        slope2 = _horner(curvature, lam)
        if not slope2 > 0.0:
            return none
        lam -= _horner(along, lam) / slope2
    if not (math.isfinite(lam) and _within_reach(lam, nodes)):
        return none
    return _path_coefficients(lam, basis, False)


@numba.njit(**JIT)
def _horner(coefficients: np.ndarray, lam: float) -> float:
    """The polynomial ``sum_e coefficients[e] lambda^e`` at ``lam``."""
    out = 0.0
    for e in range(coefficients.size - 1, -1, -1):
        out = out * lam + coefficients[e]
    return out


@numba.njit(**JIT)
def _path_nodes(gram: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(nodes, positions)``: the path parameters ``0, -1, -1 - a_1, ...`` of the last commands, from the
    dot products ``gram`` of their changes (the last solve's first), and which states they are.

    Change ``i`` spans ``a_i`` times the last one: the signed ratio when it lies along it (to
    1e-6 of its length: a path that turned back comes over the same parameters again), else the
    ratio of their lengths (chord-length spacing along a curve).  A state whose parameter is a
    newer state's (within 1e-6: the same command, so the same state without biased units, as
    when a back-and-forth motion retraces its path) is left out, the newer one kept.  Empty
    arrays when the parameters do not spread the states apart (:func:`_apart`).
    """
    k = gram.shape[0]
    nodes, positions = np.empty(k + 1), np.empty(k + 1, np.int64)
    last2 = gram[0, 0]
    if not last2 > 0.0:
        return nodes[:0], positions[:0]
    nodes[0], nodes[1], positions[0], positions[1] = 0.0, -1.0, 0, 1
    count, node = 2, -1.0
    for i in range(1, k):
        ratio = gram[i, 0] / last2
        off = gram[i, i] - ratio * gram[i, 0]  # |c_i - ratio c_0|^2
        node -= ratio if off <= 1e-12 * gram[i, i] else math.sqrt(gram[i, i] / last2)
        new = True
        for c in range(count):
            new = new and abs(node - nodes[c]) > 1e-6
        if new:
            nodes[count], positions[count] = node, i + 1
            count += 1
    if not _apart(nodes[:count]):
        return nodes[:0], positions[:0]
    return nodes[:count], positions[:count]


@numba.njit(**JIT)
def _apart(nodes: np.ndarray) -> bool:
    """Whether path parameters (in last changes) spread a polynomial's states apart: no two within
    0.2, no change between consecutive ones longer than 10."""
    for i in range(nodes.size):
        for j in range(i):
            if not abs(nodes[i] - nodes[j]) >= 0.2:
                return False
    for i in range(nodes.size - 1):
        if not abs(nodes[i] - nodes[i + 1]) <= 10.0:
            return False
    return True


def _truncated(record: PathRecord | None, depth: int) -> PathRecord | None:
    """``record`` with at most ``depth`` records in its chain of :attr:`PathRecord.before` (itself included)."""
    if record is None or depth <= 0:
        return None
    if record.before is None:
        return record
    return dataclasses.replace(record, before=_truncated(record.before, depth - 1))


def _along(v: np.ndarray, u: np.ndarray, exact: bool = True) -> float | None:
    """``s = <v, u> / <u, u>``; None when ``u = 0``, or (``exact``) when ``v`` is not ``s u`` to 1e-9."""
    norm2 = float(u @ u)
    if norm2 == 0.0:
        return None
    scale = float(v @ u) / norm2
    if exact and np.abs(v - scale * u).max() > 1e-9 * np.abs(v).max():
        return None
    return scale


def _usable(ratio: float | None) -> float | None:
    """A ratio ``a`` of the previous path's change to the last one's that spreads the quadratic's
    three points apart (:func:`_apart`: ``|a|`` and ``|1 + a|`` at least 0.2, ``|a|`` at most 10), else None."""
    if ratio is None or not _apart(_quadratic_nodes(ratio)):
        return None
    return ratio


#: Degree of the polynomial through the last states that a solve without biased units continues
#: (:meth:`EquilibriumSolver._secant`): 3, the cubic through four states.  On the node's command
#: stream (a 1 Hz sine on each unit, a third of a period apart, 500 Hz) its predictor left a first
#: Newton correction ~10 times smaller than the quadratic's, and the updates that needed a second
#: iteration fell from ~20 % to ~7 % (docs/architecture.md).
CONTINUATION_DEGREE = 3
#: How far a continuation may reach from the last state, in spans of the states it extrapolates.
REACH = 3.0
#: How far the secant alone (no third state, or a curve out of reach) may reach, in last changes: a
#: quadratic continuation is limited by :data:`REACH` instead (a node that missed a tick continues its
#: path over twice the last change, or a little more; with this limit on it too the first residual of
#: such an update was ~1000 times larger and took 6-8 Newton iterations instead of 2).
SECANT_REACH = 2.0


@numba.njit(**JIT)
def _within_reach(scale: float, nodes: np.ndarray) -> bool:
    """Whether ``lambda = scale`` lies within ``REACH`` spans of the last state, the span being
    that of the path parameters ``nodes`` of the states the continuation passes through (``[-1, 0]``,
    or with a third state also ``-1 - a``, ...): near a turning point of a motion the last step
    is short and the ones before it may span the new one."""
    return abs(scale) <= REACH * (nodes.max() - nodes.min())


def _balanced(res: np.ndarray, n_free: int, r_tol: float, x_tol: float, fact: Factorisation | None,
              border: IndenterBorder | None) -> bool:
    """Whether the residual ``res`` of :func:`_residual` is within the tolerances.

    Each free row within ``r_tol`` [N].  A biased height's row ``R_w`` is a force on the
    rigid disk: with ``S`` the heights' stiffness (membrane ``K_m``, bias and, in a Newmark
    step, the inertial ``m / (beta dt^2)``; the diagonal of the Schur complement of the
    step that led to ``res``, :attr:`.indenters.IndenterBorder.step_stiffness`) it leaves a
    height error ``R_w / S`` and a membrane force error ``K_m R_w / S``.  The row converges
    when the first is within ``x_tol`` and the second within ``r_tol``, and always within
    ``r_tol`` itself.  In a quasi-static solve ``S`` is about ``K_m`` and the tolerance about
    ``r_tol``; in a Newmark step the inertial term (5000 N/m for 5 g at 2 ms, against a
    membrane's ~60 N/m) makes the force ``R_w`` some 80 times more sensitive to the height
    than the membrane is, and holding it to ``r_tol`` cost a heights-only Newton step for a
    height error of picometres.
    """
    if np.abs(res[:n_free]).max(initial=0.0) > r_tol:
        return False
    r_w = np.abs(res[n_free:])
    if np.all(r_w <= r_tol):
        return True
    if border is None or border.step_stiffness is None:
        return False
    s = np.abs(border.step_stiffness)
    k_m = np.abs(np.diagonal(border.membrane_stiffness(fact)))
    tol = np.maximum(r_tol, np.minimum(x_tol * s, r_tol * s / np.maximum(k_m, np.finfo(float).tiny)))
    return bool(np.all(r_w <= tol))


def _residual(r: np.ndarray, x: np.ndarray, free: np.ndarray, border: IndenterBorder | None) -> np.ndarray:
    """The residual Newton drives to zero: ``r_f``, and the biased heights' ``R_w`` after it."""
    if border is None:
        return r[free]
    return np.concatenate([r[free], border.residual(r, x)])
