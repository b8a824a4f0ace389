"""The outer loop of bias design: the largest guaranteed stroke over the scenarios, on the inner model.

Problem (per unit or one design shared by the designed units): choose the parameters
``theta`` of a bias family (:mod:`.families`) that maximise

    min over scenarios (k, s) of  stroke_k,s(theta)

subject to, in every low and high state of every scenario, a stability margin
``lambda_min(dF/dw - diag(dB/dw)) >= K`` [N/m] (for one unit ``dF/dw - dB/dw >= K``), a
bias force ``|B| <= B_max``, the units inside the position range, and no snap-through
on any path (unless allowed).

Method: :func:`maximise_min_stroke` runs scipy's differential evolution (seeded, so a
run is repeatable) over the parameter box on the inner model (:mod:`.inner`), a whole
population per evaluation, with constraints by the feasibility rule (a feasible design
beats an infeasible one; infeasible ones compare by their total normalised violation),
then polishes the best by a direct search on the same function (:func:`direct_search`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy.optimize import differential_evolution

from .inner import Evaluation, InnerModel

#: Differential evolution: population per parameter (the inner model evaluates a whole
#: population at about the cost of a few designs: a call costs its Python overhead, so
#: few large generations), generations at most, seed.
POPULATION = 25
GENERATIONS = 20
SEED = 13
#: First step of a local polish (fraction of each parameter's range).
LOCAL_STEP = 0.02


@dataclass(frozen=True)
class Constraints:
    """What every state of every scenario must satisfy.

    Attributes
    ----------
    margin : float
        Smallest stability margin ``K`` [N/m].
    max_force : float
        Largest ``|B|`` [N] (inf: no limit).
    stiffness_scale, force_scale, length_scale : float
        Normalisations of the violations [N/m, N, m].
    """

    margin: float
    max_force: float
    stiffness_scale: float
    force_scale: float
    length_scale: float


@dataclass(frozen=True)
class Scored:
    """A population's evaluation and what the optimiser makes of it.

    Attributes
    ----------
    evaluation : Evaluation
    min_stroke : ndarray
        Smallest stroke over the scenarios [m] (NaN if some is missing).
    violation : ndarray
        Total normalised constraint violation (0: feasible).
    objective : ndarray
        ``-min_stroke / D`` when feasible, else ``1 + violation``.
    """

    evaluation: Evaluation
    min_stroke: np.ndarray
    violation: np.ndarray
    objective: np.ndarray


def score(model: InnerModel, theta: np.ndarray, limits: Constraints) -> Scored:
    """Evaluate designs ``theta`` (designs, parameters) and rate them (see the module text)."""
    ev = model.evaluate(theta)
    missing = np.any(~np.isfinite(ev.stroke), axis=1)
    min_stroke = np.where(missing, np.nan, np.min(np.where(np.isfinite(ev.stroke), ev.stroke, np.inf), axis=1))
    margin = np.nanmin(np.where(np.isfinite(ev.margin), ev.margin, np.nan), axis=1, initial=np.inf)
    force = np.nanmax(np.where(np.isfinite(ev.bias_force), ev.bias_force, np.nan), axis=1, initial=0.0)
    violation = (ev.failed + missing
                 + np.maximum(0.0, limits.margin - margin) / limits.stiffness_scale
                 + np.maximum(0.0, force - limits.max_force) / limits.force_scale
                 + (ev.snapped & ~model.allow_snap))
    feasible = violation <= 0.0
    objective = np.where(feasible, -np.nan_to_num(min_stroke) / limits.length_scale, 1.0 + violation)
    return Scored(ev, min_stroke, violation, objective)


@dataclass(frozen=True)
class Optimum:
    """The best design found on the inner model.

    Attributes
    ----------
    theta : ndarray
        Its parameters.
    scored : Scored
        Its evaluation (one design).
    evaluations : int
        Designs evaluated.
    """

    theta: np.ndarray
    scored: Scored
    evaluations: int

    @property
    def feasible(self) -> bool:
        """Whether it satisfies every constraint on the inner model."""
        return bool(self.scored.violation[0] <= 0.0)


def maximise_min_stroke(model: InnerModel, bounds: Sequence[tuple[float, float]], limits: Constraints,
                        guesses: Sequence[np.ndarray] = (), local: bool = False, population: int = POPULATION,
                        generations: int = GENERATIONS) -> Optimum:
    """The parameters in ``bounds`` with the largest smallest stroke on ``model`` (see the module text).

    ``guesses`` (parameter vectors) join the initial population: a previous design
    gives the search a feasible start.  ``local``: only polish the best guess (the model
    was re-anchored near it: its optimum is close; a guess just outside a constraint
    on the new model is walked back by the penalty).  ``population`` (per parameter) and
    ``generations``: the differential evolution's effort.
    """
    lo = np.array([b[0] for b in bounds], dtype=float)
    hi = np.array([b[1] for b in bounds], dtype=float)
    count = [0]

    def objective(x: np.ndarray) -> np.ndarray:
        """Penalised objective of unit-box points ``x`` (parameters, designs)."""
        theta = lo + np.atleast_2d(x.T) * (hi - lo)
        count[0] += theta.shape[0]
        return score(model, theta, limits).objective

    unit_box = [(0.0, 1.0)] * lo.size
    start = [np.clip((np.asarray(g, dtype=float) - lo) / (hi - lo), 0.0, 1.0) for g in guesses]
    best = None
    if start:
        values = objective(np.array(start).T)
        best = start[int(np.argmin(values))]
    if local and best is not None:
        x, _ = direct_search(objective, best, float(values.min()), step=LOCAL_STEP)
    else:
        result = differential_evolution(objective, unit_box, popsize=population, maxiter=generations, tol=1e-4,
                                        seed=SEED, polish=False, vectorized=True, updating="deferred",
                                        init="sobol", x0=best)
        x, _ = direct_search(objective, result.x, result.fun)
    theta = lo + x * (hi - lo)
    return Optimum(theta, score(model, theta[None, :], limits), count[0] + 1)


def direct_search(objective: Callable[[np.ndarray], np.ndarray], x: np.ndarray, value: float,
                  step: float = 0.05, smallest: float = 1e-4, max_iterations: int = 60) -> tuple[np.ndarray, float]:
    """Minimise ``objective`` over the unit box from ``x`` by a direct search (a polish).

    Each iteration evaluates, in one batch, the points ``x +- step d`` for the coordinate
    directions and as many seeded random unit directions (a max-min objective has kinks
    that coordinate steps alone cannot follow); it moves to the best point that improves
    on ``x`` and doubles the step, or halves the step, until it is below ``smallest``.
    """
    rng = np.random.default_rng(SEED)
    n = x.size
    for _ in range(max_iterations):
        if step < smallest:
            break
        random = rng.normal(size=(n, n))
        directions = np.vstack([np.eye(n), random / np.linalg.norm(random, axis=1, keepdims=True)])
        trial = np.clip(np.vstack([x + step * directions, x - step * directions]), 0.0, 1.0)
        values = objective(trial.T)
        i = int(np.argmin(values))
        if values[i] < value:
            x, value, step = trial[i], float(values[i]), min(2.0 * step, 0.25)
        else:
            step *= 0.5
    return x, value
