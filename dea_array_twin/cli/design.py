"""``dea-twin design-bias``: each unit's bias element for the largest guaranteed stroke in the array.

``design-bias [CONFIG] --bias lbs|nbs|lbs+nbs|table-family --voltage V [--units 1,2,3]
[--shared] [--scenarios SPEC] [--margin K] [--max-force F] [--position-range LO,HI]
[--allow-snap] [--workers N | --scheduler ADDR] [--out DIR]``: the library's
:func:`~dea_array_twin.design.bias_design.design_bias`, progress on stderr, the summary
on stdout; with ``--out`` also ``design.yaml`` (a config whose ``unit_modes`` and
``bias`` are the design: ``dea-twin stroke DIR/design.yaml`` takes it), ``strokes.csv``
(every unit in every scenario, both designs), ``summary.md`` and, with matplotlib (the
``plot`` extra), ``unit_K.png`` per designed unit (figures 5b/6b of the paper).  Exit
codes: 0 ok, 1 no feasible design, a solve that fails, or a design whose full solves are
unstable, below the margin at a path point, or snap through without ``--allow-snap``, 2 bad
arguments or config.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

from ..configfile import load_config
from ..design.bias_design import DesignSettings, design_bias
from ..design.families import FAMILIES
from ..design.report import design_yaml, summary, write_strokes
from ..model.config import ConfigError
from ..model.solver import ConvergenceError
from ..parallel import ExecutorError
from .argtypes import float_list


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``design-bias``."""
    parser.add_argument("config", nargs="?", help="config YAML (default: the paper's 1-by-3 array)")
    parser.add_argument("--bias", choices=FAMILIES, required=True,
                        help="family: lbs (linear, k > 0), nbs (linear, k < 0), table-family (the config's bias "
                             "table scaled and shifted), lbs+nbs (an LBS plus that table)")
    parser.add_argument("--voltage", type=float, required=True, help="actuation voltage V [V]")
    parser.add_argument("--units", type=float_list(example="1,2,3"),
                        help="designed units, 1-based (default: the config's biased units, else every unit)")
    parser.add_argument("--shared", action="store_true", help="one design for every designed unit")
    parser.add_argument("--scenarios", default="all",
                        help="all (every state of the other units, sampled above 64), nominal, sample:N, or "
                             "states like 000,101 (default all)")
    parser.add_argument("--margin", type=float, help="smallest stiffness margin dF/dw - dB/dw [N/m] in every state "
                                                     "(default 0.1 of the softest nominal slope)")
    parser.add_argument("--max-force", type=float, default=float("inf"), help="largest bias force |B| [N]")
    parser.add_argument("--position-range", type=float_list(count=2, example="0,0.015"),
                        help="where the units may be in any state, LO,HI [m] (default 0 to 0.75 D)")
    parser.add_argument("--allow-snap", action="store_true", help="accept designs that snap through")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=1, help="local worker processes (default 1: run here)")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="Dask distributed scheduler, e.g. tcp://10.0.0.5:8786 (workers need this package)")
    parser.add_argument("--out", help="folder for design.yaml, strokes.csv, summary.md and the figures")


def run(args: argparse.Namespace) -> int:
    """``dea-twin design-bias``; returns the exit code."""
    try:
        cfg = load_config(args.config)
        units = None
        if args.units is not None:
            if any(u != int(u) for u in args.units):
                raise ConfigError(f"--units must be whole unit numbers, got {args.units}")
            units = tuple(int(u) - 1 for u in args.units)
        if args.workers < 1:
            raise ConfigError(f"--workers must be >= 1, got {args.workers}")
        settings = DesignSettings(args.bias, args.voltage, units=units, shared=args.shared, scenarios=args.scenarios,
                                  margin=args.margin, max_force=args.max_force,
                                  position_range=None if args.position_range is None else tuple(args.position_range),
                                  allow_snap=args.allow_snap)
        out = Path(args.out) if args.out else None
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)

        def progress(stage: str, done: int, total: int) -> None:
            print(f"design-bias: {stage}: {done}/{total}", file=sys.stderr, flush=True)

        result = design_bias(cfg, settings, args.workers, args.scheduler, progress)
    except (ConfigError, ValueError, ExecutorError) as exc:
        print(f"dea-twin: error: {exc}", file=sys.stderr)
        return 2
    except (ConvergenceError, RuntimeError) as exc:
        print(f"dea-twin: design failed: {exc}", file=sys.stderr)
        return 1
    lines = summary(result)
    print("\n".join(lines))
    if out is not None:
        (out / "design.yaml").write_text(design_yaml(result))
        write_strokes(result, out / "strokes.csv")
        (out / "summary.md").write_text("\n".join(lines) + "\n")
        written = ["design.yaml", "strokes.csv", "summary.md"]
        if importlib.util.find_spec("matplotlib") is None:
            print("dea-twin: figures skipped: they need matplotlib (pip install 'dea_array_twin[plot]')",
                  file=sys.stderr)
        else:
            from ..design.plots import plot_unit

            for k in result.settings.units:
                written.append(plot_unit(result, k, out / f"unit_{k + 1}.png").name)
        print(f"design-bias: wrote {', '.join(written)} to {out}", file=sys.stderr)
    return 0 if result.accepted else 1
