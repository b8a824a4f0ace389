"""Re-simulate a recorded run: the twin on a bag's commands, offline or republished live.

``dea-twin replay BAG`` reads the per-unit commands of a recording (a single ``.mcap``
file or a rosbag2 directory of them), re-runs :class:`~.twin.ArrayTwin` on them as fast
as it can and writes what the twin answers; ``dea-twin replay --realtime BAG`` instead
republishes the recorded commands with their original timing, for a controller or a
live twin in the loop without ``ros2 bag play``.

Bag contract (what the twin's recorder writes; a rig recorded with ``ros2 bag record -s
mcap`` has the command topics only):

* ``command/displacement``, ``command/voltage``: ``std_msgs/msg/Float64MultiArray``,
  one value per unit [m], [V]; any namespace (``/left_array/command/voltage``), or any
  other name mapped with ``--topic-map OLD=NEW``;
* recorded outputs ``force``, ``capacitance`` (Float64MultiArray), used for the FIT;
* metadata record ``dea_array_twin_config``: every :class:`~.config.ArrayConfig` field
  as ``str(value)``, plus ``unit_modes`` (``"[driven, free, driven]"``) and
  ``update_rate``.

Offline replay (:func:`replay_commands`) is sample and hold: displacement and voltage
start at zero, each command message in log-time order replaces one of them and triggers
one solve.  Commands the twin node would reject (:func:`~.node.command_error`: wrong
length, NaN/inf, beyond ``max_displacement``, negative or breakdown voltage) are
skipped and counted.  The first solver failure stops the replay (exit code 1); what
was computed up to it is still written.  Outputs, one entry per solve:

* ``OUT.mcap``: ``/command/displacement`` or ``/command/voltage`` (the accepted command
  that triggered the solve), ``/force``, ``/capacitance`` (Float64MultiArray) and
  ``/unit_states`` (JointState: position = centre deflection [m], velocity = 0 (the
  model is quasi-static), effort = force [N]), each with log time = the command's log
  time, plus the ``dea_array_twin_config`` metadata actually used and a
  ``dea_array_twin_replay`` record (source, ``time_origin_ns``).  The output is itself a
  replayable, plottable bag;
* ``OUT.csv``: ``time_s`` (from the first message of the input bag), ``d1_m..``,
  ``V1_V..``, ``F1_N..``, ``C1_F..``.

If the bag holds recorded ``force``/``capacitance``, each recorded message is compared
with the replayed state current at its log time (the latest accepted command at or
before it; the zero command before the first one) and the paper's FIT (eq. 12, :func:`fit`)
is printed per unit and channel.  A recording of the live node at ``update_rate`` > 0
lags its commands by up to one tick, which costs a little FIT on fast command changes.

A file without a summary (the recorder was killed) is refused with a pointer to
``python -m dea_array_twin.bag_recover``, not recovered silently: the recovered copy
may lack the last chunk, and the user should know.

Exit codes: 0 ok, 1 solver failure, 2 bad input (missing or non-MCAP file, truncated
bag, no command topics, bad config), 130 interrupted (``--realtime``).
"""

from __future__ import annotations

import argparse
import csv
import heapq
import math
import struct
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, NamedTuple, Sequence

import numpy as np
import yaml

from .config import ArrayConfig, ConfigError
from .configfile import load_config
from .mcap_writer import CONFIG_RECORD
from .metrics import fit
from .model import DRIVEN, MODES
from .solver import ConvergenceError
from .twin import ArrayTwin

__all__ = ["Bag", "BagError", "BagMessage", "ReplayRun", "compare_outputs", "fit", "parse_topic_map",
           "realtime_replay", "replay_commands", "run_from_args", "select_topic"]

REPLAY_METADATA = "dea_array_twin_replay"
NON_CONFIG_KEYS = ("unit_modes", "update_rate")
FLOAT_ARRAY = "std_msgs/msg/Float64MultiArray"
JOINT_STATE = "sensor_msgs/msg/JointState"
COMMANDS = ("displacement", "voltage")
OUTPUTS = ("force", "capacitance")
MCAP_MAGIC = b"\x89MCAP0\r\n"
_MAX_LISTED_WARNINGS = 5


class BagError(ValueError):
    """The input is not a usable bag (missing, not MCAP, truncated, no command topics...)."""


# ------------------------------------------------------------------------ bags

class BagMessage(NamedTuple):
    """One recorded message: topic, ``pkg/msg/Type``, log time [ns], CDR bytes, decoded (or None)."""

    topic: str
    type_name: str
    log_time_ns: int
    data: bytes
    decoded: Any = None


@dataclass
class _FileInfo:
    path: Path
    topics: dict[str, str]
    counts: dict[str, int]
    start_ns: int | None
    metadata: dict[str, dict[str, str]]


def _normalise_type(name: str) -> str:
    """``pkg/Type`` or ``pkg/msg/Type`` -> ``pkg/msg/Type``."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


def _mcap_modules():
    try:
        from mcap.exceptions import McapError
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise BagError(f"reading bags needs the 'mcap' extra (pip install 'dea_array_twin[mcap]'): {exc}") from None
    return McapError, make_reader, DecoderFactory


def _damage_errors() -> tuple[type[BaseException], ...]:
    McapError, _, _ = _mcap_modules()
    return (McapError, struct.error, ValueError, EOFError, UnicodeDecodeError, KeyError, IndexError)


def bag_files(path: str | Path) -> list[Path]:
    """The ``.mcap`` files of a bag, in order.

    Parameters
    ----------
    path
        A ``.mcap`` file, or a rosbag2 directory (``metadata.yaml`` plus ``.mcap``
        files, in the order of its ``relative_file_paths``), or a folder holding one
        recording split by the twin's recorder (``X.mcap``, ``X_1.mcap``, ...).

    Raises
    ------
    BagError
        The path does not exist, or the directory holds no ``.mcap`` file or several
        recordings.
    """
    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such file or directory")
    if not path.is_dir():
        return [path]
    listed: list[Path] = []
    meta = path / "metadata.yaml"
    if meta.is_file():
        try:
            info = (yaml.safe_load(meta.read_text()) or {}).get("rosbag2_bagfile_information", {})
        except (OSError, yaml.YAMLError, AttributeError):
            info = {}
        storage = str(info.get("storage_identifier", "mcap") or "mcap")
        if storage != "mcap":
            raise BagError(f"{path} is a rosbag2 bag in '{storage}' storage; only MCAP is supported "
                           f"(convert it with 'ros2 bag convert')")
        listed = [path / p for p in info.get("relative_file_paths", []) or [] if str(p).endswith(".mcap")]
        listed = [p for p in listed if p.is_file()]
    if not listed:
        listed = _one_series(path, sorted(path.glob("*.mcap")))
    return listed


def _one_series(folder: Path, files: list[Path]) -> list[Path]:
    """The files of a folder without ``metadata.yaml``: one recording, ``X.mcap`` plus its splits ``X_<n>.mcap``.

    Raises
    ------
    BagError
        No file, or several recordings (say which, so the user can pick one).
    """
    if not files:
        present = ", ".join(sorted(p.name for p in folder.iterdir())[:10]) or "nothing"
        raise BagError(f"{folder} holds no .mcap file (found: {present})")
    stems = {p.stem for p in files}
    bases = [p for p in files if not any(p.stem.startswith(s + "_") and p.stem[len(s) + 1:].isdigit() for s in stems)]
    if len(bases) != 1:
        names = ", ".join(p.name for p in bases[:6]) + (", ..." if len(bases) > 6 else "")
        raise BagError(f"{folder} holds {len(bases)} recordings ({names}) and no rosbag2 metadata.yaml; "
                       f"pass one .mcap file")
    base = bases[0].stem

    def split_number(p: Path) -> int:
        return 0 if p.stem == base else int(p.stem[len(base) + 1:])

    return sorted(files, key=split_number)


def _recover_hint(path: Path) -> str:
    return (f"Copy its complete records into a readable file with:\n"
            f"    python -m dea_array_twin.bag_recover {path} {path.with_name(path.stem + '_recovered.mcap')}")


def _inspect(path: Path) -> _FileInfo:
    """Check one file is a complete MCAP file and read its channels, counts and metadata."""
    McapError, make_reader, _ = _mcap_modules()
    damage = _damage_errors()
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
            f.seek(max(0, size - len(MCAP_MAGIC)))
            tail = f.read(len(MCAP_MAGIC))
    except OSError as exc:
        raise BagError(f"cannot read {path}: {exc.strerror or exc}") from None
    if head != MCAP_MAGIC:
        raise BagError(f"{path} is not an MCAP file (it does not start with the MCAP magic bytes)")
    if size < 2 * len(MCAP_MAGIC) or tail != MCAP_MAGIC:
        raise BagError(f"{path} has no MCAP footer: the recording was cut off (recorder killed?). "
                       + _recover_hint(path))
    topics: dict[str, str] = {}
    counts: Counter = Counter()
    start_ns = None
    metadata: dict[str, dict[str, str]] = {}
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            if summary is not None:
                for channel in summary.channels.values():
                    schema = summary.schemas.get(channel.schema_id)
                    topics[channel.topic] = _normalise_type(schema.name) if schema else ""
            if summary is not None and summary.statistics is not None:
                for cid, n in summary.statistics.channel_message_counts.items():
                    if cid in summary.channels:
                        counts[summary.channels[cid].topic] += n
                if summary.statistics.message_count:
                    start_ns = summary.statistics.message_start_time
            else:  # complete but without summary or statistics: scan it once
                for schema, channel, message in reader.iter_messages(log_time_order=False):
                    topics[channel.topic] = _normalise_type(schema.name) if schema else ""
                    counts[channel.topic] += 1
                    start_ns = message.log_time if start_ns is None else min(start_ns, message.log_time)
            for record in reader.iter_metadata():
                metadata.setdefault(record.name, dict(record.metadata))
    except damage as exc:
        raise BagError(f"{path} is damaged ({type(exc).__name__}: {exc}). " + _recover_hint(path)) from None
    return _FileInfo(path, topics, dict(counts), start_ns, metadata)


class Bag:
    """A recorded bag: one ``.mcap`` file or a rosbag2 directory of them.

    Every file is checked on opening (MCAP magic at both ends, readable summary), so a
    bag that opens can be read to the end.

    Parameters
    ----------
    path
        The ``.mcap`` file or the rosbag2 directory.

    Raises
    ------
    BagError
        Missing, not MCAP, truncated or damaged.

    Attributes
    ----------
    path : Path
    files : list of Path
        The ``.mcap`` files, in order.
    topics : dict
        Topic name -> ``pkg/msg/Type`` over all files.
    counts : dict
        Topic name -> number of messages.
    start_ns : int or None
        Log time of the first message [ns].
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.files = bag_files(self.path)
        self._infos = [_inspect(p) for p in self.files]
        self.topics: dict[str, str] = {}
        self.counts: Counter = Counter()
        for info in self._infos:
            for topic, type_name in info.topics.items():
                self.topics.setdefault(topic, type_name)
            self.counts.update(info.counts)
        starts = [i.start_ns for i in self._infos if i.start_ns is not None]
        self.start_ns: int | None = min(starts) if starts else None

    def metadata(self, name: str) -> dict[str, str] | None:
        """The first metadata record called ``name`` (``{key: value}``), or None."""
        for info in self._infos:
            if name in info.metadata:
                return dict(info.metadata[name])
        return None

    def describe_topics(self) -> str:
        """The topics present, one per line with type and message count."""
        if not self.topics:
            return "    (no topics)"
        return "\n".join(f"    {t}  [{self.topics[t] or '?'}]  {self.counts.get(t, 0)} msgs"
                         for t in sorted(self.topics))

    def messages(self, topics: Iterable[str], decode: bool = False) -> Iterator[BagMessage]:
        """The messages of ``topics`` over all files, in log-time order.

        Parameters
        ----------
        topics
            Topic names as recorded.
        decode
            Also decode each message (``mcap_ros2``: an object with the message's
            fields as attributes) into :attr:`BagMessage.decoded`.

        Raises
        ------
        BagError
            A record or message cannot be read (damaged file).
        """
        topics = sorted(set(topics))
        if not topics:
            return iter(())
        streams = [self._file_messages(info.path, topics, decode) for info in self._infos]
        return heapq.merge(*streams, key=lambda m: m.log_time_ns) if len(streams) > 1 else streams[0]

    def _file_messages(self, path: Path, topics: list[str], decode: bool) -> Iterator[BagMessage]:
        _, make_reader, DecoderFactory = _mcap_modules()
        damage = _damage_errors()
        factory = DecoderFactory()  # decoders are cached by schema id: one factory per file
        try:
            with open(path, "rb") as f:
                reader = make_reader(f)
                for schema, channel, message in reader.iter_messages(topics=topics, log_time_order=True):
                    type_name = _normalise_type(schema.name) if schema else ""
                    decoded = None
                    if decode:
                        decoder = factory.decoder_for(channel.message_encoding, schema)
                        if decoder is None:
                            raise BagError(f"{path}: cannot decode {channel.topic} (encoding "
                                           f"{channel.message_encoding!r}, schema {type_name or 'none'})")
                        decoded = decoder(message.data)
                    yield BagMessage(channel.topic, type_name, message.log_time, bytes(message.data), decoded)
        except BagError:
            raise
        except OSError as exc:
            raise BagError(f"cannot read {path}: {exc.strerror or exc}") from None
        except damage as exc:
            raise BagError(f"{path} is damaged ({type(exc).__name__}: {exc})") from None


# -------------------------------------------------------------- topic selection

def parse_topic_map(items: Sequence[str] | None) -> dict[str, str]:
    """``["/rig/disp=command/displacement", ...]`` -> ``{"/rig/disp": "command/displacement"}``.

    OLD is a topic as recorded (a leading ``/`` is added if missing); NEW is the name it
    plays the role of (``command/displacement``, ``force``...) and, for ``--realtime``,
    the name it is republished on.

    Raises
    ------
    BagError
        An item is not ``OLD=NEW``.
    """
    out: dict[str, str] = {}
    for item in items or []:
        old, sep, new = item.partition("=")
        if not sep or not old.strip() or not new.strip():
            raise BagError(f"--topic-map expects OLD=NEW (e.g. /rig/disp=command/displacement), got {item!r}")
        old = old.strip()
        out[old if old.startswith("/") else "/" + old] = new.strip()
    return out


def _plays(name: str, role: str) -> bool:
    name = name.lstrip("/")
    return name == role or name.endswith("/" + role)


def select_topic(topics: dict[str, str], role: str, topic_map: dict[str, str] | None = None,
                 namespace: str | None = None, type_name: str = FLOAT_ARRAY) -> str | None:
    """The recorded topic that plays ``role`` (e.g. ``command/displacement``), or None.

    Topics mapped to the role with ``--topic-map`` come first; otherwise any topic whose
    name ends with the role (``/role`` or ``/ns/role``) and that is not mapped to something
    else.  Among several, the one in ``namespace`` wins.

    Raises
    ------
    BagError
        Several candidates and no way to choose, or the topic has another type.
    """
    topic_map = topic_map or {}
    candidates = [t for t, new in topic_map.items() if t in topics and _plays(new, role)]
    if not candidates:
        candidates = [t for t in topics if t not in topic_map and _plays(t, role)]
    if len(candidates) > 1 and namespace is not None:
        preferred = [t for t in candidates if t == f"{namespace}/{role}"]
        candidates = preferred or candidates
    if len(candidates) > 1:
        raise BagError(f"several topics could be {role}: {', '.join(sorted(candidates))}; choose one with "
                       f"--topic-map {sorted(candidates)[0]}={role}")
    if not candidates:
        return None
    topic = candidates[0]
    if topics[topic] and topics[topic] != type_name:
        raise BagError(f"topic {topic} has type {topics[topic]}, expected {type_name} for {role}")
    return topic


def command_topics(bag: Bag, topic_map: dict[str, str] | None = None) -> dict[str, str]:
    """``{"displacement": topic, "voltage": topic}`` for the command topics found (at least one).

    Raises
    ------
    BagError
        No command topic, listing the topics present.
    """
    found = {kind: select_topic(bag.topics, f"command/{kind}", topic_map) for kind in COMMANDS}
    found = {k: t for k, t in found.items() if t is not None}
    if not found:
        raise BagError(f"{bag.path}: no command topics (names ending with command/displacement or "
                       f"command/voltage; map others with --topic-map OLD=command/displacement). "
                       f"Topics present:\n{bag.describe_topics()}")
    return found


def output_topics(bag: Bag, commands: dict[str, str], topic_map: dict[str, str] | None = None) -> dict[str, str]:
    """Recorded ``force``/``capacitance`` topics, preferring the commands' namespace."""
    namespace = None
    for kind, topic in commands.items():
        suffix = f"/command/{kind}"
        if topic.endswith(suffix):
            namespace = topic[: -len(suffix)]
    found = {}
    for kind in OUTPUTS:
        try:
            topic = select_topic(bag.topics, kind, topic_map, namespace)
        except BagError as exc:
            print(f"dea-twin: warning: ignoring recorded {kind}: {exc}", file=sys.stderr)
            continue
        if topic is not None:
            found[kind] = topic
    return found


# ------------------------------------------------------------------- config

def config_from_metadata(values: dict[str, str]) -> tuple[ArrayConfig, list[str] | None, list[str]]:
    """The config and unit modes of a ``dea_array_twin_config`` metadata record.

    Returns
    -------
    config : ArrayConfig
    modes : list of str or None
        ``unit_modes`` if recorded.
    ignored : list of str
        Keys that are neither config fields nor node parameters (skipped).

    Raises
    ------
    ConfigError
        A field is out of range or unparsable.
    """
    parsed = {}
    for key, text in values.items():
        try:
            parsed[key] = yaml.safe_load(text)
        except yaml.YAMLError:
            parsed[key] = text
    modes = parsed.pop("unit_modes", None)
    for key in NON_CONFIG_KEYS:
        parsed.pop(key, None)
    known = set(ArrayConfig().to_dict())
    ignored = sorted(set(parsed) - known)
    cfg = ArrayConfig.from_dict({k: v for k, v in parsed.items() if k in known})
    if modes is not None and not isinstance(modes, list):
        raise ConfigError(f"unit_modes: expected a list like [driven, free], got {values.get('unit_modes')!r}")
    return cfg, None if modes is None else [str(m) for m in modes], ignored


def metadata_from_config(cfg: ArrayConfig, modes: Sequence[str], update_rate: float = 0.0) -> dict[str, str]:
    """The ``dea_array_twin_config`` record for ``cfg`` (the inverse of :func:`config_from_metadata`)."""
    out = {k: str(v) for k, v in cfg.to_dict().items()}
    out["unit_modes"] = "[" + ", ".join(modes) + "]"
    out["update_rate"] = str(float(update_rate))
    return out


def resolve_config(bag: Bag, config_path: str | None,
                   modes: Sequence[str] | None) -> tuple[ArrayConfig, tuple[str, ...], list[str]]:
    """Config and unit modes for a replay, and where each came from (notes for stderr).

    Config: ``config_path``, else the bag's metadata, else the default.  Modes:
    ``modes``, else the bag's metadata, else all driven.

    Raises
    ------
    ConfigError
        Bad config file, bad recorded config, or modes of the wrong length or value.
    """
    notes = []
    recorded = bag.metadata(CONFIG_RECORD)
    recorded_modes = None
    if recorded is not None:
        try:
            recorded_cfg, recorded_modes, ignored = config_from_metadata(recorded)
        except ConfigError as exc:
            if config_path is None:
                raise ConfigError(f"the config recorded in {bag.path} is invalid ({exc}); pass --config") from None
            recorded_cfg, ignored = None, []
    if config_path is not None:
        cfg = load_config(config_path)
        notes.append(f"config from {config_path}")
    elif recorded is not None:
        cfg = recorded_cfg
        notes.append(f"config from the bag's '{CONFIG_RECORD}' metadata")
        if ignored:
            notes.append(f"warning: ignoring unknown recorded config keys {ignored} (another version of the twin?)")
    else:
        cfg = ArrayConfig()
        notes.append("no config in the bag and no --config: using the default ArrayConfig (the paper's 1-by-3 array)")
    n = cfg.n_units
    if modes is not None:
        source = "--modes"
    elif recorded_modes is not None and len(recorded_modes) == n:
        modes, source = recorded_modes, "the bag's metadata"
    else:
        if recorded_modes is not None:
            notes.append(f"warning: recorded unit_modes {recorded_modes} do not fit {n} units; ignored")
        modes, source = [DRIVEN] * n, "default (all driven)"
    modes = tuple(modes)
    if len(modes) != n or any(m not in MODES for m in modes):
        raise ConfigError(f"unit modes must be {n} values out of {MODES}, got {list(modes)} (from {source})")
    notes.append(f"unit modes {', '.join(modes)} from {source}")
    return cfg, modes, notes


# ------------------------------------------------------------- offline replay

@dataclass
class ReplayRun:
    """The twin's answers to a sequence of commands: one row per solve (SI units).

    Attributes
    ----------
    times_ns : ndarray, shape (k,)
        Log time of the command that triggered each solve [ns].
    kinds : list of str
        ``"displacement"`` or ``"voltage"``: which command triggered the solve.
    displacement, voltage, force, capacitance, centre_deflection : ndarray, shape (k, n)
        Held commands [m], [V] and outputs [N], [F], [m] after each solve.
    initial_force, initial_capacitance, initial_centre_deflection : ndarray, shape (n,)
        The state at the zero command, current before the first accepted command.
    skipped : Counter
        Rejected commands per kind.
    state_warnings : Counter
        Solves whose result carries a warning (wrinkling, field...), per warning kind.
    error : str or None
        Why the replay stopped early (solver failure), else None.
    """

    times_ns: np.ndarray
    kinds: list[str]
    displacement: np.ndarray
    voltage: np.ndarray
    force: np.ndarray
    capacitance: np.ndarray
    centre_deflection: np.ndarray
    initial_force: np.ndarray
    initial_capacitance: np.ndarray
    initial_centre_deflection: np.ndarray
    skipped: Counter = field(default_factory=Counter)
    state_warnings: Counter = field(default_factory=Counter)
    error: str | None = None

    @property
    def n_solves(self) -> int:
        """Number of solves (rows)."""
        return len(self.times_ns)


def _warning_kind(text: str) -> str:
    """A TwinResult warning without its numbers, for counting."""
    if "wrinkle" in text:
        return "compressive stress: the membrane would wrinkle"
    if "breakdown" in text:
        return "electric field above breakdown_field"
    return text


def replay_commands(twin: ArrayTwin, modes: Sequence[str], commands: Iterable[tuple[int, str, Sequence[float]]],
                    total: int | None = None, progress: bool = True, time_origin_ns: int = 0) -> ReplayRun:
    """Run the twin on commands in order, sample and hold: one solve per accepted command.

    Parameters
    ----------
    twin : ArrayTwin
        The twin (reset first).
    modes
        ``"driven"``/``"free"`` per unit.
    commands
        ``(log_time_ns, kind, values)`` with kind ``"displacement"`` [m] or ``"voltage"`` [V],
        in log-time order.
    total
        Number of commands, for the progress bar.
    progress
        Show a tqdm bar on stderr (only on a terminal).
    time_origin_ns
        Log time shown as t = 0 in messages.

    Returns
    -------
    ReplayRun
        What was computed; ``error`` is set if a solve failed (the run stops there).
    """
    from tqdm import tqdm

    from .node import command_error

    n = twin.n_units
    twin.reset()
    held = {kind: np.zeros(n) for kind in COMMANDS}
    first = twin.solve(held["displacement"], held["voltage"], modes, check_stability=False)
    rows: dict[str, list] = {k: [] for k in ("t", "kind", "d", "v", "f", "c", "z")}
    skipped: Counter = Counter()
    state_warnings: Counter = Counter()
    error = None
    bar = tqdm(total=total, desc="replay", unit="cmd", file=sys.stderr, disable=None if progress else True)
    try:
        for log_time, kind, values in commands:
            bar.update(1)
            values = list(values)
            t_s = (log_time - time_origin_ns) * 1e-9
            problem = command_error(kind, values, twin.config)
            if problem:
                skipped[kind] += 1
                if sum(skipped.values()) <= _MAX_LISTED_WARNINGS:
                    bar.write(f"dea-twin replay: warning: skipping {kind} command at t = {t_s:.6f} s: {problem}",
                              file=sys.stderr)
                continue
            held[kind] = np.asarray(values, dtype=float)
            try:
                res = twin.solve(held["displacement"], held["voltage"], modes, check_stability=False)
            except (ConvergenceError, ValueError) as exc:
                error = f"solve failed at t = {t_s:.6f} s ({kind} command {values}): {exc}"
                break
            for text in res.warnings:
                state_warnings[_warning_kind(text)] += 1
            rows["t"].append(int(log_time))
            rows["kind"].append(kind)
            rows["d"].append(held["displacement"].copy())
            rows["v"].append(held["voltage"].copy())
            rows["f"].append(np.asarray(res.force, dtype=float))
            rows["c"].append(np.asarray(res.capacitance, dtype=float))
            rows["z"].append(np.asarray(res.centre_deflection, dtype=float))
    finally:
        bar.close()

    def stack(key: str) -> np.ndarray:
        return np.array(rows[key], dtype=float).reshape(-1, n)

    return ReplayRun(times_ns=np.array(rows["t"], dtype=np.int64), kinds=rows["kind"], displacement=stack("d"),
                     voltage=stack("v"), force=stack("f"), capacitance=stack("c"), centre_deflection=stack("z"),
                     initial_force=np.asarray(first.force, dtype=float),
                     initial_capacitance=np.asarray(first.capacitance, dtype=float),
                     initial_centre_deflection=np.asarray(first.centre_deflection, dtype=float),
                     skipped=skipped, state_warnings=state_warnings, error=error)


def compare_outputs(run: ReplayRun, recorded: dict[str, tuple[np.ndarray, np.ndarray]],
                    lag_ns: int = 0) -> dict[str, np.ndarray]:
    """FIT per unit of the replayed outputs against recorded ones.

    Parameters
    ----------
    run
        The replay.
    recorded
        ``{"force": (times_ns, values), "capacitance": ...}``, values of shape (m, n).
    lag_ns
        Largest latency of the recorded outputs behind their commands [ns].  Each
        recorded message is compared with the replayed state current at its log time
        or, if one fits it better, with a state current up to ``lag_ns`` earlier (the
        live node answers a command at one of its next updates).  0 pairs each message
        with the latest solve at or before it (or the zero-command state before the first).

    Returns
    -------
    dict
        Kind -> FIT [%] per unit (``nan`` where the recorded signal is constant).
    """
    out = {}
    for kind, (times, values) in recorded.items():
        model_rows = np.vstack([getattr(run, f"initial_{kind}")[None, :], getattr(run, kind)])
        times = np.asarray(times, dtype=np.int64)
        last = np.searchsorted(run.times_ns, times, side="right")
        first = np.searchsorted(run.times_ns, times - int(lag_ns), side="right")
        idx = last.copy()
        for i in np.flatnonzero(first < last):  # several candidate states: take the closest
            candidates = np.arange(first[i], last[i] + 1)
            idx[i] = candidates[np.argmin(np.abs(model_rows[candidates] - values[i]).sum(axis=1))]
        model = model_rows[idx]
        out[kind] = np.array([fit(values[:, k], model[:, k]) for k in range(values.shape[1])])
    return out


# ------------------------------------------------------------------- outputs


def write_mcap(path: Path, run: ReplayRun, metadata: dict[str, dict[str, str]], frame_id: str = "dea_array") -> None:
    """Write the replay as a ROS 2 MCAP bag (see the module docstring for the topics).

    Every sequence is filled (``serialize_message`` may append junk bytes to empty ones).
    """
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    from .mcap_writer import Ros2McapWriter
    from .node import unit_array

    n = run.force.shape[1]
    names = [f"unit_{k + 1}" for k in range(n)]
    with Ros2McapWriter(path, metadata=metadata, flush_period=None) as rec:
        ids = {kind: rec.add_topic(f"/command/{kind}", FLOAT_ARRAY) for kind in COMMANDS}
        ids.update({kind: rec.add_topic(f"/{kind}", FLOAT_ARRAY) for kind in OUTPUTS})
        ids["unit_states"] = rec.add_topic("/unit_states", JOINT_STATE)
        for i, t in enumerate(run.times_ns.tolist()):
            kind = run.kinds[i]
            held = run.displacement[i] if kind == "displacement" else run.voltage[i]
            rec.write(ids[kind], serialize_message(unit_array(held)), t)
            rec.write(ids["force"], serialize_message(unit_array(run.force[i])), t)
            rec.write(ids["capacitance"], serialize_message(unit_array(run.capacitance[i])), t)
            states = JointState(name=names, position=[float(v) for v in run.centre_deflection[i]],
                                velocity=[0.0] * n, effort=[float(v) for v in run.force[i]])
            states.header.stamp.sec, states.header.stamp.nanosec = divmod(t, 1_000_000_000)
            states.header.frame_id = frame_id
            rec.write(ids["unit_states"], serialize_message(states), t)


def csv_header(n: int) -> list[str]:
    """CSV column names for ``n`` units."""
    units = range(1, n + 1)
    return (["time_s"] + [f"d{k}_m" for k in units] + [f"V{k}_V" for k in units] + [f"F{k}_N" for k in units]
            + [f"C{k}_F" for k in units])


def write_csv(path: Path, run: ReplayRun, origin_ns: int) -> None:
    """Write the replay as CSV: one row per solve, time relative to ``origin_ns``, SI units."""
    n = run.force.shape[1]
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(csv_header(n))
        for i, t in enumerate(run.times_ns.tolist()):
            writer.writerow([round((t - origin_ns) * 1e-9, 9), *run.displacement[i].tolist(), *run.voltage[i].tolist(),
                             *run.force[i].tolist(), *run.capacitance[i].tolist()])


def _output_base(bag_path: Path, out: str | None) -> Path:
    if out is not None:
        base = Path(out)
        return base.with_suffix("") if base.suffix in (".mcap", ".csv") else base
    bag_path = bag_path.resolve()
    stem = bag_path.name if bag_path.is_dir() else bag_path.stem
    return bag_path.parent / f"{stem}_replay"


def _fit_table(fits: dict[str, np.ndarray], topics: dict[str, str], counts: dict[str, int]) -> str:
    kinds = [k for k in OUTPUTS if k in fits]
    n = len(next(iter(fits.values())))
    head = ", ".join(f"{topics[k]} ({counts[k]} msgs)" for k in kinds)
    lines = [f"FIT [%] (paper eq. 12) of the replay against the recorded {head}:",
             "  unit" + "".join(f"  {k + ' [%]':>16}" for k in kinds)]
    for u in range(n):
        cells = "".join(f"  {'n/a' if math.isnan(fits[k][u]) else f'{fits[k][u]:.4f}':>16}" for k in kinds)
        lines.append(f"  {u + 1:>4}{cells}")
    if any(np.isnan(fits[k]).any() for k in kinds):
        lines.append("  n/a: the recorded signal is constant (e.g. a free unit's zero force): FIT undefined")
    return "\n".join(lines)


def _log(text: str) -> None:
    print(f"dea-twin replay: {text}", file=sys.stderr)


def replay_offline(bag: Bag, topic_map: dict[str, str], config_path: str | None, modes: Sequence[str] | None,
                   out: str | None, fit_lag: float | None = None) -> int:
    """``dea-twin replay BAG``: re-run the twin, write OUT.mcap and OUT.csv, print FIT; the exit code."""
    commands = command_topics(bag, topic_map)
    outputs = output_topics(bag, commands, topic_map)
    cfg, modes, notes = resolve_config(bag, config_path, modes)
    for note in notes:
        _log(note)
    base = _output_base(bag.path, out)
    mcap_path, csv_path = base.with_name(base.name + ".mcap"), base.with_name(base.name + ".csv")
    if any(mcap_path.resolve() == p.resolve() for p in bag.files):
        raise BagError(f"the output {mcap_path} would overwrite the input; choose another --out")
    _log("commands from " + ", ".join(f"{t} ({bag.counts.get(t, 0)} msgs)" for t in commands.values()))
    twin = ArrayTwin(cfg)
    kind_of = {topic: kind for kind, topic in commands.items()}
    recorded: dict[str, tuple[list, list]] = {k: ([], []) for k in outputs}
    output_kind = {topic: kind for kind, topic in outputs.items()}
    bad_outputs: Counter = Counter()
    n = cfg.n_units

    def command_stream() -> Iterator[tuple[int, str, list[float]]]:
        for msg in bag.messages(list(commands.values()) + list(outputs.values()), decode=True):
            if msg.topic in kind_of:
                yield msg.log_time_ns, kind_of[msg.topic], list(msg.decoded.data)
            else:
                kind = output_kind[msg.topic]
                values = np.asarray(msg.decoded.data, dtype=float)
                if values.shape != (n,) or not np.all(np.isfinite(values)):
                    bad_outputs[kind] += 1
                    continue
                recorded[kind][0].append(msg.log_time_ns)
                recorded[kind][1].append(values)

    total = sum(bag.counts.get(t, 0) for t in commands.values()) or None
    origin = bag.start_ns or 0
    tic = time.perf_counter()
    run = replay_commands(twin, modes, command_stream(), total=total, time_origin_ns=origin)
    elapsed = time.perf_counter() - tic
    for kind, count in run.skipped.items():
        _log(f"warning: skipped {count} invalid {kind} command(s)")
    for text, count in run.state_warnings.items():
        _log(f"warning: {count} replayed state(s) flagged: {text}")
    for kind, count in bad_outputs.items():
        _log(f"warning: {count} recorded {kind} message(s) of the wrong length or not finite: not compared")
    if run.n_solves == 0 and run.error is None:
        raise BagError(f"no valid command in {bag.path} ({sum(run.skipped.values())} rejected); "
                       f"does the config match the recording? (--config)")
    metadata = {CONFIG_RECORD: metadata_from_config(cfg, modes),
                REPLAY_METADATA: {"source": str(bag.path.resolve()), "time_origin_ns": str(origin),
                                  "config_source": notes[0], "solves": str(run.n_solves)}}
    write_mcap(mcap_path, run, metadata)
    write_csv(csv_path, run, origin)
    print(f"replayed {run.n_solves} command(s) in {elapsed:.2f} s "
          f"({sum(run.skipped.values())} skipped): wrote {mcap_path} and {csv_path}")
    if run.error is not None:
        print(f"dea-twin replay: solver failed, replay stopped: {run.error}; outputs hold the states before it",
              file=sys.stderr)
        return 1
    data = {k: (np.array(t, dtype=np.int64), np.array(v, dtype=float).reshape(-1, n))
            for k, (t, v) in recorded.items() if t}
    if data:
        if fit_lag is None:
            rate = float((bag.metadata(CONFIG_RECORD) or {}).get("update_rate", 0.0) or 0.0)
            fit_lag = 3.0 / rate if rate > 0 else 0.0
        _log(f"FIT pairs each recorded output with a replayed state current up to {fit_lag * 1e3:.1f} ms before "
             "it (three update periods of the recording node; --fit-lag to change)")
        fits = compare_outputs(run, data, int(round(fit_lag * 1e9)))
        print(_fit_table(fits, outputs, {k: len(v[0]) for k, v in data.items()}))
    return 0


# ------------------------------------------------------------------ realtime

def _message_class(type_name: str):
    import importlib

    package, _, name = _normalise_type(type_name).split("/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError):
        raise BagError(f"message type {type_name} is not installed (python package {package}.msg)") from None


def realtime_replay(bag: Bag, topic_map: dict[str, str], rate: float = 1.0, wait: float = 2.0) -> int:
    """``dea-twin replay --realtime``: republish the recorded commands with their timing scaled by 1/rate.

    The raw CDR bytes go out on rclpy publishers (reliable, volatile, depth 10: reliable
    and best-effort subscribers both connect) of the recorded type, on the mapped name
    (``--topic-map``) or else the recorded name made relative, so they resolve the same
    in the root namespace.  Uses the caller's ROS domain.  Waits up to ``wait`` seconds
    for a subscriber on every topic first.

    Returns
    -------
    int
        0 after the last message, 130 on Ctrl-C.
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.duration import Duration
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from tqdm import tqdm

    if not (rate > 0 and math.isfinite(rate)):
        raise BagError(f"--rate must be a number > 0, got {rate}")
    commands = command_topics(bag, topic_map)
    names = {topic: topic_map.get(topic, topic.lstrip("/")) for topic in commands.values()}
    classes = {topic: _message_class(bag.topics[topic] or FLOAT_ARRAY) for topic in commands.values()}
    total = sum(bag.counts.get(t, 0) for t in commands.values())
    context = Context()
    # Nothing spins here, so rclpy's signal handlers are not needed; without them Ctrl-C
    # raises KeyboardInterrupt in the sleep between messages.
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    sent = 0
    try:
        node = Node("dea_twin_replay", context=context)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        pubs = {topic: node.create_publisher(classes[topic], names[topic], qos) for topic in commands.values()}
        _log("republishing " + ", ".join(f"{t} -> {pubs[t].topic_name}" for t in pubs)
             + f" ({total} msgs) at {rate:g}x on ROS domain {context.get_domain_id()}")
        deadline = time.monotonic() + max(0.0, wait)
        while time.monotonic() < deadline and not all(p.get_subscription_count() for p in pubs.values()):
            time.sleep(0.02)
        missing = [p.topic_name for p in pubs.values() if not p.get_subscription_count()]
        if missing:
            _log(f"no subscriber yet on {', '.join(missing)} after {wait:g} s; starting anyway")
        else:
            time.sleep(0.3)  # matched on our side; let the subscribers' side match too
        start_wall = None
        start_log = 0
        with tqdm(total=total, desc="republish", unit="msg", file=sys.stderr, disable=None) as bar:
            for msg in bag.messages(commands.values()):
                if start_wall is None:
                    start_wall, start_log = time.monotonic(), msg.log_time_ns
                delay = start_wall + (msg.log_time_ns - start_log) * 1e-9 / rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                pubs[msg.topic].publish(msg.data)
                sent += 1
                bar.update(1)
        # Let reliable subscribers acknowledge the last messages before the publishers go.
        # Bounded: Fast DDS readers acknowledge on the writer's heartbeat (seconds), and
        # best-effort readers never do; on localhost the data has arrived long before.
        linger = time.monotonic() + 0.5
        for pub in pubs.values():
            pub.wait_for_all_acked(Duration(nanoseconds=max(0, int((linger - time.monotonic()) * 1e9))))
        _log(f"published {sent} message(s)")
        return 0
    except KeyboardInterrupt:
        _log(f"interrupted after {sent} of {total} message(s)")
        return 130
    finally:
        if node is not None:
            node.destroy_node()
        context.try_shutdown()


# ----------------------------------------------------------------------- CLI

def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``dea-twin replay`` options."""
    parser.add_argument("bag", help="recorded bag: an .mcap file or a rosbag2 directory")
    parser.add_argument("--config", help="config YAML (default: the bag's recorded config, else the paper's array)")
    parser.add_argument("--out", help="output base name: writes OUT.mcap and OUT.csv "
                                      "(default: <bag stem>_replay next to the bag)")
    parser.add_argument("--topic-map", nargs="+", action="extend", default=[], metavar="OLD=NEW",
                        help="use recorded topic OLD as NEW (e.g. /rig/disp=command/displacement)")
    parser.add_argument("--modes", type=lambda t: t.replace(",", " ").split(),
                        help="per-unit 'driven' or 'free', comma separated (default: recorded, else all driven)")
    parser.add_argument("--fit-lag", type=float, default=None, metavar="SECONDS",
                        help="largest latency of recorded outputs behind their commands (default: three update "
                             "periods of the recording node, 0 if unknown)")
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
            unused = [opt for opt, value in (("--config", args.config), ("--out", args.out), ("--modes", args.modes))
                      if value is not None]
            if unused:
                raise BagError(f"{', '.join(unused)} do(es) not apply to --realtime (it republishes the commands)")
            return realtime_replay(Bag(args.bag), topic_map, 1.0 if args.rate is None else args.rate, args.wait)
        if args.rate is not None:
            raise BagError("--rate needs --realtime")
        return replay_offline(Bag(args.bag), topic_map, args.config, args.modes, args.out, args.fit_lag)
    except (BagError, ConfigError) as exc:
        print(f"dea-twin replay: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # includes RecordingError (cannot write the outputs)
        print(f"dea-twin replay: error: {exc}", file=sys.stderr)
        return 2
