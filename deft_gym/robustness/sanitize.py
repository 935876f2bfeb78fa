"""Input validation for the hardening wrappers (ASTAA section 4.2.2).

*Sanitisation* checks are univariate and come from the message schemas: JSON types, finite
numbers, magnitude bounds per unit, enum members, array sizes. *Consistency* checks are
multivariate and per message type: equally long trajectory/prediction series, increasing
trajectory times, positive sizes, stamps close to the bus clock and strictly increasing per
topic, routes that exist on the map, and a pose continuous with the last accepted one. :func:`problem` returns the first problem found (or None).
"""

from __future__ import annotations

import itertools
import math
from typing import Any

from deft_gym.bus.messages import SCHEMAS

#: magnitude bounds per unit (x-unit); positions are also checked against the map by callers
UNIT_BOUNDS = {"m": 1e5, "m/s": 100.0, "m/s^2": 100.0, "rad": 100.0, "rad/s": 100.0, "s": 1e7, "": 1e9}
MAX_ITEMS = 1000
MAX_STRING = 256
MAX_INT = 2**31 - 1


def _is_num(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _schema_problem(value: Any, schema: dict[str, Any], path: str) -> str | None:
    t = schema.get("type")
    if t == "number":
        if not _is_num(value) or not math.isfinite(value):
            return f"{path}: not a finite number ({value!r})"[:120]
        if abs(value) > UNIT_BOUNDS.get(schema.get("x-unit", ""), 1e9):
            return f"{path}: out of bounds ({value!r})"
    elif t == "integer":
        if not isinstance(value, int) or isinstance(value, bool) or abs(value) > MAX_INT:
            return f"{path}: not a 32-bit integer ({value!r})"[:120]
    elif t == "boolean":
        if not isinstance(value, bool):
            return f"{path}: not a boolean"
    elif t == "string":
        if not isinstance(value, str) or not value or len(value) > MAX_STRING:
            return f"{path}: not a valid string"
        if "enum" in schema and value not in schema["enum"]:
            return f"{path}: {value!r} is not one of {schema['enum']}"
    elif t == "array":
        if not isinstance(value, list) or len(value) > MAX_ITEMS:
            return f"{path}: not an array of at most {MAX_ITEMS} items"
        items = schema.get("items", {})
        if isinstance(items, list):
            if len(value) not in (0, len(items)):  # [] means "none" (e.g. no lane)
                return f"{path}: expected {len(items)} items"
            for i, (v, s) in enumerate(zip(value, items)):
                p = _schema_problem(v, s, f"{path}[{i}]")
                if p:
                    return p
        else:
            for i, v in enumerate(value):
                p = _schema_problem(v, items, f"{path}[{i}]")
                if p:
                    return p
    elif t == "object":
        if not isinstance(value, dict):
            return f"{path}: not an object"
        if schema.get("x-planner-defined"):  # the planner's own keys (a decision): any object
            return None
        props = schema.get("properties", {})
        for key in schema.get("required", ()):
            if key not in value:
                return f"{path}.{key}: missing"
        for key, sub in props.items():
            if key in value:
                p = _schema_problem(value[key], sub, f"{path}.{key}" if path else key)
                if p:
                    return p
    return None


def _lengths(*series: Any) -> set[int]:
    return {len(s) for s in series}


def _consistency(role: str, p: dict[str, Any], roadmap: Any) -> str | None:
    if role == "localization":
        if p["v"] < 0.0:
            return "v: negative speed"
    elif role in ("perception_obstacles", "prediction"):
        for i, ob in enumerate(p["obstacles"]):
            if not (0.0 < ob["length"] <= 50.0 and 0.0 < ob["width"] <= 10.0) or ob["v"] < 0.0:
                return f"obstacles[{i}]: size or speed out of range"
            if role == "prediction":
                if _lengths(ob["x"], ob["y"], ob["heading"]) != {len(ob["x"])} or not ob["x"]:
                    return f"obstacles[{i}]: inconsistent series"
                if not 0.0 < ob["dt"] <= 5.0:
                    return f"obstacles[{i}].dt: out of range"
    elif role == "planning":
        tr = p["trajectory"]
        n = len(tr["t"])
        if n < 2 or _lengths(tr["t"], tr["x"], tr["y"], tr["v"], tr["heading"], tr["a"]) != {n}:
            return "trajectory: inconsistent series"
        if any(b <= a for a, b in itertools.pairwise(tr["t"])):
            return "trajectory.t: not increasing"
        if min(tr["v"]) < -0.1:
            return "trajectory.v: reversing"
    elif role == "routing":
        if not 0.0 < p["cruise_speed"] <= 40.0:
            return "cruise_speed: out of range"
        if roadmap is not None:
            lane = tuple(p["destination"]["lane"])
            if not roadmap.has_lane(lane):
                return "destination.lane: not on the map"
            if not 0.0 <= p["destination"]["s"] <= roadmap.geom(lane).length + 1.0:
                return "destination.s: beyond the lane"
            for seg in p["segments"]:
                road = seg["road"]
                if len(road) != 2 or not all(roadmap.has_lane((road[0], road[1], k)) for k in seg["lanes"]):
                    return "segments: not on the map"
    return None


def continuity(role: str, last: dict[str, Any] | None, payload: dict[str, Any]) -> str | None:
    """Consistency with the last accepted message of the topic: a pose cannot jump further than
    40 m/s allows (plus 2 m), its heading turn faster than 1 rad + 2 rad/s, its speed change
    faster than 2 m/s + 12 m/s^2 (only localization is checked)."""
    if role != "localization" or last is None:
        return None
    dt = max(payload["header"]["stamp"] - last["header"]["stamp"], 0.0)
    if math.hypot(payload["x"] - last["x"], payload["y"] - last["y"]) > 2.0 + 40.0 * dt:
        return "x, y: the pose jumped"
    dh = (payload["heading"] - last["heading"] + math.pi) % (2 * math.pi) - math.pi
    if abs(dh) > 1.0 + 2.0 * dt:
        return "heading: jumped"
    if abs(payload["v"] - last["v"]) > 2.0 + 12.0 * dt:
        return "v: jumped"
    return None


def problem(role: str, payload: Any, now_s: float | None = None, last_stamp: float | None = None,
            roadmap: Any = None, max_age_s: float = 5.0, last: dict[str, Any] | None = None) -> str | None:
    """The first reason to reject a ``role`` message, or None when it is valid.

    ``now_s``: bus time, stamps must be within [now - max_age_s, now + 0.5]; ``last_stamp``: the
    stamp of the last accepted message of the topic, which must be older (strictly)."""
    schema = SCHEMAS.get(role)
    if schema is None:
        return None
    p = _schema_problem(payload, schema, "")
    if p:
        return p
    stamp = payload["header"]["stamp"]
    if now_s is not None and not (now_s - max_age_s <= stamp <= now_s + 0.5):
        return f"header.stamp: {stamp!r} is not close to the bus time {now_s:.3f}"
    if last_stamp is not None and stamp <= last_stamp:
        return f"header.stamp: {stamp!r} does not advance (last {last_stamp!r})"
    try:
        return _consistency(role, payload, roadmap) or continuity(role, last, payload)
    except (KeyError, TypeError, IndexError, ValueError) as exc:
        return f"inconsistent message: {type(exc).__name__}"
