"""Episode logs: every bus message at its publish time in an MCAP file, plus the truth file.

The MCAP file (chunks with CRCs and a summary section with message counts and a chunk index,
see :class:`deft_gym.record.worker.EpisodeLog`; zstd chunks with ``compress``) has one channel
per topic (ROS 1 bytes with a ``ros1msg`` schema for the roles with a binary layout - plus a JSON
channel for any message that does not fit it -, JSON with a JSON schema for the others; see
:func:`log_channels` and docs/logs.md) and metadata
records ``deft_gym.episode`` (scenario, seeds, configuration; written first) and
``deft_gym.outcome`` (written last). It is written to ``<name>.tmp`` and renamed when complete,
so a finished log is never partial; a crashed run leaves the ``.tmp`` for inspection.

Messages are encoded and framed as MCAP records when published (:class:`RecordTap`) and
written by a recorder process of their own (:mod:`deft_gym.record.worker`), as Apollo's
``cyber_recorder`` is a process of its own: chunks, CRCs, indexes and the file then run beside
the simulation instead of inside it. Set ``DEFT_GYM_RECORDER=inline`` (or pass ``background=False``) to encode and write
in the simulation's process; both write the same bytes. That is the default where the process
may use only one CPU (``auto``), and in the workers of a pool of simulation processes that fill the
CPUs (:func:`init_pool_worker`: training envs, evaluation, extraction accuracy, robustness).

The truth file (``truth.jsonl``) lists, per planning output, the sequence numbers of the
messages the planner actually consumed and its frame time. It is for measuring extraction
accuracy only.
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import itertools
import json
import os
import subprocess
import sys
import threading
from collections.abc import Callable
from itertools import accumulate
from pathlib import Path
from typing import Any

import orjson
from mcap.opcode import Opcode

from deft_gym.bus import ros1
from deft_gym.bus.codec import _default, encode
from deft_gym.bus.messages import SCENE_TOPIC, SCHEMAS, Message, log_start_ns
from deft_gym.bus.ros1 import Program
from deft_gym.cli.common import cpus as available_cpus  # how many CPUs this process may run on
from deft_gym.files import checked_kernel, write_atomic
from deft_gym.record.mcapwrite import MESSAGE_FIELDS, MESSAGE_HEAD, ChannelSpec, RecordBatch
from deft_gym.record.scene import expand
from deft_gym.record.worker import EpisodeLog, read_frame, write_frame

try:  # the recorder's tap compiled (setup.py): the same records, no Python frame per message
    from deft_gym.record import _tap_c
except ImportError:  # pragma: no cover - the build is optional
    _tap_c = None
# a kernel built before recorder.py or _tap_c.c was edited is not used (the edit must count)
_tap_c = checked_kernel(_tap_c, Path(__file__).with_name("_tap_c.c"), Path(__file__))

EPISODE_METADATA = "deft_gym.episode"
OUTCOME_METADATA = "deft_gym.outcome"
#: a search run's optimal (reference) path and the half lane a plan may stray from it (the
#: extractor's non-optimal-decision test reads it)
OPTIMAL_PATH_METADATA = "deft_gym.optimal_path"
RECORDER_ENV = "DEFT_GYM_RECORDER"


def recorder_in_process() -> bool:
    """Whether logs are written in the simulation's process (``DEFT_GYM_RECORDER``: ``process``,
    ``inline``, or ``auto``, the default: inline when this process may use only one CPU, where
    a recorder process would compete with the simulation instead of running beside it)."""
    mode = os.environ.get(RECORDER_ENV, "auto")
    if mode not in ("auto", "process", "inline"):
        raise ValueError(f"{RECORDER_ENV}={mode!r}: expected auto, process or inline")
    return mode == "inline" or (mode == "auto" and available_cpus() < 2)


def init_pool_worker(workers: int) -> None:
    """Initializer of a worker of a pool of ``workers`` simulation processes: when they are at
    least as many as the CPUs, each writes its logs in its own process (``DEFT_GYM_RECORDER``
    defaults to ``inline`` there; a value the user set stands), since a recorder process per
    worker would compete with the workers instead of running beside them."""
    if workers >= available_cpus():
        os.environ.setdefault(RECORDER_ENV, "inline")


def _meta(values: dict[str, Any]) -> dict[str, str]:
    """MCAP metadata values are strings: JSON-encode everything that is not one."""
    return {k: v if isinstance(v, str) else json.dumps(v, sort_keys=True) for k, v in values.items()}


class RecorderError(RuntimeError):
    """The recorder process could not write a log (or is gone)."""


class RecorderProcess:
    """This process's recorder process: started on first use, shared by all its logs, replaced
    after a fork (a forked child never writes to its parent's pipe) or after it died."""

    _current: RecorderProcess | None = None
    PIPE_BYTES = 1 << 20

    @classmethod
    def get(cls) -> RecorderProcess:
        """The running recorder process of this process (started if needed)."""
        cur = cls._current
        if cur is None or cur.pid != os.getpid() or cur.proc.poll() is not None:
            if cur is not None:
                cur.stop()
            cur = cls._current = cls()
        return cur

    def __init__(self) -> None:
        self.pid = os.getpid()
        # the package's own directory first on the path: the process imports this deft_gym
        root = str(Path(__file__).resolve().parents[2])
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (root, os.environ.get("PYTHONPATH"))))}
        self.proc = subprocess.Popen([sys.executable, "-m", "deft_gym.record.worker"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, close_fds=True, env=env)
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        atexit.register(self.stop)
        # a pipe buffer that holds several batches: a send then never waits for the recorder
        # process to be scheduled (Linux; elsewhere the default buffer is kept)
        with contextlib.suppress(ImportError, AttributeError, OSError):
            import fcntl

            fcntl.fcntl(self.proc.stdin.fileno(), fcntl.F_SETPIPE_SZ, self.PIPE_BYTES)

    def stop(self, timeout: float = 10.0) -> None:
        """End the recorder process (its open logs stay ``.tmp``), wait for it, close the pipes."""
        if self.pid != os.getpid():
            return
        for pipe in (self.proc.stdin, self.proc.stdout):
            with contextlib.suppress(OSError):  # unsent data of a process that is gone
                pipe.close()
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()

    def new_id(self) -> int:
        """A log id not used before in this recorder process."""
        return next(self._ids)

    def send(self, *cmd: Any, raw: bytes | None = None) -> None:
        """Send a command (and ``raw`` bytes after it) without waiting."""
        with self._lock:
            self._send(cmd, raw)

    def request(self, *cmd: Any) -> tuple[Any, ...]:
        """Send a command and wait for its answer; an ``error`` answer raises :class:`RecorderError`."""
        with self._lock:
            self._send(cmd)
            reply = read_frame(self.proc.stdout)
        if reply is None:
            raise RecorderError(f"the recorder process exited (code {self.proc.wait()}) before answering {cmd[0]!r}")
        if reply[0] == "error":
            raise RecorderError(reply[1])
        return reply

    def _send(self, cmd: tuple[Any, ...], raw: bytes | None = None) -> None:
        try:
            write_frame(self.proc.stdin, cmd, raw)
        except (BrokenPipeError, ValueError) as exc:
            raise RecorderError(f"the recorder process is gone (code {self.proc.poll()})") from exc


class RecordTap:
    """The bus tap of an episode log (:attr:`tap`): each message encoded - ROS 1 bytes for a topic
    in ``binary`` (topic -> (channel id, layout program)), else JSON - and framed as an MCAP
    ``Message`` record when it is published (log time = ``start_ns`` + publish time), handed to
    ``flush`` in batches (:data:`RecordBatch`, the records as two pieces per message: nothing is
    copied here). A compact scene state (:func:`deft_gym.record.scene.expand`) becomes the scene
    and frame-transform messages; a topic outside ``channels`` (the JSON channels), or a binary
    topic's message that does not fit its layout, gets a JSON channel through
    ``new_channel(topic) -> id`` just before its first such message. A payload that cannot be
    encoded is held in :attr:`error` (``"<topic> message <seq>: <reason>"``) and left out; the
    log is then not finished."""

    BATCH = 256

    def __init__(self, channels: dict[str, int], start_ns: int, flush: Callable[[RecordBatch], None],
                 new_channel: Callable[[str], int], binary: dict[str, tuple[int, Program]] | None = None) -> None:
        self.channels = dict(channels)  # the JSON channels
        self.binary = dict(binary or {})  # topic -> (its ros1 channel, the layout program)
        self.start_ns = start_ns
        self.error: str | None = None
        self.count = 0  # messages handed on so far
        # the common path, without attribute look-ups: topics with a channel, scenes aside; a
        # binary topic's entry is (channel id, program)
        fast: dict[str, Any] = {t: c for t, c in channels.items() if t != SCENE_TOPIC}
        fast.update(self.binary)
        pieces: list[bytes] = []  # two per message: its record's head and its data
        times: list[int] = []
        cids: list[int] = []
        pack, head, limit = MESSAGE_HEAD.pack, Opcode.MESSAGE, self.BATCH
        dumps, default, opts = orjson.dumps, _default, orjson.OPT_SERIALIZE_NUMPY
        bencode, binary_topics = ros1.encode_fast, self.binary

        def add(cid: int, publish_ns: int, data: bytes, seq: int) -> None:
            t = start_ns + publish_ns
            pieces.append(pack(head, MESSAGE_FIELDS + len(data), cid, seq, t, t))
            pieces.append(data)
            times.append(t)
            cids.append(cid)

        def tap(msg: Any) -> None:  # compiled in _tap_c.c (the same bytes)
            cid = fast.get(msg.topic)
            if cid is None:
                general(msg)
                return
            if type(cid) is tuple:  # ROS 1 bytes; a payload that does not fit its layout: JSON
                cid, program = cid
                data = bencode(program, msg.payload)
                if data is None:
                    general(msg)
                    return
            else:
                try:
                    data = dumps(msg.payload, default=default, option=opts)  # encode(), inlined
                except TypeError:  # bytes (JSON already), or no JSON form: general decides
                    general(msg)
                    return
                if b"null" in data:  # a non-finite float, tagged (or a None): general decides
                    general(msg)
                    return
            t = start_ns + msg.publish_ns
            pieces.append(pack(head, MESSAGE_FIELDS + len(data), cid, msg.seq, t, t))
            pieces.append(data)
            times.append(t)
            cids.append(cid)
            if len(cids) >= limit:
                flush_all()

        def general(msg: Any) -> None:
            """Any message: a scene state, a topic's first message without a channel yet, a
            payload that orjson alone does not encode as the log needs, one that does not fit
            its topic's binary layout (JSON on a JSON channel of the topic)."""
            topic, payload = msg.topic, msg.payload
            if topic == SCENE_TOPIC and (scene := expand(msg.publish_ns, msg.seq, payload, start_ns)) is not None:
                entries = scene
            else:
                try:
                    entries = [(topic, msg.publish_ns, encode(payload), msg.seq)]
                except TypeError as exc:
                    fail(msg, exc)
                    return
            for topic, ns, data, seq in entries:
                cid = self.channels.get(topic)
                if cid is None:  # its channel record goes into the log just before its first message
                    flush_all()
                    cid = self.channels[topic] = new_channel(topic)
                    if topic != SCENE_TOPIC and topic not in binary_topics:
                        fast[topic] = cid
                add(cid, ns, data, seq)
            if len(cids) >= limit:
                flush_all()

        def fail(msg: Any, exc: Exception) -> None:
            if self.error is None:
                self.error = f"{msg.topic} message {msg.seq}: {exc}"

        def flush_all() -> None:
            if cids:
                self.count += len(cids)
                ends = list(accumulate(map(len, pieces)))[1::2]  # [bytes] each record's end
                batch = (pieces[:], ends, times[:], cids[:])
                pieces.clear(), times.clear(), cids.clear()
                flush(batch)

        if _tap_c is not None and not os.environ.get("DEFT_GYM_PURE_PYTHON"):
            tap = _tap_c.Tap(fast, start_ns, dumps, {"default": default, "option": opts}, bencode, general,
                             flush_all, pieces, times, cids, limit)
        self.tap: Callable[[Any], None] = tap
        self.flush: Callable[[], None] = flush_all
        self.pending: Callable[[], int] = cids.__len__

    def __call__(self, msg: Any) -> None:
        self.tap(msg)


class McapRecorder:
    """A bus tap writing every message to an MCAP episode log (:attr:`tap` is the tap itself,
    without the method call of calling the recorder).

    Each message's payload is encoded and framed as an MCAP record when it is published
    (:class:`RecordTap`), so the log holds the payload as it was then: in ROS 1's binary form for
    the roles that have a layout (:mod:`deft_gym.bus.ros1`; a message that does not fit it goes
    as JSON on a second, JSON channel of its topic), as JSON for the others (``routing``,
    ``map``) and for every role with ``encoding="json"`` (or ``DEFT_GYM_LOG_ENCODING=json``).
    The records are handed in batches to the log's writer, in the recorder process
    (``background``, by default unless :func:`recorder_in_process`) or in this one: the same
    bytes either way. :meth:`close` returns once the log is complete and in place, and raises
    :class:`RecorderError` if it could not be written.

    ``log_time`` is ``metadata["log_start_ns"]`` (an epoch time, 0 when absent) plus the
    publish time; ``extra_channels`` are ``(topic, "", schema title, JSON schema)`` of
    viewer-only topics (no role).
    """

    BATCH = RecordTap.BATCH

    def __init__(self, path: Path | str, topics: dict[str, str], metadata: dict[str, Any],
                 compress: bool = False, background: bool | None = None,
                 extra_channels: list[tuple[str, str, str, bytes]] = (), encoding: str | None = None) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if background is None:
            background = not recorder_in_process()
        channels, self._json_specs, programs = log_channels(topics, encoding)
        channels += list(extra_channels)
        # the ids the log gives its channels: in order, from 1 (LogWriter.register_channel)
        self._n_channels = len(channels)
        json_ids = {spec[0]: k for k, spec in enumerate(channels, 1) if len(spec) == 4 or spec[5] == "json"}
        binary = {spec[0]: (k, programs[spec[0]]) for k, spec in enumerate(channels, 1) if spec[0] in programs}
        self.start_ns = log_start_ns(metadata)
        args = (str(self.path), channels, EPISODE_METADATA, _meta(metadata), compress, self.start_ns)
        self._log: EpisodeLog | None = None
        self._proc: RecorderProcess | None = None
        if background:
            self._proc = RecorderProcess.get()
            self._id = self._proc.new_id()
            self._request("open", *args)
        else:
            self._log = EpisodeLog(*args)
        self._tap = RecordTap(json_ids, self.start_ns, self._send_batch if background else self._log.write,
                              self._new_channel, binary)
        self.tap: Callable[[Message], None] = self._tap.tap
        self.closed = False
        self.process_seconds = 0.0  # CPU time the recorder process spent on this log (after close)

    def _request(self, op: str, *args: Any, wait: bool = True) -> tuple[Any, ...] | None:
        """A command about this log to the recorder process; its errors name the log."""
        try:
            if wait:
                return self._proc.request(op, self._id, *args)
            self._proc.send(op, self._id, *args)
            return None
        except RecorderError as exc:
            raise RecorderError(f"MCAP log {self.path}: {exc}") from None

    def _send_batch(self, batch: RecordBatch) -> None:
        pieces, ends, times, cids = batch
        try:
            self._proc.send("write", self._id, ends, times, cids, ends[-1], raw=pieces)
        except RecorderError as exc:
            raise RecorderError(f"MCAP log {self.path}: {exc}") from None

    def _new_channel(self, topic: str) -> int:
        """The next channel, for ``topic``: its role's JSON channel when its messages are binary,
        else schemaless JSON; the writer numbers channels in order, as here."""
        spec = self._json_specs.get(topic)
        if self._proc is not None:
            with contextlib.suppress(RecorderError):  # the process is gone: the next batch or close says so
                self._request("channel", topic, spec, wait=False)
        else:
            self._log.add_channel(topic, spec)
        self._n_channels += 1
        return self._n_channels

    def __call__(self, msg: Message) -> None:
        self.tap(msg)

    @property
    def count(self) -> int:
        """Messages recorded so far (a scene state is two: the scene and the ego's transform)."""
        return self._tap.count + self._tap.pending()

    def flush(self) -> None:
        """Hand the messages held back to the log, in publish order."""
        self._tap.flush()

    def add_metadata(self, name: str, values: dict[str, Any]) -> None:
        """Add a metadata record (values that are not strings are JSON-encoded)."""
        self.flush()
        if self._proc is not None:
            self._request("meta", name, _meta(values), wait=False)
        else:
            self._log.add_metadata(name, _meta(values))

    def close(self, outcome: dict[str, Any] | None = None) -> Path:
        """Write the outcome record, finish the file and move it into place."""
        if self.closed:
            return self.path
        self.closed = True
        self.flush()
        args = (OUTCOME_METADATA, _meta(outcome)) if outcome is not None else (None, None)
        error = self._tap.error
        if self._proc is not None:
            if error is not None:
                self._request("fail", error, wait=False)
            _, _, self.process_seconds = self._request("close", *args)
        elif error is not None:
            self._log.abandon()
            raise RecorderError(f"MCAP log {self.path}: TypeError: {error}")
        else:
            self._log.close(*args)
        return self.path


LOG_ENCODING_ENV = "DEFT_GYM_LOG_ENCODING"


def log_channels(topics: dict[str, str], encoding: str | None = None
                 ) -> tuple[list[ChannelSpec], dict[str, ChannelSpec], dict[str, Program]]:
    """The channels of a log of the bus topics ``topics`` (role -> topic): a ROS 1 channel for
    each role with a binary layout (``encoding`` ``"ros1"``, the default, or
    ``DEFT_GYM_LOG_ENCODING``), a JSON one for the others and for every role with ``"json"``;
    the JSON channel of each binary topic (registered on its first message that does not fit);
    and each binary topic's layout program."""
    encoding = encoding or os.environ.get(LOG_ENCODING_ENV) or "ros1"
    if encoding not in ("ros1", "json"):
        raise ValueError(f"{LOG_ENCODING_ENV}={encoding!r}: expected 'ros1' (binary where a topic has a layout) or "
                         "'json'")
    layouts = _role_layouts() if encoding == "ros1" else {}
    channels, json_specs, programs = [], {}, {}
    for role, topic in topics.items():
        spec = (topic, role, SCHEMAS[role]["title"], _json_schema(role), "jsonschema", "json")
        layout = layouts.get(role)
        if layout is None:
            channels.append(spec)
            continue
        channels.append((topic, role, layout.name, _definition(layout), ros1.SCHEMA_ENCODING, ros1.MESSAGE_ENCODING))
        json_specs[topic] = spec
        programs[topic] = layout.program
    return channels, json_specs, programs


@functools.cache
def _role_layouts() -> dict[str, ros1.Layout]:
    return ros1.role_layouts(SCHEMAS)


@functools.cache
def _json_schema(role: str) -> bytes:
    return json.dumps(SCHEMAS[role]).encode()


@functools.cache
def _definition(layout: ros1.Layout) -> bytes:
    return layout.definition()


def write_truth(path: Path | str, records: list[dict[str, Any]], topics: dict[str, str]) -> Path:
    """``truth.jsonl``: one JSON object per planning output (inputs keyed by topic name, keys
    sorted)."""
    dumps, sort = orjson.dumps, orjson.OPT_SORT_KEYS
    lines = [dumps({"planning_seq": r["seq"], "publish_ns": r["publish_ns"], "frame_ns": r["frame_ns"],
                    "frame_time": r["frame_time"], "inputs": {topics[role]: seq for role, seq in r["inputs"].items()}},
                   option=sort) for r in records]
    return write_atomic(path, b"\n".join(lines) + (b"\n" if lines else b""))
