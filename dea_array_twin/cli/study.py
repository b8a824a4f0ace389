"""``dea-twin study``: the paper's studies as CSV + PNG files in an output folder.

``coupling``   the three coupling indices of one configuration (eqs. 13-16)
``curves``     force and capacitance curves of every unit swept, neighbours free or
               pre-deflected, at 0 V and at the eq. 14 voltage (figures 12-16 style)
``sweep NAME`` one of section 6's studies: spacing, edge_distance, prestretch, scale,
               shape, or ``all`` of them plus the coupling of the base configuration

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
from ..studies import tasks as study
from ..studies.parallel import ExecutorError, run_tasks
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


def _neighbours(text: str) -> list[float | str | None]:
    out: list[float | str | None] = []
    for item in text.replace(",", " ").split():
        if item in ("free", "pre"):
            out.append(None if item == "free" else "pre")
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
    coupling = kinds.add_parser("coupling", parents=[common],
                                help="coupling indices eta_F,LV, eta_F,HV, eta_C (eqs. 13-16)")
    coupling.add_argument("config", nargs="?", help=config_help)
    curves = kinds.add_parser("curves", parents=[common],
                              help="every unit swept to --to, others free or pre-deflected, LV and HV")
    curves.add_argument("--to", type=float, help="final displacement [m] (default 0.75 D)")
    curves.add_argument("--neighbours", type=_neighbours, default=[None, "pre"],
                        help="comma-separated 'free', 'pre' (0.4 D) and/or pre-deflections [m] of the "
                             "other units (default: free,pre)")
    curves.add_argument("config", nargs="?", help=config_help)
    curves.add_argument("--voltages", type=float_list(), help="voltages on the swept unit [V] (default: 0 and eq. 14)")
    sweep = kinds.add_parser("sweep", parents=[common], help="a parameter study of section 6")
    sweep.add_argument("name", choices=[*study.SWEEPS, "shape", "all"])
    sweep.add_argument("config", nargs="?", help=config_help)
    sweep.add_argument("--values", type=float_list(),
                       help="parameter values in SI (m, -, downscale factor; default: the paper's range)")


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
    """Long-format table of every point of every curve (SI units)."""
    n = results[0].task.config.n_units
    units = range(1, n + 1)
    head = (["study", "value", "case", "swept_unit", "neighbours_m", "voltage_V", "displacement_m"]
            + [f"F{k}_N" for k in units] + [f"C{k}_F" for k in units] + [f"dC{k}_F" for k in units]
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
                                res.min_principal_stress[i], int(res.wrinkled[i]), int(res.field_exceeded[i]),
                                int(res.stable[i]), ""])
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

    if name == "coupling":
        tasks = study.coupling_tasks(base, args.steps)
        stem, notes = "coupling", ["coupling indices of the configuration (eqs. 13, 15, 16)"]
    else:
        sweep = study.SWEEPS[name]
        tasks = study.sweep_tasks(sweep, base, args.values if args.study == "sweep" else None, args.steps)
        stem, notes = f"sweep_{name}", [f"parameter: {sweep.parameter}", f"geometry: {sweep.geometry}"]
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
    from ..studies.plots import plot_curves

    tasks = study.curves_tasks(base, args.steps, args.to, args.neighbours, args.voltages)
    stroke = tasks[0].stroke
    results = _run(tasks, args, "curves")
    _write_csv(out / "curves.csv", *curve_rows(results))
    ok = all(isinstance(r, CurveResult) for r in results)
    if ok:
        plot_curves(results, out / "curves.png")  # type: ignore[arg-type]
    flagged = sorted({f"unit {r.task.swept + 1}, neighbours {r.task.key[1]}, {r.task.key[2]}" for r in results
                      if isinstance(r, CurveResult) and (r.wrinkled.any() or r.field_exceeded.any())})
    summary += ["## curves", "", f"{len(results)} curves, swept to {stroke * 1e3:g} mm.",
                *(f"- flagged (wrinkling or field): {f}" for f in flagged), ""]
    return ok


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
                   f"HV = Ec t0 / lp^2 with Ec = 80 V/um (eq. 14). Mesh: order {base.element_order}, element sizes "
                   f"{base.mesh_size * 1e3:g}/{base.mesh_size_electrode * 1e3:g}/{base.mesh_size_indenter * 1e3:g} mm "
                   f"(far field/electrode edges/indenter edges, before scaling); {args.steps} steps per curve.", ""]
        if args.study == "curves":
            ok = _curves(base, args, out, summary)
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
