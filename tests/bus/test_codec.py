"""Message encoding: every float survives the JSON round trip bit for bit."""

from __future__ import annotations

import math
import random
import struct

import numpy as np

from deft_gym.bus.codec import decode, encode


def _bits(x: float) -> bytes:
    return struct.pack("<d", x)


def test_random_doubles_round_trip_bit_exactly() -> None:
    rng = random.Random(3)
    values = []
    while len(values) < 20000:
        x = struct.unpack("<d", struct.pack("<Q", rng.getrandbits(64)))[0]
        if math.isfinite(x):
            values.append(x)
    values += [5e-324, 2.2250738585072014e-308, 1.7976931348623157e308, -0.0, 0.1, 1 / 3]
    back = decode(encode({"v": values}))["v"]
    assert [_bits(v) for v in back] == [_bits(v) for v in values]


def test_non_finite_values_fall_back_to_json5_tokens() -> None:
    payload = {"a": [float("nan"), float("inf"), -float("inf"), 1.5], "b": {"c": float("nan")}}
    data = encode(payload)
    assert b"NaN" in data and b"Infinity" in data and b"null" not in data
    back = decode(data)
    assert math.isnan(back["a"][0]) and back["a"][1] == math.inf and back["a"][2] == -math.inf
    assert back["a"][3] == 1.5 and math.isnan(back["b"]["c"])


def test_numpy_values_encode_as_plain_numbers() -> None:
    payload = {"x": np.arange(3, dtype=float), "y": np.float64(0.1), "z": (1, 2)}
    assert decode(encode(payload)) == {"x": [0.0, 1.0, 2.0], "y": 0.1, "z": [1, 2]}
