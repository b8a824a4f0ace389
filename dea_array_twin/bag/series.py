"""The command and output channels of a bag as time series (for plots and calibration).

Also the column names of the CSV time series ``dea-twin replay`` writes and ``dea-twin
calibrate`` reads (:func:`csv_header`).

Channels are found as ``replay`` finds them (:mod:`.topics`, ``--topic-map``
included).  Time runs from the bag's first message, or from the ``time_origin_ns``
that a ``dea-twin replay`` output records (:data:`.twin_config.REPLAY_METADATA`), so
times match the replay's CSV.
"""

from __future__ import annotations

import math
from collections import Counter
from typing import NamedTuple

import numpy as np

from .reader import Bag, BagError
from .topics import COMMANDS, output_topics, select_topic
from .twin_config import REPLAY_METADATA

__all__ = ["Series", "csv_header", "load_series"]


class Series(NamedTuple):
    """One channel of a bag: times [s] from the origin and values, shape (m, n_units), SI units."""

    topic: str
    time_s: np.ndarray
    values: np.ndarray


def load_series(bag: Bag, topic_map: dict[str, str] | None = None) -> tuple[dict[str, Series], float]:
    """Read the command and output channels of a bag.

    Messages the twin would reject are dropped: another length than most messages of the
    channel, or NaN/inf in a command.

    Returns
    -------
    series : dict
        Channel (``displacement``, ``voltage``, ``force``, ``capacitance``) -> :class:`Series`;
        only the channels present.
    end_s : float
        Time of the last message read [s], where held commands are drawn to.

    Raises
    ------
    BagError
        No command and no output topic in the bag, or an ambiguous one (see ``--topic-map``).
    """
    commands = {kind: topic for kind in COMMANDS
                if (topic := select_topic(bag.topics, f"command/{kind}", topic_map)) is not None}
    outputs = output_topics(bag, commands, topic_map)
    if not commands and not outputs:
        raise BagError(f"{bag.path}: nothing to plot (no topics ending with command/displacement, "
                       f"command/voltage, force or capacitance). Topics present:\n{bag.describe_topics()}")
    topics = {**commands, **outputs}
    origin = bag.start_ns
    replay_info = bag.metadata(REPLAY_METADATA) or {}
    try:
        origin = int(replay_info["time_origin_ns"])
    except (KeyError, ValueError):
        pass
    kind_of = {topic: kind for kind, topic in topics.items()}
    times: dict[str, list[int]] = {k: [] for k in topics}
    values: dict[str, list[list[float]]] = {k: [] for k in topics}
    last = None
    for msg in bag.messages(topics.values(), decode=True):
        if origin is None:
            origin = msg.log_time_ns
        kind = kind_of[msg.topic]
        times[kind].append(msg.log_time_ns)
        values[kind].append(list(msg.decoded.data))
        last = msg.log_time_ns
    out = {}
    for kind, topic in topics.items():
        lengths = Counter(len(v) for v in values[kind])
        n = lengths.most_common(1)[0][0] if lengths else 0
        # what the twin would reject: another length than most messages, NaN/inf in a command
        keep = [i for i, v in enumerate(values[kind])
                if n and len(v) == n and (kind in ("force", "capacitance") or all(map(math.isfinite, v)))]
        if keep:
            t = (np.array([times[kind][i] for i in keep], dtype=np.int64) - origin) * 1e-9
            out[kind] = Series(topic, t, np.array([values[kind][i] for i in keep], dtype=float))
    end_s = 0.0 if last is None or origin is None else (last - origin) * 1e-9
    return out, end_s


def csv_header(n: int) -> list[str]:
    """CSV column names for ``n`` units."""
    units = range(1, n + 1)
    return (["time_s"] + [f"d{k}_m" for k in units] + [f"V{k}_V" for k in units] + [f"F{k}_N" for k in units]
            + [f"C{k}_F" for k in units])
