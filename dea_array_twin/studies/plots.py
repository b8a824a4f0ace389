"""PNG figures of the studies, in the panel layout of the paper's figures 12-23.

Matplotlib's object-oriented API on the Agg canvas (no pyplot, no display).  Axes
show mm, N and pF; points where the solver flagged wrinkling are drawn hollow.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from .tasks import CurveResult, Sweep, coupling_indices, neighbour_label

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
    """The three indices against the swept parameter (figures 19-22), the HV in the legend.

    Hollow markers: a curve that index comes from was flagged as wrinkled at that
    point.  For the scale sweep a dotted line marks where d falls below the air
    breakdown gap.
    """
    label, factor = _AXIS[sweep.name]
    fig, axes = _figure(1, 1, (7, 4.5))
    ax = axes[0, 0]
    x = np.array([row["value"] for row in rows]) * factor
    volts = {round(row["hv_voltage_V"]) for row in rows}
    hv = f"{volts.pop()} V" if len(volts) == 1 else "$E_C t_0 / \\lambda_p^2$"
    for key, name, marker, colour in _INDICES:
        name = f"{name} (HV = {hv}, eq. 14)" if key == "eta_f_hv" else name
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


def _mark_max(ax, res: CurveResult, unit: int, kind: str, colour: str, text: str) -> float:
    """Mark the largest-magnitude value of a curve with ``text`` (formatted with it); return it."""
    y = res.force[:, unit] if kind == "force" else res.delta_capacitance[:, unit] * 1e12
    i = int(np.argmax(np.abs(y)))
    ax.plot(res.displacement[i] * 1e3, y[i], ".", color=colour)
    ax.annotate(text.format(y[i]), (res.displacement[i] * 1e3, y[i]), textcoords="offset points", xytext=(-7, 0),
                ha="right", va="center", fontsize=7, color=colour)
    return float(y[i])


def _delta_arrow(ax, x: float, low: float, high: float, colour: str) -> None:
    """A vertical double arrow from ``low`` to ``high`` at ``x`` (the paper's dF_max)."""
    ax.annotate("", (x, low), (x, high), arrowprops={"arrowstyle": "<->", "color": colour, "lw": 0.8})


def plot_coupling_curves(results: Sequence, path: Path) -> Path:
    """Figures 17(c)/18(c): the measured unit's force and dC curves, annotated like the paper's.

    Force panel: LV (blue) and HV (red), default (solid) and perturbed (dashed), the
    voltages in the legend, dF_max as an arrow between the two maxima and the index
    (eqs. 13, 15).  Capacitance panel: the measured unit's dC with itself and with its
    neighbour swept, dC_max of both and eta_C (eq. 16).  Indices need all five curves.
    """
    fig, axes = _figure(1, 2, (11, 4.5))
    curves = {r.task.key[-1]: r for r in results if isinstance(r, CurveResult)}
    centre = results[0].task.swept
    index = coupling_indices(curves) if len(curves) == len(results) == 5 else None
    stroke = results[0].task.stroke * 1e3
    for kind, colour in (("lv", "tab:blue"), ("hv", "tab:red")):
        maxima = {}
        for case, style in ((f"{kind}_default", "-"), (f"{kind}_perturbed", "--")):
            if case in curves:
                res = curves[case]
                label = (f"{kind.upper()} {res.task.voltage:.0f} V, neighbours "
                         f"{neighbour_label(res.task.neighbours)}")
                _curve_axes(axes[0, 0], res, centre, "force", style, colour, label)
                maxima[case] = float(res.force[:, centre].max())
        if index is not None:
            eta = index.eta_f_lv if kind == "lv" else index.eta_f_hv
            low, high = sorted(maxima.values())
            _delta_arrow(axes[0, 0], stroke, low, high, colour)
            axes[0, 0].text(0.97, 0.05 + (0.09 if kind == "lv" else 0.0), f"$\\Delta F_{{max,{kind.upper()}}}$ = "
                            f"{1e3 * (high - low):.1f} mN, $\\eta_{{F,{kind.upper()}}}$ = {eta:.2f} %",
                            transform=axes[0, 0].transAxes, ha="right", color=colour)
    maxima = {}
    for case, style, label in (("lv_default", "-", f"unit {centre + 1} swept"),
                               ("c_neighbour", "--", "neighbour swept")):
        if case in curves:
            _curve_axes(axes[0, 1], curves[case], centre, "capacitance", style, "tab:green", label)
            maxima[case] = _mark_max(axes[0, 1], curves[case], centre, "capacitance", "tab:green",
                                     "$\\Delta C_{{max}}$ = {:.2f} pF")
    if index is not None:
        axes[0, 1].text(0.03, 0.95, f"$\\eta_C$ = {index.eta_c:.2f} %", transform=axes[0, 1].transAxes,
                        va="top", color="tab:green")
    return _save_pair(fig, axes, "swept unit's displacement [mm]", f"unit {centre + 1}",
                      "coupling curves (hollow circles: wrinkling flagged)", path)


def plot_capacitance_figure(results: Sequence[CurveResult], path: Path, title: str) -> Path:
    """Figures 12/13: row = unit deformed, column = unit measured; dC from the start of the test.

    One curve per panel (the paper measures capacitance at 0 V, neighbours not
    pre-deflected); the end value is written on it.
    """
    units = sorted({r.task.swept for r in results})
    n = len(units)
    fig, axes = _figure(n, n, (3.8 * n, 2.9 * n))
    for res in results:
        i = units.index(res.task.swept)
        for j, unit in enumerate(units):
            ax = axes[i, j]
            _curve_axes(ax, res, unit, "capacitance", "-", "tab:green", f"{res.task.voltage:g} V")
            _mark_max(ax, res, unit, "capacitance", "tab:green", "{:.2f} pF")
            ax.set_title(f"DE{res.task.swept + 1} deformed, DE{unit + 1} measured", fontsize=9)
            ax.grid(alpha=0.3)
    for i in range(n):
        axes[i, 0].set_ylabel("capacitance change [pF]")
        axes[-1, i].set_xlabel("displacement of the deformed DE [mm]")
    fig.suptitle(title)
    fig.savefig(path, dpi=100)
    return path


def plot_force_figure(results: Sequence[CurveResult], path: Path, title: str) -> Path:
    """Figures 15/16: row = neighbour setting, column = unit swept and measured; LV blue, HV red.

    The legend gives each curve's voltage; its largest force is written on it.
    """
    units = sorted({r.task.swept for r in results})
    settings = list(dict.fromkeys(r.task.neighbours for r in results))
    volts = sorted({r.task.voltage for r in results})
    colours = {v: "tab:blue" if i == 0 else ("tab:red" if i == 1 else f"C{i + 2}") for i, v in enumerate(volts)}
    names = {v: "LV" if i == 0 and v == 0 else "HV" for i, v in enumerate(volts)}
    fig, axes = _figure(len(settings), len(units), (4.2 * len(units), 2.5 * len(settings)))
    for res in results:
        i, j = settings.index(res.task.neighbours), units.index(res.task.swept)
        ax = axes[i, j]
        volt = res.task.voltage
        _curve_axes(ax, res, res.task.swept, "force", "-", colours[volt], f"{names[volt]} {volt:.0f} V")
        _mark_max(ax, res, res.task.swept, "force", colours[volt], "{:.3f} N")
    for i, setting in enumerate(settings):
        for j, unit in enumerate(units):
            axes[i, j].set_title(f"DE{unit + 1} measured, neighbours {neighbour_label(setting)}", fontsize=9)
            axes[i, j].grid(alpha=0.3)
            axes[i, j].legend(fontsize=7, loc="lower right")
        axes[i, 0].set_ylabel("force [N]")
    for ax in axes[-1]:
        ax.set_xlabel("displacement [mm]")
    fig.suptitle(title)
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



def plot_stroke(study, path: Path) -> Path:
    """Figures 5(b) and 6(b): the measured unit's 0 V (blue) and HV (red) force curves with the LBS
    (solid black) and NBS (dashed black) lines, equilibria as dots; (b) neighbours pre-deflected,
    the nominal curves dotted."""
    fig, axes = _figure(1, 2, (12, 4.8))
    unit = study.curves["lv"].task.swept
    stroke_max = study.curves["lv"].displacement[-1]
    w = np.linspace(0.0, stroke_max, 200)
    for ax, neighbours, cases in ((axes[0, 0], "free", ("lv", "hv")), (axes[0, 1], "pre", ("lv_pre", "hv_pre"))):
        for case, colour in zip(cases, ("tab:blue", "tab:red")):
            res = study.curves[case]
            label = f"{'0 V' if case.startswith('lv') else f'{study.voltage:g} V'}"
            ax.plot(res.displacement * 1e3, res.force[:, unit], "-", color=colour, label=label)
            if neighbours == "pre":
                nominal = study.curves[case.removesuffix("_pre")]
                ax.plot(nominal.displacement * 1e3, nominal.force[:, unit], ":", color=colour,
                        label=f"{label}, nominal")
        for name, style in (("LBS", "-"), ("NBS", "--")):
            law = study.biases[name]
            ax.plot(w * 1e3, [law.force(v) for v in w], style, color="k", lw=1.2, label=name)
            row = study.row(name, neighbours)
            for x, colour in ((row.rest_position, "tab:blue"), (row.position, "tab:red")):
                ax.plot(x * 1e3, law.force(x), "o", color=colour, mec="k", zorder=5)
            height = -0.045 if name == "LBS" else -0.02
            ax.annotate("", xy=(row.position * 1e3, height), xytext=(row.rest_position * 1e3, height),
                        arrowprops={"arrowstyle": "->", "color": "k"})
            ax.text(row.rest_position * 1e3 - 0.2, height, f"{name} stroke {row.stroke * 1e3:.2f} mm",
                    ha="right", va="center", fontsize=8)
        ax.set(xlabel=f"unit {unit + 1} position w [mm]", ylabel=f"force on unit {unit + 1} [N]",
               ylim=(-0.06, None), xlim=(0, stroke_max * 1e3))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper left")
    axes[0, 0].set_title("(a) neighbours not deflected (figure 5b)")
    axes[0, 1].set_title("(b) neighbours pre-deflected by 0.4 D (figure 6b)")
    fig.savefig(path, dpi=110)
    return path
