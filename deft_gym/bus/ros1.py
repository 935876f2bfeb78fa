"""Binary payloads: the ROS 1 serialisation of a topic's messages, laid out by its JSON schema.

A role whose schema has only numbers, integers, booleans, strings, arrays of numbers, objects and
arrays of objects (every bus role but ``routing`` and ``map``) is written to the log in ROS 1's
binary serialisation (MCAP message encoding ``ros1``, schema encoding ``ros1msg``; Foxglove reads
both): little-endian ``float64``/``int64``/``bool``, ``string`` and arrays as a ``uint32`` count
and their items. An object's optional properties (``decision`` and ``debug`` of a plan, ``intent``
of a predicted obstacle) travel as one JSON object in a last ``string json_rest`` field (empty:
none). Its :class:`Layout` is derived from :data:`~deft_gym.bus.messages.SCHEMAS`; readers build it
back from the schema text in the log (:func:`parse_definition`), so a log is read by its own
layout.

A payload is written this way only when it fits its layout exactly - a dict with the layout's keys
in its order, then only optional ones; floats of Python type ``float``, integers of type ``int``
within int64, booleans, strings that UTF-8 can hold, lists - so that :func:`decode` gives back the
same values (every float bit for bit) and re-encoding them as JSON gives the JSON the log would
have held (:func:`json_bytes`; the behaviour digests are taken over it). Anything else (an
injected exceptional value of another type, an int where a float belongs, a numpy value, a
non-finite float in the JSON part) makes :func:`encode` return None, and the recorder writes that
message as JSON on a JSON channel of the same topic. Encoding and decoding (:func:`decoder`) are
compiled in ``_ros1_c`` (the same bytes and values; this file is the Python version).
"""

from __future__ import annotations

import os
import struct
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache, lru_cache
from pathlib import Path
from typing import Any

import orjson

from deft_gym.bus.codec import _default
from deft_gym.bus.codec import decode as decode_json
from deft_gym.bus.codec import encode as encode_json
from deft_gym.files import checked_kernel

F64, I64, BOOL, STR, F64S, OBJ, OBJS = range(7)
#: the last field of an object with optional properties: those properties as one JSON object
REST_FIELD = "json_rest"
MESSAGE_ENCODING = "ros1"
SCHEMA_ENCODING = "ros1msg"
_SEPARATOR = "=" * 80
_ROS_TYPE = {F64: "float64", I64: "int64", BOOL: "bool", STR: "string", F64S: "float64[]"}
_KIND = {v: k for k, v in _ROS_TYPE.items()}
_SCALAR = {F64: "d", I64: "q", BOOL: "?"}
_U32 = struct.Struct("<I")
_OPTS = orjson.OPT_SERIALIZE_NUMPY

# (key, kind, sub-program) per field and whether optional keys follow as JSON: what _ros1_c walks
Program = tuple[tuple[tuple[str, int, Any], ...], bool]

try:
    from deft_gym.bus import _ros1_c
except ImportError:  # not compiled: the Python version below
    _ros1_c = None
# a kernel built before this file or _ros1_c.c was edited is not used (the edit must count)
_ros1_c = checked_kernel(_ros1_c, Path(__file__).with_name("_ros1_c.c"), Path(__file__))


@dataclass(frozen=True)
class Layout:
    """One ROS 1 message type: ``name`` (``pkg/Type``), its fields as ``(key, kind, sub-layout of
    an object or array of objects, comment)`` and whether optional keys follow (``rest``)."""

    name: str
    fields: tuple[tuple[str, int, Layout | None, str], ...]
    rest: bool = False

    @property
    def program(self) -> Program:
        """The nested tuples :func:`encode` walks."""
        return _program(self)

    def definition(self) -> bytes:
        """The ``ros1msg`` schema text: this type, then every nested type after a separator line."""
        nested: dict[str, Layout] = {}
        self._collect(nested)
        parts = [self._text()] + [f"{_SEPARATOR}\nMSG: {t.name}\n{t._text()}" for t in nested.values()]
        return "\n".join(parts).encode()

    def _collect(self, into: dict[str, Layout]) -> None:
        for _, _, sub, _ in self.fields:
            if sub is not None and sub.name not in into:
                into[sub.name] = sub
                sub._collect(into)

    def _text(self) -> str:
        lines = []
        for key, kind, sub, comment in self.fields:
            ros = _ROS_TYPE.get(kind) or (sub.name + ("[]" if kind == OBJS else ""))
            lines.append(f"{ros} {key}" + (f"  # {comment}" if comment else ""))
        if self.rest:
            lines.append(f"string {REST_FIELD}  # the object's other (optional) keys as one JSON object; empty: none")
        return "\n".join(lines) + "\n"


@cache
def _program(layout: Layout) -> Program:
    return tuple((key, kind, None if sub is None else _program(sub)) for key, kind, sub, _ in layout.fields), layout.rest


def _comment(prop: dict[str, Any]) -> str:
    unit = prop.get("x-unit")
    frame = prop.get("x-frame")
    text = " ".join(str(prop.get("description", "")).split())
    return (f"[{unit}] " if unit and unit != "1" else "") + text + (f" ({frame})" if frame else "")


def layout_of_schema(schema: dict[str, Any], name: str) -> Layout | None:
    """The layout of an object schema (named ``name``), or None when a required property has no
    ROS 1 form here (an array of strings, a mixed array, an object without properties)."""
    props = schema.get("properties")
    if schema.get("type") != "object" or not props:
        return None
    required = schema.get("required", list(props))
    fields = []
    for key, prop in props.items():
        if key not in required:
            continue
        kind, sub = _kind_of(prop, f"{name}_{key}")
        if kind is None:
            return None
        fields.append((key, kind, sub, _comment(prop)))
    return Layout(name, tuple(fields), rest=len(fields) < len(props))


def _kind_of(prop: dict[str, Any], name: str) -> tuple[int | None, Layout | None]:
    t = prop.get("type")
    if t in ("number", "integer", "boolean", "string"):
        return {"number": F64, "integer": I64, "boolean": BOOL, "string": STR}[t], None
    if t == "object":
        sub = layout_of_schema(prop, name)
        return (None, None) if sub is None else (OBJ, sub)
    if t == "array" and isinstance(items := prop.get("items"), dict):
        if items.get("type") == "number":
            return F64S, None
        if items.get("type") == "object" and (sub := layout_of_schema(items, name)) is not None:
            return OBJS, sub
    return None, None


def role_layouts(schemas: dict[str, dict[str, Any]]) -> dict[str, Layout]:
    """The layout of every role that has one (``pkg/Type`` from the schema's title)."""
    out = {}
    for role, schema in schemas.items():
        layout = layout_of_schema(schema, schema["title"].replace(".", "/"))
        if layout is not None:
            out[role] = layout
    return out


# ---------------------------------------------------------------------------------------------
# writing

def encode(program: Program, payload: Any) -> bytes | None:
    """The ROS 1 bytes of ``payload`` laid out by ``program`` (:attr:`Layout.program`), or None
    when it does not fit the layout exactly (the recorder then writes it as JSON)."""
    if _kernel is not None:
        return _kernel(program, payload)
    out = bytearray()
    try:
        return bytes(out) if _put(program, payload, out) else None
    except (TypeError, UnicodeEncodeError, OverflowError, struct.error):
        return None


def _put(program: Program, obj: Any, out: bytearray) -> bool:  # compiled in _ros1_c.c (the same bytes)
    fields, rest = program
    if type(obj) is not dict or len(obj) < len(fields) or (not rest and len(obj) != len(fields)):
        return False
    items = iter(obj.items())
    for (key, kind, sub), (k, v) in zip(fields, items):
        if k != key:
            return False
        t = type(v)
        if kind == F64:
            if t is not float:
                return False
            out += struct.pack("<d", v)
        elif kind == I64:
            if t is not int or not -(1 << 63) <= v < (1 << 63):
                return False
            out += struct.pack("<q", v)
        elif kind == BOOL:
            if t is not bool:
                return False
            out.append(v)
        elif kind == STR:
            if t is not str:
                return False
            data = v.encode()
            out += _U32.pack(len(data)) + data
        elif kind == F64S:
            if t is not list or any(type(x) is not float for x in v):
                return False
            out += _U32.pack(len(v)) + struct.pack(f"<{len(v)}d", *v)
        elif kind == OBJ:
            if not _put(sub, v, out):
                return False
        else:  # OBJS
            if t is not list:
                return False
            out += _U32.pack(len(v))
            for item in v:
                if not _put(sub, item, out):
                    return False
    if rest:
        extra = dict(items)
        data = orjson.dumps(extra, default=_default, option=_OPTS) if extra else b""
        if b"null" in data:  # a non-finite float (or a None): the JSON of the whole payload tags it
            return False
        out += _U32.pack(len(data)) + data
    return True


_kernel = None if _ros1_c is None or os.environ.get("DEFT_GYM_PURE_PYTHON") else _ros1_c.encode
if _kernel is not None:
    _ros1_c.configure(orjson.dumps, {"default": _default, "option": _OPTS}, decode_json)
#: :func:`encode` without the Python call in front where it is compiled (the recorder's tap calls it)
encode_fast: Callable[[Program, Any], bytes | None] = _kernel or encode


# ---------------------------------------------------------------------------------------------
# reading

def parse_definition(text: bytes | str) -> Layout:
    """The layout of a ``ros1msg`` schema text written by :meth:`Layout.definition` (ValueError
    for a type this reader does not know)."""
    if isinstance(text, bytes | bytearray | memoryview):
        text = bytes(text).decode()
    sections = [s.strip("\n") for s in text.split(_SEPARATOR)]
    bodies = {"": sections[0]}
    for s in sections[1:]:
        head, _, body = s.partition("\n")
        if not head.startswith("MSG: "):
            raise ValueError(f"ros1msg schema: expected 'MSG: <type>' after a separator, got {head!r}")
        bodies[head[5:].strip()] = body
    built: dict[str, Layout] = {}

    def build(name: str, body: str) -> Layout:
        fields: list[tuple[str, int, Layout | None, str]] = []
        rest = False
        for line in body.splitlines():
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            parts = line.split()
            if len(parts) != 2 or "=" in line:
                raise ValueError(f"ros1msg schema of {name or 'the message'}: cannot read {line!r}")
            ros, key = parts
            if rest:
                raise ValueError(f"ros1msg schema of {name or 'the message'}: {REST_FIELD} must be the last field")
            if ros == "string" and key == REST_FIELD:
                rest = True
            elif ros in _KIND:
                fields.append((key, _KIND[ros], None, ""))
            else:
                sub_name = ros[:-2] if ros.endswith("[]") else ros
                if sub_name not in bodies:
                    raise ValueError(f"ros1msg schema: type {ros!r} of field {key!r} is not one this reader knows")
                if sub_name not in built:
                    built[sub_name] = build(sub_name, bodies[sub_name])
                fields.append((key, OBJS if ros.endswith("[]") else OBJ, built[sub_name], ""))
        return Layout(name, tuple(fields), rest)

    return build("", bodies[""])


def _reader(layout: Layout) -> Callable[[memoryview, int], tuple[dict[str, Any], int]]:
    """A function reading one object of ``layout`` at an offset: ``(value, offset after it)``;
    consecutive scalars are read by one struct."""
    steps: list[tuple[int, Any, Any]] = []
    run: list[tuple[str, str]] = []

    def close_run() -> None:
        if run:
            steps.append((-1, tuple(k for k, _ in run), struct.Struct("<" + "".join(c for _, c in run))))
            run.clear()

    for key, kind, sub, _ in layout.fields:
        if kind in _SCALAR:
            run.append((key, _SCALAR[kind]))
        else:
            close_run()
            steps.append((kind, key, None if sub is None else _reader(sub)))
    close_run()
    rest = layout.rest
    u32 = _U32.unpack_from
    unpack_from = struct.unpack_from

    def read(buf: memoryview, off: int) -> tuple[dict[str, Any], int]:
        out: dict[str, Any] = {}
        for kind, key, aux in steps:
            if kind == -1:
                out.update(zip(key, aux.unpack_from(buf, off)))
                off += aux.size
            elif kind == F64S:
                (n,) = u32(buf, off)
                out[key] = list(unpack_from(f"<{n}d", buf, off + 4))
                off += 4 + 8 * n
            elif kind == STR:
                (n,) = u32(buf, off)
                off += 4
                if off + n > len(buf):
                    raise ValueError("not a message of its ros1 schema: a string runs past the end of the message")
                out[key] = str(buf[off:off + n], "utf-8")
                off += n
            elif kind == OBJ:
                out[key], off = aux(buf, off)
            else:  # OBJS
                (n,) = u32(buf, off)
                off += 4
                items = []
                for _ in range(n):
                    value, off = aux(buf, off)
                    items.append(value)
                out[key] = items
        if rest:
            (n,) = u32(buf, off)
            off += 4
            if n:
                if off + n > len(buf):
                    raise ValueError("not a message of its ros1 schema: the JSON part runs past the end of the message")
                extra = decode_json(bytes(buf[off:off + n]))
                if type(extra) is not dict:
                    raise ValueError(f"{REST_FIELD} is not a JSON object")
                out.update(extra)
                off += n
        return out, off

    return read


@lru_cache(maxsize=64)
def decoder(definition: bytes) -> Callable[[bytes], dict[str, Any]]:
    """The function decoding messages of a ``ros1msg`` schema text (cached per text); it raises
    ValueError for bytes that are not one whole message of it. Compiled in ``_ros1_c`` (the same
    values)."""
    layout = parse_definition(definition)
    if _kernel is not None:
        program, kernel_decode = layout.program, _ros1_c.decode

        def decode_compiled(data: bytes) -> dict[str, Any]:
            return kernel_decode(program, data)

        return decode_compiled
    return python_decoder(layout)


def python_decoder(layout: Layout) -> Callable[[bytes], dict[str, Any]]:  # compiled in _ros1_c.c
    """:func:`decoder`'s Python version, for ``layout``."""
    read = _reader(layout)

    def decode(data: bytes) -> dict[str, Any]:
        buf = memoryview(data)
        try:
            out, end = read(buf, 0)
        except (struct.error, UnicodeDecodeError, OverflowError) as exc:
            raise ValueError(f"not a message of its ros1 schema: {exc}") from None
        if end != len(buf):
            raise ValueError(f"not a message of its ros1 schema: {len(buf) - end} byte(s) after its end")
        return out

    return decode


def payload_decoder(message_encoding: str, schema_encoding: str | None = None,
                    schema_data: bytes | None = None) -> Callable[[bytes], Any]:
    """How to decode a channel's messages: JSON (``json``) or ROS 1 by the channel's ``ros1msg``
    schema; ValueError names any other encoding."""
    if message_encoding == "json":
        return decode_json
    if message_encoding == MESSAGE_ENCODING and schema_encoding == SCHEMA_ENCODING and schema_data:
        return decoder(bytes(schema_data))
    raise ValueError(f"message encoding {message_encoding!r} (schema {schema_encoding!r}): expected 'json', or "
                     f"'ros1' with a 'ros1msg' schema")


def channel_decoder(schema: Any, channel: Any) -> Callable[[bytes], Any]:
    """:func:`payload_decoder` of an ``mcap`` reader's schema (None for none) and channel."""
    if schema is None:
        return payload_decoder(channel.message_encoding)
    return payload_decoder(channel.message_encoding, schema.encoding, schema.data)


class ChannelDecoders:
    """Decodes messages read with the ``mcap`` reader, by their channel's encoding (each channel's
    decoder made once): ``decoders(schema, channel, data)``; ``decoders.json(...)`` gives the
    JSON the log would hold on a JSON channel."""

    def __init__(self) -> None:
        self._by_id: dict[int, Callable[[bytes], Any]] = {}

    def _of(self, schema: Any, channel: Any) -> Callable[[bytes], Any]:
        dec = self._by_id.get(channel.id)
        if dec is None:
            dec = self._by_id[channel.id] = channel_decoder(schema, channel)
        return dec

    def __call__(self, schema: Any, channel: Any, data: bytes) -> Any:
        return self._of(schema, channel)(data)

    def json(self, schema: Any, channel: Any, data: bytes) -> bytes:
        return json_bytes(self._of(schema, channel), data)


def json_bytes(decode: Callable[[bytes], Any], data: bytes) -> bytes:
    """The JSON of a message as the log would hold it on a JSON channel (``data`` itself when
    ``decode`` is JSON's): what frames files and the behaviour digests take."""
    if decode is decode_json:
        return bytes(data)
    return encode_json(decode(data))
