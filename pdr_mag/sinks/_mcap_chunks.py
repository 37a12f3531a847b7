"""The MCAP sink's file writer: message records built in batches with numpy, chunks written by an I/O thread.

:class:`ChunkWriter` writes the same structure as mcap's own ``Writer`` (chunked, message indexes, chunk
indexes, statistics, summary offsets, CRCs of chunks and summary — checked by mcap's reader in the tests)
but takes messages as whole batches of finished records: mcap's per-message ``add_message`` costs about
4 µs a message, and a one-hour 200 Hz replay writes millions.

A message record is a 31-byte header (opcode, record length, channel, sequence, log and publish time) and
the payload.  For CDR messages, :func:`record_dtype` puts the header and the payload in one numpy structured
dtype, so a batch of records is one array whose bytes are the records back to back (:func:`new_records`,
:func:`record_bytes`); a variable-length field (a string) is handled by trimming each row to its size.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pdr_mag.sinks._mcap_schemas import CDR_LE

MAGIC = b"\x89MCAP0\r\n"
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
#: Message record header: opcode, record length, channel id, sequence, log time, publish time (31 bytes).
HEADER_FIELDS = [("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("seq", "<u4"), ("log", "<u8"), ("pub", "<u8")]
HEADER = np.dtype(HEADER_FIELDS)
HEADER_SIZE = HEADER.itemsize  # 31


def record_dtype(payload: np.dtype) -> np.dtype:
    """The message-record dtype: :data:`HEADER`, then ``payload`` (made with ``prefix=HEADER_SIZE``)."""
    names = [n for n, _ in HEADER_FIELDS] + list(payload.names)
    formats = [HEADER.fields[n][0] for n, _ in HEADER_FIELDS] + [payload.fields[n][0] for n in payload.names]
    offsets = [HEADER.fields[n][1] for n, _ in HEADER_FIELDS] + [payload.fields[n][1] for n in payload.names]
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": payload.itemsize})


def new_records(dtype: np.dtype, cid: int, ns: np.ndarray, sizes: np.ndarray | None = None) -> np.ndarray:
    """Zeroed records of ``dtype`` with the header filled in (CDR encapsulation too, when the dtype has it).

    ``sizes``: the record sizes when they vary (default: all ``dtype.itemsize``).
    """
    rec = np.zeros(len(ns), dtype)
    rec["op"] = OP_MESSAGE
    rec["len"] = (dtype.itemsize if sizes is None else sizes) - 9
    rec["ch"] = cid
    rec["log"] = ns
    rec["pub"] = ns
    if "encapsulation" in dtype.names:
        rec["encapsulation"] = CDR_LE
    return rec


def record_bytes(rec: np.ndarray, sizes: np.ndarray | None = None) -> tuple[bytes, np.ndarray]:
    """The records back to back and their sizes; rows trimmed to ``sizes`` when given."""
    n, w = len(rec), rec.dtype.itemsize
    if sizes is None:
        return rec.tobytes(), np.full(n, w, dtype=np.int64)
    u8 = rec.view(np.uint8).reshape(n, w)
    return u8[np.arange(w) < np.asarray(sizes)[:, None]].tobytes(), np.asarray(sizes, dtype=np.int64)


def one_record(cid: int, ns: int, data: bytes) -> tuple[bytes, np.ndarray]:
    """A single message record (header + ``data``) and its size."""
    hdr = np.zeros(1, HEADER)
    hdr["op"], hdr["len"], hdr["ch"] = OP_MESSAGE, HEADER_SIZE - 9 + len(data), cid
    hdr["log"] = hdr["pub"] = ns
    return hdr.tobytes() + data, np.array([HEADER_SIZE + len(data)], dtype=np.int64)


class ChunkWriter:
    """A streaming MCAP writer that takes messages in batches and builds chunks with numpy.

    The records around the messages (header, schema, channel, chunk, chunk index, metadata, statistics,
    summary, footer) are mcap's own record classes; only the message and message-index records inside
    and after each chunk are assembled here, vectorised, because mcap's per-message ``add_message`` costs
    about 4 µs a message (a one-hour 200 Hz replay writes several million).  The file has the same
    structure as mcap's ``Writer`` output (chunked, message indexes, chunk indexes, statistics, summary
    offsets, CRCs of chunks and summary) and is validated by mcap's reader in the tests.

    Compression, CRCs and file writes run on one background thread (zstd/lz4/zlib release the GIL), fed
    through a queue of at most ``_QUEUE`` finished chunks, so memory stays bounded to a few chunks.  All
    file access happens on that thread, in submission order; an error there is raised by the next call.
    """

    _QUEUE = 3

    def __init__(self, path: Path, chunk_size: int, compression: str):
        import queue
        import threading

        from mcap.data_stream import RecordBuilder
        from mcap.records import Header

        self._rb = RecordBuilder()  # used on the I/O thread only
        self._stream = open(path, "wb")  # noqa: SIM115 - closed in finish()
        self._chunk_size = chunk_size
        self._compression = compression
        self._schemas: list = []
        self._channels: list = []
        self._chunk_indexes: list = []
        self._metadata_indexes: list = []
        self._counts: dict[int, int] = {}
        self._n_messages = 0
        self._t_start: int | None = None
        self._t_end = 0
        self._metadata_count = 0
        # the chunk being filled: list of (channel id, ns (n,), records bytes, record lengths (n,))
        self._pending: list[tuple[int, np.ndarray, bytes, np.ndarray]] = []
        self._pending_bytes = 0
        self._zstd = None
        self._error: BaseException | None = None
        self._jobs: queue.Queue = queue.Queue(maxsize=self._QUEUE)
        self._thread = threading.Thread(target=self._work, name="pdr_mag-mcap-writer", daemon=True)
        self._thread.start()

        def start():
            self._stream.write(MAGIC)
            Header(profile="", library="pdr_mag (mcap-python records)").write(self._rb)
            self._flush()

        self._submit(start)

    # ------------------------------------------------------------------ the I/O thread
    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            if self._error is None:
                try:
                    job()
                except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
                    self._error = exc

    def _submit(self, job) -> None:
        if self._error is not None:
            raise RuntimeError(f"MCAP writer failed: {self._error}") from self._error
        self._jobs.put(job)

    def _flush(self) -> None:
        self._stream.write(self._rb.end())

    # ------------------------------------------------------------------ records
    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        from mcap.records import Schema

        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)

        def job():
            schema.write(self._rb)
            self._flush()

        self._submit(job)
        return schema.id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int, metadata: dict) -> int:
        from mcap.records import Channel

        channel = Channel(
            id=len(self._channels) + 1,
            topic=topic,
            message_encoding=message_encoding,
            schema_id=schema_id,
            metadata=dict(metadata),
        )
        self._channels.append(channel)
        self._counts[channel.id] = 0

        def job():
            channel.write(self._rb)
            self._flush()

        self._submit(job)
        return channel.id

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        from mcap.records import Metadata, MetadataIndex

        record = Metadata(name=name, metadata=dict(data))
        self._metadata_count += 1

        def job():
            offset = self._stream.tell()
            record.write(self._rb)
            self._metadata_indexes.append(MetadataIndex(offset=offset, length=self._rb.count, name=name))
            self._flush()

        self._submit(job)

    def add_records(self, ns: np.ndarray, blob: bytes, sizes: np.ndarray) -> None:
        """Queue finished message records (``blob``: n records back to back, ``sizes`` their lengths,
        ``ns`` their log times) and write every chunk that fills up."""
        n = len(sizes)
        if n == 0:
            return
        sizes = np.asarray(sizes, dtype=np.int64)
        if len(ns) != n or int(sizes.sum()) != len(blob):
            raise ValueError(f"add_records: {n} sizes, {len(ns)} log times, {len(blob)} bytes do not match")
        cid = int.from_bytes(blob[9:11], "little")
        self._counts[cid] += n
        if self._pending_bytes + len(blob) < self._chunk_size:  # the usual case: it all fits
            self._pending.append((cid, ns, blob, sizes))
            self._pending_bytes += len(blob)
            return
        ends = np.cumsum(sizes)
        start, base = 0, 0
        while start < n:
            room = self._chunk_size - self._pending_bytes
            stop = start + max(1, int(np.searchsorted(ends[start:] - base, room, side="right")))
            end = int(ends[stop - 1])
            self._pending.append((cid, ns[start:stop], blob[base:end], sizes[start:stop]))
            self._pending_bytes += end - base
            start, base = stop, end
            if self._pending_bytes >= self._chunk_size:
                self._finalize_chunk()

    def _finalize_chunk(self) -> None:
        """Join the pending records into one chunk (here) and hand it to the I/O thread."""
        if not self._pending:
            return
        pending, self._pending, self._pending_bytes = self._pending, [], 0
        data = b"".join(p[2] for p in pending)
        ns = np.concatenate([p[1] for p in pending]).astype(np.int64, copy=False)
        sizes = np.concatenate([p[3] for p in pending])
        cids = np.repeat([p[0] for p in pending], [len(p[1]) for p in pending])
        starts = np.cumsum(sizes) - sizes  # offset of each record in the uncompressed chunk
        index_bodies = {}
        for cid in sorted({p[0] for p in pending}):
            sel = cids == cid
            t, off = ns[sel], starts[sel]
            if np.any(t[1:] < t[:-1]):  # message indexes are sorted by log time (offsets break ties)
                order = np.argsort(t, kind="stable")
                t, off = t[order], off[order]
            entries = np.empty((len(t), 2), dtype="<u8")
            entries[:, 0], entries[:, 1] = t, off
            index_bodies[cid] = entries.tobytes()
        t_lo, t_hi = int(ns.min()), int(ns.max())
        self._n_messages += len(ns)
        self._t_start = t_lo if self._t_start is None else min(self._t_start, t_lo)
        self._t_end = max(self._t_end, t_hi)
        self._submit(lambda: self._write_chunk(data, index_bodies, t_lo, t_hi))

    def _write_chunk(self, data: bytes, index_bodies: dict[int, bytes], t_lo: int, t_hi: int) -> None:
        """On the I/O thread: compress, write the chunk record and its message-index records."""
        import struct
        import zlib

        from mcap.records import ChunkIndex

        if self._compression == "zstd":
            if self._zstd is None:
                import zstandard

                self._zstd = zstandard.ZstdCompressor(level=1)
            compressed, compression = self._zstd.compress(data), "zstd"
        elif self._compression == "lz4":
            import lz4.frame

            compressed, compression = lz4.frame.compress(data), "lz4"
        else:
            compressed, compression = data, ""
        # the Chunk record (mcap.records.Chunk's layout), written without copying the data into a builder
        comp = compression.encode()
        head = struct.pack(
            f"<QQQI I{len(comp)}sQ", t_lo, t_hi, len(data), zlib.crc32(data), len(comp), comp, len(compressed)
        )
        chunk_start = self._stream.tell()
        self._stream.write(struct.pack("<BQ", OP_CHUNK, len(head) + len(compressed)) + head)
        self._stream.write(compressed)
        chunk_length = 9 + len(head) + len(compressed)
        index_start = self._stream.tell()
        offsets, parts, pos = {}, [], 0
        for cid, body in index_bodies.items():
            rec = (
                bytes([OP_MESSAGE_INDEX])
                + (6 + len(body)).to_bytes(8, "little")
                + cid.to_bytes(2, "little")
                + len(body).to_bytes(4, "little")
                + body
            )
            offsets[cid] = index_start + pos
            parts.append(rec)
            pos += len(rec)
        self._stream.write(b"".join(parts))
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=t_lo,
                message_end_time=t_hi,
                chunk_start_offset=chunk_start,
                chunk_length=chunk_length,
                message_index_offsets=offsets,
                message_index_length=pos,
                compression=compression,
                compressed_size=len(compressed),
                uncompressed_size=len(data),
            )
        )

    def finish(self) -> None:
        """Write the last chunk, the summary and the footer; stop the I/O thread; close the file."""
        self._finalize_chunk()
        self._submit(self._write_summary)
        self._jobs.put(None)
        self._thread.join()
        self._stream.close()
        if self._error is not None:
            raise RuntimeError(f"MCAP writer failed: {self._error}") from self._error

    def _write_summary(self) -> None:
        import struct
        import zlib

        from mcap.data_stream import RecordBuilder
        from mcap.opcode import Opcode
        from mcap.records import DataEnd, Footer, Statistics, SummaryOffset

        DataEnd(data_section_crc=0).write(self._rb)
        self._flush()
        summary_start = self._stream.tell()
        sb = RecordBuilder()
        groups = []

        def group(opcode, records):
            begin = sb.count
            for r in records:
                r.write(sb)
            if sb.count > begin:
                groups.append(SummaryOffset(opcode, summary_start + begin, sb.count - begin))

        group(Opcode.SCHEMA, self._schemas)
        group(Opcode.CHANNEL, self._channels)
        stats = Statistics(
            message_count=self._n_messages,
            schema_count=len(self._schemas),
            channel_count=len(self._channels),
            attachment_count=0,
            metadata_count=self._metadata_count,
            chunk_count=len(self._chunk_indexes),
            message_start_time=self._t_start or 0,
            message_end_time=self._t_end,
            channel_message_counts=dict(self._counts),
        )
        group(Opcode.STATISTICS, [stats])
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.METADATA_INDEX, self._metadata_indexes)
        summary_offset_start = summary_start + sb.count
        for g in groups:
            g.write(sb)
        summary = sb.end()
        crc = zlib.crc32(summary)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start), crc)
        self._stream.write(summary)
        Footer(summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=crc).write(
            self._rb
        )
        self._flush()
        self._stream.write(MAGIC)
