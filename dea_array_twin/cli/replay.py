"""``dea-twin replay BAG``: re-simulate a recorded run offline, or republish its commands live.

The options and the exit codes; the work is :func:`~dea_array_twin.replay.offline.replay_offline` and
:func:`~dea_array_twin.replay.realtime.realtime_replay`.
"""

from __future__ import annotations

import argparse
import sys

from ..bag.reader import Bag, BagError
from ..bag.topics import parse_topic_map
from ..model.config import ConfigError
from ..replay.offline import replay_offline
from ..replay.realtime import realtime_replay
from .argtypes import add_topic_map, word_list


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``dea-twin replay`` options."""
    parser.add_argument("bag", help="recorded bag: an .mcap file or a rosbag2 directory")
    parser.add_argument("--config", help="config YAML (default: the bag's recorded config, else the paper's array)")
    parser.add_argument("--out", help="output base name: writes OUT.mcap and OUT.csv "
                                      "(default: <bag stem>_replay next to the bag)")
    add_topic_map(parser, "/rig/disp=command/displacement")
    parser.add_argument("--modes", type=word_list,
                        help="per-unit 'driven' or 'free', comma separated (default: recorded, else all driven)")
    parser.add_argument("--fit-lag", type=float, default=None, metavar="SECONDS",
                        help="largest latency of recorded outputs behind their commands (default: three update "
                             "periods of the recording node, 0 if unknown)")
    parser.add_argument("--rom", metavar="ROM.npz",
                        help="replay with this reduced model (dea-twin rom train) instead of the FE")
    parser.add_argument("--compare", action="store_true",
                        help="with --rom: also replay the FE and print the reduced model's differences from it")
    parser.add_argument("--realtime", action="store_true",
                        help="republish the recorded commands on ROS 2 with their timing instead of simulating")
    parser.add_argument("--rate", type=float, default=None, help="--realtime speed factor (default 1)")
    parser.add_argument("--wait", type=float, default=2.0,
                        help="--realtime: seconds to wait for subscribers before starting (default 2)")


def run_from_args(args: argparse.Namespace) -> int:
    """Run ``dea-twin replay`` for parsed arguments; return the exit code."""
    try:
        topic_map = parse_topic_map(args.topic_map)
        if args.realtime:
            unused = [opt for opt, value in (("--config", args.config), ("--out", args.out), ("--modes", args.modes),
                                             ("--rom", args.rom), ("--compare", args.compare or None))
                      if value is not None]
            if unused:
                raise BagError(f"{', '.join(unused)} do(es) not apply to --realtime (it republishes the commands)")
            return realtime_replay(Bag(args.bag), topic_map, 1.0 if args.rate is None else args.rate, args.wait)
        if args.rate is not None:
            raise BagError("--rate needs --realtime")
        return replay_offline(Bag(args.bag), topic_map, args.config, args.modes, args.out, args.fit_lag,
                              args.rom, args.compare)
    except (BagError, ConfigError, ValueError) as exc:
        print(f"dea-twin replay: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # includes RecordingError (cannot write the outputs)
        print(f"dea-twin replay: error: {exc}", file=sys.stderr)
        return 2
