"""Figures of a bias design, like the paper's 5b and 6b: force curves with the bias drawn over them.

One PNG per designed unit, two panels: the unit's nominal scenario (every other unit at
0 V) and its worst scenario of the array-aware design.  Each panel shows the unit's
membrane force ``F`` [N] against its height ``w`` [mm] at 0 V and at V (the last inner
model's sweeps: the other held units at the heights the full solves found in that
voltage pattern), the array-aware bias ``B(w)`` (solid) and the single-unit-tuned bias
(dashed), and the full solves' equilibria of the array-aware design (circle at 0 V,
star at V).  Matplotlib (the ``plot`` extra) is imported here, lazily by the callers.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..model.bias import BiasLaw
from .bias_design import BiasDesign, ScenarioResult


def _bias_curve(law: BiasLaw, w: np.ndarray) -> np.ndarray:
    return np.array([law.force(float(x)) if law.contains(float(x)) else np.nan for x in w])


def _panel(ax, result: BiasDesign, row: ScenarioResult, title: str) -> None:
    sc = row.scenario
    k = sc.unit
    i = result.settings.units.index(k)
    for pattern, label, colour in ((sc.low, "0 V", "tab:blue"), (sc.high, f"{result.settings.voltage:g} V",
                                                                  "tab:red")):
        sweep = result.sweeps.get((pattern, k))
        if sweep is not None:
            ax.plot(1e3 * np.asarray(sweep.task.grid), sweep.force, color=colour, label=f"F, unit {k + 1} at {label}")
    w = np.asarray(next(iter(result.sweeps.values())).task.grid)
    ax.plot(1e3 * w, _bias_curve(result.aware.laws[i], w), "k-", label="B, array-aware")
    ax.plot(1e3 * w, _bias_curve(result.single.laws[i], w), "k--", lw=0.8, label="B, single-unit-tuned")
    for state, marker, colour in ((row.low, "o", "tab:blue"), (row.high, "*", "tab:red")):
        if state is not None:
            ax.plot(1e3 * state.position[k], state.bias_force[k], marker, color=colour, ms=9, mec="k")
    stroke = f"stroke {1e3 * row.stroke:.3f} mm" if np.isfinite(row.stroke) else "no equilibrium"
    ax.set_title(f"{title}: scenario {sc.label}, {stroke}", fontsize=9)
    ax.set_xlabel("height w [mm]")
    ax.set_ylabel("force [N]")
    ax.grid(alpha=0.3)


def plot_unit(result: BiasDesign, unit: int, path: Path) -> Path:
    """The two panels of designed unit ``unit`` (0-based) to ``path`` (see the module text)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = [r for r in result.aware.verification.rows if r.scenario.unit == unit]
    nominal = next((r for r in rows if r.scenario.nominal), rows[0])
    worst = min(rows, key=lambda r: r.stroke if np.isfinite(r.stroke) else -np.inf)
    fig = Figure(figsize=(11, 4.5), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2, sharey=True)
    _panel(axes[0], result, nominal, "nominal" if nominal.scenario.nominal else "first scenario")
    _panel(axes[1], result, worst, "worst")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"unit {unit + 1}: membrane force and bias (circle: 0 V equilibrium, star: at V)", fontsize=10)
    fig.savefig(path, dpi=100)
    return path
