"""The compiled payload snapshot (deft_gym/record/_snapshot_c.c): every plain payload comes back with
the same types, key order and float bits; anything else goes through pickle; malformed data is
a ValueError."""

from __future__ import annotations

import math
import pickle
import random
import struct

import numpy as np
import pytest

from deft_gym.bus.codec import encode
from deft_gym.bus.messages import Message
from deft_gym.record.worker import PyBatch, py_read_batch
from deft_gym.sim.simulation import Simulation
from tests.support.fixtures import SCENARIOS, same_values

_snapshot_c = pytest.importorskip("deft_gym.record._snapshot_c")
dumps, loads = _snapshot_c.dumps, _snapshot_c.loads

SCENARIO = SCENARIOS / "lane_follow_static.yaml"




def _round_trip(obj) -> bytes:
    data = dumps(obj)
    assert data[:1] == b"S", "a plain payload is written in the snapshot format"
    back = loads(data)
    assert same_values(obj, back)
    assert same_values(loads(bytearray(data)), back) and same_values(loads(memoryview(data)), back)
    return data


ODD_FLOATS = [0.0, -0.0, 1e-300, -1e300, 5e-324, math.inf, -math.inf, math.nan,
              struct.unpack("<d", struct.pack("<Q", 0x7FF8_0000_0000_0123))[0],  # a NaN with a payload
              struct.unpack("<d", struct.pack("<Q", 0xFFF0_0000_0000_0001))[0],  # a signalling NaN
              0.1 + 0.2, 2.0**53 + 1]


def test_every_message_of_a_run_round_trips() -> None:
    topics: dict[str, int] = {}

    def check(m) -> None:
        data = dumps(m.payload)
        assert data[:1] == b"S" and same_values(loads(data), m.payload)
        assert encode(loads(data)) == encode(m.payload)  # what the recorder process writes
        topics[m.topic] = topics.get(m.topic, 0) + 1

    sim = Simulation(SCENARIO, jitter_seed=2, keep_planning=False)
    sim.bus.taps.append(check)
    sim.run()
    assert len(topics) >= 7 and sum(topics.values()) > 1000


def test_odd_values_round_trip() -> None:
    _round_trip(ODD_FLOATS)  # an all-float list
    _round_trip([*ODD_FLOATS, 1])  # a mixed list
    _round_trip({"f": ODD_FLOATS[3], "l": [], "d": {}, "t": (), "s": "", "n": None})
    _round_trip([True, False, 1, 0, None, 2**63 - 1, -(2**63), -1])  # bools stay bools
    _round_trip({"é": "Ünïcode ✓ 🚗", 3: "int key", (1, 2.5): "tuple key", None: [[[1.5]]]})
    _round_trip(("a", ("b", ("c", [1.0, {"x": (2.0,)}]))))
    _round_trip({f"k{i}": i for i in range(300)})  # key order of a large dict
    _round_trip("x" * 100_000)  # grows the buffer


class F(float):
    """A float subclass (pickled, as the snapshot takes exact types only)."""


def test_other_values_are_pickled() -> None:
    for obj in ({"x": np.float64(1.5)}, [np.arange(3)], {"big": 2**63}, [-(2**63) - 1], {"s": "\ud800"},
                [F(1.0)], {1.0, 2.0}, b"bytes", [1, [2, [bytearray(b"x")]]]):
        data = dumps(obj)
        assert data[:1] == b"\x80" and data == pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
        back = loads(data)
        if isinstance(obj, dict) and "x" in obj:
            assert type(back["x"]) is np.float64
        else:
            assert repr(back) == repr(obj)


def test_deep_or_recursive_trees_are_pickled() -> None:
    deep: list = []
    node = deep
    for _ in range(100):
        node.append([])
        node = node[0]
    assert dumps(deep)[:1] == b"\x80" and loads(dumps(deep)) == deep
    with pytest.raises(AttributeError, match="local object"):  # what pickle cannot take fails as in pickle
        dumps({"f": lambda: None})
    shallow: list = [[[[1.0]]]]
    _round_trip(shallow)
    loop: list = [1.0]
    loop.append(loop)
    back = loads(dumps(loop))
    assert back[1] is back  # pickle keeps the cycle


def test_random_trees_round_trip() -> None:
    rng = random.Random(7)

    def tree(depth: int):
        kind = rng.randrange(9 if depth < 6 else 5)
        if kind == 0:
            return struct.unpack("<d", rng.randbytes(8))[0]  # any bit pattern
        if kind == 1:
            return rng.randrange(-(2**63), 2**63)
        if kind == 2:
            return "".join(chr(rng.randrange(1, 0xD000)) for _ in range(rng.randrange(6)))
        if kind == 3:
            return rng.choice([True, False, None])
        if kind == 4:
            return [rng.uniform(-1e6, 1e6) for _ in range(rng.randrange(40))]
        if kind in (5, 6):
            return {f"k{rng.randrange(50)}": tree(depth + 1) for _ in range(rng.randrange(5))}
        if kind == 7:
            return [tree(depth + 1) for _ in range(rng.randrange(5))]
        return tuple(tree(depth + 1) for _ in range(rng.randrange(4)))

    for _ in range(500):
        _round_trip(tree(0))


def test_malformed_data_is_a_value_error() -> None:
    data = dumps({"header": {"seq": 1, "module": "m"}, "x": [1.0, 2.0], "t": (1, "a"), "ok": True})
    for n in range(1, len(data)):
        with pytest.raises(ValueError, match="truncated or malformed"):
            loads(data[:n])
    for bad in (data + b"N", b"S?", b"S" + b"l" + struct.pack("=q", -1), b"S" + b"F" + struct.pack("=q", 2**62)):
        with pytest.raises(ValueError, match="truncated or malformed"):
            loads(bad)
    with pytest.raises(UnicodeDecodeError):
        loads(b"S" + b"s" + struct.pack("=q", 1) + b"\xff")
    with pytest.raises(TypeError):  # an unhashable key
        loads(b"S" + b"d" + struct.pack("=q", 1) + b"l" + struct.pack("=q", 0) + b"N")


def _messages(n: int) -> list[Message]:
    out = []
    for i in range(n):
        payload = {"header": {"seq": i, "stamp": i / 3}, "x": [i * 0.5, -0.0, math.nan], "ok": i % 2 == 0}
        if i % 5 == 4:
            payload["np"] = np.float64(i)  # pickled
        out.append(Message(f"/topic/{i % 3}/é", i, 10_000_000 * i, payload))
    return out


def test_batch_entries_read_back_in_order() -> None:
    flushed: list[bytes] = []
    batch = _snapshot_c.Batch(4, lambda: flushed.append(batch.take()))
    msgs = _messages(10)
    for m in msgs:
        batch(m)
    assert (batch.count, batch.total, batch.limit, len(flushed)) == (2, 10, 4, 2)
    flushed.append(batch.take())
    assert batch.count == 0 and batch.take() == b""
    entries = [e for data in flushed for e in _snapshot_c.read_batch(data)]
    assert len(entries) == 10
    for (topic, ns, payload, seq), m in zip(entries, msgs, strict=True):
        assert (topic, ns, seq) == (m.topic, m.publish_ns, m.seq) and same_values(payload, m.payload)


def test_python_batch_writes_the_same_entries() -> None:
    """PyBatch (no compiled module) frames entries as Batch does; with every payload pickled the
    bytes are the same, and each reader reads the other's batches."""
    msgs = [Message(m.topic, m.seq, m.publish_ns, {**m.payload, "np": np.float64(1)}) for m in _messages(6)]
    c, py = _snapshot_c.Batch(100, lambda: None), PyBatch(100, lambda: None)
    for m in msgs:
        c(m)
        py(m)
    data = c.take()
    assert data == py.take()
    assert repr(py_read_batch(data)) == repr(_snapshot_c.read_batch(data))
    c2 = _snapshot_c.Batch(100, lambda: None)
    for m in _messages(6):
        c2(m)
    assert [e[::3] for e in _snapshot_c.read_batch(c2.take())] == [(m.topic, m.seq) for m in _messages(6)]


def test_batch_errors_leave_the_batch_as_it_was() -> None:
    batch = _snapshot_c.Batch(10, lambda: None)
    batch(Message("/a", 0, 0, {"v": 1.0}))
    before = batch.count
    with pytest.raises(TypeError, match="topic must be a str"):
        batch(Message(b"/a", 1, 1, {}))  # type: ignore[arg-type]
    with pytest.raises(AttributeError, match="local object"):
        batch(Message("/a", 1, 1, {"f": lambda: None}))
    with pytest.raises(OverflowError):
        batch(Message("/a", 2**64, 1, {}))
    with pytest.raises(TypeError, match="one message"):
        batch()
    assert batch.count == before and len(_snapshot_c.read_batch(batch.take())) == 1
    for bad in ((0, lambda: None), (1, 5)):
        for cls in (_snapshot_c.Batch, PyBatch):
            with pytest.raises(ValueError, match="limit >= 1"):
                cls(*bad)


def test_truncated_batches_are_value_errors() -> None:
    for cls in (_snapshot_c.Batch, PyBatch):
        batch = cls(10, lambda: None)
        ends = []  # where each entry ends
        for m in _messages(3):
            batch(m)
            ends.append(len(batch.take()) + (ends[-1] if ends else 0))
        for m in _messages(3):
            batch(m)
        data = batch.take()
        assert len(data) == ends[-1]
        readers = [_snapshot_c.read_batch] + ([py_read_batch] if cls is PyBatch else [])
        for read in readers:
            assert len(read(data)) == 3
            for n in range(1, len(data)):
                if n in ends:
                    assert len(read(data[:n])) == ends.index(n) + 1
                    continue
                with pytest.raises((ValueError, UnicodeDecodeError, pickle.UnpicklingError, EOFError)):
                    read(data[:n])
