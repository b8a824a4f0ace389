"""Argument types shared by the ``dea-twin`` sub-commands (no numerics, no ROS)."""

from __future__ import annotations

import argparse
import sys
from typing import Callable

from ..model.config import ConfigError


def float_list(min_count: int = 1, count: int | None = None,
               example: str = "0,0.015,0") -> Callable[[str], list[float]]:
    """An argparse type: ``"a,b,c"`` (or space separated) -> floats, ``count`` or at least ``min_count`` of them."""

    def parse(text: str) -> list[float]:
        try:
            values = [float(v) for v in text.replace(",", " ").split()]
        except ValueError:
            values = []
        if len(values) < min_count or (count is not None and len(values) != count):
            size = f"{count}" if count is not None else f"at least {min_count}"
            raise argparse.ArgumentTypeError(f"expected {size} numbers separated by commas (e.g. {example}), "
                                             f"got {text!r}")
        return values

    return parse


def word_list(text: str) -> list[str]:
    """An argparse type: ``"driven,free"`` (or space separated) -> ``["driven", "free"]``."""
    return text.replace(",", " ").split()


def add_topic_map(parser: argparse.ArgumentParser, example: str) -> None:
    """The ``--topic-map OLD=NEW ...`` option of the commands that read bags."""
    parser.add_argument("--topic-map", nargs="+", action="extend", default=[], metavar="OLD=NEW",
                        help=f"use recorded topic OLD as NEW (e.g. {example})")


def failure_exit_code(exc: Exception) -> int:
    """Print a sub-command's failure in one line and give its exit code: 2 for a bad input
    (``ConfigError``, ``ValueError``), 1 for a solver that did not converge."""
    if isinstance(exc, (ConfigError, ValueError)):
        print(f"dea-twin: error: {exc}", file=sys.stderr)
        return 2
    print(f"dea-twin: solver failed: {exc}", file=sys.stderr)
    return 1
