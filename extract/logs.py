"""Reading episode logs: every message of the topics a mapping names, from any MCAP file.

The reader scans the records in file order, so it needs neither the summary section nor the
footer: a log cut short (a crashed run's ``.tmp``, a partial copy) yields everything before the
damage, and :attr:`EpisodeLog.status` says where reading stopped. Payloads are kept as the raw
JSON bytes of the log and decoded on demand (:meth:`TopicMessages.payload`); the raw bytes are
what the frames file stores, so frames round-trip bit-exactly.
"""

from __future__ import annotations

import io
import json
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.records import Channel, Chunk, Metadata

from deft_gym.bus.codec import decode
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
class EpisodeLog:
    """What a log holds for extraction."""

    path: Path
    topics: dict[str, TopicMessages]
    metadata: dict[str, dict[str, Any]]
    channel_roles: dict[str, str]
    status: str = "complete"
    warnings: list[str] = field(default_factory=list)

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


class _Scan:
    """A direct scan of MCAP records in a buffer: messages of the wanted channels are sliced out
    with one ``struct.unpack_from`` each (the generic reader parses every record into objects,
    ~5x slower); channels, metadata and compressed chunks go through the ``mcap`` record
    classes."""

    def __init__(self, wanted: set[str]) -> None:
        self.wanted = wanted
        self.chan_topic: dict[int, str] = {}
        self.roles: dict[str, str] = {}
        self.rows: dict[str, tuple[list[int], list[int], list[bytes]]] = {t: ([], [], []) for t in wanted}
        self.metadata: dict[str, dict[str, Any]] = {}
        self.records = 0
        self.footer = False

    def run(self, buf: bytes, pos: int, end: int) -> str | None:
        """Scan records in ``buf[pos:end]``; returns why it stopped early, or None."""
        unpack = struct.unpack_from
        chan_topic, rows = self.chan_topic, self.rows
        while pos < end:
            if pos + 9 > end:
                return f"{end - pos} stray bytes at offset {pos}"
            op = buf[pos]
            (length,) = unpack("<Q", buf, pos + 1)
            body, stop = pos + 9, pos + 9 + length
            if stop > end:
                return f"record at offset {pos} runs past the end of the data"
            if op == _MESSAGE:
                cid, seq, _, pub = unpack("<HIQQ", buf, body)
                topic = chan_topic.get(cid)
                if topic is not None:
                    r = rows[topic]
                    r[0].append(pub)
                    r[1].append(seq)
                    r[2].append(buf[body + 22:stop])
            elif op == _CHANNEL:
                ch = Channel.read(ReadDataStream(io.BytesIO(buf[body:stop])))
                self.roles[ch.topic] = ch.metadata.get("role", "")
                if ch.topic in self.wanted:
                    chan_topic[ch.id] = ch.topic
            elif op == _METADATA:
                md = Metadata.read(ReadDataStream(io.BytesIO(buf[body:stop])))
                self.metadata[md.name] = _meta_values(md)
            elif op == _CHUNK:
                chunk = Chunk.read(ReadDataStream(io.BytesIO(buf[body:stop])))
                data = chunk.data if chunk.compression == "" else _decompress(chunk)
                why = self.run(data, 0, len(data))
                if why is not None:
                    return f"chunk at offset {pos}: {why}"
            elif op == _FOOTER:
                self.footer = True
                return None
            self.records += 1
            pos = stop
        return None


_MESSAGE, _CHANNEL, _METADATA, _CHUNK, _FOOTER = 0x05, 0x04, 0x0C, 0x06, 0x02


def _decompress(chunk: Chunk) -> bytes:
    if chunk.compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
    if chunk.compression == "lz4":
        import lz4.frame  # type: ignore[import-not-found]

        return lz4.frame.decompress(chunk.data)
    raise ValueError(f"unsupported chunk compression {chunk.compression!r}")


def read_log(path: Path | str, topics: list[str], seq_field: str | None = None) -> EpisodeLog:
    """Read the messages of ``topics`` (and all metadata records) from an MCAP file.

    Raises :class:`LogError` when the file is missing or not MCAP; damage later on ends reading
    there and is reported in ``status`` (everything before it is kept)."""
    path = Path(path)
    try:
        buf = path.read_bytes()
    except OSError as exc:
        raise LogError(f"{path}: cannot read log: {exc.strerror or exc}") from None
    if buf[:len(MCAP_MAGIC)] != MCAP_MAGIC:
        what = "empty file" if not buf else "bad magic bytes"
        raise LogError(f"{path}: not an MCAP file ({what}); expected an episode log (.mcap)")
    scan = _Scan(set(topics))
    try:
        why = scan.run(buf, len(MCAP_MAGIC), len(buf))
    except Exception as exc:  # a damaged record body: mcap, struct, zstd and lz4 errors alike
        why = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    if why is None and not scan.footer:
        why = "no footer"
    status = "complete" if why is None else f"truncated after {scan.records} records ({why})"
    out: dict[str, TopicMessages] = {}
    for topic, (pub, seq, raw) in scan.rows.items():
        pub_a = np.asarray(pub, dtype=np.int64)
        seq_a = np.asarray(seq, dtype=np.int64)
        if len(pub_a) > 1 and np.any(np.diff(pub_a) < 0):  # stable: keep file order among ties
            order = np.argsort(pub_a, kind="stable")
            pub_a, seq_a, raw = pub_a[order], seq_a[order], [raw[i] for i in order]
        out[topic] = TopicMessages(topic, pub_a, seq_a, raw)
    log = EpisodeLog(path, out, scan.metadata, scan.roles, status)
    if seq_field:
        for tm in out.values():
            seqs = [get_field(tm.payload(i), seq_field) for i in range(len(tm))]
            tm.seq = np.asarray([s if isinstance(s, int) else -1 for s in seqs], dtype=np.int64)
    if log.truncated:
        log.warnings.append(f"{path}: {status}; extracting what is intact")
    return log
