"""Reading episode logs: every message of the topics a mapping names, verified, from any MCAP file.

The reader scans the records in file order, so it needs neither the summary section nor the
footer, and it trusts nothing it can check:

- every chunk's content against its CRC-32; a chunk that fails is dropped whole (which of its
  messages is damaged cannot be known) and reported with its offset, its time range and the
  messages it held (topics and sequence numbers, as far as they can be read);
- when the file has a summary section (verified by its own CRC): every chunk against the chunk
  index (a record whose type byte or length was damaged is found at its indexed offset with its
  indexed length; if its content passes the CRC it is kept), and the message count of every
  channel against the statistics, so that nothing goes missing unnoticed;
- the data section against its CRC (damage outside the chunks' contents: a record header, a
  metadata record).

Records of unknown type are reported with their offset and skipped (their content is kept when
it is a chunk whose CRC passes: a damaged type byte). After a damaged record length the reader
resynchronises: at the next indexed chunk, else at the next offset where a record verifies.
A log cut short (a crashed run's ``.tmp``, a partial copy) yields every intact chunk before the
cut, and the time range of what is missing. :attr:`EpisodeLog.integrity` says what was lost;
logs without CRCs (written unchunked by earlier versions) are read as before, unverified.

Payloads are kept as the raw JSON bytes of the log and decoded on demand
(:meth:`TopicMessages.payload`); the raw bytes are what the frames file stores, so frames
round-trip bit-exactly. A message of a binary channel (ROS 1 bytes, :mod:`deft_gym.bus.ros1`) is
kept as the JSON a JSON channel would have held for it: the same bytes, whichever encoding a log
was written with.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import itertools
import json
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.records import Channel, Chunk, ChunkIndex, Metadata, Schema, Statistics

from deft_gym.bus import ros1
from deft_gym.bus.codec import decode
from deft_gym.bus.messages import NS_PER_S, VIEWER_TOPICS, log_start_ns
from extract.mapping import get_field

MCAP_MAGIC = b"\x89MCAP0\r\n"


class LogError(ValueError):
    """A log cannot be used at all. The message names the file and what was expected."""


@dataclass
class TopicMessages:
    """The messages of one topic, in publish order."""

    topic: str
    publish_ns: np.ndarray  # int64, non-decreasing
    seq: np.ndarray  # int64
    raw: list[bytes]
    _decoded: dict[int, Any] = field(default_factory=dict, repr=False)
    bad: set[int] = field(default_factory=set, repr=False)

    def __len__(self) -> int:
        return len(self.raw)

    def payload(self, i: int) -> Any:
        """Decoded payload of message ``i`` (cached; None when its bytes are not valid JSON)."""
        out = self._decoded.get(i)
        if out is None and i not in self.bad:
            try:
                out = decode(self.raw[i])
            except ValueError:
                self.bad.add(i)
                return None
            self._decoded[i] = out
        return out

    def fresh(self, i: int) -> Any:
        """A newly decoded copy of payload ``i`` (for handing to a planner that may mutate it);
        ValueError (and ``i`` noted in :attr:`bad`) when its bytes are not valid JSON."""
        try:
            return decode(self.raw[i])
        except ValueError:
            self.bad.add(i)
            raise

    def index_of_seq(self) -> dict[int, int]:
        """Sequence number -> message index (the last one when a number repeats)."""
        return {int(s): i for i, s in enumerate(self.seq.tolist())}


@dataclass
class Damage:
    """One damaged, unknown or missing part of a log: where (byte offset, time range [ns]) and
    which messages it cost (per topic: count and the sequence numbers that could be read)."""

    offset: int
    kind: str  #: crc | record-type | record-length | unknown-record | truncated | data-crc | summary | count
    detail: str
    start_ns: int | None = None
    end_ns: int | None = None
    lost: dict[str, list[int]] = field(default_factory=dict)
    unreadable: int = 0  #: further messages lost whose topic could not be read
    partial: bool = False  #: the damaged content stopped parsing before its end: it may have held more

    @property
    def messages(self) -> int:
        return sum(len(v) for v in self.lost.values()) + self.unreadable

    def text(self) -> str:
        when = ""
        if self.start_ns is not None and self.end_ns is None:
            when = f" (t >= {self.start_ns / NS_PER_S:.3f} s)"
        elif self.start_ns is not None:
            when = f" (t {self.start_ns / NS_PER_S:.3f}-{self.end_ns / NS_PER_S:.3f} s)"
        out = f"offset {self.offset}{when}: {self.detail}"
        if self.lost or self.unreadable:
            parts = [f"{t} {len(v)} ({_seq_ranges(v)})" if v and v[0] >= 0 else f"{t} {len(v)}"
                     for t, v in sorted(self.lost.items())]
            if self.unreadable:
                parts.append(f"{self.unreadable} unreadable")
            out += f"; {self.messages} message(s) lost: " + ", ".join(parts)
        return out

    def as_dict(self) -> dict[str, Any]:
        return {"offset": self.offset, "kind": self.kind, "detail": self.detail,
                "start_s": None if self.start_ns is None else self.start_ns / NS_PER_S,
                "end_s": None if self.end_ns is None else self.end_ns / NS_PER_S,
                "lost": {t: len(v) for t, v in self.lost.items()}, "unreadable": self.unreadable,
                "text": self.text()}


def _seq_ranges(seqs: list[int]) -> str:
    """``[3, 4, 5, 9]`` -> ``"seq 3-5, 9"``."""
    out: list[str] = []
    for s in sorted(seqs):
        if out and out[-1][1] == s - 1:
            out[-1] = (out[-1][0], s)
        else:
            out.append((s, s))  # type: ignore[arg-type]
    text = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in out)  # type: ignore[misc]
    return "seq " + (text if len(text) < 80 else text[:77] + "...")


@dataclass
class Integrity:
    """What verifying a log found: whether it carries CRCs and a summary, how many chunks
    passed, every damage, and the message count per topic found intact vs written (the
    summary's statistics; None without a summary)."""

    crcs: bool = False
    summary: bool = False
    chunks: int = 0
    chunks_ok: int = 0
    damage: list[Damage] = field(default_factory=list)
    found: dict[str, int] = field(default_factory=dict)
    expected: dict[str, int] | None = None

    @property
    def intact(self) -> bool:
        return not self.damage

    def lost(self) -> dict[str, int]:
        """Messages lost per topic (written - found when the statistics are known)."""
        if self.expected is not None:
            return {t: n - self.found.get(t, 0) for t, n in self.expected.items() if n > self.found.get(t, 0)}
        out: dict[str, int] = {}
        for d in self.damage:
            for t, v in d.lost.items():
                out[t] = out.get(t, 0) + len(v)
        return out

    def as_dict(self) -> dict[str, Any]:
        return {"crcs": self.crcs, "summary": self.summary, "chunks": self.chunks, "chunks_ok": self.chunks_ok,
                "intact": self.intact, "messages_found": sum(self.found.values()),
                "messages_written": sum(self.expected.values()) if self.expected is not None else None,
                "lost": self.lost(), "damage": [d.as_dict() for d in self.damage]}


@dataclass
class EpisodeLog:
    """What a log holds for extraction."""

    path: Path
    topics: dict[str, TopicMessages]
    metadata: dict[str, dict[str, Any]]
    channel_roles: dict[str, str]
    status: str = "complete"
    warnings: list[str] = field(default_factory=list)
    integrity: Integrity = field(default_factory=Integrity)

    @property
    def truncated(self) -> bool:
        return self.status != "complete"

    def episode_meta(self) -> dict[str, Any]:
        """The deft_gym episode record (empty for foreign logs)."""
        return self.metadata.get("deft_gym.episode", {})


def _meta_values(md: Metadata) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in md.metadata.items():
        try:
            out[k] = json.loads(v)
        except ValueError:
            out[k] = v
    return out


class _Lost(dict):  # type: ignore[type-arg]
    """Lost messages per topic, and whether the damaged content they were read from parsed to
    its end (when it did not, it may have held more)."""

    partial = False


class _Scan:
    """A direct scan of MCAP records in a buffer: messages of the wanted channels are sliced out
    with one ``struct.unpack_from`` each (the generic reader parses every record into objects,
    ~5x slower); channels, metadata and compressed chunks go through the ``mcap`` record
    classes. Every chunk is verified (CRC, and against the summary's chunk index when there is
    one) before its messages are taken."""

    def __init__(self, wanted: set[str], summary: _Summary | None) -> None:
        self.wanted = wanted
        self.summary = summary
        self.chan_topic: dict[int, str] = dict(summary.channels) if summary else {}
        self.schemas: dict[int, tuple[str, bytes]] = {}
        # a binary channel's decoder (its messages are kept as the JSON a JSON channel holds)
        self.chan_decode: dict[int, Any] = dict(summary.decoders) if summary else {}
        self.roles: dict[str, str] = dict(summary.roles) if summary else {}
        self.rows: dict[str, tuple[list[int], list[int], list[bytes]]] = {t: ([], [], []) for t in wanted}
        self.metadata: dict[str, dict[str, Any]] = {}
        self.counts: dict[int, int] = {}
        self.records = 0
        self.footer = False
        self.data_end: tuple[int, int] | None = None  # (offset, data section CRC)
        self.integrity = Integrity(summary=summary is not None)
        self.top_messages = 0  # messages outside chunks (unchunked logs: no CRCs)
        self.last_ok = -1  # offset of the last chunk that verified
        self.last_damage = -1  # offset of the last damaged record
        self.tail_unknown = False  # a damaged record may have held messages no later one shows

    # -- the data section ------------------------------------------------------------------------
    def run(self, buf: bytes, pos: int, end: int) -> str | None:
        """Scan the top-level records of ``buf[pos:end]``; returns why it stopped before the
        footer (None when it reached it)."""
        index = self.summary.chunk_at if self.summary else {}
        while pos < end:
            if pos + 9 > end:
                return self._cut(pos, end, f"{end - pos} stray bytes at the end")
            op = buf[pos]
            (length,) = struct.unpack_from("<Q", buf, pos + 1)
            ci = index.get(pos)
            if ci is not None:
                pos = self._indexed_chunk(buf, pos, op, length, ci, end)
                continue
            body, stop = pos + 9, pos + 9 + length
            if op == _CHUNK and (stop > end or chunk_head(buf, body, stop) is None):
                real = _chunk_stop(buf, body, end)
                if real is not None and real != stop and self._chunk(buf, body, real, pos, quiet=True):
                    self._note(pos, "record-length", f"record length damaged ({length}; the chunk's own fields say "
                               f"{real - body}): its content passes the CRC: kept", *struct.unpack_from("<QQ", buf, body))
                    pos = real
                    continue
            if op not in _KNOWN or stop > end:
                nxt = self._next_indexed(pos)
                if op == _CHUNK and stop > end and nxt is None:
                    return self._cut(pos, end, "the file ends inside a chunk", buf)
                if op in _KNOWN or op == 0:
                    why = f"record of type 0x{op:02x} at offset {pos} claims {length} bytes, past the end of the file"
                    kind = "record-length"
                else:
                    why, kind = f"record of unknown type 0x{op:02x} ({length} bytes)", "unknown-record"
                    if stop <= end and self._chunk(buf, body, stop, pos, quiet=True):
                        self._note(pos, "record-type", f"record type byte damaged (0x{op:02x}); its content is a "
                                   "chunk whose CRC verifies: kept", *struct.unpack_from("<QQ", buf, body))
                        pos = stop
                        continue
                resume = nxt if nxt is not None else self._resync(buf, pos + 1, end)
                if resume is None:
                    if kind == "unknown-record" and stop <= end:  # MCAP: skip records of unknown type
                        self._note(pos, kind, why + ": skipped")
                        pos = stop
                        continue
                    return self._cut(pos, end, why + "; nothing verifiable after it", buf)
                if kind == "unknown-record" and stop == resume:
                    self._note(pos, kind, why + ": skipped", lost=self._peek_lost(buf, body, stop))
                else:
                    self._note(pos, kind, why + f"; resynchronised at offset {resume} ({resume - pos} bytes skipped)",
                               lost=self._peek_lost(buf, body, min(resume, end)) if op == _CHUNK else None)
                pos = resume
                continue
            if op == _CHUNK:
                self._chunk(buf, body, stop, pos)
            elif op == _MESSAGE:
                self._message(buf, body, stop)
                self.top_messages += 1
            elif op == _CHANNEL:
                self._channel(buf, body, stop)
            elif op == _SCHEMA:
                self._schema(buf, body, stop)
            elif op == _METADATA:
                try:
                    md = Metadata.read(ReadDataStream(io.BytesIO(buf[body:stop])))
                    self.metadata[md.name] = _meta_values(md)
                except Exception as exc:
                    self._note(pos, "unknown-record", f"metadata record does not parse ({type(exc).__name__})")
            elif op == _DATA_END:
                self.data_end = (pos, struct.unpack_from("<I", buf, body)[0] if length >= 4 else 0)
            elif op == _FOOTER:
                self.footer = True
                return None
            self.records += 1
            pos = stop
        return None

    def _message(self, buf: bytes, body: int, stop: int) -> None:
        cid, seq, _, pub = struct.unpack_from("<HIQQ", buf, body)
        self.counts[cid] = self.counts.get(cid, 0) + 1
        topic = self.chan_topic.get(cid)
        if topic is not None and topic in self.wanted:
            r = self.rows[topic]
            r[0].append(pub)
            r[1].append(seq)
            data = buf[body + 22:stop]
            if (binary := self.chan_decode.get(cid)) is not None:
                with contextlib.suppress(ValueError):  # else kept as it is: it then reads as a bad payload
                    data = ros1.json_bytes(binary, data)
            r[2].append(data)

    def _channel(self, buf: bytes, body: int, stop: int) -> None:
        ch = Channel.read(ReadDataStream(io.BytesIO(buf[body:stop])))
        self.roles[ch.topic] = ch.metadata.get("role", "")
        self.chan_topic[ch.id] = ch.topic
        # (a schema this scan has not seen, in a damaged chunk: the summary's decoder stands)
        self.chan_decode[ch.id] = _binary_decoder(ch, self.schemas) or self.chan_decode.get(ch.id)

    def _schema(self, buf: bytes, body: int, stop: int) -> None:
        """A schema record (the first of each id counts: the summary's repeat them). One that does
        not parse is passed over: a binary channel without its schema reads as bad payloads."""
        try:
            sc = Schema.read(ReadDataStream(io.BytesIO(buf[body:stop])))
        except Exception:  # any damage of the record's fields
            return
        self.schemas.setdefault(sc.id, (sc.encoding, sc.data))

    def _chunk(self, buf: bytes, body: int, stop: int, pos: int, quiet: bool = False) -> bool:
        """Verify one chunk and take its messages; whether it was intact. A damaged one is noted
        here unless ``quiet`` (the caller notes it, with more to say)."""
        head = chunk_head(buf, body, stop)
        if head is None:
            if not quiet:
                self.integrity.chunks += 1
                self._note(pos, "record-length", "chunk fields do not add up to its record length (or it does "
                           "not decompress): dropped")
            return False
        t0, t1, crc, data = head
        self.integrity.crcs |= bool(crc)
        if crc and zlib.crc32(data) != crc:
            if not quiet:
                self.integrity.chunks += 1
                salvaged = self._salvage_channels(data)
                self._note(pos, "crc", "chunk content fails its CRC-32: dropped" + salvaged, t0, t1, self._lost_in(data))
            return False
        if quiet and not crc:  # the content of a damaged record that nothing verifies: not taken
            return False
        self.integrity.chunks += 1
        why = self._records(data)
        if why is not None:
            self._note(pos, "crc", f"chunk content does not parse ({why})", t0, t1)
            return False
        self.integrity.chunks_ok += 1
        self.last_ok = max(self.last_ok, pos)
        return True

    def _records(self, data: bytes) -> str | None:
        """Records inside a verified chunk (messages, channels, schemas)."""
        pos, end = 0, len(data)
        while pos < end:
            if pos + 9 > end:
                return f"{end - pos} stray bytes"
            op = data[pos]
            (length,) = struct.unpack_from("<Q", data, pos + 1)
            body, stop = pos + 9, pos + 9 + length
            if stop > end:
                return f"record at offset {pos} runs past the chunk"
            if op == _MESSAGE:
                self._message(data, body, stop)
            elif op == _CHANNEL:
                self._channel(data, body, stop)
            elif op == _SCHEMA:
                self._schema(data, body, stop)
            self.records += 1
            pos = stop
        return None

    def _indexed_chunk(self, buf: bytes, pos: int, op: int, length: int, ci: ChunkIndex, end: int) -> int:
        """A chunk the summary indexes at ``pos``: checked against the index (type byte, length),
        read with the indexed length; returns where the next record starts."""
        stop = pos + ci.chunk_length
        notes = []
        if op != _CHUNK:
            notes.append(f"record type byte damaged (0x{op:02x}, the chunk index says a chunk)")
        if length != ci.chunk_length - 9:
            notes.append(f"record length damaged ({length}, the chunk index says {ci.chunk_length - 9})")
        if stop > end:
            return self._cut_at(pos, end, "the file ends inside an indexed chunk", ci)
        ok = self._chunk(buf, pos + 9, stop, pos, quiet=bool(notes))
        if notes:
            if ok:
                self._note(pos, "record-type" if op != _CHUNK else "record-length",
                           "; ".join(notes) + ": read at its indexed offset and length, its content passes the CRC: kept",
                           ci.message_start_time, ci.message_end_time)
            else:
                head = chunk_head(buf, pos + 9, stop)
                self._note(pos, "record-type" if op != _CHUNK else "record-length", "; ".join(notes)
                           + " and its content fails the CRC: dropped", ci.message_start_time, ci.message_end_time,
                           self._lost_in(head[3]) if head else None)
        return stop

    def _next_indexed(self, pos: int) -> int | None:
        if not self.summary:
            return None
        later = [o for o in self.summary.chunk_at if o > pos]
        return min(later) if later else self.summary.data_end

    def _resync(self, buf: bytes, pos: int, end: int) -> int | None:
        """The next offset from ``pos`` where a record verifies: a chunk whose CRC passes, a
        metadata record that parses and is followed by a known record, the data end."""
        q = pos
        while q < end:
            cands = [i for i in (buf.find(b"\x06", q, end), buf.find(b"\x0c", q, end), buf.find(b"\x0f", q, end))
                     if i >= 0]
            if not cands:
                return None
            q = min(cands)
            if q + 9 <= end:
                (length,) = struct.unpack_from("<Q", buf, q + 1)
                stop = q + 9 + length
                if stop <= end:
                    op = buf[q]
                    if op == _CHUNK:
                        head = chunk_head(buf, q + 9, stop)
                        if head is not None and head[2] and zlib.crc32(head[3]) == head[2]:
                            return q
                    elif op == _DATA_END and length == 4 and stop + 9 <= end and buf[stop] in _KNOWN:
                        return q
                    elif op == _METADATA and stop + 9 <= end and buf[stop] in _KNOWN:
                        try:
                            Metadata.read(ReadDataStream(io.BytesIO(buf[q + 9:stop])))
                            return q
                        except Exception:
                            pass
            q += 1
        return None

    def _salvage_channels(self, data: bytes) -> str:
        """Channel records of a damaged chunk whose topic the episode record lists (a log without
        its summary knows its channels only from them): later, intact chunks stay readable."""
        episode = self.metadata.get("deft_gym.episode", {})
        listed = set((episode.get("topics") or {}).values())
        if episode:  # a deft_gym log also has the viewer topics (Foxglove scene)
            listed |= set(VIEWER_TOPICS)
        taken = []
        for op, body, stop in walk_records(data):
            if op == _CHANNEL:
                try:
                    ch = Channel.read(ReadDataStream(io.BytesIO(data[body:stop])))
                except Exception:
                    ch = None
                if ch is not None and ch.id not in self.chan_topic and ch.topic in listed:
                    self._channel(data, body, stop)
                    taken.append(ch.topic)
        return f" (its {len(taken)} channel record(s) kept: their topics match the episode record)" if taken else ""

    def _lost_in(self, data: bytes) -> dict[str, list[int]]:
        """Topics and sequence numbers of the messages in a damaged chunk, as far as they read
        (``.partial``: its records stopped parsing before the end)."""
        lost = _Lost()
        last = 0
        for op, body, stop in walk_records(data):
            last = stop
            if op == _MESSAGE and stop - body >= 22:
                cid, seq = struct.unpack_from("<HI", data, body)
                lost.setdefault(self.chan_topic.get(cid, f"channel {cid}"), []).append(seq)
        lost.partial = last != len(data)
        return lost

    def _peek_lost(self, buf: bytes, body: int, stop: int) -> dict[str, list[int]] | None:
        head = chunk_head(buf, body, stop)
        return self._lost_in(head[3]) if head else None

    def _note(self, pos: int, kind: str, detail: str, t0: int | None = None, t1: int | None = None,
              lost: dict[str, list[int]] | None = None) -> None:
        self.integrity.damage.append(Damage(pos, kind, detail, t0, t1, lost or {},
                                            partial=bool(getattr(lost, "partial", False))))
        if pos >= 0:
            self.last_damage = max(self.last_damage, pos)

    def _cut(self, pos: int, end: int, why: str, buf: bytes | None = None) -> str:
        """The file ends at ``end`` inside the record at ``pos`` (a chunk header still tells the
        time range of what is missing)."""
        t0 = None
        if buf is not None and buf[pos] == _CHUNK and pos + 9 + 16 <= end:
            (t0,) = struct.unpack_from("<Q", buf, pos + 9)
        rest = "" if t0 is None else f"; every message from t={t0 / NS_PER_S:.3f} s on is missing"
        self._note(pos, "truncated", f"{why} (offset {pos}, {end - pos} bytes there){rest}", t0, None)
        return f"{why} at offset {pos}"

    def _cut_at(self, pos: int, end: int, why: str, ci: ChunkIndex) -> int:
        self._note(pos, "truncated", f"{why} (offset {pos}, {end - pos} of {ci.chunk_length} bytes there)",
                   ci.message_start_time, ci.message_end_time)
        return end


_MESSAGE, _CHANNEL, _METADATA, _CHUNK, _FOOTER, _DATA_END, _SCHEMA = 0x05, 0x04, 0x0C, 0x06, 0x02, 0x0F, 0x03
_KNOWN = set(range(0x01, 0x11))  # the record types of MCAP v0 (header .. data end)


def walk_records(data: bytes) -> Iterator[tuple[int, int, int]]:
    """``(record type, body start, body end)`` of the records in ``data``, up to the first that
    is not of a known type or does not fit (the records of a chunk that failed its CRC)."""
    pos, end = 0, len(data)
    while pos + 9 <= end:
        op = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        if pos + 9 + length > end or op not in _KNOWN:
            return
        yield op, pos + 9, pos + 9 + length
        pos += 9 + length


def _chunk_stop(buf: bytes, body: int, end: int) -> int | None:
    """Where a chunk whose record starts its body at ``body`` ends by its own fields (not its
    record length), or None when they do not fit in ``buf[:end]``."""
    try:
        clen = struct.unpack_from("<I", buf, body + 28)[0]
        (dlen,) = struct.unpack_from("<Q", buf, body + 32 + clen)
    except struct.error:
        return None
    stop = body + 32 + clen + 8 + dlen
    return stop if stop <= end else None


def chunk_head(buf: bytes, body: int, stop: int) -> tuple[int, int, int, bytes] | None:
    """``(start ns, end ns, CRC, uncompressed content)`` of a chunk body, or None when its
    fields do not add up to the record (a damaged length) or it cannot be decompressed."""
    try:
        t0, t1, _size, crc, clen = struct.unpack_from("<QQQII", buf, body)
        at = body + 32
        compression = bytes(buf[at:at + clen]).decode()
        (dlen,) = struct.unpack_from("<Q", buf, at + clen)
        start = at + clen + 8
        if start + dlen != stop:
            return None
        data = bytes(buf[start:stop])
        if compression:
            data = _decompress(Chunk(compression=compression, data=data, message_start_time=t0,
                                     message_end_time=t1, uncompressed_crc=crc, uncompressed_size=_size))
        return t0, t1, crc, data
    except Exception:  # struct, UTF-8, zstd and lz4 errors alike
        return None


@dataclass
class _Summary:
    """What the summary section says (read only when its CRC passes)."""

    channels: dict[int, str]
    roles: dict[str, str]
    chunk_at: dict[int, ChunkIndex]
    statistics: Statistics | None
    data_end: int
    decoders: dict[int, Any] = field(default_factory=dict)  # per channel: :func:`_binary_decoder`


def read_summary(buf: bytes) -> tuple[_Summary | None, Damage | None]:
    """The summary section via the footer at the end of the file: ``(summary, None)``, or
    ``(None, damage)`` when it is there but does not verify, or ``(None, None)`` without one."""
    n = len(buf)
    foot = n - 8 - 29
    if n < 8 + 29 + 8 or buf[n - 8:] != MCAP_MAGIC or buf[foot] != _FOOTER:
        return None, None
    length, start, offsets, crc = struct.unpack_from("<QQQI", buf, foot + 1)
    if length != 20 or not start:
        return None, None
    if not 8 <= start <= foot:
        return None, Damage(foot, "summary", f"footer names a summary at offset {start}, outside the file")
    if crc and zlib.crc32(struct.pack("<BQQQ", _FOOTER, 20, start, offsets), zlib.crc32(buf[start:foot])) != crc:
        return None, Damage(start, "summary", "summary section fails its CRC-32: not used (chunks are verified "
                            "by their own CRCs, message counts cannot be checked)")
    channels: dict[int, str] = {}
    roles: dict[str, str] = {}
    schemas: dict[int, tuple[str, bytes]] = {}
    decoders: dict[int, Any] = {}
    chunk_at: dict[int, ChunkIndex] = {}
    stats = None
    pos = start
    while pos + 9 <= foot:
        op = buf[pos]
        (length,) = struct.unpack_from("<Q", buf, pos + 1)
        body = ReadDataStream(io.BytesIO(buf[pos + 9:pos + 9 + length]))
        if op == _SCHEMA:
            sc = Schema.read(body)
            schemas[sc.id] = (sc.encoding, sc.data)
        elif op == _CHANNEL:
            ch = Channel.read(body)
            channels[ch.id] = ch.topic
            roles[ch.topic] = ch.metadata.get("role", "")
            decoders[ch.id] = _binary_decoder(ch, schemas)
        elif op == 0x0B:
            stats = Statistics.read(body)
        elif op == 0x08:
            ci = ChunkIndex.read(body)
            chunk_at[ci.chunk_start_offset] = ci
        pos += 9 + length
    return _Summary(channels, roles, chunk_at, stats, _data_end_offset(buf, start), decoders), None


def _binary_decoder(channel: Channel, schemas: dict[int, tuple[str, bytes]]) -> Any:
    """The decoder of a channel whose messages are ROS 1 bytes (:mod:`deft_gym.bus.ros1`), None
    for JSON (and for a binary channel without a schema it can read: its messages read as bad)."""
    if channel.message_encoding != ros1.MESSAGE_ENCODING:
        return None
    encoding, data = schemas.get(channel.schema_id, ("", b""))
    try:
        return ros1.payload_decoder(channel.message_encoding, encoding, data)
    except ValueError:
        return None


def _data_end_offset(buf: bytes, summary_start: int) -> int:
    """Offset of the data end record (13 bytes just before the summary)."""
    return summary_start - 13


def _decompress(chunk: Chunk) -> bytes:
    if chunk.compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
    if chunk.compression == "lz4":
        import lz4.frame  # type: ignore[import-not-found]

        return lz4.frame.decompress(chunk.data)
    raise ValueError(f"unsupported chunk compression {chunk.compression!r}")


def log_id(path: Path | str) -> str:
    """A short id of a log file: the first 8 hex digits of its SHA-256 (two logs differ in
    their bytes - every log records its own start time - so their ids differ)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:8]


def read_log(path: Path | str, topics: list[str], seq_field: str | None = None) -> EpisodeLog:
    """Read the messages of ``topics`` (and all metadata records) from an MCAP file, verified
    (see the module docstring).

    Raises :class:`LogError` when the file is missing or not MCAP. Damage is reported in
    :attr:`EpisodeLog.integrity`, ``status`` (``complete``, ``damaged: ...``, ``truncated: ...``)
    and one warning per damage; every intact message is kept."""
    path = Path(path)
    try:
        buf = path.read_bytes()
    except OSError as exc:
        raise LogError(f"{path}: cannot read log: {exc.strerror or exc}") from None
    if buf[:len(MCAP_MAGIC)] != MCAP_MAGIC:
        what = "empty file" if not buf else "bad magic bytes"
        raise LogError(f"{path}: not an MCAP file ({what}); expected an episode log (.mcap)")
    summary, bad_summary = read_summary(buf)
    scan = _Scan(set(topics), summary)
    integ = scan.integrity
    if bad_summary is not None:
        integ.damage.append(bad_summary)
    try:
        why = scan.run(buf, len(MCAP_MAGIC), summary.data_end if summary else len(buf))
        if summary is not None and why is None:
            scan.run(buf, summary.data_end, summary.data_end + 13)
            scan.footer = True  # read (and verified with the summary) first
    except Exception as exc:  # a record body the mcap classes cannot read
        why = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        scan._note(-1, "unknown-record", f"reading stopped: {why}")
    _check_totals(scan, buf, summary)
    if integ.expected is None and integ.damage:
        _sequence_gaps(scan)
    start = log_start_ns(scan.metadata.get("deft_gym.episode"))  # log_time = epoch start + sim time
    for d in integ.damage:
        d.start_ns = None if d.start_ns is None else d.start_ns - start
        d.end_ns = None if d.end_ns is None else d.end_ns - start
    out: dict[str, TopicMessages] = {}
    for topic, (pub, seq, raw) in scan.rows.items():
        pub_a = np.asarray(pub, dtype=np.int64) - start
        seq_a = np.asarray(seq, dtype=np.int64)
        if len(pub_a) > 1 and np.any(np.diff(pub_a) < 0):  # stable: keep file order among ties
            order = np.argsort(pub_a, kind="stable")
            pub_a, seq_a, raw = pub_a[order], seq_a[order], [raw[i] for i in order]
        out[topic] = TopicMessages(topic, pub_a, seq_a, raw)
    status = _status(integ, scan)
    log = EpisodeLog(path, out, scan.metadata, scan.roles, status, integrity=integ)
    if seq_field:
        for tm in out.values():
            seqs = [get_field(tm.payload(i), seq_field) for i in range(len(tm))]
            tm.seq = np.asarray([s if isinstance(s, int) else -1 for s in seqs], dtype=np.int64)
    for d in integ.damage:
        log.warnings.append(f"{path}: {d.text()}")
    if integ.damage:
        found = sum(integ.found.values())
        written = f" of {sum(integ.expected.values())} written" if integ.expected is not None else ""
        lost = ", ".join(f"{t} {n}" for t, n in sorted(integ.lost().items())) or "none known"
        log.warnings.append(f"{path}: {status}; extracting the {found} intact messages{written} (lost: {lost})")
    elif not integ.crcs and scan.top_messages:
        log.warnings.append(f"{path}: the log carries no CRCs (written unchunked): its messages are not verified")
    return log


def _check_totals(scan: _Scan, buf: bytes, summary: _Summary | None) -> None:
    """Message counts per topic against the summary's statistics, and the data section CRC."""
    integ = scan.integrity
    for cid, n in scan.counts.items():
        topic = scan.chan_topic.get(cid, f"channel {cid}")
        integ.found[topic] = integ.found.get(topic, 0) + n
    if summary is not None and summary.statistics is not None:
        expected = {scan.chan_topic.get(cid, summary.channels.get(cid, f"channel {cid}")): n
                    for cid, n in summary.statistics.channel_message_counts.items()}
        integ.expected = expected
        accounted = {t: integ.found.get(t, 0) for t in expected}
        for d in integ.damage:
            for t, v in d.lost.items():
                accounted[t] = accounted.get(t, 0) + len(v)
        missing = {t: n - accounted.get(t, 0) for t, n in expected.items() if n > accounted.get(t, 0)}
        if missing:
            integ.damage.append(Damage(-1, "count", "the summary's statistics count more messages than the file "
                                       "holds, intact or in damaged chunks",
                                       lost={t: [-1] * n for t, n in missing.items()}))
    if scan.data_end is not None and scan.data_end[1]:
        at, crc = scan.data_end
        if zlib.crc32(buf[:at]) != crc and not any(d.kind != "count" for d in integ.damage):
            integ.damage.append(Damage(at, "data-crc", "the data section fails its CRC-32 though every chunk passes "
                                       "its own: damage outside the chunks' contents (a record header or a "
                                       "metadata record)"))


def _sequence_gaps(scan: _Scan) -> None:
    """Without the summary's statistics, what a damaged record held is known only as far as its
    content still parses (a damaged message header in a chunk hides every message after it: 3
    reported lost where 46 were). A topic whose messages carry consecutive sequence numbers
    tells the rest: the numbers missing between those read are lost messages too - noted as one
    more problem (``count``) so that the loss stated is every message missing inside the log
    (what a truncation cut from its end stays unknown)."""
    counted: dict[str, set[int]] = {}
    for d in scan.integrity.damage:
        for t, v in d.lost.items():
            counted.setdefault(t, set()).update(s for s in v if s >= 0)
    missing: dict[str, list[int]] = {}
    bus = "deft_gym.episode" in scan.metadata  # a deft_gym log: every bus topic is numbered from 0
    for topic, (_, seq, _) in scan.rows.items():
        s = np.unique(np.asarray(seq, dtype=np.int64))
        numbered = bus and (bool(scan.roles.get(topic)) or topic in VIEWER_TOPICS)  # from 0, one by one
        if numbered and not len(s) and not counted.get(topic):
            missing[topic] = [0]  # a topic of which nothing was read: its first message at least is lost
            continue
        if len(s) < (1 if numbered else 3):
            continue
        d = np.diff(s)
        if len(d) and (np.mean(d == 1) < 0.9 or int(d.max()) > 100_000):  # not numbered one by one
            continue
        if numbered and 0 < s[0] <= 100_000:
            s = np.concatenate([[-1], s])  # the numbers before the first one read
        extra = [int(x) for a, b in itertools.pairwise(s) if b - a > 1 for x in range(int(a) + 1, int(b))
                 if int(x) not in counted.get(topic, ())]
        if extra:
            missing[topic] = extra
    if missing:
        scan.integrity.damage.append(Damage(-1, "count", "messages missing from their topic's consecutive sequence "
                                            "numbers, which no damaged record showed (a damaged record's content "
                                            "hid them)", lost=missing))
    if scan.last_damage > scan.last_ok and any(d.partial for d in scan.integrity.damage):
        # a damaged record after the last intact chunk whose content stopped parsing: what it held
        # after that point has no later message to show it
        scan.tail_unknown = True


def _status(integ: Integrity, scan: _Scan) -> str:
    if not integ.damage and not scan.footer:
        integ.damage.append(Damage(-1, "truncated", "no footer: the file ends without the end of the log"))
    if not integ.damage:
        return "complete"
    kinds = sorted({d.kind for d in integ.damage})
    head = "truncated" if "truncated" in kinds else "damaged"
    n = sum(integ.lost().values())
    unknown = integ.expected is None and (getattr(scan, "tail_unknown", False) or any(
        d.kind == "truncated" or (d.kind in ("crc", "record-length") and not d.messages and "dropped" in d.detail)
        for d in integ.damage))
    return f"{head}: {len(integ.damage)} problem(s) ({', '.join(kinds)}); {n}{'+' if unknown else ''} message(s) lost"
