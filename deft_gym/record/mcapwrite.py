"""The episode log's MCAP writer: the ``mcap`` library's bytes, per chunk rather than per message.

:class:`LogWriter` writes the bytes that ``mcap.writer.Writer`` writes with the options of an
episode log (chunks of :data:`CHUNK_BYTES` with CRCs, data-section CRC, chunk and metadata
indexes, statistics, summary offsets; uncompressed or zstd), checked byte for byte by
``tests/record/test_mcapwrite.py``; but it takes messages as ready-made ``Message`` records in
batches (:meth:`LogWriter.add_batch`), not one Python call chain per message.

The bus tap that makes those records (:class:`deft_gym.record.recorder.RecordTap`) encodes each
payload with orjson where it is published: that costs less CPU in all than a snapshot of the
payload that the recorder process reads back and then encodes (issue 36). This module imports
only ``mcap`` and the standard library, so the recorder process starts quickly.
"""

from __future__ import annotations

import struct
import zlib
from bisect import bisect_right
from collections import Counter
from typing import Any, BinaryIO

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

CHUNK_BYTES = 32 * 1024  # [bytes] a chunk is closed once its records exceed this
MAGIC = struct.pack("<8B", 137, 77, 67, 65, 80, 48, 13, 10)
# a Message record's head: opcode, record length [bytes], channel id, sequence, log and publish time [ns]
MESSAGE_HEAD = struct.Struct("<BQHIQQ")
MESSAGE_FIELDS = MESSAGE_HEAD.size - 9
#: a channel of a log: (topic, role ("" for a viewer-only topic), schema name, schema data, schema
#: encoding, message encoding); the last two may be left out: ``jsonschema`` and ``json``
ChannelSpec = tuple
# a Chunk record's head up to its compression name: opcode, record length, message time range
# [ns], uncompressed size, its CRC-32, the name's length
_CHUNK_HEAD = struct.Struct("<BQQQQII")  # the record length counts the fields after opcode and length

# (message records - one bytes-like object, or two pieces per message: its record's head and its
# data -, their end offsets [bytes], their log times [ns], their channel ids)
RecordBatch = tuple[Any, list[int], list[int], list[int]]


class LogWriter:
    """An MCAP file with the bytes ``mcap.writer.Writer(stream, chunk_size, ZSTD or NONE,
    IndexType.CHUNK | IndexType.METADATA, enable_crcs=True, enable_data_crcs=True)`` writes
    for the same calls, messages added in batches of ready-made records."""

    def __init__(self, stream: BinaryIO, chunk_size: int = CHUNK_BYTES, compress: bool = False) -> None:
        self._out = stream
        self._limit = chunk_size
        self._compress = compress
        self._crc = 0  # CRC-32 of the data section so far
        self._chunk: list[Any] = []  # the open chunk's records, as pieces (bytes-like, not copied)
        self._chunk_len = 0  # their length [bytes]
        self._chunk_n = 0  # messages in it
        self._chunk_lo = self._chunk_hi = 0  # its message time range [ns]
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._counts: dict[int, int] = {}  # per channel, in the order of their first message
        self._count = self._lo = self._hi = 0  # messages, their time range [ns]
        self._chunk_count = self._metadata_count = 0
        self._chunk_index: list[ChunkIndex] = []
        self._metadata_index: list[MetadataIndex] = []

    def _emit(self, data: bytes) -> None:
        self._crc = zlib.crc32(data, self._crc)
        self._out.write(data)

    @staticmethod
    def _record(rec: Any) -> bytes:
        rb = RecordBuilder()
        rec.write(rb)
        return rb.end()

    def start(self, profile: str = "", library: str = "deft_gym") -> None:
        """The magic and the header record."""
        self._emit(MAGIC)
        self._emit(self._record(Header(profile, library)))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        """A schema record (in the open chunk); returns its id."""
        sid = len(self._schemas) + 1
        self._schemas[sid] = schema = Schema(id=sid, data=data, encoding=encoding, name=name)
        self._add_pieces([self._record(schema)])
        self._maybe_finish_chunk()
        return sid

    def register_channel(self, topic: str, message_encoding: str, schema_id: int,
                         metadata: dict[str, str] | None = None) -> int:
        """A channel record (in the open chunk); returns its id."""
        cid = len(self._channels) + 1
        self._channels[cid] = channel = Channel(id=cid, topic=topic, message_encoding=message_encoding,
                                                schema_id=schema_id, metadata=dict(metadata or {}))
        self._add_pieces([self._record(channel)])
        self._maybe_finish_chunk()
        return cid

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A metadata record (between chunks, indexed)."""
        offset = self._out.tell()
        rec = self._record(Metadata(name=name, metadata=data))
        self._metadata_count += 1
        self._metadata_index.append(MetadataIndex(offset=offset, length=len(rec), name=name))
        self._emit(rec)

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0) -> None:
        """One message (``mcap``'s signature)."""
        head = MESSAGE_HEAD.pack(Opcode.MESSAGE, MESSAGE_FIELDS + len(data), channel_id, sequence, log_time,
                                 publish_time)
        rec = head + data
        self.add_batch((rec, [len(rec)], [log_time], [channel_id]))

    def _add_pieces(self, pieces: list[Any]) -> None:
        self._chunk += pieces
        self._chunk_len += sum(map(len, pieces))

    def add_batch(self, batch: RecordBatch) -> None:
        """Messages as ``Message`` records: ``(records, end offsets, log times [ns], channel ids)``,
        chunked where ``mcap``'s writer would close a chunk (after the message that takes its
        records past the chunk size). ``records`` are one bytes-like object or a list of two
        pieces per message (its record's head and its data)."""
        data, ends, times, cids = batch
        n = len(ends)
        if n == 0:
            return
        pieces = isinstance(data, list)
        view = data if pieces else memoryview(data)
        i = start = 0
        while i < n:
            room = self._limit - self._chunk_len  # a chunk closes once its records exceed the limit
            j = bisect_right(ends, start + room, i)  # the first message that takes it past the limit
            last = min(j, n - 1)
            self._add_pieces(view[2 * i:2 * last + 2] if pieces else [view[start:ends[last]]])
            lo, hi = min(times[i:last + 1]), max(times[i:last + 1])
            if self._chunk_n == 0:
                self._chunk_lo, self._chunk_hi = lo, max(0, hi)
            else:
                self._chunk_lo, self._chunk_hi = min(self._chunk_lo, lo), max(self._chunk_hi, hi)
            self._chunk_n += last + 1 - i
            start, i = ends[last], last + 1
            if j < n:
                self._finish_chunk()
        lo, hi = min(times), max(times)
        self._lo = lo if self._count == 0 else min(self._lo, lo)
        self._hi = max(self._hi, hi)
        self._count += n
        counts = self._counts
        for cid, k in Counter(cids).items():
            counts[cid] = counts.get(cid, 0) + k

    def _maybe_finish_chunk(self) -> None:
        if self._chunk_len > self._limit:
            self._finish_chunk()

    def _finish_chunk(self) -> None:
        if self._chunk_n == 0:
            return
        self._chunk_count += 1
        raw = self._chunk[0] if len(self._chunk) == 1 else b"".join(self._chunk)
        size, crc = self._chunk_len, zlib.crc32(raw)
        if self._compress:
            import zstandard

            compression, packed = "zstd", zstandard.compress(raw)
        else:
            compression, packed = "", raw
        name = compression.encode()
        packed_size = len(packed)
        # the Chunk record (mcap.records.Chunk.write), its head packed here: the records are
        # not copied into it
        fields = 8 + 8 + 8 + 4 + 4 + len(name) + 8 + packed_size
        head = _CHUNK_HEAD.pack(Opcode.CHUNK, fields, self._chunk_lo, self._chunk_hi, size, crc,
                                len(name)) + name + struct.pack("<Q", packed_size)
        offset = self._out.tell()
        self._chunk_index.append(ChunkIndex(
            message_start_time=self._chunk_lo, message_end_time=self._chunk_hi, chunk_start_offset=offset,
            chunk_length=9 + fields, message_index_offsets={}, message_index_length=0, compression=compression,
            compressed_size=packed_size, uncompressed_size=size))
        self._emit(head)
        self._emit(packed)
        self._chunk = []
        self._chunk_len = self._chunk_n = self._chunk_lo = self._chunk_hi = 0

    def finish(self) -> None:
        """The last chunk, the data end, the summary (schemas, channels, statistics, chunk and
        metadata indexes), the summary offsets, the footer and the closing magic; the stream
        stays open."""
        self._finish_chunk()
        self._emit(self._record(DataEnd(self._crc)))
        summary_start = self._out.tell()
        rb = RecordBuilder()
        offsets: list[SummaryOffset] = []

        def group(opcode: int, records: list[Any]) -> None:
            begin = rb.count
            for rec in records:
                rec.write(rb)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + begin,
                                         group_length=rb.count - begin))

        stats = Statistics(attachment_count=0, channel_count=len(self._channels), channel_message_counts=self._counts,
                           chunk_count=self._chunk_count, message_count=self._count,
                           metadata_count=self._metadata_count, message_start_time=self._lo,
                           message_end_time=self._hi, schema_count=len(self._schemas))
        group(Opcode.SCHEMA, list(self._schemas.values()))
        group(Opcode.CHANNEL, list(self._channels.values()))
        group(Opcode.STATISTICS, [stats])
        group(Opcode.CHUNK_INDEX, self._chunk_index)
        group(Opcode.METADATA_INDEX, self._metadata_index)
        offset_start = summary_start + rb.count
        for off in offsets:
            off.write(rb)
        summary = rb.end()
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 8 + 8 + 4, summary_start if summary else 0, offset_start),
                         zlib.crc32(summary))
        self._out.write(summary)
        self._emit(self._record(Footer(summary_start=summary_start if summary else 0,
                                       summary_offset_start=offset_start, summary_crc=crc)))
        self._out.write(MAGIC)
