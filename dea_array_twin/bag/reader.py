"""Reading recorded bags: one ``.mcap`` file or a rosbag2 directory of them.

:func:`bag_files` finds the files of a bag (a rosbag2 ``metadata.yaml``, or one
recording split by the twin's recorder into ``X.mcap``, ``X_1.mcap``, ...).
:class:`Bag` checks every file on opening (MCAP magic at both ends, readable summary),
lists its topics, message counts and metadata records, and yields the messages of
chosen topics over all files in log-time order, optionally decoded with ``mcap_ros2``.
Needs ``mcap`` and ``mcap_ros2`` (core dependencies), no rclpy.

A file without a summary (the recorder was killed) is refused with a pointer to
``python -m dea_array_twin.bag.recover``, not recovered silently: the recovered copy
may lack the last chunk, and the user should know.
"""

from __future__ import annotations

import heapq
import struct
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import yaml
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

__all__ = ["Bag", "BagError", "BagMessage", "bag_files"]

MCAP_MAGIC = b"\x89MCAP0\r\n"


class BagError(ValueError):
    """The input is not a usable bag (missing, not MCAP, truncated, no command topics...)."""


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


#: What reading a damaged or cut-off file raises inside ``mcap`` / ``mcap_ros2``.
_DAMAGE = (McapError, struct.error, ValueError, EOFError, UnicodeDecodeError, KeyError, IndexError)


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
            f"    python -m dea_array_twin.bag.recover {path} {path.with_name(path.stem + '_recovered.mcap')}")


def _inspect(path: Path) -> _FileInfo:
    """Check one file is a complete MCAP file and read its channels, counts and metadata."""
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
    except _DAMAGE as exc:
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

    def output_path(self, suffix: str) -> Path:
        """Where an output derived from this bag goes by default: next to it, ``<name><suffix>``."""
        resolved = self.path.resolve()
        return resolved.parent / f"{resolved.name if resolved.is_dir() else resolved.stem}{suffix}"

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
        except _DAMAGE as exc:
            raise BagError(f"{path} is damaged ({type(exc).__name__}: {exc})") from None
