"""``dea-twin study``: the paper's studies as CSV + PNG files in an output folder.

``coupling``   the three coupling indices of one configuration (eqs. 13-16)
``curves``     the experiments' curves, figures 12-16: DE1 and DE2 swept to 15 mm at
               lp = 1.10 and 1.20, neighbours free or pre-deflected by 4, 6 or 8 mm,
               at 0 V and at the experiments' HV (2730 V / 2300 V)
``sweep NAME`` one of section 6's studies: spacing, edge_distance, prestretch, scale,
               shape, or ``all`` of them plus the coupling of the base configuration
``stroke``     figures 5-6: the measured unit's stroke on an LBS and on an NBS matched
               to its nominal curves, neighbours free and pre-deflected

Tasks run here, on ``--workers N`` local processes or on a Dask cluster
(``--scheduler ADDRESS``); the numbers are the same whichever ran them.  Exit codes:
0 ok, 1 some curve failed to solve (the rest are written), 2 bad arguments or config.
"""

from __future__ import annotations

import argparse
import csv
import importlib.util
import math
import sys
import time
from pathlib import Path
from typing import Sequence

from ..configfile import load_config
from ..model.config import ArrayConfig, ConfigError
from ..parallel import ExecutorError, run_tasks
from ..studies import stroke as stroke_study
from ..studies import tasks as study
from ..studies.tasks import CurveFailure, CurveResult, CurveTask
from .argtypes import float_list

#: What the paper reports for each sweep (section 6.2), printed next to the twin's numbers.
PAPER = {
    "spacing": "force coupling ~12% at d = 1 mm falling to ~1% at 15 mm, HV above LV; capacitance "
               "coupling ~15% at 1 mm converging to a plateau near 8%",
    "edge_distance": "force coupling rises with b, more for HV; capacitance coupling falls from ~10% to ~0%",
    "prestretch": "capacitance coupling falls to ~2%; force coupling stays near 8% above lp = 1.25",
    "scale": "all three indices unchanged; d falls below the air breakdown gap (1.1 mm) beyond k ~ 13",
    "shape": "circle and square electrodes of equal area give virtually the same curves",
}


#: The paper's figure numbers of the curves at its two pre-stretches: (capacitance, force).
PAPER_FIGURES = {1.10: (12, 15), 1.20: (13, 16)}


def _neighbours(text: str) -> list[float | None]:
    out: list[float | None] = []
    for item in text.replace(",", " ").split():
        if item == "free":
            out.append(None)
        else:
            try:
                out.append(float(item))
            except ValueError:
                raise argparse.ArgumentTypeError(f"expected 'free' or displacements in m, got {item!r}") from None
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``study`` sub-commands and their options to ``parser``."""
    kinds = parser.add_subparsers(dest="study", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--out", default="study", help="output folder (default ./study)")
    common.add_argument("--steps", type=int, default=15, help="displacement steps per curve (default 15)")
    where = common.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=1, help="local worker processes (default 1: run here)")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="Dask distributed scheduler, e.g. tcp://10.0.0.5:8786 (workers need this package)")
    config_help = "config YAML (default: the paper's 1-by-3 array, lp = 1.10)"
    indices = argparse.ArgumentParser(add_help=False)
    indices.add_argument("--undeflected", choices=("free", "held"), default="free",
                         help="the paper's 'neighbours not deflected': free units (default) or indenters held at 0 m")
    coupling = kinds.add_parser("coupling", parents=[common, indices],
                                help="coupling indices eta_F,LV, eta_F,HV, eta_C (eqs. 13-16)")
    coupling.add_argument("config", nargs="?", help=config_help)
    curves = kinds.add_parser("curves", parents=[common],
                              help="figures 12-16: DE1 and DE2 swept, neighbours free or pre-deflected, LV and HV")
    curves.add_argument("config", nargs="?", help=config_help)
    curves.add_argument("--prestretch", type=float_list(example="1.10,1.20"),
                        help="pre-stretches to run (default: those of the config's experimental_hv_prestretch, "
                             "the paper's 1.10 and 1.20)")
    curves.add_argument("--hv", choices=("experimental", "eq14"), default="experimental",
                        help="HV on the swept unit: the experiments' per pre-stretch (config experimental_hv_*, "
                             "default: 2730 V at 1.10, 2300 V at 1.20) or eq. 14, Ec t0 / lp^2")
    curves.add_argument("--voltages", type=float_list(example="0,2730"),
                        help="voltages on the swept unit [V] at every pre-stretch, instead of 0 and --hv")
    curves.add_argument("--neighbours", type=_neighbours,
                        help="comma-separated 'free' and/or pre-deflections [m] of the other units, 0 = held flat "
                             "(default: free,0.2D,0.3D,0.4D = free,0.004,0.006,0.008); the first setting is "
                             "also that of the capacitance figure")
    curves.add_argument("--to", type=float, help="final displacement [m] (default 0.75 D = 15 mm)")
    sweep = kinds.add_parser("sweep", parents=[common, indices], help="a parameter study of section 6")
    sweep.add_argument("name", choices=[*study.SWEEPS, "shape", "all"])
    sweep.add_argument("config", nargs="?", help=config_help)
    sweep.add_argument("--values", type=float_list(),
                       help="parameter values in SI (m, -, downscale factor; default: the paper's range)")
    stroke = kinds.add_parser("stroke", parents=[common],
                              help="figures 5-6: stroke on an LBS and an NBS designed on the nominal curves, "
                                   "neighbours free and pre-deflected")
    stroke.add_argument("config", nargs="?", help=config_help)
    stroke.add_argument("--voltage", type=float,
                        help="HV on the measured unit [V] (default: the experiments' HV at the config's "
                             "pre-stretch, 2730 V at lp = 1.10)")
    stroke.add_argument("--operating-point", type=float,
                        help=f"0 V position the biases are designed for [m] (default "
                             f"{stroke_study.OPERATING_POINT:g} D)")
    stroke.add_argument("--rate-fraction", type=float, default=stroke_study.RATE_FRACTION,
                        help=f"NBS rate as a fraction of the nominal HV stiffness at the operating point "
                             f"(default {stroke_study.RATE_FRACTION:g})")


# ----------------------------------------------------------------------- running

def _run(tasks: list[CurveTask], args: argparse.Namespace, label: str) -> list[CurveResult | CurveFailure]:
    from tqdm import tqdm

    where = f"Dask at {args.scheduler}" if args.scheduler else f"{args.workers} worker(s)"
    tic = time.perf_counter()
    with tqdm(total=len(tasks), desc=f"{label} ({where})", unit="curve", file=sys.stderr, disable=None) as bar:
        results = run_tasks(study.try_curve, tasks, workers=args.workers, scheduler=args.scheduler,
                            progress=lambda done: bar.update(done - bar.n))
    print(f"dea-twin study: {label}: {len(tasks)} curves in {time.perf_counter() - tic:.1f} s on {where}",
          file=sys.stderr)
    return results


def curve_rows(results: Sequence[CurveResult | CurveFailure]) -> tuple[list[str], list[list]]:
    """Long-format table of every point of every curve (SI units; dC from the start of each curve)."""
    n = results[0].task.config.n_units
    units = range(1, n + 1)
    head = (["study", "value", "case", "swept_unit", "neighbours_m", "voltage_V", "displacement_m"]
            + [f"F{k}_N" for k in units] + [f"C{k}_F" for k in units] + [f"dC{k}_F" for k in units]
            + [f"peak_field{k}_V_m" for k in units]
            + ["min_principal_stress_Pa", "wrinkled", "field_exceeded", "stable", "error"])
    rows = []
    for res in results:
        t = res.task
        key = t.key if len(t.key) == 3 else ("coupling", "", t.key[-1])
        lead = [*key, t.swept + 1, "free" if t.neighbours is None else t.neighbours, t.voltage]
        if isinstance(res, CurveFailure):
            rows.append(lead + [""] * (len(head) - len(lead) - 1) + [res.message])
            continue
        for i, d in enumerate(res.displacement):
            rows.append(lead + [d, *res.force[i], *res.capacitance[i], *res.delta_capacitance[i],
                                *res.peak_field[i], res.min_principal_stress[i], int(res.wrinkled[i]),
                                int(res.field_exceeded[i]), int(res.stable[i]), ""])
    return head, rows


def _write_csv(path: Path, head: list[str], rows: list[list], notes: Sequence[str] = ()) -> None:
    with open(path, "w", newline="") as f:
        for note in notes:
            f.write(f"# {note}\n")
        writer = csv.writer(f)
        writer.writerow(head)
        writer.writerows(rows)


def _write_index_table(path: Path, rows: list[dict], notes: Sequence[str]) -> None:
    head = list(dict.fromkeys(k for row in rows for k in row))
    _write_csv(path, head, [[row.get(k, "") for k in head] for row in rows], notes)


def _fmt(value: float) -> str:
    return "n/a" if isinstance(value, float) and math.isnan(value) else f"{value:.3f}"


def index_summary(name: str, rows: list[dict]) -> list[str]:
    """Markdown lines: the sweep's table, its geometry rule and the paper's statement."""
    lines = [f"## {name}", ""]
    if name in study.SWEEPS:
        lines += [f"Geometry: {study.SWEEPS[name].geometry}.", ""]
    label, scale = {"spacing": ("d [mm]", 1e3), "edge_distance": ("b [mm]", 1e3), "prestretch": ("lp", 1.0),
                    "scale": ("downscale k", 1.0)}.get(name, ("value", 1.0))
    lines += [f"| {label} | eta_F,LV [%] | eta_F,HV [%] | eta_C [%] | HV [V] | flags |", "|---|---|---|---|---|---|"]
    for row in rows:
        flags = [f"wrinkled: {row['wrinkled']}" if row.get("wrinkled") else "",
                 f"field > limit: {row['field_exceeded']}" if row.get("field_exceeded") else "",
                 f"unstable: {row['unstable']}" if row.get("unstable") else "",
                 "d below air breakdown gap" if row["below_air_breakdown"] else "",
                 f"FAILED: {row['error']}" if row.get("error") else ""]
        value = "base" if math.isnan(row["value"]) else f"{row['value'] * scale:g}"
        lines.append(f"| {value} | {_fmt(row['eta_f_lv'])} | {_fmt(row['eta_f_hv'])} | {_fmt(row['eta_c'])} "
                     f"| {row['hv_voltage_V']:.0f} | {'; '.join(f for f in flags if f)} |")
    if name in PAPER:
        lines += ["", f"The paper reports: {PAPER[name]}."]
    return lines + [""]


def _coupling_or_sweep(name: str, base: ArrayConfig, args: argparse.Namespace, out: Path,
                       summary: list[str]) -> bool:
    """Run the coupling of ``base`` (``name == "coupling"``) or one index sweep; True if all solved."""
    from ..studies.plots import plot_coupling_curves, plot_sweep

    undeflected = None if args.undeflected == "free" else 0.0
    if name == "coupling":
        tasks = study.coupling_tasks(base, args.steps, undeflected=undeflected)
        stem, notes = "coupling", ["coupling indices of the configuration (eqs. 13, 15, 16)"]
    else:
        sweep = study.SWEEPS[name]
        tasks = study.sweep_tasks(sweep, base, args.values if args.study == "sweep" else None, args.steps,
                                  undeflected)
        stem, notes = f"sweep_{name}", [f"parameter: {sweep.parameter}", f"geometry: {sweep.geometry}"]
    notes.append(f"neighbours not deflected = {study.neighbour_label(undeflected)} (--undeflected)")
    notes.append("indices in %; F in N, C in F, lengths in m; flags list the curves where a point was flagged")
    results = _run(tasks, args, name)
    rows = study.index_rows(results)
    _write_index_table(out / f"{stem}.csv", rows, notes)
    _write_csv(out / f"{stem}_curves.csv", *curve_rows(results))
    if name == "coupling":
        plot_coupling_curves(results, out / f"{stem}.png")
    else:
        plot_sweep(study.SWEEPS[name], rows, out / f"{stem}.png")
    summary += index_summary(name, rows)
    return all(isinstance(r, CurveResult) for r in results)


def _shape(base: ArrayConfig, args: argparse.Namespace, out: Path, summary: list[str]) -> bool:
    from ..studies.plots import plot_shape

    results = _run(study.shape_tasks(base, args.steps), args, "shape")
    _write_csv(out / "sweep_shape_curves.csv", *curve_rows(results), notes=[f"geometry: {study.SHAPE_GEOMETRY}"])
    summary += ["## shape", "", f"Geometry: {study.SHAPE_GEOMETRY}.", ""]
    if not all(isinstance(r, CurveResult) for r in results):
        summary += ["A curve failed to solve: see sweep_shape_curves.csv.", ""]
        return False
    by_key = {r.task.key[1:]: r for r in results}
    for case in ("lv", "hv"):
        df, dc = study.shape_difference(by_key[("circle", case)], by_key[("square", case)])  # type: ignore[arg-type]
        summary.append(f"- {case.upper()}: square vs circle differ by at most {100 * df:.2f}% in force and "
                       f"{100 * dc:.2f}% in capacitance change (of the curves' maxima).")
    plot_shape(results, out / "sweep_shape.png")  # type: ignore[arg-type]
    summary += ["", f"The paper reports: {PAPER['shape']}.", ""]
    return True


def _curves(base: ArrayConfig, args: argparse.Namespace, out: Path, summary: list[str]) -> bool:
    """Figures 12-16 per pre-stretch: ``capacitance_lpX.csv/png`` and ``force_lpX.csv/png``."""
    from ..studies.plots import plot_capacitance_figure, plot_force_figure

    configs = [base.replace(prestretch=lp)
               for lp in args.prestretch or base.experimental_hv_prestretch or (base.prestretch,)]
    tasks = []
    for cfg in configs:
        voltages = args.voltages
        if voltages is None:
            hv = cfg.experimental_hv() if args.hv == "experimental" else cfg.hv_voltage(study.CRITICAL_FIELD)
            voltages = [0.0, hv]
        tasks += study.curves_tasks(cfg, args.steps, args.to, args.neighbours, voltages)
    results = _run(tasks, args, "curves")
    ok = all(isinstance(r, CurveResult) for r in results)
    for cfg in configs:
        mine = [r for r in results if r.task.key[1] == cfg.prestretch]
        first = mine[0].task  # its voltage and neighbours: those of the capacitance figure
        cap = [r for r in mine if (r.task.voltage, r.task.neighbours) == (first.voltage, first.neighbours)]
        stem = f"lp{cfg.prestretch:.2f}"
        figures = PAPER_FIGURES.get(round(cfg.prestretch, 6))
        _write_csv(out / f"capacitance_{stem}.csv", *curve_rows(cap),
                   notes=[f"capacitance curves at lp = {cfg.prestretch:g}, {first.voltage:g} V, neighbours "
                          f"{study.neighbour_label(first.neighbours)}; dC from the start of each curve"])
        _write_csv(out / f"force_{stem}.csv", *curve_rows(mine),
                   notes=[f"force curves at lp = {cfg.prestretch:g}; dC from the start of each curve"])
        if ok:
            cf = f" (cf. paper figure {figures[0]})" if figures else ""
            ff = f" (cf. paper figure {figures[1]})" if figures else ""
            plot_capacitance_figure(cap, out / f"capacitance_{stem}.png",  # type: ignore[arg-type]
                                    f"capacitance change, lp = {cfg.prestretch:.2f}, {first.voltage:g} V, neighbours "
                                    f"{study.neighbour_label(first.neighbours)}{cf}")
            plot_force_figure(mine, out / f"force_{stem}.png",  # type: ignore[arg-type]
                              f"force, lp = {cfg.prestretch:.2f}{ff}")
        summary += curves_summary(cfg, mine, cap, figures)
    return ok


def _stroke(base: ArrayConfig, args: argparse.Namespace, out: Path, summary: list[str]) -> bool:
    from ..studies.plots import plot_stroke

    tasks = stroke_study.stroke_curve_tasks(base, args.voltage, args.steps)
    voltage = tasks[1].voltage
    results = _run(tasks, args, "stroke curves")
    _write_csv(out / "stroke_curves.csv", *curve_rows(results))
    if not all(isinstance(r, CurveResult) for r in results):
        summary += ["## stroke", "", "A curve failed to solve: see stroke_curves.csv.", ""]
        return False
    if not 0.0 < args.rate_fraction < 1.0:
        raise ConfigError(f"--rate-fraction must be in (0, 1) for a stable NBS, got {args.rate_fraction}")
    result = stroke_study.stroke_study(
        base, results, args.operating_point, args.rate_fraction,
        on_row=lambda r: print(f"dea-twin study: {r.bias}, neighbours {r.neighbours}: stroke "
                               f"{r.stroke * 1e3:.3f} mm", file=sys.stderr))
    head = ["bias", "stiffness_N_per_m", "free_position_m", "neighbours", "position_0V_m", "position_HV_m",
            "stroke_m", "stable", "snap"]
    rows = [[r.bias, r.law.stiffness, r.law.free_position, r.neighbours, r.rest_position, r.position, r.stroke,
             int(r.stable), int(r.snap)] for r in result.rows]
    _write_csv(out / "stroke.csv", head, rows, [f"HV {voltage:g} V; operating point "
                                                f"{result.operating_point:g} m; NBS rate fraction "
                                                f"{args.rate_fraction:g}"])
    plot_stroke(result, out / "stroke.png")
    summary += stroke_study.stroke_summary(result)
    return True


def curves_summary(cfg: ArrayConfig, results: Sequence[CurveResult | CurveFailure],
                   cap: Sequence[CurveResult | CurveFailure], figures: tuple[int, int] | None) -> list[str]:
    """Markdown: the capacitance changes and force maxima of one pre-stretch's curves, and their flags."""
    lp = f"{cfg.prestretch:.2f}"
    volts = sorted({r.task.voltage for r in results})
    lines = [f"## curves at lp = {lp}" + (f" (paper figures {figures[0]} and {figures[1]})" if figures else ""), "",
             f"{len(results)} curves swept to {results[0].task.stroke * 1e3:g} mm, voltages "
             f"{', '.join(f'{v:g}' for v in volts)} V.", ""]
    done = [r for r in cap if isinstance(r, CurveResult)]
    units = sorted({r.task.swept for r in done})
    if done:
        lines += [f"Largest capacitance change [pF] (`capacitance_lp{lp}.png`, from the start of each test):", "",
                  "| deformed \\ measured | " + " | ".join(f"DE{u + 1}" for u in units) + " |",
                  "|---" * (len(units) + 1) + "|"]
        lines += [f"| DE{r.task.swept + 1} | " + " | ".join(
            f"{study.largest(r.delta_capacitance[:, u]) * 1e12:.3f}" for u in units) + " |" for r in done]
        lines.append("")
    settings = list(dict.fromkeys(r.task.neighbours for r in results))
    forces = {(r.task.neighbours, r.task.swept, r.task.voltage): float(r.force[:, r.task.swept].max())
              for r in results if isinstance(r, CurveResult)}
    columns = [(u, v) for u in units for v in volts]
    lines += [f"Largest force [N] (`force_lp{lp}.png`):", "",
              "| neighbours | " + " | ".join(f"DE{u + 1}, {v:g} V" for u, v in columns) + " |",
              "|---" * (len(columns) + 1) + "|"]
    for nb in settings:
        cells = [f"{forces[(nb, u, v)]:.4f}" if (nb, u, v) in forces else "failed" for u, v in columns]
        lines.append(f"| {study.neighbour_label(nb)} | " + " | ".join(cells) + " |")
    flagged = [f"- flagged: {r.task.key[-1]}: " + ", ".join(
        name for name, on in (("wrinkling", r.wrinkled.any()), ("field above breakdown_field", r.field_exceeded.any()),
                              ("unstable", not r.stable.all())) if on)
        for r in results if isinstance(r, CurveResult) and (r.wrinkled.any() or r.field_exceeded.any()
                                                               or not r.stable.all())]
    failed = [f"- FAILED: {r.task.key[-1]}: {r.message}" for r in results if isinstance(r, CurveFailure)]
    return lines + [""] + flagged + failed + ([""] if flagged or failed else [])


def _hv_text(args: argparse.Namespace) -> str:
    """Which HV (and, for the indices, which reading of "not deflected") the study applies, for the summary."""
    if args.study == "stroke":
        return ("HV on the measured unit = " + (f"{args.voltage:g} V" if args.voltage is not None
                                                 else "the experiments' voltage at the pre-stretch (section 5.1)"))
    if args.study != "curves":
        return ("HV = Ec t0 / lp^2 with Ec = 80 V/um (eq. 14); neighbours not deflected = "
                + ("free units" if args.undeflected == "free" else "indenters held at 0 mm"))
    if args.voltages is not None:
        return f"voltages {', '.join(f'{v:g}' for v in args.voltages)} V (--voltages)"
    if args.hv == "eq14":
        return "HV = Ec t0 / lp^2 with Ec = 80 V/um (eq. 14)"
    return "HV = the experiments' voltage at each pre-stretch (config experimental_hv_*, section 5.1)"


def run_from_args(args: argparse.Namespace) -> int:
    """Run ``dea-twin study ...``; returns the exit code."""
    if importlib.util.find_spec("matplotlib") is None:  # checked before hours of solving, not after
        print("dea-twin study: error: needs matplotlib for the figures (pip install 'dea_array_twin[plot]')",
              file=sys.stderr)
        return 2
    try:
        base = load_config(args.config)
        if args.steps < 1:
            raise ConfigError(f"--steps must be >= 1, got {args.steps}")
        if args.workers < 1:
            raise ConfigError(f"--workers must be >= 1, got {args.workers}")
        if args.study == "sweep" and args.values is not None and args.name in ("all", "shape"):
            raise ConfigError(f"--values applies to one parameter sweep, not to '{args.name}'")
        if args.study != "curves":
            study.measured_units(base)
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        summary = [f"# dea-twin study {args.study}{' ' + args.name if args.study == 'sweep' else ''}", "",
                   f"Base configuration: {args.config or 'the paper default (Table 1, lp = 1.10)'}; "
                   f"{_hv_text(args)}. Mesh: order {base.element_order}, element sizes "
                   f"{base.mesh_size * 1e3:g}/{base.mesh_size_electrode * 1e3:g}/{base.mesh_size_indenter * 1e3:g} mm "
                   f"(far field/electrode edges/indenter edges, before scaling); {args.steps} steps per curve.", ""]
        if args.study == "curves":
            ok = _curves(base, args, out, summary)
        elif args.study == "stroke":
            ok = _stroke(base, args, out, summary)
        elif args.study == "coupling":
            ok = _coupling_or_sweep("coupling", base, args, out, summary)
        else:
            names = ["coupling", *study.SWEEPS, "shape"] if args.name == "all" else [args.name]
            ok = True
            for name in names:
                done = _shape(base, args, out, summary) if name == "shape" else \
                    _coupling_or_sweep(name, base, args, out, summary)
                ok = ok and done
        (out / "summary.md").write_text("\n".join(summary))
    except (ConfigError, ValueError, ExecutorError, OSError) as exc:
        print(f"dea-twin study: error: {exc}", file=sys.stderr)
        return 2
    print("\n".join(summary))
    print(f"dea-twin study: results in {out.resolve()}", file=sys.stderr)
    if not ok:
        print("dea-twin study: some curves failed to solve (see the 'error' column)", file=sys.stderr)
        return 1
    return 0
