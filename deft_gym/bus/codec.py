"""JSON encoding of message payloads that round-trips every float bit-exactly.

orjson writes the shortest representation that parses back to the same double, ~20x faster
than the standard library. It writes NaN and +-inf as ``null`` though, so when the fast output
contains ``null`` the payload is encoded again with every non-finite float written as the
object ``{"$float": "NaN"}`` (``"Infinity"``, ``"-Infinity"``): plain JSON, which any JSON
reader - Foxglove's included - decodes, and which :func:`decode` turns back into the float.
(Logs written before used the JSON5 tokens ``NaN``/``Infinity``; :func:`decode` reads those too.)
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import orjson

_FAST_OPTS = orjson.OPT_SERIALIZE_NUMPY


def _default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, tuple):
        return list(obj)
    raise TypeError(f"cannot encode {type(obj).__name__} in a message payload")


def encode(payload: Any) -> bytes:
    """Encode a payload of plain values (dict, list, str, int, float, bool) to JSON bytes; a
    ``bytes`` payload is JSON already (the recorder's viewer topics) and is returned as is."""
    if type(payload) is bytes:
        return payload
    data = orjson.dumps(payload, default=_default, option=_FAST_OPTS)
    if b"null" in data:
        data = orjson.dumps(_plain(payload), option=_FAST_OPTS)
    return data


FLOAT_TAG = "$float"
_TAGGED = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}
_TAG_BYTES = b'{"$float":'


def decode(data: bytes | str) -> Any:
    """Decode JSON bytes written by :func:`encode` (tagged non-finite floats; also the JSON5
    ``NaN``/``Infinity`` tokens of older logs)."""
    try:
        out = orjson.loads(data)
    except orjson.JSONDecodeError:
        return json.loads(data)
    raw = data if isinstance(data, bytes | bytearray | memoryview) else str(data).encode()
    return _untag(out) if _TAG_BYTES in raw else out


def _untag(obj: Any) -> Any:
    if isinstance(obj, dict):
        if len(obj) == 1 and FLOAT_TAG in obj and obj[FLOAT_TAG] in _TAGGED:
            return _TAGGED[obj[FLOAT_TAG]]
        return {k: _untag(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_untag(v) for v in obj]
    return obj


def _plain(obj: Any) -> Any:
    """Numpy values and tuples as plain Python values, non-finite floats tagged."""
    if isinstance(obj, float):
        if math.isfinite(obj):
            return obj
        return {FLOAT_TAG: "NaN" if obj != obj else ("Infinity" if obj > 0 else "-Infinity")}
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return _plain(obj.item())
    return obj
