"""The episode log's MCAP writer writes the ``mcap`` library's bytes for the same calls, batches
cut anywhere, chunks closed where the library closes them, uncompressed and zstd."""

from __future__ import annotations

import io
import random

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType, Writer

from deft_gym.record.mcapwrite import MESSAGE_FIELDS, MESSAGE_HEAD, LogWriter


def _calls(seed: int) -> list[tuple]:
    """A log's calls: schemas and channels (one big schema), metadata, messages of random sizes
    (some times out of order), a channel and metadata in the middle."""
    rng = random.Random(seed)
    calls: list[tuple] = [("schema", "s1", "jsonschema", b"{}"), ("schema", "big", "jsonschema", b"x" * 40_000),
                          ("channel", "/a", "json", 1, {"role": "a"}), ("channel", "/b", "json", 2, {}),
                          ("meta", "deft_gym.episode", {"k": "v"})]
    t = 1_700_000_000 * 10**9
    for i in range(3000):
        t += rng.randrange(0, 10_000_000)
        if i == 1500:
            calls.append(("channel", "/new", "json", 0, {}))
            calls.append(("meta", "mid", {"at": "1500"}))
        cid = 3 if i > 1500 and i % 7 == 0 else 1 + i % 2
        late = t - rng.randrange(0, 5_000_000) if i % 97 == 0 else t
        calls.append(("msg", cid, late, rng.randbytes(rng.choice((3, 150, 1200, 5000, 40_000))), i % 50_000))
    calls.append(("meta", "deft_gym.outcome", {"outcome": "ok"}))
    return calls


def _reference(calls: list[tuple], compress: bool) -> bytes:
    out = io.BytesIO()
    w = Writer(out, chunk_size=32 * 1024, compression=CompressionType.ZSTD if compress else CompressionType.NONE,
               index_types=IndexType.CHUNK | IndexType.METADATA, enable_crcs=True, enable_data_crcs=True)
    w.start(profile="", library="deft_gym")
    for op, *a in calls:
        if op == "schema":
            w.register_schema(*a)
        elif op == "channel":
            w.register_channel(*a)
        elif op == "meta":
            w.add_metadata(*a)
        else:
            cid, t, data, seq = a
            w.add_message(cid, t, data, t, seq)
    w.finish()
    return out.getvalue()


def _ours(calls: list[tuple], compress: bool, seed: int) -> bytes:
    rng = random.Random(seed)
    out = io.BytesIO()
    w = LogWriter(out, 32 * 1024, compress)
    w.start(profile="", library="deft_gym")
    buf, ends, times, cids = bytearray(), [], [], []

    def flush() -> None:
        w.add_batch((bytes(buf), ends[:], times[:], cids[:]))
        buf.clear(), ends.clear(), times.clear(), cids.clear()

    for op, *a in calls:
        if op != "msg":
            flush()
            {"schema": w.register_schema, "channel": w.register_channel, "meta": w.add_metadata}[op](*a)
            continue
        cid, t, data, seq = a
        buf += MESSAGE_HEAD.pack(5, MESSAGE_FIELDS + len(data), cid, seq, t, t) + data
        ends.append(len(buf)), times.append(t), cids.append(cid)
        if rng.random() < 0.02:
            flush()
    flush()
    w.finish()
    return out.getvalue()


@pytest.mark.parametrize("compress", [False, True])
@pytest.mark.parametrize("seed", [0, 1])
def test_the_mcap_librarys_bytes(compress: bool, seed: int) -> None:
    calls = _calls(seed)
    ours = _ours(calls, compress, seed)
    assert ours == _reference(calls, compress)
    reader = make_reader(io.BytesIO(ours), validate_crcs=True)
    assert sum(1 for _ in reader.iter_messages()) == sum(1 for c in calls if c[0] == "msg")


def test_single_messages_and_an_empty_log() -> None:
    for calls in ([], [("schema", "s", "jsonschema", b"{}"), ("channel", "/a", "json", 1, {}),
                       ("msg", 1, 5, b"{}", 0), ("msg", 1, 3, b"[]", 1)]):
        out = io.BytesIO()
        w = LogWriter(out)
        w.start(profile="", library="deft_gym")
        for op, *a in calls:
            if op == "msg":
                cid, t, data, seq = a
                w.add_message(cid, t, data, t, seq)
            else:
                {"schema": w.register_schema, "channel": w.register_channel}[op](*a)
        w.finish()
        assert out.getvalue() == _reference(calls, False)
