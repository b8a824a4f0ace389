"""Snap-through of biased units: detect a limit point on a quasi-static path and land past it.

With a negative-rate bias (NBS) the equilibrium height ``w(t)`` of a biased unit along
a load path (voltage, force, neighbours) can turn back at a limit point ``t*``, where
the bordered Schur complement ``S = dF/dw - dB/dw`` (condensed) passes through zero.
Past ``t*`` there is no equilibrium nearby: the unit snaps to another branch.  The
solver (:mod:`.solver`) notices when a step no longer than ``snap_step`` of the path
fails to converge, or converges ``jump_tol`` away from its linear prediction; then
:func:`land_after_snap` continues the state *in the snapping unit's height* at the
load ``t`` just past the limit point:

1. the unit is the one the bordered Newton step moves most (the critical direction of
   ``S``);
2. it is held (driven) at heights ``w_j = w_0 + sigma j h`` (``h = snap_march * D``),
   the other biased units staying in equilibrium, and the out-of-balance force
   ``g_j = F(w_j) - G(w_j)`` is evaluated; ``sigma = -sign(g_0)`` is where the
   unbalanced force pushes the indenter;
3. where ``g`` changes sign the unit has passed an equilibrium of the new branch: a
   full biased Newton solve from there lands on it, and it is accepted if its tangent
   (with the bias stiffness) has no negative eigenvalue; otherwise the march goes on.

The landed state is a stable equilibrium at the same load, reached as the physical
system would (the first stable equilibrium in the direction the unbalanced force
pushes); the solver records a :class:`Snap` (from where to where) and carries on
along the path from there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .bias import BiasRangeError
from .indenters import IndenterBorder, negative_eigenvalues
from .kernels import internal_forces


@dataclass(frozen=True)
class Snap:
    """One snap-through on a quasi-static path.

    Attributes
    ----------
    unit : int
        The unit that snapped (0-based).
    start, end : float
        Its height before and after [m].
    load_fraction : float
        Where on the solve's load path (0 = start, 1 = the command) it snapped.
    """

    unit: int
    start: float
    end: float
    load_fraction: float

    def describe(self) -> str:
        """One line for users: which unit, from where to where."""
        return (f"unit {self.unit + 1} snapped through from {1e3 * self.start:.4g} mm to {1e3 * self.end:.4g} mm "
                f"(at {100 * self.load_fraction:.3g}% of the command change)")


def land_after_snap(solver, trial: np.ndarray, free: np.ndarray, prescribed: np.ndarray,
                    maxwell: np.ndarray, border: IndenterBorder, stats, cancel=None) -> tuple | None:
    """The stable equilibrium a biased unit snaps to, at the load of ``trial``.

    Parameters
    ----------
    solver : EquilibriumSolver
    trial : ndarray
        The last converged state before the limit point with the prescribed dofs at
        the load just past it (the failed step's start).
    free, prescribed : ndarray
        The partition (biased disks prescribed).
    maxwell : ndarray
        Per element Maxwell coefficient at that load.
    border : IndenterBorder
        The biased heights, bound to that load (``border.t``).
    stats : SolveStats
        Counts iterations and factorisations.
    cancel : callable, optional
        The solve's cancel point (:class:`~.solver.SolveCancelled`), asked by every Newton solve.

    Returns
    -------
    tuple or None
        ``(x, r, point, factorisation, unit)`` of the landed state, or None when the
        continuation finds no stable equilibrium within ``max_displacement``.
    """
    model, settings = solver.model, solver.settings
    fact = solver.factorise_at(trial, maxwell, free, prescribed, stats)
    r, _ = internal_forces(model.disc, trial, model.yeoh, maxwell, model.thickness)
    step = border.direction(fact, r[free], border.residual(r, trial), trial)
    if step is None or not np.all(np.isfinite(step[1])):
        return None
    i = int(np.argmax(np.abs(step[1])))
    unit, group, dof = int(border.units[i]), border.groups[i], border.dofs[i][0]
    others = border.without(unit)
    t = border.t

    def held_at(state: np.ndarray, w: float, fact) -> tuple | None:
        """Equilibrium with ``unit`` held at height ``w``; its out-of-balance force ``F - G``."""
        moved = state.copy()
        before = moved[prescribed].copy()
        model.place_disk(moved, unit, w)
        moved[free] += fact.predict(moved[prescribed] - before, [group])
        if others is not None:
            others.begin(t)
        out = solver._newton(moved, free, prescribed, maxwell, fact, stats, cancel, others)
        if out is None:
            return None
        try:
            g = out[1][border.dofs[i]].sum() - border.load(unit, w, t)[0]
        except BiasRangeError:
            return None
        return out[0], out[3] if out[3] is not None else fact, g

    w0 = float(trial[dof])
    start = held_at(trial, w0, fact)
    if start is None or start[2] == 0.0:
        return None
    state, fact, g0 = start
    sigma = -np.sign(g0)
    h = settings.snap_march * model.length_scale
    limit = model.cfg.scaled("max_displacement")
    for j in range(1, int(2.0 * limit / h) + 2):
        w = w0 + sigma * j * h
        if abs(w) > limit:
            return None
        step_out = held_at(state, w, fact)
        if step_out is None:
            return None
        state, fact, g = step_out
        if np.sign(g) == np.sign(g0):
            continue
        border.begin(t)
        out = solver._newton(state, free, prescribed, maxwell, fact, stats, cancel, border)
        g0 = g
        if out is None:
            continue
        landed, r, point, _ = out
        fact_landed = solver.factorise_at(landed, maxwell, free, prescribed, stats)
        if negative_eigenvalues(fact_landed, landed, border, static=False) == 0:
            return landed, r, point, fact_landed, unit
    return None
