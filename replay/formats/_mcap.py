"""Shared MCAP helpers of the two MCAP readers: magic check, channel discovery, damaged-file messages.

Every call into the ``mcap`` package made by the readers goes through here or through the two reader
modules; it is imported lazily, so reading other formats never needs it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from replay.errors import InputError

MAGIC = b"\x89MCAP0\r\n"


@dataclass(frozen=True)
class ChannelInfo:
    id: int
    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    metadata: dict


def is_mcap(path: Path) -> bool:
    if not path.is_file():
        return False
    with path.open("rb") as fh:
        return fh.read(len(MAGIC)) == MAGIC


def scan(path: Path, max_records: int = 100_000) -> tuple[list[ChannelInfo], str | None]:
    """Channels of an MCAP file and, if the file is damaged, why.

    From the summary section when there is one (cheap); else by reading records from the start until the
    first message (channels precede their messages) or a damaged record.
    """
    from mcap.reader import make_reader
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    errors = read_errors()
    with path.open("rb") as fh:
        try:
            summary = make_reader(fh).get_summary()
        except errors:
            summary = None
        if summary is not None:
            return [_info(c, summary.schemas.get(c.schema_id)) for c in summary.channels.values()], None
    schemas: dict[int, object] = {}
    channels: list[ChannelInfo] = []
    error = None
    with path.open("rb") as fh:
        try:
            for n, rec in enumerate(StreamReader(fh).records):
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels.append(_info(rec, schemas.get(rec.schema_id)))
                elif (isinstance(rec, Message) and channels) or n > max_records:
                    break
        except errors as exc:
            error = damaged(exc)
    return channels, error


def read_errors() -> tuple[type[BaseException], ...]:
    """What reading a damaged MCAP raises inside the ``mcap`` package: its own errors, a record cut short
    (``EOFError``, ``struct.error``, ``ValueError``), and a chunk whose compressed data is corrupt
    (zstandard's ``ZstdError``; lz4's ``RuntimeError``)."""
    import struct

    from mcap.exceptions import McapError

    errors: list[type[BaseException]] = [McapError, EOFError, OSError, ValueError, struct.error, RuntimeError]
    try:
        import zstandard

        errors.append(zstandard.ZstdError)
    except ImportError:  # the mcap package then reads no zstd chunk either
        pass
    return tuple(errors)


def _info(channel, schema) -> ChannelInfo:
    return ChannelInfo(
        id=channel.id,
        topic=channel.topic,
        message_encoding=channel.message_encoding,
        schema_name=getattr(schema, "name", "") or "",
        schema_encoding=getattr(schema, "encoding", "") or "",
        metadata=dict(channel.metadata or {}),
    )


def damaged(exc: BaseException) -> str:
    detail = str(exc).strip() or type(exc).__name__
    return f"truncated or damaged MCAP ({type(exc).__name__}: {detail[:120]})"


def why_unknown(path: Path) -> str:
    """The one-line reason an MCAP file was not recognised by either MCAP reader."""
    channels, error = scan(path)
    if error is not None:
        return error
    topics = ", ".join(sorted({c.topic for c in channels})[:8]) or "none"
    return (
        "an MCAP file without /mag/raw (pdr_mag layout) or a sensor_msgs/msg/MagneticField channel "
        f"(topics: {topics})"
    )


def iter_messages(path: Path, topics: list[str], decoder_factories=(), opened: list | None = None):
    """Yield ``(channel, message[, decoded])`` of ``topics`` in file order; a damaged file → InputError.

    ``opened``, when given, gets the open file appended (its position tells the progress)."""
    from mcap.reader import make_reader

    errors = read_errors()
    with path.open("rb") as fh:
        if opened is not None:
            opened.append(fh)
        reader = make_reader(fh, decoder_factories=list(decoder_factories))
        try:
            if decoder_factories:
                for _, channel, message, decoded in reader.iter_decoded_messages(
                    topics=topics, log_time_order=False
                ):
                    yield channel, message, decoded
            else:
                for _, channel, message in reader.iter_messages(topics=topics, log_time_order=False):
                    yield channel, message
        except errors as exc:
            raise InputError(path, damaged(exc)) from None
