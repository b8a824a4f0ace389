"""Recover an MCAP recording whose writer was killed before it wrote the summary.

Such a file has no footer, so seeking readers (``mcap.reader.make_reader``,
``mcap_ros2``, ``rosbags``, rosbag2) refuse it, but every record written before the
kill is intact.  :func:`recover` reads the file front to back with ``mcap``'s stream
reader, stops at the first incomplete record, and writes a complete copy (schemas,
channels, metadata, attachments, messages, then a fresh summary)::

    python -m dea_array_twin.bag.recover killed.mcap recovered.mcap
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from mcap.exceptions import InvalidMagic
from mcap.records import Attachment, Channel, Chunk, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import Writer

from .writer import best_compression

__all__ = ["RecoveryError", "recover"]

# What a truncated or damaged record raises inside ``mcap`` varies: McapError (short read,
# record too long), struct.error (cut-off integer), UnicodeDecodeError, ValueError (CRC),
# and whatever the lz4/zstd decompressors raise.  Any failure while parsing is damage.
_DAMAGE = Exception


class RecoveryError(ValueError):
    """The input is not an MCAP file (or not even its first record is readable)."""


def recover(src: str | os.PathLike, dst: str | os.PathLike) -> int:
    """Copy every complete record of a (possibly summary-less) MCAP file into a complete one.

    Parameters
    ----------
    src
        The damaged recording, e.g. left by a killed :class:`~.mcap_writer.Ros2McapWriter`.
    dst
        The file to write (overwritten); must differ from ``src``.

    Returns
    -------
    int
        The number of messages copied.  Messages of a chunk that was cut off or fails its
        checksum are lost; so are messages whose channel record was lost.

    Raises
    ------
    RecoveryError
        ``src`` is not an MCAP file (wrong magic bytes, too short, or no Header record
        first), or ``dst`` is ``src``.
    OSError
        ``src`` cannot be read or ``dst`` cannot be written.
    """
    src, dst = Path(src), Path(dst)
    if src.resolve() == dst.resolve():
        raise RecoveryError(f"the destination must differ from the source {src}: the copy is written beside it")
    with open(src, "rb") as f_in:
        records = _records(f_in, src)
        header = next(records)  # checks the magic and the Header: nothing written before that
        try:
            with open(dst, "wb") as f_out:
                count = _copy(header, records, f_out)
        except BaseException:
            dst.unlink(missing_ok=True)
            raise
    return count


def _records(stream, src: Path):
    """Yield the Header, then every complete top-level record (chunks expanded); stop at damage."""
    reader = StreamReader(stream, emit_chunks=True, record_size_limit=1 << 30)
    it = iter(reader.records)
    try:
        first = next(it)
    except StopIteration:
        first = None
    except InvalidMagic:
        raise RecoveryError(f"{src} is not an MCAP file: it does not start with the MCAP magic bytes") from None
    except _DAMAGE as exc:
        raise RecoveryError(f"{src} is not an MCAP file: {_describe(exc)}") from None
    if not isinstance(first, Header):
        raise RecoveryError(f"{src} is not an MCAP file: the first record is not an MCAP Header")
    yield first
    while True:
        try:
            record = next(it)
        except StopIteration:
            return
        except _DAMAGE:  # the record the writer was writing when it died: everything after it is lost
            return
        if isinstance(record, Chunk):
            try:
                inner = breakup_chunk(record, validate_crc=True)
            except _DAMAGE:  # a damaged chunk with intact framing: skip it, keep going
                continue
            yield from inner
        else:
            yield record


def _describe(exc: BaseException) -> str:
    text = str(exc)
    if not text or "unpack requires a buffer" in text or type(exc).__name__ == "EndOfFile":
        return "the file ends before the first record"
    return text


def _copy(header: Header, records, f_out) -> int:
    library = f"{header.library} (recovered by dea_array_twin.bag.recover)" if header.library else \
        "dea_array_twin.bag.recover"
    writer = Writer(f_out, compression=best_compression())
    writer.start(profile=header.profile, library=library)
    schema_ids: dict[int, int] = {0: 0}
    channel_ids: dict[int, int] = {}
    count = 0
    for record in records:
        if isinstance(record, Schema):
            if record.id not in schema_ids:
                schema_ids[record.id] = writer.register_schema(name=record.name, encoding=record.encoding,
                                                               data=record.data)
        elif isinstance(record, Channel):
            if record.id not in channel_ids and record.schema_id in schema_ids:
                channel_ids[record.id] = writer.register_channel(topic=record.topic,
                                                                 message_encoding=record.message_encoding,
                                                                 schema_id=schema_ids[record.schema_id],
                                                                 metadata=dict(record.metadata))
        elif isinstance(record, Message):
            new_id = channel_ids.get(record.channel_id)
            if new_id is not None:
                writer.add_message(channel_id=new_id, log_time=record.log_time, data=record.data,
                                   publish_time=record.publish_time, sequence=record.sequence)
                count += 1
        elif isinstance(record, Metadata):
            writer.add_metadata(record.name, dict(record.metadata))
        elif isinstance(record, Attachment):
            writer.add_attachment(create_time=record.create_time, log_time=record.log_time, name=record.name,
                                  media_type=record.media_type, data=record.data)
        # indexes, statistics, summary offsets, DataEnd, Footer: rebuilt by finish()
    writer.finish()
    return count


def main(argv: list[str] | None = None) -> int:
    """``python -m dea_array_twin.bag.recover SRC DST``: recover, print the message count.

    Exit codes: 0 recovered, 2 bad input (not an MCAP file, ``DST`` = ``SRC``, unreadable
    or unwritable file), as every ``dea-twin`` sub-command.
    """
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print("usage: python -m dea_array_twin.bag.recover SRC.mcap DST.mcap", file=sys.stderr)
        return 2
    try:
        count = recover(args[0], args[1])
    except (RecoveryError, OSError) as exc:
        print(f"dea-twin bag-recover: error: {exc}", file=sys.stderr)
        return 2
    print(f"recovered {count} messages into {args[1]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
