"""The recorder's compiled tap (deft_gym/record/_tap_c.c) hands on the records of its Python
version, byte for byte: plain payloads, non-finite floats, bytes, a topic without a channel, a
scene state, and the errors (a payload without a JSON form, a sequence number beyond 32 bits)."""

from __future__ import annotations

import math
import struct

import pytest

from deft_gym.bus.messages import SCENE_TOPIC, Message
from deft_gym.record import recorder
from deft_gym.record.scene import COMPACT

pytest.importorskip("deft_gym.record._tap_c")
if recorder._tap_c is None:
    pytest.skip("the compiled tap is stale or missing", allow_module_level=True)

MESSAGES = [
    Message("/a", 0, 0, {"header": {"seq": 0}, "v": [1.0, -0.0, 5e-324, 1e300], "s": "x\u00e9"}),
    Message("/a", 1, 10, {"v": math.nan}),  # non-finite: tagged by encode()
    Message("/b", 7, 20, b'{"already":"json"}'),
    Message("/new", 0, 30, {"w": 1}),  # no channel yet: one is made before it
    Message("/a", 2, 40, {"v": None}),
    Message(SCENE_TOPIC, 0, 50, {COMPACT: [[("ego", "ego", 1.0, 2.0, 0.1, 3.0, 5.0, 2.0)], [1.0, 2.0], [0.5, 0.6],
                                           "1.5", None]}),
    Message("/a", 3, 60, {"bad": {1, 2}}),  # no JSON form: held as the error
    Message("/new", 1, 70, {"w": 2}),
] + [Message("/b", 8 + i, 100 + i, {"i": i, "f": i / 3}) for i in range(20)]


def _records(compiled: bool, monkeypatch, messages: list[Message]) -> tuple[list, list[str], str | None]:
    if compiled:
        monkeypatch.delenv("DEFT_GYM_PURE_PYTHON", raising=False)
    else:
        monkeypatch.setenv("DEFT_GYM_PURE_PYTHON", "1")
    batches, new = [], []

    def new_channel(topic: str) -> int:
        new.append(topic)
        return 10 + len(new)

    monkeypatch.setattr(recorder.RecordTap, "BATCH", 7)  # flushes inside the run
    tap = recorder.RecordTap({"/a": 1, "/b": 2, SCENE_TOPIC: 3, "/deft_gym/tf": 4}, 1_700_000_000 * 10**9,
                             batches.append, new_channel)
    assert (type(tap.tap).__name__ == "Tap") == compiled
    for m in messages:
        tap.tap(m)
    tap.flush()
    return [(b"".join(p), e, t, c) for p, e, t, c in batches], new, tap.error


def test_compiled_tap_writes_the_python_records(monkeypatch) -> None:
    py = _records(False, monkeypatch, MESSAGES)
    c = _records(True, monkeypatch, MESSAGES)
    assert c == py
    assert py[1] == ["/new"] and "/a message 3" in py[2] and "set" in py[2]
    assert sum(len(b[3]) for b in py[0]) == len(MESSAGES) - 1 + 1  # the bad one left out, a scene is two


def test_out_of_range_fields_raise_as_in_python(monkeypatch) -> None:
    for bad in (Message("/a", 2**32, 0, {"v": 1}), Message("/a", -1, 0, {"v": 1}), Message("/a", 0, 2**64, {"v": 1})):
        for compiled in (False, True):
            with pytest.raises(struct.error):
                _records(compiled, monkeypatch, [bad])
