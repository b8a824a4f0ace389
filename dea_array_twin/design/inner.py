"""The inner model of bias design: equilibria and strokes for any bias parameters, without FE solves.

For each voltage pattern ``P`` of the scenarios (:mod:`.scenarios`) and each biased unit
i, the twin has swept unit i's force over a grid of heights with every other held unit at
its *anchor* height ``a_j`` (the equilibrium of a design solved with full biased solves),
recording ``F_i`` and the condensed stiffness ``K_ij = dF_i/dw_j`` at every point
(:mod:`.solves`).  The inner model carries those curves to other neighbour heights to
first order:

    F_i(w) = f_i(w_i) + sum_{j != i} K_ij(w_i) (w_j - a_j),

with ``f_i`` the cubic Hermite interpolant of the swept force through the grid values
and their exact slopes ``K_ii``, ``K_ij`` cubic between the points.  It is exact at the
anchors (to the interpolation error) and first-order accurate around them, so the
design loop (:mod:`.optimise`) re-anchors it at each new design's full solves until the
strokes it predicts agree with them.

An equilibrium of the biased units solves ``F(w) - B(w) = 0`` (``B`` the bias laws of
the design) by Newton with the Jacobian ``J = dF/dw - diag(dB/dw)``; its stability
margin is the smallest eigenvalue of ``J``'s symmetric part (for one unit
``dF/dw - dB/dw``).  Paths follow the twin's (:func:`~dea_array_twin.model.response.rest_state`
and :mod:`.scenarios`):

* rest: the indenters held at ``start`` are released onto their biases, the homotopy
  ``G = t B(w) + (1 - t) F(start)`` from t = 0 to 1 at 0 V;
* a voltage change from pattern P to Q: ``F = (1 - s) F_P + s F_Q`` with ``s = u^2`` at
  the voltage fraction u (the electrostatic load goes with V^2), in steps of at most
  1 / :data:`PATH_LEVELS` of the voltage (the full solves' path points,
  :data:`~.solves.PATH_LEVELS`).

The stability margin a design must keep is checked at every point of the voltage
paths: the state a voltage change starts from and every step it takes (the smallest of
them is the scenario's margin), not only at the end states: the net stiffness of a unit
on a bias whose slope peaks between its 0 V and its V height dips on the way.  The
release's intermediate states are not physical (the held indenter is let go), so only
its end, the rest state, counts.

Each step starts with the Newton step from the last equilibrium (the linear
prediction); a step that fails to converge, ends on an unstable state, or lands more
than ``jump_tol`` (0.01 D, the solver's) from the prediction is a snap-through.  Without
``allow_snap`` that design is infeasible; with it the state is continued in the snapping
unit's height until the out-of-balance force changes sign and lands on the stable
branch, as :mod:`dea_array_twin.model.snap` does.  A state outside the swept heights has
no force (never an extrapolation), so a design that needs one has no equilibrium: that is
how the position range constrains the designs.  Every array here is vectorised over rows
of (design, path): one population of designs costs three batched ramps per context (the
release, the low patterns, the scenarios), whatever the number of scenarios.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from .scenarios import Scenario
from .solves import PATH_LEVELS

#: Load steps of the release onto the bias; the shortest step (fraction of the path) a
#: design's path is cut to before a bad step counts as a snap-through.
LEVELS = 2
MIN_STEP = 1.0 / 256.0
#: Newton iterations per step, and the convergence tolerance as a fraction of the grid step.
MAX_ITERATIONS = 25
STEP_TOL = 1e-8
#: Height increment (fraction of D) of the continuation that looks for a snap's landing.
SNAP_MARCH = 0.02

#: ``bias(w) -> (B, dB/dw)`` for heights of shape (designs, biased units).
BiasFunction = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


class Curves:
    """Piecewise cubic Hermite curves on one uniform grid, evaluated many at once.

    On ``[x_i, x_i + h]`` with ``t = (x - x_i) / h``:
    ``p = y_i + h m_i t + (3 dy - 2 h m_i - h m_{i+1}) t^2 + (h m_i + h m_{i+1} - 2 dy) t^3``,
    ``dy = y_{i+1} - y_i``; outside the grid NaN (never an extrapolation).

    Parameters
    ----------
    start, step : float
        First grid point and spacing [m].
    values, slopes : ndarray, shape (curves, points)
    """

    def __init__(self, start: float, step: float, values: np.ndarray, slopes: np.ndarray):
        self.start, self.step, self.points = start, step, values.shape[1]
        y0, y1 = values[:, :-1], values[:, 1:]
        m0, m1 = step * slopes[:, :-1], step * slopes[:, 1:]
        self.coef = np.stack([y0, m0, 3 * (y1 - y0) - 2 * m0 - m1, m0 + m1 - 2 * (y1 - y0)], axis=-1)

    def __call__(self, x: np.ndarray, curve: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Values and slopes of curves ``curve`` (int array broadcast with ``x``) at ``x``."""
        u = (x - self.start) / self.step
        inside = (u >= -1e-9) & (u <= self.points - 1 + 1e-9)
        seg = np.floor(np.where(inside, u, 0.0)).astype(int).clip(0, self.points - 2)
        t = u - seg
        c = self.coef[curve, seg]
        value = c[..., 0] + t * (c[..., 1] + t * (c[..., 2] + t * c[..., 3]))
        slope = (c[..., 1] + t * (2 * c[..., 2] + 3 * t * c[..., 3])) / self.step
        return np.where(inside, value, np.nan), np.where(inside, slope, np.nan)


@dataclass
class PatternModel:
    """The membrane forces of the biased units under every voltage pattern, as functions of their heights.

    Attributes
    ----------
    force : Curves
        ``f_i(w_i)`` under pattern p: curve ``p * nb + i``.
    coupling : Curves
        ``K_ij(w_i)`` under pattern p: curve ``(p * nb + i) * nb + j``.
    anchors : ndarray, shape (patterns, nb)
        The heights the other units were held at in each pattern's sweeps [m].
    index : dict
        The row of each voltage pattern (the rest pattern, all 0 V, included).
    """

    force: Curves
    coupling: Curves
    anchors: np.ndarray
    index: dict

    @property
    def size(self) -> int:
        """Number of biased units."""
        return self.anchors.shape[1]

    @property
    def span(self) -> float:
        """Length of the swept height range [m]."""
        return self.force.step * (self.force.points - 1)

    def __call__(self, w: np.ndarray, pattern: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``F`` (rows, nb) and ``dF/dw`` (rows, nb, nb) at heights ``w`` (rows, nb) under ``pattern`` (rows,)."""
        nb = self.size
        idx = np.arange(nb)
        base = pattern[:, None] * nb + idx
        f, df = self.force(w, base)
        if nb == 1:  # no neighbour to couple to
            return f, df[..., None]
        k, dk = self.coupling(np.broadcast_to(w[..., :, None], w.shape + (nb,)), base[:, :, None] * nb + idx)
        off = ~np.eye(nb, dtype=bool)
        dw = w - self.anchors[pattern]
        k = np.where(off, k, 0.0)
        dk = np.where(off, dk, 0.0)
        force = f + np.einsum("mij,mj->mi", k, dw)
        jac = k + np.einsum("mi,ij->mij", df + np.einsum("mij,mj->mi", dk, dw), np.eye(nb))
        return force, jac


@dataclass
class Context:
    """A set of biased units (an array configuration) and its pattern models.

    Attributes
    ----------
    units : tuple of int
        The biased units, 0-based (the columns of every height array).
    patterns : PatternModel
        The forces under every voltage pattern of the scenarios, the rest pattern included.
    bias : callable
        ``bias(theta, w) -> (B, dB/dw)`` for parameters ``theta`` (rows, p) and
        heights ``w`` (rows, nb).
    """

    units: tuple
    patterns: PatternModel
    bias: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass
class Evaluation:
    """The inner model's answer for a population of designs.

    Attributes
    ----------
    stroke : ndarray, shape (designs, scenarios)
        High minus low height of the stroking unit [m]; NaN where an equilibrium is missing.
    low, high : ndarray, shape (designs, scenarios, n_units)
        Heights of every unit in the low and high state (NaN for units not biased there).
    margin : ndarray, shape (designs, scenarios)
        Smallest stability margin along the paths to the low and the high state [N/m]
        (every load step of the voltage changes, and the state they start from).
    bias_force : ndarray, shape (designs, scenarios)
        Largest ``|B|`` of a biased unit in the low and high states [N].
    snapped : ndarray of bool, shape (designs,)
        Some path snapped through.
    failed : ndarray, shape (designs,)
        Fraction of the paths that end without an equilibrium (0 when all were found).
    """

    stroke: np.ndarray
    low: np.ndarray
    high: np.ndarray
    margin: np.ndarray
    bias_force: np.ndarray
    snapped: np.ndarray
    failed: np.ndarray


@dataclass
class _Path:
    """Where a path ends for each design: heights, whether it snapped, the smallest margin on the way."""

    w: np.ndarray
    snapped: np.ndarray
    margin: np.ndarray


def _smallest_eigenvalue(jac: np.ndarray) -> np.ndarray:
    sym = 0.5 * (jac + np.swapaxes(jac, -1, -2))
    out = np.full(jac.shape[0], np.nan)
    ok = np.all(np.isfinite(sym), axis=(-1, -2))
    if ok.any():
        out[ok] = np.linalg.eigvalsh(sym[ok])[:, 0]
    return out


@dataclass
class _Step:
    """One load level: the membrane force ``F`` and the bias side ``G`` of the designs.

    ``membrane(w, rows)`` and ``load(w, rows)`` answer for the designs ``rows`` (indices
    into the population; the level may differ between designs) at their heights ``w``."""

    membrane: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
    load: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]

    def residual(self, w: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``R = F - G`` (rows, nb) and its Jacobian ``dF/dw - diag(dG/dw)``."""
        f, jf = self.membrane(w, rows)
        g, dg = self.load(w, rows)
        return f - g, jf - dg[..., :, None] * np.eye(w.shape[-1])


class InnerModel:
    """Equilibria, strokes and margins of designs on the swept curves (see the module text).

    Parameters
    ----------
    contexts : sequence of Context
        The array configurations the scenarios run in.
    scenarios : sequence of (Scenario, int)
        Each scenario with the index of its context.
    n_units : int
        Units of the array.
    start : float
        Height the indenters are released from [m].
    length_scale : float
        The electrode diameter D [m] (jump tolerance and snap march).
    allow_snap : bool
        Follow snap-throughs to their landing instead of marking the design infeasible.
    """

    def __init__(self, contexts: Sequence[Context], scenarios: Sequence[tuple[Scenario, int]], n_units: int,
                 start: float, length_scale: float, allow_snap: bool = False):
        self.contexts, self.scenarios = list(contexts), list(scenarios)
        self.n_units, self.start, self.length_scale, self.allow_snap = n_units, start, length_scale, allow_snap
        self.span = max(context.patterns.span for context in self.contexts)

    # ------------------------------------------------------------------ paths
    def _newton(self, step: _Step, w: np.ndarray, rows: np.ndarray, tol: float) -> np.ndarray:
        """Newton from ``w`` (one row per design of ``rows``); rows that do not converge become NaN."""
        w = w.copy()
        done = ~np.all(np.isfinite(w), axis=1)
        converged = np.zeros_like(done)
        for _ in range(MAX_ITERATIONS):
            sub = np.flatnonzero(~done)
            if not sub.size:
                break
            r, jac = step.residual(w[sub], rows[sub])
            dw = _solve_rows(jac, -r)
            w[sub] = w[sub] + dw
            small = np.all(np.abs(dw) <= tol, axis=1)
            lost = ~np.all(np.isfinite(w[sub]), axis=1)
            converged[sub[small]] = True
            done[sub[small | lost]] = True
        w[~converged] = np.nan
        return w

    def _advance(self, step: _Step, w: np.ndarray, rows: np.ndarray, tol: float,
                 jump: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One load step of the designs ``rows`` from their equilibria ``w``.

        Returns the new heights, whether the step is good (found, stable, within ``jump``
        of the linear prediction) and the new states' margins."""
        r, jac = step.residual(w, rows)
        predicted = w + _solve_rows(jac, -r)
        new = self._newton(step, predicted, rows, tol)
        found = np.all(np.isfinite(new), axis=1)
        margin = np.full(w.shape[0], np.nan)
        if found.any():
            margin[found] = _smallest_eigenvalue(step.residual(new[found], rows[found])[1])
        ok = found & (margin > 0) & (np.abs(new - predicted).max(axis=1, initial=0.0) <= jump)
        return new, ok, margin

    def _ramp(self, level: Callable[[np.ndarray], _Step], w: np.ndarray, tol: float, jump: float,
              levels: int) -> _Path:
        """Follow the load ``level(t)`` (``t`` per design, from 0 to 1) from the equilibria ``w``.

        Steps start at 1 / ``levels`` of the path, halve after a bad step and double after
        a good one up to that, and stop at every path point ``j / levels``; a bad step of
        :data:`MIN_STEP` is a limit point: a snap-through (the design fails, or with
        ``allow_snap`` lands on the branch it jumps to).  The margin is the smallest at ``w``
        and at every step taken."""
        m = w.shape[0]
        started = np.all(np.isfinite(w), axis=1)
        active = started.copy()
        x = w.copy()
        t = np.zeros(m)
        dt = np.full(m, 1.0 / levels)
        snapped = np.zeros(m, dtype=bool)
        path_margin = np.full(m, np.nan)
        if started.any():
            rows = np.flatnonzero(started)
            path_margin[rows] = _smallest_eigenvalue(level(t).residual(x[rows], rows)[1])
        while True:
            rows = np.flatnonzero(active & (t < 1.0))
            if not rows.size:
                break
            t_next = t.copy()
            path_point = (np.floor(t[rows] * levels + 1e-9) + 1.0) / levels  # never stepped over
            t_next[rows] = np.minimum(np.minimum(1.0, path_point), t[rows] + dt[rows])
            step = level(t_next)
            new, ok, margin = self._advance(step, x[rows], rows, tol, jump)
            good, bad = rows[ok], rows[~ok]
            x[good], t[good] = new[ok], t_next[good]
            path_margin[good] = np.fmin(path_margin[good], margin[ok])
            dt[good] = np.minimum(2.0 * dt[good], 1.0 / levels)
            dt[bad[dt[bad] > MIN_STEP]] *= 0.5
            for row in bad[dt[bad] <= MIN_STEP]:  # a limit point: no good step however short
                snapped[row] = True
                x[row] = self._land(step, x[row], row, tol) if self.allow_snap else np.nan
                if np.all(np.isfinite(x[row])):
                    t[row] = t_next[row]
                    landed = _smallest_eigenvalue(step.residual(x[row][None, :], np.array([row]))[1])[0]
                    path_margin[row] = min(path_margin[row], landed)
                else:
                    active[row] = False
        x[~active] = np.nan
        path_margin[~active] = np.nan
        return _Path(x, snapped, path_margin)

    def _land(self, step: _Step, w: np.ndarray, row: int, tol: float) -> np.ndarray:
        """The stable state design ``row`` snaps to at ``step``'s load, from its last equilibrium ``w``.

        The unit the Newton step moves most marches in its height (the others in
        equilibrium) in the direction its out-of-balance force pushes until that force
        changes sign; Newton lands there and is accepted on a positive margin."""
        rows = np.array([row])

        def residual(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            r, jac = step.residual(x[None, :], rows)
            return r[0], jac[0]

        r, jac = residual(w)
        direction = _solve_or_nan(jac, -r)
        if not np.all(np.isfinite(direction)):
            return np.full_like(w, np.nan)
        unit = int(np.argmax(np.abs(direction)))
        others = np.arange(w.size) != unit
        h = SNAP_MARCH * self.length_scale

        def held(x: np.ndarray) -> np.ndarray | None:
            """Equilibrium of the other units with ``unit`` held at ``x[unit]``."""
            x = x.copy()
            for _ in range(MAX_ITERATIONS if others.any() else 0):
                r, jac = residual(x)
                dx = _solve_or_nan(jac[np.ix_(others, others)], -r[others])
                if not np.all(np.isfinite(dx)):
                    return None
                x[others] += dx
                if np.abs(dx).max() <= tol:
                    break
            return x if np.all(np.isfinite(residual(x)[0])) else None

        x = held(w)
        if x is None:
            return np.full_like(w, np.nan)
        g0 = residual(x)[0][unit]
        sigma = -np.sign(g0)
        for _ in range(int(self.span / h) + 2):
            trial = x.copy()
            trial[unit] += sigma * h
            x_new = held(trial)
            if x_new is None:
                break
            x = x_new
            g = residual(x)[0][unit]
            if np.sign(g) == np.sign(g0):
                continue
            landed = self._newton(step, x[None, :], rows, tol)[0]
            if np.all(np.isfinite(landed)) and _smallest_eigenvalue(residual(landed)[1][None])[0] > 0:
                return landed
            g0 = g
        return np.full_like(w, np.nan)

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, theta: np.ndarray) -> Evaluation:
        """Strokes, states and margins of the designs ``theta`` (designs, parameters).

        Per context three batches of paths, each one vectorised ramp over (design, path)
        rows: the release onto the biases at 0 V; the rest state to every low pattern of
        the scenarios; each scenario's low to high pattern."""
        m = theta.shape[0]
        n_scen = len(self.scenarios)
        stroke = np.full((m, n_scen), np.nan)
        low = np.full((m, n_scen, self.n_units), np.nan)
        high = np.full((m, n_scen, self.n_units), np.nan)
        margin = np.full((m, n_scen), np.nan)
        bias_force = np.full((m, n_scen), np.nan)
        snapped = np.zeros(m, dtype=bool)
        failed, ramps = np.zeros(m), np.zeros(m)
        jump = 0.01 * self.length_scale
        rest_pattern = (False,) * self.n_units
        for c, context in enumerate(self.contexts):
            models = context.patterns
            nb = models.size
            tol = STEP_TOL * models.force.step
            mine = [(i, sc) for i, (sc, ctx) in enumerate(self.scenarios) if ctx == c]
            lows = [p for p in dict.fromkeys(sc.low for _, sc in mine) if p != rest_pattern]

            def batch(design: np.ndarray, start: np.ndarray, end: np.ndarray, w: np.ndarray,
                      release: bool = False) -> tuple[np.ndarray, np.ndarray]:
                """Ramp rows (design, start pattern -> end pattern) from heights ``w``: the end heights and
                the smallest margin on the way (of the release: its end's)."""
                nonlocal snapped, failed, ramps
                p0 = np.array([models.index[p] for p in start], dtype=int)
                p1 = np.array([models.index[p] for p in end], dtype=int)
                params = theta[design]

                def bias(x: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
                    return context.bias(params[rows], x)

                if release:  # the indenters let go at 0 V: G = t B(w) + (1 - t) F(start)
                    held = models(w, p0)[0]

                    def level(t: np.ndarray) -> _Step:
                        def load(x, rows):
                            b, db = bias(x, rows)
                            f = t[rows, None]
                            return f * b + (1 - f) * held[rows], f * db
                        return _Step(lambda x, rows: models(x, p0[rows]), load)
                else:  # the voltages change: F = (1 - s) F_P + s F_Q, s = u^2 (the load goes with V^2)
                    def level(t: np.ndarray) -> _Step:
                        s = t * t

                        def membrane(x, rows):
                            fp, jp = models(x, p0[rows])
                            fq, jq = models(x, p1[rows])
                            f = s[rows]
                            return (1 - f)[:, None] * fp + f[:, None] * fq, \
                                (1 - f)[:, None, None] * jp + f[:, None, None] * jq
                        return _Step(membrane, bias)

                path = self._ramp(level, w, tol, jump, LEVELS if release else PATH_LEVELS)
                np.logical_or.at(snapped, design, path.snapped)
                np.add.at(failed, design, ~np.all(np.isfinite(path.w), axis=1))
                np.add.at(ramps, design, 1.0)
                if release:  # its intermediate states are not physical: only the rest state counts
                    rest_margin = np.full(design.size, np.nan)
                    found = np.flatnonzero(np.all(np.isfinite(path.w), axis=1))
                    if found.size:
                        jac = level(np.ones(design.size)).residual(path.w[found], found)[1]
                        rest_margin[found] = _smallest_eigenvalue(jac)
                    return path.w, rest_margin
                return path.w, path.margin

            everyone = np.arange(m)
            rest, rest_margin = batch(everyone, [rest_pattern] * m, [rest_pattern] * m,
                                      np.full((m, nb), self.start), True)
            states = {rest_pattern: (rest, rest_margin)}
            if lows:
                design = np.tile(everyone, len(lows))
                ends, on_the_way = batch(design, [rest_pattern] * design.size, [p for p in lows for _ in everyone],
                                         np.tile(rest, (len(lows), 1)))
                states.update({p: (ends[j * m:(j + 1) * m], on_the_way[j * m:(j + 1) * m])
                               for j, p in enumerate(lows)})
            design = np.tile(everyone, len(mine))
            start = [sc.low for _, sc in mine for _ in everyone]
            end = [sc.high for _, sc in mine for _ in everyone]
            w_low = np.concatenate([states[sc.low][0] for _, sc in mine])
            low_margin = np.concatenate([states[sc.low][1] for _, sc in mine])
            w_high, high_margin = batch(design, start, end, w_low)
            cols = list(context.units)
            force = np.fmax(np.abs(context.bias(theta[design], w_low)[0]).max(axis=1),
                            np.abs(context.bias(theta[design], w_high)[0]).max(axis=1))
            for j, (i, sc) in enumerate(mine):
                rows = slice(j * m, (j + 1) * m)
                k = context.units.index(sc.unit)
                stroke[:, i] = w_high[rows, k] - w_low[rows, k]
                low[:, i, cols] = w_low[rows]
                high[:, i, cols] = w_high[rows]
                margin[:, i] = np.fmin(low_margin[rows], high_margin[rows])
                bias_force[:, i] = force[rows]
        return Evaluation(stroke, low, high, margin, bias_force, snapped, failed / np.maximum(ramps, 1))


def _solve_or_nan(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.solve(a, b)
    except np.linalg.LinAlgError:
        return np.full(b.shape, np.nan)


def _solve_rows(jac: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``jac^-1 rhs`` row by row; NaN for rows that are not finite or singular."""
    out = np.full(rhs.shape, np.nan)
    ok = np.all(np.isfinite(rhs), axis=1) & np.all(np.isfinite(jac), axis=(1, 2))
    if ok.any():
        try:
            out[ok] = np.linalg.solve(jac[ok], rhs[ok][..., None])[..., 0]
        except np.linalg.LinAlgError:
            out[ok] = np.stack([_solve_or_nan(j, x) for j, x in zip(jac[ok], rhs[ok])])
    return out
