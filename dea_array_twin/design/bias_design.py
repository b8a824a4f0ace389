"""Bias design for the whole array: each unit's bias element for the largest guaranteed stroke.

The paper's first future-work item and the point of its section 3.2: a bias matched to
one unit's nominal curves loses stroke once the neighbours deflect, so the design must
be done "in a monolithic way, explicitly keeping into account the interactions among
neighbor elements".  :func:`design_bias` does it:

1. **Nominal curves** of each designed unit alone (the other units free, as the paper's
   "neighbours not deflected"), at 0 V and at V (:class:`~.solves.SweepTask`); they give
   the membrane's stiffness and force scales (default parameter boxes and margin) and the
   **single-unit-tuned** design: the same optimiser on those curves alone, what a designer
   gets from one unit's characteristics.
2. The single-unit-tuned design solved in the array, in every scenario, with full
   biased solves (:class:`~.solves.PathTask`): the stroke it really gives, and the anchors
   of the first array inner model.
3. **Array-aware** loop: sweep every biased unit in every voltage pattern with the other
   units held at the anchors (:mod:`.inner`), maximise the smallest stroke on that inner
   model (:mod:`.optimise`), verify the optimum with full biased solves in every
   scenario, and re-anchor there; stop when the inner model's strokes agree with the full
   solves within ``tolerance`` (of the smallest stroke), or after ``max_iterations``.

Every finite-element task runs on :func:`~dea_array_twin.parallel.run_tasks` (here, on
local processes or on Dask), so the result does not depend on where they ran; the
optimiser is seeded and runs here.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from ..model.bias import BiasLaw, TableBias
from ..model.config import BIASED, DRIVEN, FREE, ArrayConfig, ConfigError
from ..parallel import run_tasks
from . import optimise
from .families import Family, Ranges, find_table, make_family
from .inner import Context, Curves, InnerModel, PatternModel
from .optimise import Constraints, maximise_min_stroke
from .scenarios import Pattern, Scenario, patterns, scenarios
from .solves import PathResult, PathTask, State, Sweep, SweepTask, held_modes, run_path, run_sweep

#: Default position range as fractions of D (the experiments' 0 to 15 mm at D = 20 mm).
POSITION_RANGE = (0.0, 0.75)
#: Default margin as a fraction of the stiffness scale (the softest nominal slope).
MARGIN_FRACTION = 0.1
#: Default grid points over the position range.
GRID_POINTS = 31
#: A design is accepted with a full-solve margin down to (1 - MARGIN_SLACK) K: the inner
#: model's states, on which the margin was constrained, agree with the full solves to
#: about that (docs/bias_design.md).
MARGIN_SLACK = 0.01

#: ``progress(stage, done, total)``.
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class DesignSettings:
    """What to design and under which constraints (SI units).

    Attributes
    ----------
    family : str
        ``lbs``, ``nbs``, ``lbs+nbs`` or ``table-family`` (:mod:`.families`).
    voltage : float
        The actuation voltage V [V].
    units : tuple of int or None
        The designed units, 0-based; None: the config's biased units, or every unit if
        none is biased.
    shared : bool
        One design for every designed unit (else one per unit).
    scenarios : str
        Scenario spec (:mod:`.scenarios`); default every state of the other units.
    margin : float or None
        Smallest stability margin ``K`` [N/m]; None: 0.1 of the stiffness scale.
    max_force : float
        Largest bias force ``|B|`` in any state [N]; inf: no limit.
    position_range : (float, float) or None
        Where the units may be in any state [m]; None: 0 to 0.75 D.  Also the range
        the inner model's curves are swept over.
    allow_snap : bool
        Accept designs that snap through (the stroke then includes the jump).
    ranges : Ranges
        Parameter boxes (None entries: defaults).
    table : TableBias or None
        The characteristic of ``table-family`` and ``lbs+nbs``; None: a table in the
        config's bias, if any.
    start : float or None
        Height the indenters are released from onto their biases [m]; None: the middle of
        the position range (the release then comes down to the 0 V equilibrium instead of
        rising through the flat state, where a bias close to the membrane's slope is
        bistable).
    grid_points : int
        Points of each swept curve over the position range.
    tolerance : float
        Agreement of the inner model's strokes with the full solves, as a fraction of the
        smallest stroke, that ends the loop.
    max_iterations : int
        Array-aware iterations at most.
    population, generations : int or None
        The differential evolution's population per parameter and generations at most;
        None: :data:`~.optimise.POPULATION`, :data:`~.optimise.GENERATIONS`.
    """

    family: str
    voltage: float
    units: tuple | None = None
    shared: bool = False
    scenarios: str = "all"
    margin: float | None = None
    max_force: float = math.inf
    position_range: tuple | None = None
    allow_snap: bool = False
    ranges: Ranges = field(default_factory=Ranges)
    table: TableBias | None = None
    start: float | None = None
    grid_points: int = GRID_POINTS
    tolerance: float = 0.005
    max_iterations: int = 4
    population: int | None = None
    generations: int | None = None


@dataclass(frozen=True)
class ScenarioResult:
    """One scenario of a design solved with full biased solves.

    Attributes
    ----------
    scenario : Scenario
    low, high : State or None
        The states before and after the stroking unit's voltage (None: not reached).
    stroke : float
        High minus low height of the stroking unit [m] (NaN if a state is missing).
    hysteresis : bool
        Removing the voltage again did not return to the low state.
    error : str
        Why a state is missing.
    """

    scenario: Scenario
    low: State | None
    high: State | None
    stroke: float
    hysteresis: bool
    error: str

    @property
    def margin(self) -> float:
        """The smallest stability margin on the scenario's path [N/m]: the rest state, every path point
        of the voltage changes to the low and to the high state, those states."""
        if self.low is None or self.high is None:
            return math.nan
        return min(self.low.path_margin, self.high.path_margin)

    @property
    def stable(self) -> bool:
        """Both states, and every path point on the way to them, stable."""
        return self.low is not None and self.high is not None and self.low.stable and self.high.stable

    @property
    def snapped(self) -> bool:
        """A snap-through on the way to either state."""
        return any(s is not None and s.snaps for s in (self.low, self.high))


@dataclass(frozen=True)
class Verification:
    """A design solved in every scenario with full biased solves (the truth the inner model approximates)."""

    rows: tuple

    @property
    def strokes(self) -> np.ndarray:
        """Stroke per scenario [m]."""
        return np.array([r.stroke for r in self.rows])

    @property
    def min_stroke(self) -> float:
        """Smallest stroke [m] (NaN if some scenario failed)."""
        s = self.strokes
        return float(s.min()) if np.all(np.isfinite(s)) else math.nan

    @property
    def worst(self) -> ScenarioResult:
        """The scenario with the smallest stroke (a failed one first)."""
        return min(self.rows, key=lambda r: r.stroke if np.isfinite(r.stroke) else -math.inf)

    @property
    def min_margin(self) -> float:
        """Smallest stability margin over every path point of every scenario [N/m]."""
        return float(min(r.margin for r in self.rows))

    @property
    def max_bias_force(self) -> float:
        """Largest ``|B|`` over every state [N]."""
        return float(max(np.abs(s.bias_force).max() for r in self.rows for s in (r.low, r.high) if s is not None))

    @property
    def all_stable(self) -> bool:
        """Every state reached and stable."""
        return all(r.stable for r in self.rows)

    @property
    def any_snap(self) -> bool:
        """Some scenario snapped through."""
        return any(r.snapped for r in self.rows)

    @property
    def any_hysteresis(self) -> bool:
        """Some stroke did not return to its low state."""
        return any(r.hysteresis for r in self.rows)


@dataclass(frozen=True)
class Design:
    """One design: its parameters, its laws and what it gives.

    Attributes
    ----------
    theta : ndarray, shape (designed units, parameters)
        The family's parameters per designed unit (identical rows when shared).
    laws : tuple of BiasLaw
        Per designed unit.
    predicted : ndarray
        The inner model's stroke per scenario [m] (of the scenarios it was optimised on).
    verification : Verification
        Full biased solves in the array's scenarios.
    """

    theta: np.ndarray
    laws: tuple
    predicted: np.ndarray
    verification: Verification


@dataclass(frozen=True)
class Iteration:
    """One pass of the array-aware loop.

    Attributes
    ----------
    design : Design
    agreement : float
        Largest ``|inner - full|`` stroke over the scenarios, as a fraction of the full
        solves' smallest stroke.
    inner_feasible : bool
        Whether the optimum satisfied every constraint on the inner model.
    evaluations : int
        Designs the optimiser evaluated.
    seconds : dict
        Wall time of the sweeps, the optimisation and the verification [s].
    """

    design: Design
    agreement: float
    inner_feasible: bool
    evaluations: int
    seconds: dict


@dataclass(frozen=True)
class BiasDesign:
    """What :func:`design_bias` found.

    Attributes
    ----------
    config : ArrayConfig
        The array with the array-aware design (``unit_modes``, ``bias``): load it with
        ``dea-twin stroke`` or :class:`~dea_array_twin.model.twin.ArrayTwin`.
    settings : DesignSettings
        As given, with the defaults filled in (``margin``, ``position_range``, ``units``).
    family : Family
        The family with its parameter boxes.
    scenarios : tuple of Scenario
        The array's scenarios.
    aware : Design
        The array-aware design.
    single : Design
        The single-unit-tuned design (optimised on each unit's nominal curves alone); its
        ``predicted`` strokes are the nominal ones, ``verification`` is in the array.
    single_nominal : Verification
        The single-unit-tuned design solved on each unit alone (its nominal scenario).
    iterations : tuple of Iteration
    converged : bool
        The last iteration met ``tolerance``.
    sweeps : dict
        The last inner model's curves: ``{(pattern, unit): Sweep}`` (for figures).
    nominal_sweeps : dict
        Each designed unit's nominal curves: ``{(unit, at_voltage): Sweep}``.
    stiffness_scale, force_scale : float
        The membrane's softest nominal slope [N/m] and largest 0 V force [N] over the range.
    seconds : float
        Total wall time [s].
    """

    config: ArrayConfig
    settings: DesignSettings
    family: Family
    scenarios: tuple
    aware: Design
    single: Design
    single_nominal: Verification
    iterations: tuple
    converged: bool
    sweeps: dict
    nominal_sweeps: dict
    stiffness_scale: float
    force_scale: float
    seconds: float

    @property
    def margin_kept(self) -> bool:
        """The array-aware design's full solves keep the margin K (less :data:`MARGIN_SLACK`) at every path point."""
        return self.aware.verification.min_margin >= (1.0 - MARGIN_SLACK) * self.settings.margin

    @property
    def accepted(self) -> bool:
        """The array-aware design's full solves satisfy the problem: every path point stable with the
        margin kept, and no snap-through unless allowed."""
        full = self.aware.verification
        return full.all_stable and self.margin_kept and (self.settings.allow_snap or not full.any_snap)


# ----------------------------------------------------------------------------- helpers

def designed_units(cfg: ArrayConfig, units: Sequence[int] | None) -> tuple[int, ...]:
    """The units to design, 0-based: ``units``, or the config's biased units, or every unit.

    Raises
    ------
    ConfigError
        A unit out of range or listed twice.
    """
    n = cfg.n_units
    if units is None:
        biased = tuple(k for k, m in enumerate(cfg.modes) if m == BIASED)
        return biased or tuple(range(n))
    out = tuple(int(k) for k in units)
    if not out or any(not 0 <= k < n for k in out) or len(set(out)) != len(out):
        raise ConfigError(f"--units must be distinct units in [1, {n}], got {[k + 1 for k in out]}")
    return tuple(sorted(out))


def design_config(cfg: ArrayConfig, units: Sequence[int], laws: Sequence[BiasLaw]) -> ArrayConfig:
    """``cfg`` with ``units`` biased on ``laws`` (other units keep their mode and bias)."""
    modes = list(cfg.modes)
    bias = list(cfg.per_unit("bias"))
    for k, law in zip(units, laws):
        modes[k], bias[k] = BIASED, law
    return cfg.replace(unit_modes=tuple(modes), bias=tuple(bias))


def _vectorised(law: BiasLaw) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """``(B, dB/dw)`` of a fixed law at an array of heights (NaN where it is undefined)."""
    def evaluate(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        b, db = np.full(w.shape, np.nan), np.full(w.shape, np.nan)
        for idx, x in np.ndenumerate(w):
            if np.isfinite(x) and law.contains(float(x)):
                b[idx], db[idx] = law.force(float(x)), law.slope(float(x))
        return b, db
    return evaluate


def _context_bias(family: Family, designed: Sequence[int], biased: Sequence[int], fixed: dict, shared: bool,
                  n_params: int) -> Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """``bias(theta, w)`` of a context whose biased units are ``biased``: designed ones from ``theta``."""
    fixed_laws = {k: _vectorised(law) for k, law in fixed.items()}

    def bias(theta: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        b, db = np.empty_like(w), np.empty_like(w)
        for col, k in enumerate(biased):
            if k in designed:
                i = 0 if shared else designed.index(k)
                b[:, col], db[:, col] = family.evaluate(theta[:, i * n_params:(i + 1) * n_params], w[:, col])
            else:
                b[:, col], db[:, col] = fixed_laws[k](w[:, col])
        return b, db
    return bias


def _pattern_model(sweeps: dict[Pattern, Sequence[Sweep]], biased: Sequence[int],
                   anchors: dict[Pattern, np.ndarray]) -> PatternModel:
    """The inner model's forces from the sweeps of the biased units (in ``biased`` order) per pattern."""
    grid = np.asarray(next(iter(sweeps.values()))[0].task.grid)
    step = float(grid[1] - grid[0])
    force, slopes, coupling, coupling_slopes = [], [], [], []
    for pattern_sweeps in sweeps.values():
        for i, s in enumerate(pattern_sweeps):
            cols = [int(np.searchsorted(s.held, k)) for k in biased]
            force.append(s.force)
            slopes.append(s.stiffness[:, cols[i]])
            for c in cols:
                coupling.append(s.stiffness[:, c])
                coupling_slopes.append(np.gradient(s.stiffness[:, c], step))
    return PatternModel(Curves(float(grid[0]), step, np.array(force), np.array(slopes)),
                        Curves(float(grid[0]), step, np.array(coupling), np.array(coupling_slopes)),
                        np.array([np.asarray(anchors[p], dtype=float) for p in sweeps]),
                        {p: i for i, p in enumerate(sweeps)})


def _verification(cases: Sequence[Scenario], results: Sequence[PathResult]) -> Verification:
    """Scenario rows from the path results (one per low pattern)."""
    by_low = {r.task.low: r for r in results}
    rows = []
    for sc in cases:
        res = by_low[sc.low]
        i = res.task.units.index(sc.unit)
        low, high = res.low, res.high[i]
        stroke = (high.position[sc.unit] - low.position[sc.unit]) if (low is not None and high is not None) \
            else math.nan
        rows.append(ScenarioResult(sc, low, high, float(stroke), res.hysteresis[i], res.errors[i]))
    return Verification(tuple(rows))


def _path_tasks(cfg: ArrayConfig, cases: Sequence[Scenario], voltage: float, start: float) -> list[PathTask]:
    lows: dict[Pattern, list[int]] = {}
    for sc in cases:
        lows.setdefault(sc.low, [])
        if sc.unit not in lows[sc.low]:
            lows[sc.low].append(sc.unit)
    return [PathTask(cfg, low, tuple(units), voltage, start) for low, units in lows.items()]


def _anchors(verification: Verification, fallback: dict[Pattern, np.ndarray]) -> dict[Pattern, np.ndarray]:
    """Heights of every unit in each pattern reached by the full solves (``fallback`` where none was)."""
    out = dict(fallback)
    found: dict[Pattern, np.ndarray] = {}
    for row in verification.rows:
        for state, pattern in ((row.low, row.scenario.low), (row.high, row.scenario.high)):
            if state is not None and pattern not in found:
                found[pattern] = state.position.copy()
    out.update(found)
    return out


# ----------------------------------------------------------------------------- the design

def design_bias(cfg: ArrayConfig, settings: DesignSettings, workers: int = 1, scheduler: str | None = None,
                progress: Progress | None = None) -> BiasDesign:
    """Design the bias of ``settings.units`` of ``cfg`` for the largest guaranteed stroke (module text).

    Parameters
    ----------
    cfg : ArrayConfig
        The array (its geometry, material and mesh; the modes and biases of units not
        designed are kept).
    settings : DesignSettings
    workers, scheduler
        Where the finite-element tasks run (:func:`~dea_array_twin.parallel.run_tasks`).
    progress : callable, optional
        ``progress(stage, done, total)`` after each task.

    Raises
    ------
    ConfigError, ValueError
        Bad units, ranges, family or scenario spec (the message names it).
    RuntimeError
        No feasible design on the single units' nominal curves (nothing to start from).
    """
    tic = time.perf_counter()
    report = progress or (lambda stage, done, total: None)
    if not (math.isfinite(settings.voltage) and settings.voltage > 0):
        raise ConfigError(f"--voltage must be a finite voltage > 0 V, got {settings.voltage}")
    n = cfg.n_units
    units = designed_units(cfg, settings.units)
    diameter = cfg.scaled("electrode_diameter")
    lo, hi = settings.position_range or tuple(f * diameter for f in POSITION_RANGE)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi) or max(abs(lo), abs(hi)) > cfg.scaled(
            "max_displacement"):
        raise ConfigError(f"--position-range must be LO < HI within max_displacement, got [{lo}, {hi}] m")
    if settings.grid_points < 4:
        raise ConfigError(f"grid_points must be >= 4, got {settings.grid_points}")
    grid = tuple(np.linspace(lo, hi, settings.grid_points).tolist())
    cases = tuple(scenarios(n, units, settings.scenarios))
    table = settings.table if settings.table is not None else next(
        (t for t in (find_table(cfg.per_unit("bias")[k]) for k in units) if t is not None), None)

    def run(stage: str, function, tasks: list):
        return run_tasks(function, tasks, workers, scheduler, lambda done: report(stage, done, len(tasks)))

    # 1. each designed unit alone: nominal curves, scales, the single-unit-tuned design
    alone = {k: tuple(DRIVEN if j == k else FREE for j in range(n)) for k in units}
    zero = (0.0,) * n
    nominal_tasks = [SweepTask(cfg, alone[k], zero, tuple(settings.voltage * on if j == k else 0.0
                                                          for j in range(n)), k, grid, (k, on))
                     for k in units for on in (False, True)]
    nominal_sweeps = {t.key: s for t, s in zip(nominal_tasks, run("nominal curves", run_sweep, nominal_tasks))}
    slopes = np.concatenate([s.stiffness[:, int(np.searchsorted(s.held, s.task.unit))]
                             for s in nominal_sweeps.values()])
    stiffness_scale = float(np.nanmin(slopes))
    force_scale = float(np.nanmax([np.nanmax(nominal_sweeps[(k, False)].force) for k in units]))
    if not (stiffness_scale > 0 and force_scale > 0):
        raise RuntimeError(f"the nominal curves are not usable for design: softest slope {stiffness_scale} N/m, "
                           f"largest force {force_scale} N")
    family = make_family(settings.family, (lo, hi), stiffness_scale, force_scale, settings.ranges, table)
    n_params = len(family.names)
    bounds = family.bounds * (1 if settings.shared else len(units))
    margin = MARGIN_FRACTION * stiffness_scale if settings.margin is None else float(settings.margin)
    limits = Constraints(margin, settings.max_force, stiffness_scale,
                         force_scale if math.isinf(settings.max_force) else settings.max_force, diameter)
    settings = replace(settings, units=units, margin=margin, position_range=(lo, hi),
                       start=0.5 * (lo + hi) if settings.start is None else settings.start)
    fixed = {k: cfg.per_unit("bias")[k] for k, m in enumerate(cfg.modes) if m == BIASED and k not in units}
    rest = (False,) * n

    def alone_model(group: Sequence[int]) -> InnerModel:
        """The inner model of the units ``group``, each alone in the array (its nominal scenario)."""
        contexts, cases = [], []
        for k in group:
            on = tuple(j == k for j in range(n))
            models = _pattern_model({rest: [nominal_sweeps[(k, False)]], on: [nominal_sweeps[(k, True)]]}, (k,),
                                    {rest: np.zeros(1), on: np.zeros(1)})
            contexts.append(Context((k,), models, _context_bias(family, group, (k,), {}, True, n_params)))
            cases.append((Scenario(k, rest), len(contexts) - 1))
        return InnerModel(contexts, cases, n, settings.start, diameter, settings.allow_snap)

    # per unit, each unit alone is its own problem; shared, one problem over every unit alone
    groups = [tuple(units)] if settings.shared else [(k,) for k in units]
    effort = {"population": settings.population or optimise.POPULATION,
              "generations": settings.generations or optimise.GENERATIONS}
    alone_opts = [maximise_min_stroke(alone_model(group), family.bounds, limits, **effort) for group in groups]
    if not all(opt.feasible for opt in alone_opts):
        raise RuntimeError("no bias of the family satisfies the constraints on the units' nominal curves "
                           f"(margin {margin:.4g} N/m, max force {settings.max_force:.4g} N, position range "
                           f"[{lo:.4g}, {hi:.4g}] m): widen the ranges or lower the margin")
    theta_single = np.vstack([np.tile(opt.theta, (len(group), 1)) for opt, group in zip(alone_opts, groups)])
    single_flat = theta_single[0] if settings.shared else theta_single.ravel()
    alone_heights = {}
    for opt, group in zip(alone_opts, groups):
        ev = opt.scored.evaluation
        for i, k in enumerate(group):
            alone_heights[k] = {False: float(ev.low[0, i, k]), True: float(ev.high[0, i, k])}
    single_predicted = np.concatenate([opt.scored.evaluation.stroke[0] for opt in alone_opts])

    def laws_of(theta: np.ndarray) -> tuple:
        return tuple(family.law(row) for row in theta)

    def verify(config: ArrayConfig, cases: Sequence[Scenario], stage: str) -> Verification:
        tasks = _path_tasks(config, cases, settings.voltage, settings.start)
        return _verification(cases, run(stage, run_path, tasks))

    # 2. the single-unit-tuned design, alone and in the array
    single_laws = laws_of(theta_single)
    alone_nominal = []
    for k, law in zip(units, single_laws):
        unit_cfg = design_config(cfg.replace(unit_modes=tuple(FREE for _ in range(n))), (k,), (law,))
        alone_nominal += verify(unit_cfg, [Scenario(k, rest)], f"unit {k + 1} alone").rows
    single_nominal = Verification(tuple(alone_nominal))
    single_array = verify(design_config(cfg, units, single_laws), cases, "single-unit design in the array")
    single = Design(theta_single, single_laws, single_predicted, single_array)

    # 3. the array-aware loop
    biased = tuple(sorted(set(units) | set(fixed)))
    all_patterns = patterns(cases, n)
    fallback = {p: np.array([alone_heights[j][p[j]] if j in alone_heights else 0.0 for j in range(n)])
                for p in all_patterns}
    anchors = _anchors(single_array, fallback)
    modes = held_modes(design_config(cfg, units, single_laws))
    iterations: list[Iteration] = []
    best = single_flat
    sweeps: dict = {}
    for it in range(settings.max_iterations):
        t0 = time.perf_counter()
        tasks = [SweepTask(cfg, modes, tuple(anchors[p]), tuple(settings.voltage * float(on) for on in p), k, grid,
                           (p, k)) for p in all_patterns for k in biased]
        sweeps = {t.key: s for t, s in zip(tasks, run(f"array curves, pass {it + 1}", run_sweep, tasks))}
        models = _pattern_model({p: [sweeps[(p, k)] for k in biased] for p in all_patterns}, biased,
                                {p: anchors[p][list(biased)] for p in all_patterns})
        context = Context(biased, models, _context_bias(family, units, biased, fixed, settings.shared, n_params))
        model = InnerModel([context], [(sc, 0) for sc in cases], n, settings.start, diameter, settings.allow_snap)
        t1 = time.perf_counter()
        opt = maximise_min_stroke(model, bounds, limits, [best, single_flat], local=it > 0 or n == 1,
                                  **effort)
        t2 = time.perf_counter()
        theta = _per_unit(opt.theta, settings.shared, len(units), n_params)
        laws = laws_of(theta)
        full = verify(design_config(cfg, units, laws), cases, f"verification, pass {it + 1}")
        predicted = opt.scored.evaluation.stroke[0]
        agreement = float(np.max(np.abs(predicted - full.strokes)) / abs(full.min_stroke)) \
            if np.isfinite(full.min_stroke) and full.min_stroke != 0 else math.inf
        iterations.append(Iteration(Design(theta, laws, predicted, full), agreement, opt.feasible, opt.evaluations,
                                    {"sweeps": t1 - t0, "optimisation": t2 - t1,
                                     "verification": time.perf_counter() - t2}))
        best = opt.theta
        anchors = _anchors(full, anchors)
        if agreement <= settings.tolerance:
            break
    aware = iterations[-1].design
    return BiasDesign(design_config(cfg, units, aware.laws), settings, family, cases, aware, single, single_nominal,
                      tuple(iterations), iterations[-1].agreement <= settings.tolerance, sweeps, nominal_sweeps,
                      stiffness_scale, force_scale, time.perf_counter() - tic)


def _per_unit(theta: np.ndarray, shared: bool, count: int, n_params: int) -> np.ndarray:
    """Parameters per designed unit, shape (count, n_params)."""
    return np.tile(theta, (count, 1)) if shared else np.asarray(theta).reshape(count, n_params)
