"""The exceptional-values dictionary, per field type, plus likely-valid values.

As in Ballista and ASTAA (section 2.1, 3.2.2), test values come from a small dictionary per type
rather than from the whole input space. Every entry is a named mutation ``old -> new`` so a test
case stores a name (``float.nan``), never a raw value, and array entries can be built from the
message's own contents (``array.repeated`` repeats its first element). Likely-valid entries
(``exceptional=False``) let a test mix valid and exceptional fields.

Entries that need the previous message's value (``float.stale``: a timestamp that does not
advance) receive it as ``prev``.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from deft_gym.robustness.spec import FIELD_TYPES, FieldSpec

LONG_NUMBERS = 10_000  # elements of a "very long" numeric array
LONG_OBJECTS = 1_000  # elements of a "very long" array of objects


class UnknownEntry(KeyError, ValueError):
    """A name that is not in the dictionary."""

    def __str__(self) -> str:
        return str(self.args[0])


@dataclass(frozen=True)
class Mutation:
    """One dictionary entry: applies to ``types``; ``fn(old, prev)`` gives the new value."""

    name: str
    types: tuple[str, ...]
    exceptional: bool
    fn: Callable[[Any, Any], Any]
    doc: str = ""
    units: tuple[str, ...] = ()  # restrict to fields with these units (empty: any unit)


def _const(v: Any) -> Callable[[Any, Any], Any]:
    return lambda old, prev: v


def _long(old: Any, prev: Any) -> Any:
    if not isinstance(old, list) or not old:
        return old
    n = LONG_OBJECTS if isinstance(old[0], dict | list) else LONG_NUMBERS
    return (old * (n // len(old) + 1))[:n]


def _wrong_type(old: Any, prev: Any) -> Any:
    if isinstance(old, bool):
        return "true"
    if isinstance(old, int | float):
        return repr(old)
    if isinstance(old, str):
        return 0
    if isinstance(old, list):
        return {"items": old}
    return [old]


_I64 = 2**63
ENTRIES: list[Mutation] = [
    # floats: IEEE special values, extremes of the format, huge and tiny magnitudes
    Mutation("float.nan", ("float",), True, _const(math.nan), "NaN"),
    Mutation("float.inf", ("float",), True, _const(math.inf), "+infinity"),
    Mutation("float.neg_inf", ("float",), True, _const(-math.inf), "-infinity"),
    Mutation("float.zero", ("float",), True, _const(0.0), "+0.0"),
    Mutation("float.neg_zero", ("float",), True, _const(-0.0), "-0.0"),
    Mutation("float.max", ("float",), True, _const(sys.float_info.max), "largest double"),
    Mutation("float.neg_max", ("float",), True, _const(-sys.float_info.max), "most negative double"),
    Mutation("float.min_normal", ("float",), True, _const(sys.float_info.min), "smallest normal double"),
    Mutation("float.subnormal", ("float",), True, _const(5e-324), "smallest subnormal double"),
    Mutation("float.neg_subnormal", ("float",), True, _const(-5e-324), "negative subnormal"),
    Mutation("float.huge", ("float",), True, _const(1e300), "huge magnitude"),
    Mutation("float.neg_huge", ("float",), True, _const(-1e300), "huge negative magnitude"),
    Mutation("float.tiny", ("float",), True, _const(1e-300), "tiny magnitude"),
    Mutation("float.int_limit", ("float",), True, _const(9007199254740993.0), "2^53 + 1 (not exact)"),
    # timestamps: stale (does not advance), backwards, far future
    Mutation("float.stale", ("float",), True, lambda old, prev: old if prev is None else prev,
             "the previous message's value (a stale stamp)", units=("s",)),
    Mutation("float.backwards", ("float",), True,
             lambda old, prev: old - 1.0 if isinstance(old, float | int) else old,
             "one second in the past", units=("s",)),
    # likely-valid floats
    Mutation("float.one", ("float",), False, _const(1.0)),
    Mutation("float.neg_one", ("float",), False, _const(-1.0)),
    Mutation("float.half", ("float",), False, _const(0.5)),
    Mutation("float.ten", ("float",), False, _const(10.0)),
    Mutation("float.hundred", ("float",), False, _const(100.0)),
    Mutation("float.pi", ("float",), False, _const(math.pi)),
    Mutation("float.two_pi", ("float",), False, _const(2 * math.pi)),
    Mutation("float.negate", ("float",), False, lambda old, prev: -old if isinstance(old, float | int) else old),
    Mutation("float.double", ("float",), False, lambda old, prev: 2 * old if isinstance(old, float | int) else old),
    # integers: 0, -1 and the bounds of every width
    Mutation("int.zero", ("int",), True, _const(0)),
    Mutation("int.neg_one", ("int",), True, _const(-1)),
    Mutation("int.i8_min", ("int",), True, _const(-(2**7))),
    Mutation("int.i8_max", ("int",), True, _const(2**7 - 1)),
    Mutation("int.i16_min", ("int",), True, _const(-(2**15))),
    Mutation("int.i16_max", ("int",), True, _const(2**15 - 1)),
    Mutation("int.i32_min", ("int",), True, _const(-(2**31))),
    Mutation("int.i32_max", ("int",), True, _const(2**31 - 1)),
    Mutation("int.u32_max", ("int",), True, _const(2**32 - 1)),
    Mutation("int.i64_min", ("int",), True, _const(-_I64)),
    Mutation("int.i64_max", ("int",), True, _const(_I64 - 1)),
    Mutation("int.u64_max", ("int",), True, _const(2**64 - 1)),
    Mutation("int.one", ("int",), False, _const(1)),
    Mutation("int.two", ("int",), False, _const(2)),
    Mutation("int.next", ("int",), False, lambda old, prev: old + 1 if isinstance(old, int) else old),
    # strings
    Mutation("string.empty", ("string",), True, _const("")),
    Mutation("string.long", ("string",), True, _const("x" * 10_000)),
    Mutation("string.unicode", ("string",), True, _const("\u00e9\u2603\u0000\U0001f697")),
    Mutation("string.other", ("string",), False, lambda old, prev: f"{old}_1"),
    # enums: out of range, and other members (valid but possibly wrong)
    Mutation("enum.bogus", ("enum",), True, _const("__BOGUS__")),
    Mutation("enum.empty", ("enum",), True, _const("")),
    Mutation("enum.lower", ("enum",), True, lambda old, prev: old.lower() if isinstance(old, str) else old),
    Mutation("bool.flip", ("bool",), False, lambda old, prev: not old),
    # arrays: empty, one element, very long, repeated elements; likely-valid reorderings
    Mutation("array.empty", ("array",), True, _const([])),
    Mutation("array.one", ("array",), True, lambda old, prev: old[:1] if isinstance(old, list) else old),
    Mutation("array.long", ("array",), True, _long),
    Mutation("array.repeated", ("array",), True,
             lambda old, prev: [old[0]] * len(old) if isinstance(old, list) and old else old),
    Mutation("array.reversed", ("array",), False, lambda old, prev: old[::-1] if isinstance(old, list) else old),
    Mutation("array.drop_last", ("array",), False, lambda old, prev: old[:-1] if isinstance(old, list) else old),
    # any type: a missing value and a value of the wrong type
    Mutation("any.null", FIELD_TYPES, True, _const(None),
             "null (a missing value)"),
    Mutation("any.wrong_type", FIELD_TYPES, True, _wrong_type, "a value of another JSON type"),
]

DICTIONARY: dict[str, Mutation] = {m.name: m for m in ENTRIES}


def candidates(spec: FieldSpec, exceptional: bool | None = None) -> list[str]:
    """Names of the entries that apply to a field (``exceptional``: only those / only valid)."""
    out = []
    for m in ENTRIES:
        if spec.type not in m.types or (m.units and spec.unit not in m.units):
            continue
        if exceptional is not None and m.exceptional != exceptional:
            continue
        out.append(m.name)
    if spec.type == "enum" and exceptional is not True:
        out.extend(enum_members(spec))
    return out


def enum_members(spec: FieldSpec) -> list[str]:
    """Likely-valid enum entries: ``enum.member:<VALUE>`` for every member of the field."""
    return [f"enum.member:{v}" for v in spec.enum]


def lookup(name: str) -> Mutation:
    """The entry called ``name`` (``enum.member:<VALUE>`` sets one enum member)."""
    if name.startswith("enum.member:"):
        value = name.split(":", 1)[1]
        return Mutation(name, ("enum",), False, _const(value), f"the member {value}")
    try:
        return DICTIONARY[name]
    except KeyError:
        raise UnknownEntry(f"unknown dictionary entry {name!r}") from None


def mutate(name: str, old: Any, prev: Any = None) -> Any:
    """Apply the entry ``name`` to a value."""
    return lookup(name).fn(old, prev)
