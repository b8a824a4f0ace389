"""PNG figures of the studies, in the style of the paper's figures 12-23.

Matplotlib's object-oriented API on the Agg canvas (no pyplot, no display).  Axes
show mm, N and pF; points where the solver flagged wrinkling are drawn hollow.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from .tasks import CurveResult, Sweep

#: The paper's markers: eta_F,LV blue circles, eta_F,HV red stars, eta_C green diamonds.
_INDICES = (("eta_f_lv", "$\\eta_{F,LV}$", "o", "tab:blue"), ("eta_f_hv", "$\\eta_{F,HV}$", "*", "tab:red"),
            ("eta_c", "$\\eta_C$", "D", "tab:green"))
#: The curves each index is computed from (eqs. 13, 15, 16).
_SOURCES = {"eta_f_lv": ("lv_default", "lv_perturbed"), "eta_f_hv": ("hv_default", "hv_perturbed"),
            "eta_c": ("lv_default", "c_neighbour")}
_AXIS = {"spacing": ("electrode spacing d [mm]", 1e3), "edge_distance": ("edge distance b [mm]", 1e3),
         "prestretch": ("pre-stretch $\\lambda_p$ [-]", 1.0), "scale": ("down-scaling factor k [-]", 1.0)}


def _figure(rows: int, cols: int, size: tuple[float, float]):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    return fig, np.atleast_2d(fig.subplots(rows, cols, squeeze=False))


def plot_sweep(sweep: Sweep, rows: Sequence[dict], path: Path) -> Path:
    """The three indices against the swept parameter (figures 19-22).

    Hollow markers: a curve that index comes from was flagged as wrinkled at that
    point.  For the scale sweep a dotted line marks where d falls below the air
    breakdown gap.
    """
    label, factor = _AXIS[sweep.name]
    fig, axes = _figure(1, 1, (7, 4.5))
    ax = axes[0, 0]
    x = np.array([row["value"] for row in rows]) * factor
    for key, name, marker, colour in _INDICES:
        y = np.array([row[key] for row in rows], dtype=float)
        ax.plot(x, y, "-", color=colour, lw=0.8)
        wrinkled = np.array([bool(set(str(row.get("wrinkled", "")).split()) & set(_SOURCES[key]))
                             for row in rows])
        ax.plot(x[~wrinkled], y[~wrinkled], marker, color=colour, ls="none", label=name)
        if wrinkled.any():
            ax.plot(x[wrinkled], y[wrinkled], marker, mfc="none", color=colour, ls="none",
                    label=f"{name}, wrinkling flagged")
    if sweep.name == "scale":
        ax.set_xscale("log")
        below = [row["value"] for row in rows if row["below_air_breakdown"]]
        if below and rows:
            limit = rows[0]["d_m"] * rows[0]["value"] / rows[0]["air_gap_min_m"]
            ax.axvline(limit, color="k", ls=":", label=f"d < air breakdown gap (k > {limit:.1f})")
    ax.set_xlabel(label)
    ax.set_ylabel("coupling index [%]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"parameter study: {sweep.name}")
    fig.savefig(path, dpi=110)
    return path


def _curve_axes(ax, res: CurveResult, unit: int, kind: str, style: str, colour: str, label: str) -> None:
    d = res.displacement * 1e3
    y = res.force[:, unit] if kind == "force" else res.delta_capacitance[:, unit] * 1e12
    ax.plot(d, y, style, color=colour, label=label)
    if res.wrinkled.any():
        ax.plot(d[res.wrinkled], y[res.wrinkled], "o", mfc="none", ms=4, color=colour)


def plot_coupling_curves(results: Sequence, path: Path) -> Path:
    """Figures 17(c)/18(c): the measured unit's force (LV, HV; default and perturbed) and dC curves."""
    fig, axes = _figure(1, 2, (11, 4.5))
    curves = {r.task.key[-1]: r for r in results if isinstance(r, CurveResult)}
    centre = results[0].task.swept
    for case, style, colour in (("lv_default", "-", "tab:blue"), ("lv_perturbed", "--", "tab:blue"),
                                ("hv_default", "-", "tab:red"), ("hv_perturbed", "--", "tab:red")):
        if case in curves:
            _curve_axes(axes[0, 0], curves[case], centre, "force", style, colour, case.replace("_", ", "))
    cases = (("lv_default", "-", f"unit {centre + 1} swept"), ("c_neighbour", "--", "neighbour swept"))
    for case, style, label in cases:
        if case in curves:
            _curve_axes(axes[0, 1], curves[case], centre, "capacitance", style, "tab:green", label)
    return _save_pair(fig, axes, "swept unit's displacement [mm]", f"unit {centre + 1}",
                      "coupling curves (hollow circles: wrinkling flagged)", path)


def plot_curves(results: Sequence[CurveResult], path: Path) -> Path:
    """Figures 12-16: row = swept unit; columns = its force, then each unit's dC."""
    n = results[0].task.config.n_units
    fig, axes = _figure(n, n + 1, (3.2 * (n + 1), 2.6 * n))
    colours = {nb: f"C{i % 10}" for i, nb in enumerate(dict.fromkeys(r.task.key[1] for r in results))}
    volts = sorted({r.task.voltage for r in results})
    for res in results:
        k = res.task.swept
        nb, volt = res.task.key[1], res.task.voltage
        style = "-" if volt == volts[0] else "--"
        label = f"neighbours {nb if nb == 'free' else f'{float(nb) * 1e3:g} mm'}, {volt:.0f} V"
        _curve_axes(axes[k, 0], res, k, "force", style, colours[nb], label)
        for j in range(n):
            _curve_axes(axes[k, j + 1], res, j, "capacitance", style, colours[nb], label)
    for k in range(n):
        axes[k, 0].set_ylabel(f"unit {k + 1} swept\nforce F{k + 1} [N]")
        for j in range(n):
            axes[k, j + 1].set_title(f"dC{j + 1} [pF]", fontsize=9)
        for ax in axes[k]:
            ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("swept displacement [mm]")
    axes[0, 0].legend(fontsize=7)
    fig.savefig(path, dpi=100)
    return path


def plot_shape(results: Sequence[CurveResult], path: Path) -> Path:
    """Figure 23(b, c): force and dC of the swept unit, circle vs square electrodes."""
    fig, axes = _figure(1, 2, (11, 4.5))
    for res in results:
        shape, case = res.task.key[1], res.task.key[2]
        style = "-" if shape == "circle" else "--"
        colour = "tab:blue" if case == "lv" else "tab:red"
        label = f"{shape}, {case.upper()}"
        _curve_axes(axes[0, 0], res, res.task.swept, "force", style, colour, label)
        _curve_axes(axes[0, 1], res, res.task.swept, "capacitance", style, colour, label)
    return _save_pair(fig, axes, "displacement [mm]", "the swept unit", "electrode shape at equal area", path)


def _save_pair(fig, axes, xlabel: str, unit: str, title: str, path: Path) -> Path:
    """Label a (force, capacitance change) pair of axes, add grid and legends, save."""
    axes[0, 0].set(xlabel=xlabel, ylabel=f"force on {unit} [N]")
    axes[0, 1].set(xlabel=xlabel, ylabel=f"capacitance change of {unit} [pF]")
    for ax in axes[0]:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
    return path

