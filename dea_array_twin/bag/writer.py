"""Write ROS 2 messages to MCAP files that rosbag2, Foxglove and ``rosbags`` all open.

The writer takes raw CDR bytes and type names, so the recording node stays a thin
adapter (``raw=True`` subscriptions in, :meth:`Ros2McapWriter.write` out) and this
module needs no rclpy.  What makes a file a ROS 2 bag rather than just an MCAP file:

* header profile ``ros2``;
* one schema per message type, named ``pkg/msg/Type``, encoding ``ros2msg``, whose data
  is the type's ``.msg`` text with its nested types appended
  (:func:`~.msg_definitions.message_definition`);
* channels with message encoding ``cdr`` and the metadata rosbag2 writes,
  ``offered_qos_profiles`` (a YAML list, see :func:`default_qos_yaml`) and
  ``topic_type_hash`` (the ``RIHS01_...`` string, :func:`~.msg_definitions.type_hash`);
* log time = receive time in ns.

Durability against a killed process: the ``mcap`` writer keeps the open chunk in
memory, so :class:`Ros2McapWriter` closes the chunk (``mcap.writer.Writer.flush``)
at least every ``flush_period`` seconds of wall time.  A killed writer leaves a file
without summary; :func:`dea_array_twin.bag.recover.recover` turns it into a complete one.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import BinaryIO

import mcap
from mcap.writer import CompressionType, Writer
from mcap.writer import lz4 as _mcap_lz4
from mcap.writer import zstandard as _mcap_zstd

from .errors import RecordingError
from .msg_definitions import message_definition, split_type_name, type_hash

__all__ = ["CONFIG_RECORD", "RecordingError", "Ros2McapWriter", "default_qos_yaml"]

#: Metadata record in which the twin stores its config (field -> str(value)).
CONFIG_RECORD = "dea_array_twin_config"

PROFILE = "ros2"
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"

# rmw's RMW_DURATION_INFINITE as rosbag2 writes it: {sec: INT64_MAX // 1e9, nsec: INT64_MAX % 1e9}
_INFINITE_SEC = 9223372036
_INFINITE_NSEC = 854775807

# Summary size estimate for split_size: the statistics, summary offsets, footer and
# magic, plus one chunk index (about 90 bytes and 10 per channel) for each chunk.
_SUMMARY_BASE_BYTES = 400
_CHUNK_INDEX_BYTES = 90


def _library_string() -> str:
    try:
        from importlib.metadata import version
        own = version("dea_array_twin")
    except Exception:  # noqa: BLE001 - not installed as a distribution (e.g. source tree)
        own = "0"
    return f"dea_array_twin/{own} (mcap-python/{getattr(mcap, '__version__', '?')})"


def best_compression() -> CompressionType:
    """zstd if the ``mcap`` package can use it, else lz4, else no compression."""
    if _mcap_zstd is not None:
        return CompressionType.ZSTD
    if _mcap_lz4 is not None:
        return CompressionType.LZ4
    return CompressionType.NONE


# --------------------------------------------------------------------------- QoS

def default_qos_yaml(reliable: bool = True, depth: int = 10, *, transient_local: bool = False) -> str:
    """``offered_qos_profiles`` for one keep-last publisher, in rosbag2's (metadata v9, Jazzy) format.

    rosbag2 stores a YAML list with one entry per publisher, policies as rmw's string
    names (``keep_last``, ``reliable``/``best_effort``, ``volatile``/``transient_local``,
    ``automatic``) and durations as ``{sec, nsec}``, infinite being
    ``sec: 9223372036, nsec: 854775807``; the text is yaml-cpp's block style without a
    trailing newline.  rosbag2 reads these names only when it takes the bag as version 9,
    which it does for an MCAP file without a ``rosbag2`` metadata record.

    Parameters
    ----------
    reliable
        Reliable (True) or best-effort (False) reliability.
    depth
        History depth of the keep-last queue.
    transient_local
        Transient-local ("latched") durability instead of volatile.

    Returns
    -------
    str
        The YAML text for the channel metadata.
    """
    if depth < 0:
        raise ValueError(f"depth must be >= 0, got {depth}")
    infinite = [f"    sec: {_INFINITE_SEC}", f"    nsec: {_INFINITE_NSEC}"]
    lines = [
        "- history: keep_last",
        f"  depth: {int(depth)}",
        f"  reliability: {'reliable' if reliable else 'best_effort'}",
        f"  durability: {'transient_local' if transient_local else 'volatile'}",
        "  deadline:", *infinite,
        "  lifespan:", *infinite,
        "  liveliness: automatic",
        "  liveliness_lease_duration:", *infinite,
        "  avoid_ros_namespace_conventions: false",
    ]
    return "\n".join(lines)


# --------------------------------------------------------------------- the writer

class _Topic:
    __slots__ = ("topic", "type_name", "qos_yaml", "type_hash")

    def __init__(self, topic: str, type_name: str, qos_yaml: str, type_hash_: str):
        self.topic = topic
        self.type_name = type_name
        self.qos_yaml = qos_yaml
        self.type_hash = type_hash_


class Ros2McapWriter:
    """Record raw CDR messages of several topics to one MCAP file (or a series of split files).

    Parameters
    ----------
    path
        The ``.mcap`` file to write; missing parent directories are created.  After a split
        the next files are ``<stem>_1.mcap``, ``<stem>_2.mcap``, ... beside it.  Every file
        is created new: an existing one is an error (errno ``EEXIST``), never overwritten,
        unless ``overwrite``.
    metadata
        Metadata records ``{name: {key: value}}`` (all ``str``) written to every file,
        e.g. ``{"dea_array_twin_config": {"prestretch": "1.2", ...}}``.
    flush_period
        Wall-clock seconds after which :meth:`write` closes the open chunk and writes it
        to disk, bounding what a killed process loses.  ``None``: only full chunks
        (1 MiB) are written; ``0``: every message.
    split_size
        Start a new file before a message once the current one would, if finished now,
        hold about this many bytes: bytes on disk, the open chunk (its uncompressed size
        times the compression ratio of the last chunk written) and an estimate of the
        summary (which repeats the schemas, a few kB per type, and indexes every chunk).
    split_duration
        Start a new file before a message whose log time is this many seconds or more
        after the first message of the current file.
    overwrite
        Replace existing files (an output the user named, e.g. a replay's ``--out``)
        instead of refusing them.

    Raises
    ------
    RecordingError
        The file exists (and not ``overwrite``), or cannot be created or written.

    Examples
    --------
    >>> with Ros2McapWriter("run.mcap", metadata={"twin": {"units": "3"}}) as rec:  # doctest: +SKIP
    ...     cid = rec.add_topic("/force", "std_msgs/msg/Float64MultiArray", default_qos_yaml())
    ...     rec.write(cid, raw_cdr_bytes, log_time_ns=time.time_ns())
    """

    def __init__(self, path: str | os.PathLike, *, metadata: Mapping[str, Mapping[str, str]] | None = None,
                 flush_period: float | None = 1.0, split_size: int | None = None,
                 split_duration: float | None = None, overwrite: bool = False):
        if flush_period is not None and flush_period < 0:
            raise ValueError(f"flush_period must be >= 0 s or None, got {flush_period}")
        if split_size is not None and split_size <= 0:
            raise ValueError(f"split_size must be > 0 bytes or None, got {split_size}")
        if split_duration is not None and split_duration <= 0:
            raise ValueError(f"split_duration must be > 0 s or None, got {split_duration}")
        self._metadata = {str(name): _str_dict(name, values) for name, values in (metadata or {}).items()}
        self._first_path = Path(path)
        self._mode = "wb" if overwrite else "xb"
        self.flush_period = flush_period
        self.split_size = split_size
        self.split_duration_ns = None if split_duration is None else int(split_duration * 1e9)
        self._compression = best_compression()
        self._library = _library_string()
        self._lock = threading.RLock()
        self._topics: dict[int, _Topic] = {}
        self._paths: list[Path] = []
        self._ratio = 1.0  # bytes on disk per uncompressed byte of the last chunk
        self._stream: BinaryIO | None = None
        self._writer: Writer | None = None
        self._broken = False
        self._closed = False
        self.message_count = 0
        self._open_file(self._first_path)

    # ----------------------------------------------------------------- public API

    @property
    def path(self) -> Path:
        """The file being written now."""
        return self._paths[-1]

    @property
    def paths(self) -> list[Path]:
        """Every file written so far, in order."""
        return list(self._paths)

    def add_topic(self, topic: str, type_name: str, qos_profiles_yaml: str | None = None) -> int:
        """Register a topic; returns the channel id to pass to :meth:`write`.

        Parameters
        ----------
        topic
            Topic name, e.g. ``/array/force``.
        type_name
            ``pkg/msg/Type`` (``pkg/Type`` is accepted and normalised).
        qos_profiles_yaml
            The ``offered_qos_profiles`` text; ``None`` gives ``default_qos_yaml()``
            (reliable, volatile, keep last 10).

        Raises
        ------
        RecordingError
            The type's ``.msg`` definition is not installed, or the file cannot be written.
        ValueError
            The topic is already registered with another type.
        """
        package, name = split_type_name(type_name)
        type_name = f"{package}/msg/{name}"
        with self._lock:
            self._check_usable()
            for cid, known in self._topics.items():
                if known.topic == topic:
                    if known.type_name != type_name:
                        raise ValueError(f"topic {topic} is already recorded with type {known.type_name}")
                    return cid
            message_definition(type_name)  # fail here, before anything is registered
            entry = _Topic(topic, type_name, default_qos_yaml() if qos_profiles_yaml is None else qos_profiles_yaml,
                           type_hash(type_name))
            cid = len(self._topics) + 1
            self._topics[cid] = entry
            self._register(cid, entry)
            return cid

    def write(self, channel_id: int, data: bytes, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        """Append one serialised message.

        Parameters
        ----------
        channel_id
            From :meth:`add_topic`.
        data
            The message's CDR bytes, exactly as received (``raw=True`` subscription).
        log_time_ns
            Receive time, ns since the epoch.
        publish_time_ns
            Send time if known; defaults to ``log_time_ns``.

        Raises
        ------
        RecordingError
            Writing failed (e.g. disk full); the writer is unusable afterwards.
        KeyError
            Unknown channel id.
        """
        with self._lock:
            self._check_usable()
            if channel_id not in self._topics:
                raise KeyError(f"unknown channel id {channel_id}; register the topic with add_topic() first")
            if self._file_messages and self._should_split(log_time_ns):
                self._roll_over()
            before = self._stream.tell()
            with self._guard("write to"):
                self._writer.add_message(channel_id=self._channel_ids[channel_id], log_time=int(log_time_ns),
                                         data=bytes(data),
                                         publish_time=int(log_time_ns if publish_time_ns is None else publish_time_ns),
                                         sequence=self.message_count & 0xFFFFFFFF)
            self._pending_bytes += len(data) + 31  # message record overhead
            if self._stream.tell() != before:  # the writer just wrote a full chunk
                self._chunk_written(self._stream.tell() - before)
            if self._file_messages == 0:
                self._file_start_ns = int(log_time_ns)
            self._file_messages += 1
            self.message_count += 1
            if self.flush_period is not None and time.monotonic() - self._last_flush >= self.flush_period:
                self._flush()

    def flush(self) -> None:
        """Close the open chunk and write it to disk now (also done by :meth:`write` every ``flush_period``)."""
        with self._lock:
            self._check_usable()
            self._flush()

    def close(self) -> None:
        """Finish the current file (summary, footer) and close it.  Safe to call twice.

        After a :class:`RecordingError` this only releases the file handle.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._broken:
                self._close_stream_quietly()
                return
            self._finish_file()

    def __enter__(self) -> Ros2McapWriter:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    # ------------------------------------------------------------------ internals

    def _guard(self, action: str) -> _OsErrorGuard:
        return _OsErrorGuard(self, action)

    def _check_usable(self) -> None:
        if self._closed:
            raise RecordingError(f"recording to {self.path} is closed", path=self.path)
        if self._broken:
            raise RecordingError(f"recording to {self.path} stopped after an earlier error", path=self.path)

    def _open_file(self, path: Path) -> None:
        self._paths.append(path)
        with self._guard("create"):
            path.parent.mkdir(parents=True, exist_ok=True)
            self._stream = open(path, self._mode)  # noqa: SIM115 - closed in _finish_file / on error
        self._writer = Writer(self._stream, compression=self._compression)
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[int, int] = {}
        self._file_messages = 0
        self._file_start_ns = 0
        self._pending_bytes = 0
        self._summary_bytes = _SUMMARY_BASE_BYTES
        with self._guard("write to"):
            self._writer.start(profile=PROFILE, library=self._library)
            for name, values in self._metadata.items():
                self._writer.add_metadata(name, values)
            for cid, entry in self._topics.items():
                self._register(cid, entry)
            self._flush()

    def _register(self, cid: int, entry: _Topic) -> None:
        with self._guard("write to"):
            schema_id = self._schema_ids.get(entry.type_name)
            if schema_id is None:
                schema_id = self._writer.register_schema(name=entry.type_name, encoding=SCHEMA_ENCODING,
                                                         data=message_definition(entry.type_name).encode())
                self._schema_ids[entry.type_name] = schema_id
                self._summary_bytes += 21 + len(entry.type_name) + len(SCHEMA_ENCODING) + \
                    len(message_definition(entry.type_name))
            self._channel_ids[cid] = self._writer.register_channel(
                topic=entry.topic, message_encoding=MESSAGE_ENCODING, schema_id=schema_id,
                metadata={"offered_qos_profiles": entry.qos_yaml, "topic_type_hash": entry.type_hash})
            self._summary_bytes += 60 + len(entry.topic) + len(entry.qos_yaml) + len(entry.type_hash) + 10

    def _flush(self) -> None:
        before = self._stream.tell()
        with self._guard("write to"):
            self._writer.flush()
        if self._stream.tell() != before and self._file_messages:
            self._chunk_written(self._stream.tell() - before)
        self._pending_bytes = 0
        self._last_flush = time.monotonic()

    def _chunk_written(self, disk_bytes: int) -> None:
        """Book-keeping for the split size: the chunk's index joins the summary; learn the compression ratio."""
        if self._pending_bytes > 0:
            self._ratio = min(1.5, max(0.01, disk_bytes / self._pending_bytes))
        self._pending_bytes = 0
        self._summary_bytes += _CHUNK_INDEX_BYTES + 10 * len(self._channel_ids)

    def _should_split(self, log_time_ns: int) -> bool:
        if self.split_size is not None:
            if self._estimated_size() >= self.split_size and self._pending_bytes:
                self._flush()  # measure the open chunk rather than trust the estimated ratio
            if self._estimated_size() >= self.split_size:
                return True
        return self.split_duration_ns is not None and log_time_ns - self._file_start_ns >= self.split_duration_ns

    def _estimated_size(self) -> float:
        return self._stream.tell() + self._ratio * self._pending_bytes + self._summary_bytes

    def _roll_over(self) -> None:
        self._finish_file()
        stem, suffix = self._first_path.stem, self._first_path.suffix or ".mcap"
        self._open_file(self._first_path.with_name(f"{stem}_{len(self._paths)}{suffix}"))

    def _finish_file(self) -> None:
        with self._guard("finish"):
            self._writer.finish()
            self._stream.close()

    def _close_stream_quietly(self) -> None:
        try:
            if self._stream is not None:
                self._stream.close()
        except OSError:
            pass


class _OsErrorGuard:
    """Turn an ``OSError`` inside the block into a :class:`RecordingError` and mark the writer broken."""

    def __init__(self, owner: Ros2McapWriter, action: str):
        self.owner, self.action = owner, action

    def __enter__(self) -> None:
        return None

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc is None or not isinstance(exc, OSError) or isinstance(exc, RecordingError):
            return False
        owner = self.owner
        owner._broken = True
        owner._close_stream_quietly()
        path = owner._paths[-1]
        reason = exc.strerror or str(exc)
        if exc.filename and str(exc.filename) != str(path):
            reason += f" ({exc.filename})"
        raise RecordingError(f"cannot {self.action} MCAP recording {path}: {reason}", path=path,
                             errno=exc.errno) from exc


def _str_dict(name: str, values: Mapping[str, str]) -> dict[str, str]:
    if not isinstance(values, Mapping):
        raise TypeError(f"metadata {name!r} must be a mapping of str to str, got {type(values).__name__}")
    bad = [k for k, v in values.items() if not isinstance(k, str) or not isinstance(v, str)]
    if bad:
        raise TypeError(f"metadata {name!r} must map str to str; convert the values of {bad[:3]} with str()")
    return dict(values)
