"""``dea-twin stroke`` and ``dea-twin simulate``: the array driven as an actuator (biased units).

``stroke [CONFIG] --voltage V1,V2,... [--unit K] [--json]``: from the 0 V equilibrium of
the config's biased units, the quasi-static equilibrium at each voltage level in turn
(on unit K only, or on every biased unit; other units at 0 V).  ``--json`` prints
``{"voltage", "position", "force", "capacitance", "stable", "snap"}`` (SI units, one
entry per level, per unit inside); the table prints the stroke (position minus the 0 V
position) in mm.

``simulate [CONFIG] --voltage "T0:V1,V2,V3;T1:..." [--force ...] --duration T --dt DT
[--json | --out DIR]``: the time response from the 0 V rest state, commands piecewise
constant from each time Ti on: ``{"time", "position", "velocity", "force",
"capacitance"}`` as JSON, or ``simulate.csv`` + ``simulate.png`` in DIR, or a table.

Library behind both: :mod:`dea_array_twin.model.response`.  Exit codes: 0 ok, 1 no
equilibrium or a step that does not converge, 2 bad arguments or config.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

from ..configfile import load_config
from ..model.config import ConfigError
from ..model.response import Schedule, Simulation, simulate, stroke
from ..model.solver import ConvergenceError
from ..model.twin import ArrayTwin, TwinResult
from .argtypes import failure_exit_code, float_list


def schedule(text: str) -> Schedule:
    """An argparse type: ``"T0:V1,V2,V3;T1:..."`` -> :class:`Schedule` (times in s, increasing)."""
    times, values = [], []
    for entry in filter(None, (e.strip() for e in text.split(";"))):
        time_text, sep, value_text = entry.partition(":")
        try:
            if not sep:
                raise ValueError
            times.append(float(time_text))
            values.append(tuple(float(v) for v in value_text.replace(",", " ").split()))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected 'T:v1,v2,...' entries separated by ';' (e.g. "
                                             f"\"0:0,2730,0;0.5:0,0,0\"), got {entry!r}") from None
        if not values[-1]:
            raise argparse.ArgumentTypeError(f"entry {entry!r} has no values")
    if not times:
        raise argparse.ArgumentTypeError(f"empty schedule {text!r}")
    try:
        return Schedule(tuple(times), tuple(values))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_arguments(stroke_parser: argparse.ArgumentParser, simulate_parser: argparse.ArgumentParser) -> None:
    """Options of ``stroke`` and ``simulate``."""
    config_help = "config YAML with biased units (unit_modes, bias, mass, ...)"
    for parser in (stroke_parser, simulate_parser):
        parser.add_argument("config", nargs="?", help=config_help)
        parser.add_argument("--displacement", type=float_list(),
                            help="where the driven units are held [m], per unit (default 0)")
        parser.add_argument("--start", type=float, default=0.0,
                            help="height the biased indenters are released from onto their bias [m] (default 0; "
                                 "with a bistable bias it picks the branch)")
    stroke_parser.add_argument("--voltage", type=float_list(example="0,1000,2730"), required=True,
                               help="voltage levels [V], comma separated, applied in turn")
    stroke_parser.add_argument("--unit", type=int, help="the biased unit (1-based) that gets the voltage "
                                                        "(default: every biased unit)")
    stroke_parser.add_argument("--json", action="store_true", help="print one JSON object (SI units)")
    simulate_parser.add_argument("--voltage", type=schedule, required=True,
                                 help='voltage schedule "T0:V1,V2,...;T1:..." [s: V per unit, or one V for all]')
    simulate_parser.add_argument("--force", type=schedule,
                                 help='external force schedule on the biased indenters "T0:f1,...;..." [s: N]')
    simulate_parser.add_argument("--duration", type=float, required=True, help="simulated time [s]")
    simulate_parser.add_argument("--dt", type=float, required=True, help="time step [s]")
    out = simulate_parser.add_mutually_exclusive_group()
    out.add_argument("--json", action="store_true", help="print one JSON object (SI units)")
    out.add_argument("--out", help="folder for simulate.csv and simulate.png")


def _events(res: TwinResult, label: str) -> None:
    for text in res.events + res.warnings:
        print(f"dea-twin: {label}: {text}", file=sys.stderr)


def _check_schedules(twin: ArrayTwin, *schedules: Schedule | None) -> None:
    n = twin.n_units
    for sched in filter(None, schedules):
        for values in sched.values:
            if len(values) not in (1, n):
                raise ConfigError(f"a schedule entry has {len(values)} values; expected {n} (one per unit) or 1")


def run_stroke(args: argparse.Namespace) -> int:
    """``dea-twin stroke``; returns the exit code."""
    try:
        twin = ArrayTwin(load_config(args.config))
        if args.unit is not None and not 1 <= args.unit <= twin.n_units:
            raise ConfigError(f"--unit must be in [1, {twin.n_units}], got {args.unit}")
        curve = stroke(twin, args.voltage, None if args.unit is None else args.unit - 1,
                       0.0 if args.displacement is None else args.displacement, args.start,
                       on_level=lambda v, res: _events(res, f"{v:g} V"))
    except (ConfigError, ValueError, ConvergenceError) as exc:
        return failure_exit_code(exc)
    if args.json:
        print(json.dumps({"voltage": curve.voltage.tolist(), "position": curve.position.tolist(),
                          "force": curve.force.tolist(), "capacitance": curve.capacitance.tolist(),
                          "stable": curve.stable.tolist(), "snap": curve.snap.tolist()}))
        return 0
    n = twin.n_units
    print(f"0 V positions [mm]: {', '.join(f'{1e3 * w:.4f}' for w in curve.rest.position)}")
    head = (["V [V]"] + [f"s{k + 1} [mm]" for k in range(n)] + [f"F{k + 1} [N]" for k in range(n)]
            + [f"C{k + 1} [pF]" for k in range(n)] + ["stable", "snap"])
    print("  ".join(f"{h:>10}" for h in head))
    for i, v in enumerate(curve.voltage):
        numbers = [v, *(1e3 * curve.stroke[i]), *curve.force[i], *(1e12 * curve.capacitance[i])]
        print("  ".join(f"{x:10.4f}" for x in numbers)
              + f"  {'yes' if curve.stable[i] else 'NO':>10}  {'yes' if curve.snap[i] else 'no':>10}")
    return 0


def _columns(sim: Simulation) -> tuple[list[str], np.ndarray]:
    n = sim.position.shape[1]
    units = range(1, n + 1)
    head = (["time_s"] + [f"w{k}_m" for k in units] + [f"v{k}_m_per_s" for k in units] + [f"F{k}_N" for k in units]
            + [f"C{k}_F" for k in units] + [f"V{k}_V" for k in units] + [f"f{k}_N" for k in units])
    table = np.column_stack([sim.time, sim.position, sim.velocity, sim.force, sim.capacitance, sim.voltage,
                             sim.external_force])
    return head, table


def _plot(sim: Simulation, path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 9), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(4, 1, sharex=True)
    panels = ((sim.position * 1e3, "position w [mm]"), (sim.force, "membrane force F [N]"),
              (sim.capacitance * 1e12, "capacitance C [pF]"), (sim.voltage, "voltage [V]"))
    for ax, (values, label) in zip(axes, panels):
        for k in range(values.shape[1]):
            ax.plot(sim.time, values[:, k], label=f"unit {k + 1}")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel("time [s]")
    fig.savefig(path, dpi=100)


def run_simulate(args: argparse.Namespace) -> int:
    """``dea-twin simulate``; returns the exit code."""
    from tqdm import tqdm

    if args.out is not None:
        import importlib.util

        if importlib.util.find_spec("matplotlib") is None:
            print("dea-twin: error: --out needs matplotlib for the figure (pip install 'dea_array_twin[plot]')",
                  file=sys.stderr)
            return 2
    try:
        twin = ArrayTwin(load_config(args.config))
        _check_schedules(twin, args.voltage, args.force)
        steps = int(round(args.duration / args.dt)) if args.dt > 0 else 0
        with tqdm(total=steps, desc="simulate", unit="step", file=sys.stderr, disable=None) as bar:
            def on_step(t: float, res: TwinResult) -> None:
                _events(res, f"t = {t:.6g} s")
                bar.update(1)

            sim = simulate(twin, args.voltage, args.force, args.duration, args.dt,
                           0.0 if args.displacement is None else args.displacement, args.start, on_step)
    except (ConfigError, ValueError, ConvergenceError) as exc:
        return failure_exit_code(exc)
    if args.json:
        print(json.dumps({"time": sim.time.tolist(), "position": sim.position.tolist(),
                          "velocity": sim.velocity.tolist(), "force": sim.force.tolist(),
                          "capacitance": sim.capacitance.tolist()}))
        return 0
    head, table = _columns(sim)
    if args.out is None:
        print("  ".join(f"{h:>14}" for h in head))
        for row in table:
            print("  ".join(f"{x:14.7g}" for x in row))
        return 0
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        with open(out / "simulate.csv", "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(head)
            writer.writerows(table.tolist())
        _plot(sim, out / "simulate.png")
    except OSError as exc:
        print(f"dea-twin: error: cannot write to {out}: {exc}", file=sys.stderr)
        return 2
    print(f"dea-twin: wrote {out / 'simulate.csv'} and {out / 'simulate.png'}", file=sys.stderr)
    return 0
