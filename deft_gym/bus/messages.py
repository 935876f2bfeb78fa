"""Bus messages, topic roles and the JSON schema of every topic.

A message is a topic, a per-topic sequence number, the sim time it was published at (integer
nanoseconds, so it is exact in the MCAP log) and a payload of plain values. Every payload starts
with a ``header`` (``seq``, ``stamp`` [s], ``module``), modelled on Apollo's ``common.Header``;
``stamp`` is the measurement / frame time, which may be earlier than the publish time.

Topics are addressed by *role* in code (``"localization"``) and by *name* on the bus
(``"/apollo/localization/pose"``); the mapping is configuration (:data:`DEFAULT_TOPICS`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

NS_PER_S = 1_000_000_000


def to_ns(seconds: float) -> int:
    """Seconds to integer nanoseconds (the bus clock)."""
    return round(seconds * NS_PER_S)


def to_s(ns: int) -> float:
    """Integer nanoseconds to seconds."""
    return ns / NS_PER_S


@dataclass(slots=True)
class Message:
    """One message on the bus."""

    topic: str
    seq: int
    publish_ns: int
    payload: dict[str, Any]

    @property
    def publish_time(self) -> float:
        """Publish time [s]."""
        return self.publish_ns / NS_PER_S


ROLES = (
    "routing",
    "localization",
    "chassis",
    "perception_obstacles",
    "traffic_light",
    "prediction",
    "planning",
    "control",
)

DEFAULT_TOPICS: dict[str, str] = {
    "routing": "/apollo/routing_response",
    "localization": "/apollo/localization/pose",
    "chassis": "/apollo/canbus/chassis",
    "perception_obstacles": "/apollo/perception/obstacles",
    "traffic_light": "/apollo/perception/traffic_light",
    "prediction": "/apollo/prediction",
    "planning": "/apollo/planning",
    "control": "/apollo/control",
}

OBSTACLE_TYPES = ["VEHICLE", "CONE", "STATIC_VEHICLE", "UNKNOWN"]
LIGHT_COLORS = ["GREEN", "YELLOW", "RED", "UNKNOWN"]
BEHAVIORS = ["CRUISE", "FOLLOW", "STOP", "NUDGE", "CHANGE_LANE", "ESTOP"]

# ---------------------------------------------------------------------------------------------
# JSON schemas. ``x-brittle`` marks fields that mean something to the middleware rather than to
# the modules (ASTAA section 3.4.3 skips them by default); ``x-unit`` documents units.


def _num(unit: str = "", **kw: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"type": "number", **kw}
    if unit:
        out["x-unit"] = unit
    return out


def _series(unit: str) -> dict[str, Any]:
    return {"type": "array", "items": _num(unit)}


HEADER_SCHEMA = {
    "type": "object",
    "properties": {
        "seq": {"type": "integer", "x-brittle": True},
        "stamp": _num("s", **{"x-brittle": True}),
        "module": {"type": "string", "x-brittle": True},
    },
    "required": ["seq", "stamp", "module"],
}

LANE_ID_SCHEMA = {
    "type": "array",
    "items": [{"type": "string"}, {"type": "string"}, {"type": "integer"}],
    "description": "highway-env lane index (from node, to node, lane id)",
}

TRAJECTORY_SCHEMA = {
    "type": "object",
    "properties": {
        "t": _series("s"),
        "x": _series("m"),
        "y": _series("m"),
        "v": _series("m/s"),
        "heading": _series("rad"),
        "a": _series("m/s^2"),
    },
    "required": ["t", "x", "y", "v", "heading", "a"],
}


def _obj(properties: dict[str, Any], title: str, optional: tuple[str, ...] = ()) -> dict[str, Any]:
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "type": "object",
        "properties": {"header": HEADER_SCHEMA, **properties},
        "required": ["header", *(k for k in properties if k not in optional)],
    }


SCHEMAS: dict[str, dict[str, Any]] = {
    "routing": _obj(
        {
            "segments": {
                "type": "array",
                "items": {
                    "type": "object",
                    "properties": {
                        "road": {"type": "array", "items": {"type": "string"}},
                        "lanes": {"type": "array", "items": {"type": "integer"}},
                    },
                },
            },
            "destination": {
                "type": "object",
                "properties": {"lane": LANE_ID_SCHEMA, "s": _num("m")},
            },
            "cruise_speed": _num("m/s"),
        },
        "deft_gym.RoutingResponse",
    ),
    "localization": _obj(
        {
            "x": _num("m"),
            "y": _num("m"),
            "heading": _num("rad"),
            "v": _num("m/s"),
            "a": _num("m/s^2"),
            "yaw_rate": _num("rad/s"),
        },
        "deft_gym.LocalizationEstimate",
    ),
    "chassis": _obj(
        {
            "speed": _num("m/s"),
            "steering": _num("rad"),
            "acceleration": _num("m/s^2"),
        },
        "deft_gym.Chassis",
    ),
    "perception_obstacles": _obj(
        {
            "obstacles": {
                "type": "array",
                "items": {
                    "type": "object",
                    "properties": {
                        "id": {"type": "integer"},
                        "type": {"type": "string", "enum": OBSTACLE_TYPES},
                        "x": _num("m"),
                        "y": _num("m"),
                        "heading": _num("rad"),
                        "v": _num("m/s"),
                        "length": _num("m"),
                        "width": _num("m"),
                    },
                },
            }
        },
        "deft_gym.PerceptionObstacles",
    ),
    "traffic_light": _obj(
        {
            "lights": {
                "type": "array",
                "items": {
                    "type": "object",
                    "properties": {
                        "id": {"type": "string"},
                        "color": {"type": "string", "enum": LIGHT_COLORS},
                    },
                },
            }
        },
        "deft_gym.TrafficLightDetection",
    ),
    "prediction": _obj(
        {
            "perception_stamp": _num("s", **{"x-brittle": True}),
            "obstacles": {
                "type": "array",
                "items": {
                    "type": "object",
                    "properties": {
                        "id": {"type": "integer"},
                        "type": {"type": "string", "enum": OBSTACLE_TYPES},
                        "length": _num("m"),
                        "width": _num("m"),
                        "is_static": {"type": "boolean"},
                        "t0": _num("s"),
                        "dt": _num("s"),
                        "x": _series("m"),
                        "y": _series("m"),
                        "heading": _series("rad"),
                        "v": _num("m/s"),
                    },
                },
            },
        },
        "deft_gym.PredictionObstacles",
    ),
    "planning": _obj(
        {
            "trajectory": TRAJECTORY_SCHEMA,
            "decision": {
                "type": "object",
                "properties": {
                    "behavior": {"type": "string", "enum": BEHAVIORS},
                    "lane": LANE_ID_SCHEMA,
                    "target_lane": LANE_ID_SCHEMA,
                    "stitched": {"type": "boolean"},
                    "cost": _num(),
                },
            },
            "debug": {
                "type": "object",
                "description": "optional: input_seqs maps each input role to the sequence "
                "number of the message the planner consumed (Apollo's debug field)",
            },
        },
        "deft_gym.ADCTrajectory",
        optional=("debug",),
    ),
    "control": _obj(
        {
            "steering": _num("rad"),
            "acceleration": _num("m/s^2"),
            "trajectory_seq": {"type": "integer", "x-brittle": True},
        },
        "deft_gym.ControlCommand",
    ),
}
