"""Command line: ``dea-twin curve``, ``solve``, ``stroke``, ``simulate``, ``run``, ``demo``, ``replay``, ``plot``,
``study``, ``calibrate``, ``rom``.

Thin layer over :class:`~dea_array_twin.model.twin.ArrayTwin`: parses arguments, runs the solves, prints
a labelled table (mm, N, pF) or JSON in SI units.  Exit codes: 0 ok, 1 the solver
failed, 2 bad arguments or config.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Sequence

import numpy as np

from ..configfile import load_config
from ..model.config import ArrayConfig, ConfigError
from ..model.membrane import FREE
from ..model.solver import ConvergenceError
from ..model.twin import ArrayTwin, TwinResult
from .argtypes import failure_exit_code, float_list, word_list


def _neighbours(text: str) -> str | float:
    if text == FREE:
        return FREE
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'free' or a displacement in m, got {text!r}") from None


def _version() -> str:
    """The installed distribution's version (``setup.py``), or a note that it is not installed."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("dea_array_twin")
    except PackageNotFoundError:
        return "(not installed: run from a source tree)"


def build_parser() -> argparse.ArgumentParser:
    """The ``dea-twin`` argument parser."""
    parser = argparse.ArgumentParser(prog="dea-twin", description=(
        "Finite-element digital twin of a soft array of dielectric-elastomer transducers. "
        "SI units: displacements in m, voltages in V."))
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    curve = sub.add_parser("curve", help="force/capacitance of every unit while one unit is swept")
    curve.add_argument("config", nargs="?", help="config YAML (default: the paper's 1-by-3 array)")
    curve.add_argument("--unit", type=int, default=2, help="unit to sweep, 1-based (default 2)")
    curve.add_argument("--to", type=float, default=0.015, dest="to", help="final displacement [m] (default 0.015)")
    curve.add_argument("--steps", type=int, default=15, help="number of equal steps (N+1 rows; default 15)")
    curve.add_argument("--voltage", type=float, default=0.0, help="voltage on the swept unit [V] (default 0)")
    curve.add_argument("--neighbours", type=_neighbours, default=FREE,
                       help="'free' (default) or a displacement [m] at which the other units are driven")
    curve.add_argument("--json", action="store_true", help="print one JSON object (SI units)")
    solve = sub.add_parser("solve", help="one equilibrium state")
    solve.add_argument("config", nargs="?", help="config YAML (default: the paper's 1-by-3 array)")
    solve.add_argument("--displacement", type=float_list(), help="per-unit displacement [m], comma separated")
    solve.add_argument("--voltage", type=float_list(example="0,2730,0"), help="per-unit voltage [V], comma separated")
    solve.add_argument("--modes", type=word_list,
                       help="per-unit mode, 'driven', 'free' or 'biased', comma separated (default: the config's "
                            "unit_modes, all driven)")
    solve.add_argument("--force", type=float_list(), help="per-unit external force on biased indenters [N]")
    solve.add_argument("--json", action="store_true", help="print one JSON object (SI units)")
    run = sub.add_parser("run", help="start the twin ROS 2 node (like ros2 run dea_array_twin twin_node)")
    run.add_argument("config", nargs="?", help="config YAML (default: the paper's 1-by-3 array)")
    run.add_argument("ros_args", nargs=argparse.REMAINDER, help="--ros-args ... passed to the node")
    demo = sub.add_parser("demo", help="the twin node plus the example wave controller, printing what they do")
    demo.add_argument("config", nargs="?", help="config YAML (default: the paper's 1-by-3 array)")
    demo.add_argument("--duration", type=float, default=20.0, help="seconds to run (default 20; 0 = until Ctrl-C)")
    from . import actuator, calibrate, design, plot, replay, rom, study

    actuator.add_arguments(
        sub.add_parser("stroke", help="biased units: quasi-static equilibrium at each voltage level in turn "
                                      "(stroke, force, capacitance, stability, snap-through)"),
        sub.add_parser("simulate", help="biased units: time response to voltage (and force) schedules, "
                                        "as JSON or CSV + PNG"))
    design.add_arguments(sub.add_parser(
        "design-bias", help="bias elements for the largest guaranteed stroke of every unit in the array (every "
                            "neighbour scenario, stability margin, no snap-through), checked by full biased solves"))
    study.add_arguments(sub.add_parser(
        "study", help="the paper's studies: coupled curves, coupling indices (eqs. 13-16) and the five "
                      "parameter sweeps of section 6, as CSV + PNG, in parallel locally or on Dask"))
    calibrate.add_arguments(sub.add_parser(
        "calibrate", help="fit the Yeoh coefficients (Nelder-Mead, as the paper) to measured force curves "
                          "from CSV or MCAP; FIT per curve and a PNG overlay"))
    replay.add_arguments(sub.add_parser(
        "replay", help="re-run the twin on a recorded bag's commands (MCAP + CSV out, FIT against recorded "
                       "outputs), or republish them with --realtime"))
    plot.add_arguments(sub.add_parser("plot", help="plot commands, forces and capacitances of a bag to a PNG"))
    rom.add_arguments(sub.add_parser(
        "rom", help="reduced-order model (a kHz twin): train one from FE snapshots and validate it, or show a file"))
    rec = sub.add_parser("bag-recover", help="complete copy of an MCAP file whose writer was killed")
    rec.add_argument("src", help="the killed recording")
    rec.add_argument("dst", help="where to write the recovered file")
    return parser


def _report_warnings(result: TwinResult, label: str) -> None:
    for text in result.warnings:
        print(f"dea-twin: warning at {label}: {text}", file=sys.stderr)


def run_curve(args: argparse.Namespace, cfg: ArrayConfig) -> dict:
    """Sweep unit ``args.unit`` from 0 to ``args.to``; return the curve as a dict.

    The sweep is :func:`~dea_array_twin.studies.tasks.run_curve`.
    """
    from tqdm import tqdm

    from ..studies.tasks import CurveTask
    from ..studies.tasks import run_curve as solve_curve

    n = cfg.n_units
    if not 1 <= args.unit <= n:
        raise ConfigError(f"--unit must be in [1, {n}], got {args.unit}")
    if args.steps < 1:
        raise ConfigError(f"--steps must be >= 1, got {args.steps}")
    task = CurveTask(cfg, args.unit - 1, None if args.neighbours == FREE else float(args.neighbours), args.voltage,
                     args.to, args.steps)
    with tqdm(total=args.steps + 1, desc=f"unit {args.unit} sweep", unit="step", file=sys.stderr,
              disable=None) as bar:
        def on_point(d: float, res: TwinResult) -> None:
            _report_warnings(res, f"d = {d:.6g} m")
            bar.update(1)

        res = solve_curve(task, on_point)
    return {"unit": args.unit, "displacement": res.displacement.tolist(), "force": res.force.tolist(),
            "capacitance": res.capacitance.tolist()}


def _print_curve(curve: dict) -> None:
    n = len(curve["force"][0])
    head = ["d [mm]"] + [f"F{i + 1} [N]" for i in range(n)] + [f"C{i + 1} [pF]" for i in range(n)]
    print("  ".join(f"{h:>12}" for h in head))
    for d, f, c in zip(curve["displacement"], curve["force"], curve["capacitance"]):
        row = [d * 1e3] + list(f) + [v * 1e12 for v in c]
        print("  ".join(f"{v:12.6f}" for v in row))


def run_solve(args: argparse.Namespace, twin: ArrayTwin) -> TwinResult:
    """One equilibrium for the given displacement, voltage and modes."""
    n = twin.n_units
    res = twin.solve(args.displacement if args.displacement is not None else np.zeros(n),
                     args.voltage if args.voltage is not None else np.zeros(n), args.modes,
                     force=args.force)
    _report_warnings(res, "the requested state")
    return res


def _solve_dict(res: TwinResult) -> dict:
    keys = ("displacement", "voltage", "force", "capacitance", "delta_capacitance", "centre_deflection", "peak_field",
            "bias_force", "external_force", "lifted_off")
    out = {k: np.asarray(getattr(res, k)).tolist() for k in keys}
    out.update(modes=list(res.modes), stable=res.stable, wrinkled=res.wrinkled, field_exceeded=res.field_exceeded,
               min_principal_stress=res.min_principal_stress, iterations=res.iterations, warnings=res.warnings,
               events=res.events)
    return out


def _node_args(config: str | None, extra: Sequence[str]) -> list[str]:
    """rclpy arguments: the config file as the ``config_file`` parameter, then ``extra``."""
    from pathlib import Path

    out = ["dea-twin"]
    extra = list(extra)
    if config:
        out += ["--ros-args", "-p", f"config_file:={Path(config).resolve()}"]
        if extra[:1] == ["--ros-args"]:
            extra = extra[1:]
    return out + extra


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``dea-twin``; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "run":
        from ..ros.node import main as node_main

        node_main(_node_args(args.config, args.ros_args))
        return 0
    if args.command == "demo":
        from ..ros.demo import run_demo

        return run_demo(_node_args(args.config, []), args.duration)
    if args.command == "bag-recover":
        from ..bag.recover import main as recover_main

        return recover_main([args.src, args.dst])
    if args.command in ("stroke", "simulate"):
        from . import actuator

        return actuator.run_stroke(args) if args.command == "stroke" else actuator.run_simulate(args)
    if args.command == "design-bias":
        from . import design

        return design.run(args)
    if args.command in ("replay", "plot", "study", "calibrate", "rom"):
        from . import calibrate, plot, replay, rom, study

        module = {"replay": replay, "plot": plot, "study": study, "calibrate": calibrate, "rom": rom}[args.command]
        return module.run_from_args(args)
    try:
        cfg = load_config(args.config)
        if args.command == "curve":
            curve = run_curve(args, cfg)
            print(json.dumps(curve)) if args.json else _print_curve(curve)
        else:
            res = run_solve(args, ArrayTwin(cfg))
            if args.json:
                print(json.dumps(_solve_dict(res)))
            else:
                for key, value in _solve_dict(res).items():
                    print(f"{key}: {value}")
    except (ConfigError, ValueError, ConvergenceError) as exc:
        return failure_exit_code(exc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
