"""``dea-twin calibrate DATA...``: fit the Yeoh coefficients to measured force curves.

With ``--slip KNOTS`` it instead fits the slip table gamma(d) of eq. 11 to the
capacitance curves of DATA (:func:`~dea_array_twin.calibration.slip.fit_slip`; the Yeoh coefficients come from
the config), printing FIT before and after and writing ``DIR/slip.csv``,
``DIR/slip.yaml`` and ``DIR/slip.png``.

Reads each DATA file into :class:`~dea_array_twin.calibration.measured.MeasuredCurve` objects, fits ``c10, c20,
c30`` with :func:`~dea_array_twin.calibration.yeoh.fit_yeoh` (Nelder-Mead, a tqdm bar on stderr), prints
the coefficients with their standard errors and the FIT of every curve before and
after, and writes ``DIR/calibration.csv``, ``DIR/fit.yaml`` and ``DIR/calibration.png``.

DATA is a CSV file (the format ``dea-twin replay`` writes, see ``docs/calibration.md``)
or an MCAP bag (``.mcap`` file or rosbag2 directory).  ``FILE@CONFIG.yaml`` gives that
file its own config (e.g. curves at two pre-stretches).  Each driven unit with measured
forces in a file is one curve.

Exit codes: 0 ok (also when the search stopped at ``--max-evaluations``: a warning says
so), 1 the twin finds no equilibrium at the start point, 2 bad arguments or data.
"""

from __future__ import annotations

import argparse
import csv
import importlib.util
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import yaml

from ..bag.reader import BagError
from ..bag.topics import parse_topic_map
from ..calibration.data import DEFAULT_SETTLE, DataError, load_curves
from ..calibration.measured import MeasuredCurve
from ..calibration.slip import SlipFit, fit_slip
from ..calibration.yeoh import PARAMETERS, POORLY_DETERMINED, YeohFit, fit_yeoh
from ..model.config import ConfigError
from ..model.solver import ConvergenceError
from .argtypes import add_topic_map, float_list, word_list

__all__ = ["add_arguments", "run_from_args"]

DEFAULT_OUT = "calibration"

# --------------------------------------------------------------------- outputs

def _swept(curve: MeasuredCurve) -> int:
    """The unit whose displacement varies most in ``curve`` (0-based)."""
    return int(np.argmax(np.ptp(curve.displacement, axis=0)))


def report(result: YeohFit, curves: Sequence[MeasuredCurve]) -> str:
    """The fitted coefficients with standard errors, the hint, and FIT per curve before and after."""
    state = "converged" if result.converged else f"NOT converged ({result.message})"
    title = (f"Yeoh coefficients fitted to {len(curves)} force curve(s): Nelder-Mead, {result.n_evaluations} "
             f"evaluations ({result.failed_evaluations} without equilibrium), {state}")
    lines = [title, f"  {'':6}{'start [kPa]':>14}{'fitted [kPa]':>15}{'stderr [kPa]':>16}"]
    for name, p0, value, err in zip(PARAMETERS, result.start, result.values, result.stderr):
        relative = f"({100 * err / abs(value):.3g} %)" if value != 0 and math.isfinite(err) else ""
        flag = "  poorly determined by these curves" if name in result.poorly_determined else ""
        lines.append(f"  {name:6}{p0 / 1e3:14.4f}{value / 1e3:15.4f}  ± {err / 1e3:<10.4g}{relative}{flag}")
    pairs = [(0, 1), (0, 2), (1, 2)]
    lines.append("  correlation: " + ", ".join(f"{PARAMETERS[i]}-{PARAMETERS[j]} {result.correlation[i, j]:+.2f}"
                                               for i, j in pairs))
    if result.poorly_determined:
        lines.append(f"  hint: {', '.join(result.poorly_determined)} have a standard error above "
                     f"{POORLY_DETERMINED:.0%} of their value: these curves hardly constrain them (add curves at "
                     f"larger stretch: higher pre-stretch, deeper indentation)")
    width = max(len(c.name) for c in curves) + 2
    lines.append(f"FIT [%] of the measured force (paper eq. 12)\n  {'curve':{width}}{'start':>9}{'fitted':>9}")
    lines += [f"  {c.name:{width}}{before:9.2f}{after:9.2f}"
              for c, before, after in zip(curves, result.initial_fit, result.fit)]
    return "\n".join(lines)


def write_table(path: Path, result: YeohFit, curves: Sequence[MeasuredCurve]) -> None:
    """``calibration.csv``: per curve and sample the swept displacement, measured and model forces (SI)."""
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["curve", "unit", "sample", "swept_unit", "swept_displacement_m", "measured_force_N",
                         "model_force_N", "start_model_force_N"])
        for curve, model, initial in zip(curves, result.model_force, result.initial_model_force):
            swept = _swept(curve)
            for i in range(curve.n_samples):
                writer.writerow([curve.name, curve.unit + 1, i, swept + 1, repr(float(curve.displacement[i, swept])),
                                 repr(float(curve.force[i])), repr(float(model[i])), repr(float(initial[i]))])


def write_yaml(path: Path, result: YeohFit, curves: Sequence[MeasuredCurve]) -> None:
    """``fit.yaml``: the coefficients as a config snippet, their standard errors and FIT per curve."""
    data = {
        "config": {name: float(v) for name, v in zip(PARAMETERS, result.values)},
        "stderr": {name: float(e) for name, e in zip(PARAMETERS, result.stderr)},
        "poorly_determined": list(result.poorly_determined),
        "correlation": [[round(float(x), 6) for x in row] for row in result.correlation],
        "start": {name: float(v) for name, v in zip(PARAMETERS, result.start)},
        "fit_percent": [{"curve": c.name, "start": float(a), "fitted": float(b)}
                        for c, a, b in zip(curves, result.initial_fit, result.fit)],
        "cost": float(result.cost), "evaluations": result.n_evaluations,
        "failed_evaluations": result.failed_evaluations, "converged": result.converged, "message": result.message,
    }
    head = ("# Yeoh coefficients [Pa] fitted by 'dea-twin calibrate' (Nelder-Mead, cost sum (1 - FIT/100)^2).\n"
            "# Copy the 'config' entries into a config YAML; stderr is the Gauss-Newton standard error [Pa].\n")
    path.write_text(head + yaml.safe_dump(data, sort_keys=False))


def plot_fit(path: Path, result: YeohFit, curves: Sequence[MeasuredCurve]) -> None:
    """``calibration.png``: measured force vs the swept unit's displacement (markers), fitted model (lines)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 5.5), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    for j, (curve, model, initial, value) in enumerate(zip(curves, result.model_force, result.initial_model_force,
                                                           result.fit)):
        colour, x = f"C{j % 10}", curve.displacement[:, _swept(curve)] * 1e3
        ax.plot(x, curve.force, "o", color=colour, ms=4, label=f"{curve.name}: FIT {value:.1f} %")
        ax.plot(x, model, "-", color=colour, lw=1.6)
        ax.plot(x, initial, ":", color=colour, lw=1.0, alpha=0.6)
    ax.set_xlabel("displacement of the swept unit [mm]")
    ax.set_ylabel("force on the measured unit [N]")
    ax.grid(True, alpha=0.3)
    ax.set_title(f"Yeoh fit: c10 = {result.c10 / 1e3:.4g} kPa, c20 = {result.c20 / 1e3:.4g} kPa, "
                 f"c30 = {result.c30 / 1e3:.4g} kPa\nmarkers measured, lines fitted model, dotted start",
                 fontsize="medium")
    ax.legend(fontsize="small")
    fig.savefig(path, dpi=110)


# ------------------------------------------------------------------------- CLI

def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``dea-twin calibrate`` options."""
    parser.add_argument("data", nargs="+", metavar="DATA",
                        help="CSV file (columns time_s, d1_m.., V1_V.., F1_N.., C1_F..: what 'dea-twin replay' "
                             "writes) or MCAP bag; FILE@CONFIG.yaml gives that file its own config")
    parser.add_argument("--config", help="config YAML (default: a bag's recorded config, else the paper's array)")
    parser.add_argument("--modes", type=word_list,
                        help="per-unit 'driven' or 'free', comma separated (default: a bag's recorded modes, "
                             "else all driven)")
    parser.add_argument("--start", type=float_list(count=3, example="180e3,10e3,0"), metavar="C10,C20,C30",
                        help="starting coefficients [Pa] (default: those of the first curve's config)")
    parser.add_argument("--max-evaluations", type=int, default=400, metavar="N",
                        help="largest number of cost evaluations (each runs the twin on every curve; default 400)")
    parser.add_argument("--settle", type=float, default=DEFAULT_SETTLE, metavar="SECONDS",
                        help=f"bags: drop force messages less than this after a command change "
                             f"(default {DEFAULT_SETTLE})")
    add_topic_map(parser, "/rig/load=force")
    parser.add_argument("--out", default=DEFAULT_OUT, metavar="DIR",
                        help=f"where calibration.csv, fit.yaml and calibration.png go (default {DEFAULT_OUT}/)")
    parser.add_argument("--slip", type=float_list(min_count=2, example="0,0.0075,0.015"), metavar="D0,D1,...",
                        help="instead of the Yeoh fit, fit the slip factors gamma of eq. 11 at these indenter "
                             "displacements [m] (gamma = 1 at the first) to the capacitance curves (C{k}_F "
                             "columns or capacitance topic); writes slip.csv, slip.yaml, slip.png")


def _log(text: str) -> None:
    print(f"dea-twin calibrate: {text}", file=sys.stderr)


def _fit_with_bar(curves: list[MeasuredCurve], args: argparse.Namespace) -> YeohFit:
    from tqdm import tqdm

    with tqdm(total=args.max_evaluations, desc="calibrate", unit="eval", file=sys.stderr, disable=None) as bar:
        def progress(count: int, cost: float, best: float) -> None:
            bar.update(1)
            bar.set_postfix(cost=f"{cost:.4g}", best=f"{best:.4g}", refresh=False)

        return fit_yeoh(curves, args.start, max_evaluations=args.max_evaluations, progress=progress)


def run_from_args(args: argparse.Namespace) -> int:
    """Run ``dea-twin calibrate`` for parsed arguments; return the exit code (0 ok, 1 solver, 2 bad input)."""
    if importlib.util.find_spec("matplotlib") is None:  # checked before the fit, not after it
        _log("error: needs matplotlib for the figure (pip install 'dea_array_twin[plot]')")
        return 2
    try:
        if args.slip is not None and args.start is not None:
            raise ConfigError("--start sets Yeoh coefficients, which --slip does not fit (put them in the config)")
        if args.max_evaluations < 1:
            raise ConfigError(f"--max-evaluations must be >= 1, got {args.max_evaluations}")
        if not args.settle >= 0:
            raise ConfigError(f"--settle must be >= 0 s, got {args.settle}")
        signal = "C" if args.slip is not None else "F"
        curves, notes = load_curves(args.data, args.config, args.modes, args.settle, parse_topic_map(args.topic_map),
                                    signal)
        for note in notes:
            _log(note)
        Path(args.out).mkdir(parents=True, exist_ok=True)
        if args.slip is not None:
            return _run_slip(curves, args)
        result = _fit_with_bar(curves, args)
    except (DataError, BagError, ConfigError, ValueError) as exc:
        _log(f"error: {exc}")
        return 2
    except OSError as exc:
        _log(f"error: cannot write the outputs: {exc}")
        return 2
    except ConvergenceError as exc:
        hint = "a slip table (try other knots)" if args.slip is not None else "the start point (try another --start)"
        _log(f"solver failed for {hint}: {exc}")
        return 1
    print(report(result, curves))
    out = Path(args.out)
    paths = [out / "calibration.csv", out / "fit.yaml", out / "calibration.png"]
    try:
        write_table(paths[0], result, curves)
        write_yaml(paths[1], result, curves)
        plot_fit(paths[2], result, curves)
    except OSError as exc:
        _log(f"error: cannot write the outputs: {exc}")
        return 2
    if not result.converged:
        _log(f"warning: the search stopped before converging ({result.message}); raise --max-evaluations")
    print(f"wrote {', '.join(str(p) for p in paths)}")
    return 0


# ------------------------------------------------------------------------ slip

def _run_slip(curves: list[MeasuredCurve], args: argparse.Namespace) -> int:
    """Fit gamma of eq. 11 to the capacitance curves, report and write slip.csv, slip.yaml, slip.png."""
    from tqdm import tqdm

    with tqdm(total=args.max_evaluations, desc="slip fit", unit="eval", file=sys.stderr, disable=None) as bar:
        result = fit_slip(curves, args.slip, max_evaluations=args.max_evaluations,
                          progress=lambda count, factors, cost: bar.update(1))
    print(slip_report(result))
    before, after = result.model_dc_before, result.model_dc_after
    out = Path(args.out)
    with open(out / "slip.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["curve", "unit", "sample", "swept_unit", "swept_displacement_m", "measured_dC_F",
                         "model_dC_no_slip_F", "model_dC_fitted_F"])
        for curve, b, a in zip(curves, before, after):
            swept, m = _swept(curve), curve.capacitance
            for i in range(curve.n_samples):
                writer.writerow([curve.name, curve.unit + 1, i, swept + 1, repr(float(curve.displacement[i, swept])),
                                 repr(float(m[i] - m[0])), repr(float(b[i])), repr(float(a[i]))])
    data = {"config": {"slip_displacement": list(result.knots), "slip_factor": [float(g) for g in result.factors]},
            "fit_percent": [{"curve": n, "no_slip": float(b), "fitted": float(a)}
                            for n, b, a in zip(result.names, result.fit_before, result.fit_after)],
            "force_change": [float(x) for x in result.force_change], "cost": float(result.cost),
            "evaluations": result.n_evaluations, "converged": result.converged, "message": result.message}
    (out / "slip.yaml").write_text("# slip table of eq. 11 fitted by 'dea-twin calibrate --slip'; copy 'config' "
                                   "into a config YAML\n" + yaml.safe_dump(data, sort_keys=False))
    _plot_slip(out / "slip.png", result, curves, before, after)
    if not result.converged:
        _log(f"warning: the fit stopped before converging ({result.message}); raise --max-evaluations")
    print(f"wrote {out / 'slip.csv'}, {out / 'slip.yaml'}, {out / 'slip.png'}")
    return 0


def slip_report(result: SlipFit) -> str:
    """The fitted table and the capacitance FIT per curve without and with it."""
    lines = [f"slip table of eq. 11 fitted to {len(result.names)} capacitance curve(s): {result.n_evaluations} "
             f"evaluations, {'converged' if result.converged else 'NOT converged (' + result.message + ')'}",
             "  d [mm]   gamma"]
    lines += [f"  {d * 1e3:6.2f}  {g:7.4f}" for d, g in zip(result.knots, result.factors)]
    width = max(len(n) for n in result.names) + 2
    lines.append(f"FIT [%] of the capacitance change (eq. 12)\n  {'curve':{width}}{'no slip':>9}{'fitted':>9}"
                 f"{'force change':>14}")
    lines += [f"  {n:{width}}{b:9.2f}{a:9.2f}{100 * c:13.2f}%"
              for n, b, a, c in zip(result.names, result.fit_before, result.fit_after, result.force_change)]
    return "\n".join(lines)


def _plot_slip(path: Path, result: SlipFit, curves: Sequence[MeasuredCurve], before: Sequence[np.ndarray],
               after: Sequence[np.ndarray]) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4.5), layout="constrained")
    FigureCanvasAgg(fig)
    ax, ax_gamma = fig.subplots(1, 2, width_ratios=[2, 1])
    for j, (curve, b, a, value) in enumerate(zip(curves, before, after, result.fit_after)):
        colour, x, m = f"C{j % 10}", curve.displacement[:, _swept(curve)] * 1e3, curve.capacitance
        ax.plot(x, (m - m[0]) * 1e12, "o", color=colour, ms=4, label=f"{curve.name}: FIT {value:.1f} %")
        ax.plot(x, a * 1e12, "-", color=colour)
        ax.plot(x, b * 1e12, ":", color=colour, alpha=0.6)
    ax.set(xlabel="displacement of the swept unit [mm]", ylabel="capacitance change [pF]",
           title="markers measured, lines with slip, dotted without")
    ax_gamma.plot(np.array(result.knots) * 1e3, result.factors, "s-k")
    ax_gamma.set(xlabel="largest driven displacement [mm]", ylabel="gamma [-]", title="slip table (eq. 11)")
    for a in (ax, ax_gamma):
        a.grid(True, alpha=0.3)
    ax.legend(fontsize="small")
    fig.savefig(path, dpi=110)
