"""The MCAP episode log, and the recorder process that writes it beside the simulation.

The recorder process (``python -m deft_gym.record.worker``) is fed batches of messages that the
simulation's process encoded (ROS 1 bytes, :mod:`deft_gym.bus.ros1`, or JSON) and framed as MCAP
``Message`` records when they were published (:class:`deft_gym.record.mcapwrite.RecordTap`,
a few microseconds per message), and does the rest: chunks, CRCs, indexes, the summary and the
file (:class:`deft_gym.record.mcapwrite.LogWriter`, per chunk rather than per message). Apollo
records the same way: ``cyber_recorder`` is a process of its own, fed serialised messages.

It reads commands from its stdin and answers some on its stdout. A frame is a 4-byte
little-endian length and a pickled tuple ``(op, log_id, *args)``:

- ``("open", id, path, channels, metadata name, metadata, compress, start_ns)`` -> ``("ok",)`` or ``("error", text)``
- ``("write", id, ends, times, cids, n)`` followed by ``n`` raw bytes, the message records: a
  :data:`deft_gym.record.mcapwrite.RecordBatch` (not pickled: no copy)
- ``("channel", id, topic, spec)``: a channel for a topic: ``spec``'s (a :data:`ChannelSpec`), or
  schemaless JSON for ``None`` (a topic outside the open's channels)
- ``("fail", id, text)``: a message could not be encoded; the log is not finished
- ``("meta", id, name, values)``
- ``("close", id, outcome)`` -> ``("ok", path, cpu_seconds)`` or ``("error", text)``

The payload snapshot (:class:`Batch`, :func:`read_batch`, compiled in ``_snapshot_c.c``) is
no longer on the recording path: a snapshot read back and then encoded in the recorder process
cost about 3x the CPU, for both processes together, of encoding where a message is published
(issue 36). It is kept, with its tests, but nothing records through it now.

A failure while writing a log is held and answered at its ``close``. At end of input (the
simulation's process is gone) every open log's file is closed and left as ``<name>.tmp``.
"""

from __future__ import annotations

import os
import pickle
import signal
import struct
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

from deft_gym.files import checked_kernel
from deft_gym.record.mcapwrite import CHUNK_BYTES, ChannelSpec, LogWriter, RecordBatch

try:  # the payload snapshot compiled (setup.py), 3x faster than pickle for plain payloads
    from deft_gym.record import _snapshot_c
except ImportError:  # pragma: no cover - the build is optional
    _snapshot_c = None
# a kernel built before worker.py or _snapshot_c.c was edited is not used (the edit must count)
_snapshot_c = checked_kernel(_snapshot_c, Path(__file__).with_name("_snapshot_c.c"), Path(__file__))

FRAME = struct.Struct("<I")
_IOV_MAX = min(1024, os.sysconf("SC_IOV_MAX")) if hasattr(os, "sysconf") else 1024
_TOPIC = struct.Struct("=q")  # a batch entry: topic length, the topic (UTF-8),
_REST = struct.Struct("=qqq")  # publish time [ns], sequence number, payload length, the payload

# (topic, publish time [ns], encoded payload, per-topic sequence number)
Entry = tuple[str, int, bytes, int]


class PyBatch:
    """:class:`Batch` without the compiled module (or with ``DEFT_GYM_PURE_PYTHON`` set): the
    same entries, each payload pickled."""

    def __init__(self, limit: int, flush: Callable[[], None]) -> None:
        if limit < 1 or not callable(flush):
            raise ValueError("Batch(limit, flush): limit >= 1 and a callable flush")
        self.limit, self.flush = limit, flush
        self.count = self.total = 0
        self._buf = bytearray()

    def __call__(self, msg: Any) -> None:
        topic, data = msg.topic.encode(), pickle.dumps(msg.payload, protocol=pickle.HIGHEST_PROTOCOL)
        self._buf += _TOPIC.pack(len(topic)) + topic + _REST.pack(msg.publish_ns, msg.seq, len(data)) + data
        self.count += 1
        self.total += 1
        if self.count >= self.limit:
            self.flush()

    def take(self) -> bytes:
        """The entries so far; the batch is then empty."""
        out, self._buf, self.count = bytes(self._buf), bytearray(), 0
        return out


def py_read_batch(data: bytes) -> list[tuple[str, int, Any, int]]:
    """:func:`read_batch` without the compiled module (pickled payloads only)."""
    out, at, end = [], 0, len(data)
    while at < end:
        try:
            (n,) = _TOPIC.unpack_from(data, at)
            topic = data[at + 8 : at + 8 + n].decode()
            ns, seq, m = _REST.unpack_from(data, at + 8 + n)
        except struct.error:
            raise ValueError("snapshot data is truncated or malformed") from None
        at += 8 + n + 24
        blob = data[at : at + m]
        if len(blob) != m or n < 0 or m < 0:
            raise ValueError("snapshot data is truncated or malformed")
        at += m
        out.append((topic, ns, pickle.loads(blob), seq))
    return out


# Batch(limit, flush): the bus tap of a log written by the recorder process. Each message's
# entry goes into a buffer at its publish time, with a snapshot of its payload: compiled
# (setup.py), a tree of plain values (dict, list, tuple, str, 64-bit int, float, bool, None) in
# the module's own format (floats as their 8 bytes, 3x faster than pickle) and anything else
# pickled. read_batch(data) reads a batch back as (topic, publish_ns, payload, seq) entries.
Batch = PyBatch if _snapshot_c is None or os.environ.get("DEFT_GYM_PURE_PYTHON") else _snapshot_c.Batch
read_batch = py_read_batch if _snapshot_c is None else _snapshot_c.read_batch


class EpisodeLog:
    """One MCAP episode log being written to ``<path>.tmp``, renamed to ``path`` by :meth:`close`.

    ``channels`` are :data:`ChannelSpec` (numbered from 1 in their order); a topic outside them
    gets a schemaless JSON channel (:meth:`add_channel`) just before its first message. ``metadata``
    is the episode record (string values), written first.

    Integrity: messages go into chunks of about :attr:`CHUNK_BYTES`, each with the CRC-32 of its
    content, the data section ends with its own CRC, and the summary section (schemas, channels,
    statistics with per-channel message counts, a chunk index with every chunk's offset, length
    and time range, a metadata index) has one too. A reader can then verify every message,
    localise damage to a chunk (its offset and time range), find the next chunk from the index
    and check that it read as many messages as were written (:mod:`extract.logs`). Chunks are
    uncompressed (speed); ``compress`` makes them zstd (~5x smaller files). Message indexes are
    left out: readers take whole chunks. The bytes are those of the ``mcap`` library's writer
    (:class:`deft_gym.record.mcapwrite.LogWriter`); messages arrive as batches of ready-made
    records (:class:`deft_gym.record.mcapwrite.RecordTap`).
    """

    CHUNK_BYTES = CHUNK_BYTES

    def __init__(self, path: Path | str, channels: list[ChannelSpec], metadata_name: str,
                 metadata: dict[str, str], compress: bool = False, start_ns: int = 0) -> None:
        self.path = Path(path)
        self.start_ns = start_ns  # added to every publish time: log_time is an epoch time
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = self.path.with_name(self.path.name + ".tmp")
        self._file = open(self.tmp, "wb", buffering=1 << 20)  # noqa: SIM115 - closed in close()
        self.writer = LogWriter(self._file, self.CHUNK_BYTES, compress)
        self.writer.start(profile="", library="deft_gym")
        self.channels: dict[str, int] = {}  # the last channel of each topic
        for spec in channels:
            self._register(spec)
        self.writer.add_metadata(metadata_name, metadata)

    def _register(self, spec: ChannelSpec) -> int:
        topic, role, title, schema, *encodings = spec
        schema_encoding, message_encoding = encodings or ("jsonschema", "json")
        sid = self.writer.register_schema(title, schema_encoding, schema)
        # a viewer-only topic (role "") carries no role: readers of bus messages skip it
        cid = self.channels[topic] = self.writer.register_channel(topic, message_encoding, sid,
                                                                  {"role": role} if role else {})
        return cid

    def add_channel(self, topic: str, spec: ChannelSpec | None = None) -> int:
        """A channel for ``topic`` (``spec``'s: the JSON channel of a topic whose messages are
        binary, for one that is not; else schemaless JSON), in the log before the messages that
        follow; its id."""
        if spec is not None:
            return self._register(spec)
        cid = self.channels[topic] = self.writer.register_channel(topic, "json", 0, {})
        return cid

    def write(self, batch: RecordBatch) -> None:
        """Add a batch of message records (:meth:`RecordTap.flush`), in publish order."""
        self.writer.add_batch(batch)

    def add_metadata(self, name: str, values: dict[str, str]) -> None:
        """A metadata record (string values)."""
        self.writer.add_metadata(name, values)

    def close(self, outcome_name: str | None = None, outcome: dict[str, str] | None = None) -> Path:
        """Write the outcome record, finish the file and move it into place."""
        if outcome_name is not None and outcome is not None:
            self.writer.add_metadata(outcome_name, outcome)
        self.writer.finish()
        self._file.close()
        os.replace(self.tmp, self.path)
        return self.path

    def abandon(self) -> None:
        """Close the file unfinished, leaving ``<name>.tmp`` for inspection."""
        if not self._file.closed:
            self._file.close()


def read_frame(stream: BinaryIO) -> Any:
    """The next frame's object, or None at end of input."""
    head = stream.read(FRAME.size)
    if len(head) < FRAME.size:
        return None
    (n,) = FRAME.unpack(head)
    return pickle.loads(stream.read(n))


def write_frame(stream: BinaryIO, obj: Any, raw: list[bytes] | None = None) -> None:
    """Write one frame (and the ``raw`` pieces after it: one gathering write to the pipe, no
    copy) and flush it."""
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(FRAME.pack(len(data)) + data)
    stream.flush()
    if raw:
        fd = stream.fileno()
        for at in range(0, len(raw), _IOV_MAX):
            group = raw[at:at + _IOV_MAX]
            done, total = os.writev(fd, group), sum(map(len, group))
            if done < total:  # a write the pipe cut short (a signal): the rest as one piece
                rest = b"".join(group)[done:]
                while rest:
                    rest = rest[os.write(fd, rest):]


def serve(inp: BinaryIO, out: BinaryIO) -> None:
    """The recorder process's loop: run commands until end of input."""
    logs: dict[int, EpisodeLog] = {}
    errors: dict[int, str] = {}
    cpu: dict[int, float] = {}
    while (cmd := read_frame(inp)) is not None:
        op, lid, *args = cmd
        c0 = time.process_time()
        if op == "write" and lid in errors:  # its records are read all the same
            inp.read(args[3])
        try:
            if op == "open":
                logs[lid] = EpisodeLog(*args)
                write_frame(out, ("ok",))
            elif lid in errors:
                if op == "close":
                    write_frame(out, ("error", errors.pop(lid)))
            elif op == "write":  # the records follow the frame as raw bytes
                data = inp.read(args[3])
                logs[lid].write((data, *args[:3]))
            elif op == "channel":
                logs[lid].add_channel(*args)
            elif op == "fail":  # the simulation could not encode a message: the log is not finished
                raise TypeError(args[0])
            elif op == "meta":
                logs[lid].add_metadata(*args)
            elif op == "close":
                path = logs[lid].close(*args)  # on an error, abandoned below
                del logs[lid]
                write_frame(out, ("ok", str(path), cpu.pop(lid, 0.0) + time.process_time() - c0))
        except Exception as exc:  # held for the log's close; the process goes on
            text = f"{type(exc).__name__}: {exc}"
            log = logs.pop(lid, None)
            if log is not None:
                log.abandon()
            if op in ("open", "close"):
                write_frame(out, ("error", text))
            else:
                errors[lid] = text
        if lid in logs:
            cpu[lid] = cpu.get(lid, 0.0) + time.process_time() - c0
        else:
            cpu.pop(lid, None)
    for log in logs.values():
        log.abandon()


if __name__ == "__main__":
    # Ctrl-C reaches the whole process group: the simulation's process decides what happens
    # (it closes its logs); this process ends when its input does
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    serve(sys.stdin.buffer, sys.stdout.buffer)
