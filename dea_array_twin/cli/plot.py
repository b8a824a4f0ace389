"""``dea-twin plot BAG -o run.png``: the options and exit codes of :func:`~dea_array_twin.replay.plot.plot_series`."""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

from ..bag.reader import Bag, BagError
from ..bag.series import load_series
from ..bag.topics import parse_topic_map
from ..replay.plot import plot_series
from .argtypes import add_topic_map


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``dea-twin plot`` options."""
    parser.add_argument("bag", help="an .mcap file or a rosbag2 directory (a recording or a replay output)")
    parser.add_argument("-o", "--output", help="image to write (default: <bag stem>.png next to the bag)")
    add_topic_map(parser, "/rig/disp=command/displacement")


def run_from_args(args: argparse.Namespace) -> int:
    """Run ``dea-twin plot`` for parsed arguments; return the exit code (0 ok, 2 bad input)."""
    if importlib.util.find_spec("matplotlib") is None:
        print("dea-twin plot: error: needs matplotlib (pip install 'dea_array_twin[plot]')", file=sys.stderr)
        return 2
    try:
        bag = Bag(args.bag)
        series, end_s = load_series(bag, parse_topic_map(args.topic_map))
        out = Path(args.output) if args.output else bag.output_path(".png")
        plot_series(series, end_s, out, title=bag.path.name)
    except BagError as exc:
        print(f"dea-twin plot: error: {exc}", file=sys.stderr)
        return 2
    except (OSError, ValueError) as exc:  # cannot write the image, unknown image format
        print(f"dea-twin plot: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0
