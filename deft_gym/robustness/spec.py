"""The ASTAA test specification, derived from the message schemas.

ASTAA (section 3.1) starts from a description of the system's interfaces: the channels, the
message type on each and the fields with their types. DeFT-Gym's JSON schemas
(:data:`deft_gym.bus.messages.SCHEMAS`) already say all of that, so the specification is computed:
every topic role, its message type (the schema title) and every field reachable in it, as a
path (:mod:`.paths`) with a type the dictionary knows. Fields marked ``x-brittle`` (stamps,
sequence numbers, module names - meaning to the middleware rather than to the modules) are
listed but skipped by default, as section 3.4.3 advises.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from deft_gym.bus.messages import DEFAULT_TOPICS, ROLES, SCHEMAS

#: field types the exceptional-values dictionary covers
FIELD_TYPES = ("float", "int", "string", "enum", "bool", "array")

#: roles the planning, prediction and control modules consume (the simulator consumes control,
#: nobody consumes chassis): the default injection targets of a campaign
CONSUMED_ROLES = ("routing", "localization", "perception_obstacles", "traffic_light", "prediction",
                  "planning")


@dataclass(frozen=True)
class FieldSpec:
    """One injectable field of one topic role."""

    role: str
    path: str
    type: str
    unit: str = ""
    brittle: bool = False
    enum: tuple[str, ...] = ()
    item_type: str = ""  # arrays: float | int | string | object | tuple

    @property
    def key(self) -> str:
        """``role:path``, the field's name in reports."""
        return f"{self.role}:{self.path}"

    def as_dict(self) -> dict[str, Any]:
        return {"role": self.role, "path": self.path, "type": self.type, "unit": self.unit,
                "brittle": self.brittle, "enum": list(self.enum), "item_type": self.item_type}


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _walk(role: str, schema: dict[str, Any], path: str, brittle: bool) -> Iterator[FieldSpec]:
    brittle = brittle or bool(schema.get("x-brittle"))
    t = schema.get("type")
    unit = schema.get("x-unit", "")
    if t == "object":
        for key, sub in schema.get("properties", {}).items():
            yield from _walk(role, sub, _join(path, key), brittle)
    elif t == "array":
        items = schema.get("items", {})
        if isinstance(items, list):
            yield FieldSpec(role, path, "array", brittle=brittle, item_type="tuple")
            for i, sub in enumerate(items):
                yield from _walk(role, sub, f"{path}[{i}]", brittle)
        else:
            it = items.get("type", "")
            item_type = {"number": "float", "integer": "int"}.get(it, it)
            yield FieldSpec(role, path, "array", unit=items.get("x-unit", ""), brittle=brittle, item_type=item_type)
            yield from _walk(role, items, f"{path}[*]", brittle)
    elif t == "number":
        yield FieldSpec(role, path, "float", unit=unit, brittle=brittle)
    elif t == "integer":
        yield FieldSpec(role, path, "int", unit=unit, brittle=brittle)
    elif t == "boolean":
        yield FieldSpec(role, path, "bool", brittle=brittle)
    elif t == "string":
        enum = tuple(schema.get("enum", ()))
        yield FieldSpec(role, path, "enum" if enum else "string", brittle=brittle, enum=enum)


@dataclass
class TestSpecification:
    """Topics, message types and fields of the system under test."""

    __test__ = False  # not a pytest class

    topics: dict[str, str] = field(default_factory=lambda: dict(DEFAULT_TOPICS))
    fields: list[FieldSpec] = field(default_factory=list)
    message_types: dict[str, str] = field(default_factory=dict)

    @classmethod
    def from_schemas(cls, topics: dict[str, str] | None = None) -> TestSpecification:
        """The specification of every role in :data:`SCHEMAS`."""
        spec = cls(topics=dict(topics or DEFAULT_TOPICS))
        for role in ROLES:
            schema = SCHEMAS[role]
            spec.message_types[role] = schema["title"]
            spec.fields.extend(_walk(role, schema, "", False))
        return spec

    def select(self, roles: list[str] | tuple[str, ...] | None = None, brittle: bool = False) -> list[FieldSpec]:
        """Fields of ``roles`` (default: :data:`CONSUMED_ROLES`), brittle ones only if asked."""
        roles = tuple(roles) if roles else CONSUMED_ROLES
        return [f for f in self.fields if f.role in roles and (brittle or not f.brittle)]

    def normalise(self, role: str, path: str) -> str:
        """The schema path of a concrete one: list indices become ``[*]`` except the positions of
        fixed-shape tuples (lane ids), which are fields of their own."""
        from deft_gym.robustness.paths import parse

        tuples = {f.path for f in self.fields if f.role == role and f.item_type == "tuple"}
        out = ""
        for kind, v in parse(path):
            if kind == "key":
                out += ("." if out else "") + v
            elif kind == "idx" and out in tuples:
                out += f"[{v}]"
            else:
                out += "[*]"
        return out

    def field(self, role: str, path: str) -> FieldSpec | None:
        """The spec of a field by role and path (concrete indices allowed)."""
        norm = self.normalise(role, path)
        for f in self.fields:
            if f.role == role and f.path == norm:
                return f
        return None
