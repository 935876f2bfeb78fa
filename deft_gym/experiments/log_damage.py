"""Log integrity, measured: damage real episode logs on purpose and check what the reader says.

    python -m deft_gym.experiments.log_damage runs/x/0/episode.mcap runs/y/0/episode.mcap
    python -m deft_gym.experiments.log_damage --record 3 --out runs/log_damage        # record 3 seed logs first

For each log and each damaged chunk (the first, the middle and the last by default) it applies
one damage of each kind to a copy, reads the copy with :func:`extract.verify.verify` and checks:

- ``detected``: the reader reports the log as not intact;
- ``localised``: a reported problem names the damaged record's byte offset (and, where the
  record is a chunk, its time range);
- ``intact kept``: the messages read are exactly the intact ones - every message outside the
  damaged chunk (all of them where the damage spared the chunk's content), none of the damaged
  chunk's (a CRC cannot tell which of its messages is hurt);
- ``loss stated``: the messages reported lost, per topic, are exactly those missing (for a
  truncation: the time from which everything is missing is stated).

Damage kinds: ``record_type`` (the chunk's type byte flipped to an unknown type),
``payload_digit`` (one digit of one message payload in the chunk changed; one bit of a binary one), ``record_length``
(the chunk's record length wrong), ``message_header`` (the length of one message record inside
the chunk wrong: the chunk's content no longer parses after it), each also in a copy cut just
before its summary section (``..._no_summary``: no chunk index, no statistics - the reader has
only the records; what a damaged chunk held is then told by the topics' sequence numbers), and
``truncation`` (the file cut in the middle of the chunk). Prints a table and writes
``OUT/log_damage.json``.
"""

from __future__ import annotations

import json
import struct
import sys
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

from rich import box
from rich.table import Table

from deft_gym.bus.messages import log_start_ns
from deft_gym.cli import common
from deft_gym.files import write_atomic
from extract.logs import chunk_head, read_summary, walk_records
from extract.verify import verify

KINDS = ("record_type", "payload_digit", "record_length", "message_header", "record_type_no_summary",
         "payload_digit_no_summary", "record_length_no_summary", "message_header_no_summary", "truncation")
_MESSAGE = 0x05


def chunk_table(buf: bytes) -> list[dict[str, Any]]:
    """Every chunk of an intact log: offset, record length, time range [ns] and its messages as
    ``(channel id, seq, log time, payload offset in the file, payload length)``."""
    summary, _ = read_summary(buf)
    if summary is None:
        raise ValueError("the log has no verified summary section; damage experiments need an intact log")
    out = []
    for off, ci in sorted(summary.chunk_at.items()):
        _, _, _, data = chunk_head(buf, off + 9, off + ci.chunk_length)
        base = off + ci.chunk_length - len(data)  # uncompressed chunks: the records' offset in the file
        msgs = []
        for op, body, stop in walk_records(data):
            if op == _MESSAGE:
                cid, seq, log_t = struct.unpack_from("<HIQ", data, body)
                msgs.append((cid, seq, log_t, base + body + 22, stop - body - 22))
        out.append({"offset": off, "length": ci.chunk_length, "start": ci.message_start_time,
                    "end": ci.message_end_time, "messages": msgs, "compressed": ci.compression != ""})
    return out


def damage(buf: bytes, kind: str, chunk: dict[str, Any]) -> bytes:
    """A copy of ``buf`` with one damage of ``kind`` in ``chunk``."""
    b = bytearray(buf)
    off = chunk["offset"]
    if kind.endswith("_no_summary"):
        kind = kind.removesuffix("_no_summary")
        (summary_start,) = struct.unpack_from("<Q", buf, len(buf) - 8 - 29 + 9)
        b = b[:summary_start]
    if kind == "record_type":
        b[off] ^= 0x40
    elif kind == "record_length":
        (length,) = struct.unpack_from("<Q", b, off + 1)
        struct.pack_into("<Q", b, off + 1, length + 1237)
    elif kind == "payload_digit":
        if chunk["compressed"]:
            raise ValueError("payload damage needs uncompressed chunks")
        _, _, _, at, n = chunk["messages"][len(chunk["messages"]) // 2]
        payload = bytes(b[at:at + n])
        if payload[:1] == b"{":
            k = next(i for i, c in enumerate(payload) if 0x31 <= c <= 0x38 and i > n // 3)
            b[at + k] += 1  # one digit changed: still valid JSON, another number
        else:  # ROS 1 bytes: one bit flipped in the middle
            b[at + n // 2] ^= 1
    elif kind == "message_header":
        if chunk["compressed"]:
            raise ValueError("message header damage needs uncompressed chunks")
        _, _, _, at, _ = chunk["messages"][len(chunk["messages"]) // 2]
        struct.pack_into("<Q", b, at - 22 - 8, 10**9)  # the message record's length: the rest does not parse
    elif kind == "truncation":
        b = b[:off + chunk["length"] // 2]
    else:
        raise ValueError(f"unknown damage {kind!r}; expected one of {KINDS}")
    return bytes(b)


def _messages(log: Any) -> set[tuple[str, int, int]]:
    return {(t, int(s), int(p)) for t, tm in log.topics.items() for s, p in zip(tm.seq.tolist(), tm.publish_ns.tolist())}


def evaluate(path: Path, chunks_at: tuple[str, ...] = ("first", "middle", "last"), workdir: Path | None = None
             ) -> list[dict[str, Any]]:
    """Rows of the experiment for one intact log."""
    buf = path.read_bytes()
    table = chunk_table(buf)
    base = verify(path)
    if not base.integrity.intact:
        raise ValueError(f"{path}: not intact to begin with ({base.status})")
    everything = _messages(base)
    t0 = log_start_ns(base.episode_meta())  # the reader gives sim times; the file holds epoch times
    topic_of = {cid: t for cid, t in read_summary(buf)[0].channels.items()}
    picks = {"first": 0, "middle": len(table) // 2, "last": len(table) - 1}
    rows = []
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        for where in chunks_at:
            k = picks[where]
            ch = table[k]
            in_chunk = {(topic_of[c], s, lt - t0) for c, s, lt, _, _ in ch["messages"]}
            after = {(topic_of[c], s, lt - t0) for later in table[k + 1:] for c, s, lt, _, _ in later["messages"]}
            ch_start, ch_end = ch["start"] - t0, ch["end"] - t0
            for kind in KINDS:
                bad = Path(tmp) / f"{kind}_{where}.mcap"
                bad.write_bytes(damage(buf, kind, ch))
                log = verify(bad)
                got = _messages(log)
                if kind.startswith(("payload_digit", "message_header")):
                    intact = everything - in_chunk
                elif kind == "truncation":
                    intact = everything - in_chunk - after
                else:
                    intact = everything  # the chunk's content is unhurt
                dmg = log.integrity.damage
                here = [d for d in dmg if d.offset == ch["offset"]]
                timed = any(d.start_ns == ch_start and (d.end_ns in (ch_end, None)) for d in here)
                lost_true = Counter(t for t, _, _ in everything - got)
                reported = {t: n for t, n in log.integrity.lost().items() if n}
                if kind == "truncation":
                    stated = any(d.kind == "truncated" and d.start_ns == ch_start for d in dmg)
                elif "+" in log.status:  # the loss is stated as a lower bound ("N+ lost"): never above the truth
                    stated = bool(reported) and all(n <= lost_true.get(t, 0) for t, n in reported.items())
                else:
                    stated = reported == dict(lost_true)
                rows.append({"log": str(path), "chunk": where, "chunk_offset": ch["offset"], "kind": kind,
                             "detected": not log.integrity.intact, "localised": bool(here) and timed,
                             "intact_kept": got == intact, "intact": len(intact), "read": len(got),
                             "damaged_kept": len(got - intact), "loss_stated": stated,
                             "lost": sum(lost_true.values()), "status": log.status,
                             "report": [d.text() for d in dmg]})
    return rows


def _record(n: int, out: Path) -> list[Path]:
    from deft_gym.scenarios.scenario import list_scenarios
    from deft_gym.sim.simulation import run_episode

    seeds = [p for p in list_scenarios() if not p.name.startswith("bench")][:n]
    return [Path(run_episode(p, jitter_seed=7, out_dir=out / "logs" / p.stem, keep_planning=False).log_path)
            for p in seeds]


def main(argv: list[str] | None = None) -> int:
    ap = common.parser("log-damage", "deft_gym.experiments.log_damage", __doc__)
    ap.add_argument("logs", nargs="*", metavar="LOG", help="intact MCAP logs to damage (copies; never changed)")
    ap.add_argument("--record", type=common.int_range(0, 1000), default=0, metavar="N", help="first record N seed-scenario logs into OUT")
    common.add_out(ap, common.RUNS / "log_damage")
    common.add_output_flags(ap)
    args = ap.parse_args(argv)
    out = Path(args.out)
    console = common.console(args, width=110)
    if not args.logs and not args.record:
        return common.cli_error("LOG: no logs: name some or pass --record N")
    with common.locked_out(out):
        return _run(args, console, out)


def _run(args: Any, console: Any, out: Path) -> int:
    logs = [Path(p) for p in args.logs] + (_record(args.record, out) if args.record else [])
    rows = []
    try:
        for p in logs:
            rows += evaluate(p)
    except (ValueError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    t = Table(title=f"Log damage: {len(logs)} log(s) x {len(rows) // max(len(logs), 1)} damages", box=box.SIMPLE_HEAD)
    for col in ("kind", "cases", "detected", "localised", "intact kept", "loss stated", "messages lost"):
        t.add_column(col, justify="left" if col == "kind" else "right", no_wrap=True)
    summary = {}
    for kind in KINDS:
        rs = [r for r in rows if r["kind"] == kind]
        row = {k: sum(r[k] for r in rs) for k in ("detected", "localised", "intact_kept", "loss_stated", "lost")}
        summary[kind] = {"cases": len(rs), **row}
        t.add_row(kind, str(len(rs)), *(f"{row[k]}/{len(rs)}" for k in ("detected", "localised", "intact_kept",
                                                                        "loss_stated")), str(row["lost"]))
    common.print_table(console, t)
    write_atomic(out / "log_damage.json", json.dumps({"summary": summary, "rows": rows}, indent=1))
    console.print(f"wrote {out / 'log_damage.json'}")
    ok = all(r["detected"] and r["localised"] and r["intact_kept"] and r["loss_stated"] for r in rows)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
