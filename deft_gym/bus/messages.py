"""Bus messages, topic roles and the JSON schema of every topic.

A message is a topic, a per-topic sequence number, the sim time it was published at (integer
nanoseconds, so it is exact in the MCAP log) and a payload of plain values. Every payload starts
with a ``header`` (``seq``, ``stamp`` [s], ``module``), modelled on Apollo's ``common.Header``;
``stamp`` is the measurement / frame time, which may be earlier than the publish time.

Topics are addressed by *role* in code (``"localization"``) and by *name* on the bus
(``"/apollo/localization/pose"``); the mapping is configuration (:data:`DEFAULT_TOPICS`).
Every field of every topic is documented in :data:`SCHEMAS` with its unit and its frame or time
base (:data:`FRAMES`): positions are in highway-env's world frame (y down on screen) and refer to
a vehicle's centre, lateral offsets are positive to the right, times are absolute sim seconds.
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


# A log's MCAP ``log_time`` is a real epoch time: the episode's start (this key of its episode
# metadata record, integer ns since 1970) plus the sim time, so that viewers such as Foxglove
# show a date. Readers subtract it to get sim time back; logs without the key start at 0.
LOG_START_KEY = "log_start_ns"
# topics written for viewers only (Foxglove's SceneUpdate and FrameTransform), not bus messages
SCENE_TOPIC = "/deft_gym/scene"
SCENE_MAP_TOPIC = "/deft_gym/scene/map"
TF_TOPIC = "/deft_gym/tf"
VIEWER_TOPICS = (SCENE_TOPIC, SCENE_MAP_TOPIC, TF_TOPIC)


def log_start_ns(episode_metadata: dict[str, Any] | None) -> int:
    """The epoch start [ns] of a log's ``log_time`` (0 for logs that start at 0): from its
    episode metadata record, raw (JSON strings) or decoded."""
    value = (episode_metadata or {}).get(LOG_START_KEY, 0)
    try:
        return int(value)
    except (TypeError, ValueError):
        return 0


def non_finite_field(value: Any) -> str | None:
    """The dotted path (``trajectory.x.3``) of the first NaN or infinity in a payload of plain
    values, or None when every number is finite (a list of numbers is checked in one C loop)."""
    path = _non_finite(value)
    return None if path is None else ".".join(map(str, path))


_SCALARS = (str, int, bool, type(None))  # no float in them (an int is finite)
_NUMBERS = (float, int)  # types whose lists are summed first (exact types: no bool, no subclass)
_SEQUENCES = (list, tuple)  # isinstance(v, list | tuple), without building the union on every call


def _non_finite(v: Any) -> tuple[Any, ...] | None:
    if isinstance(v, dict):
        for k, x in v.items():
            t = type(x)
            if t is float:
                if x - x != 0.0:  # inf - inf and nan - nan are nan
                    return (k,)
            elif t not in _SCALARS and (r := _non_finite(x)) is not None:
                return (k, *r)
        return None
    if isinstance(v, _SEQUENCES):
        if not v:
            return None
        if type(v[0]) in _NUMBERS and type(v[-1]) in _NUMBERS:  # numbers, most likely: one C loop
            try:  # a sum of finite floats is finite (unless it overflows: then element by element)
                total = sum(v)
                if total - total == 0.0:
                    return None
            except (TypeError, OverflowError, ValueError):  # not all numbers (an int beyond floats; numpy
                # values beside lists, which numpy tries to make an array of)
                pass
        for i, x in enumerate(v):
            if type(x) not in _SCALARS and (r := _non_finite(x)) is not None:
                return (i, *r)
        return None
    if isinstance(v, float) and v - v != 0.0:
        return ()
    return None


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
    "map",
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
    "map": "/deft_gym/map",
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
#: the reference planner's decision behaviours (its own vocabulary; other planners have theirs)
BEHAVIORS = ["CRUISE", "FOLLOW", "STOP", "NUDGE", "CHANGE_LANE", "ESTOP"]

# ---------------------------------------------------------------------------------------------
# JSON schemas. Every field has a ``description``; numbers have ``x-unit`` (``1``: a pure
# number) and positions, headings and times ``x-frame`` (one of FRAMES). ``x-brittle`` marks
# fields that mean something to the middleware rather than to the modules (ASTAA section 3.4.3
# skips them by default). ``x-planner-defined`` marks an object whose keys are the planner's
# own (the decision): the keys listed are the reference planner's, documented, not required.

#: the coordinate frames and time bases fields refer to (``x-frame``)
FRAMES = {
    "world": "highway-env's world frame: x [m] and y [m] of the map, y pointing down on screen; "
             "headings [rad] from +x towards +y (clockwise on screen), any real value",
    "vehicle_centre": "world frame, the centre of the vehicle's bounding box (not the rear axle)",
    "lane": "along one lane from its start: s [m] along the centre line; d [m] lateral, positive to the "
            "right of the driving direction",
    "sim_time": "absolute simulation time [s] since the episode started (the bus clock)",
    "relative": "a duration or a spacing [s], not a point in time",
}


def _num(unit: str, description: str, frame: str | None = None, **kw: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"type": "number", "description": description, "x-unit": unit or "1", **kw}
    if frame:
        out["x-frame"] = frame
    return out


def _int(description: str, **kw: Any) -> dict[str, Any]:
    return {"type": "integer", "description": description, **kw}


def _str(description: str, **kw: Any) -> dict[str, Any]:
    return {"type": "string", "description": description, **kw}


def _series(unit: str, description: str, frame: str | None = None) -> dict[str, Any]:
    return {"type": "array", "description": description, "items": _num(unit, description, frame)}


HEADER_SCHEMA = {
    "type": "object",
    "description": "Apollo-style message header",
    "properties": {
        "seq": _int("sequence number of the message on its topic, from 0", **{"x-brittle": True}),
        "stamp": _num("s", "measurement time of sensor messages, frame time of prediction and planning "
                      "outputs", "sim_time", **{"x-brittle": True}),
        "module": _str("name of the publishing module", **{"x-brittle": True}),
    },
    "required": ["seq", "stamp", "module"],
}

LANE_ID_SCHEMA = {
    "type": "array",
    "items": [_str("from node"), _str("to node"), _int("lane index on the road: 0 the leftmost, growing to "
                                                       "the right")],
    "description": "lane id (highway-env lane index: from node, to node, lane index); [] for none",
}

TRAJECTORY_SCHEMA = {
    "type": "object",
    "description": "the planned trajectory: equally long series, one entry per point (any number >= 2, "
                   "any spacing)",
    "properties": {
        "t": _series("s", "time of each point, absolute, strictly increasing; t[0] is the frame time "
                     "(header.stamp)", "sim_time"),
        "x": _series("m", "planned position of the ego's centre, x", "vehicle_centre"),
        "y": _series("m", "planned position of the ego's centre, y", "vehicle_centre"),
        "v": _series("m/s", "planned speed (>= 0)"),
        "heading": _series("rad", "planned heading", "world"),
        "a": _series("m/s^2", "planned acceleration along the path (negative: braking)"),
    },
    "required": ["t", "x", "y", "v", "heading", "a"],
}


def _obj(properties: dict[str, Any], title: str, description: str, optional: tuple[str, ...] = ()) -> dict[str, Any]:
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "description": description,
        "type": "object",
        "properties": {"header": HEADER_SCHEMA, **properties},
        "required": ["header", *(k for k in properties if k not in optional)],
    }


def _box(prefix: str) -> dict[str, Any]:
    return {"length": _num("m", f"{prefix} bounding-box length (along its heading)"),
            "width": _num("m", f"{prefix} bounding-box width")}


SCHEMAS: dict[str, dict[str, Any]] = {
    "routing": _obj(
        {
            "segments": {
                "type": "array",
                "description": "the route, road by road, in driving order",
                "items": {
                    "type": "object",
                    "description": "one road of the route",
                    "properties": {
                        "road": {"type": "array", "description": "the road: [from node, to node] (see map.lanes)",
                                 "items": _str("node name")},
                        "lanes": {"type": "array", "description": "lane indices of this road from which the route "
                                  "continues onto the next road (the destination lane on the last)",
                                  "items": _int("lane index")},
                    },
                },
            },
            "destination": {
                "type": "object",
                "description": "where the ego must stop",
                "properties": {"lane": LANE_ID_SCHEMA,
                               "s": _num("m", "distance of the destination from the lane's start", "lane")},
            },
            "cruise_speed": _num("m/s", "the speed to drive at where the map allows it"),
        },
        "deft_gym.RoutingResponse", "the lane-level route from the ego's start to its destination; published once "
        "at start-up (latched)",
    ),
    "map": _obj(
        {
            "name": _str("map family (intersection, highway, uturn)"),
            "lanes": {
                "type": "array",
                "description": "every lane of the map",
                "items": {
                    "type": "object",
                    "description": "one lane",
                    "properties": {
                        "id": LANE_ID_SCHEMA,
                        "x": _series("m", "centre line, x, from the lane's start to its end (exact at the points; "
                                     "straight lanes have 2, curved ones one every 0.5 m or less)", "world"),
                        "y": _series("m", "centre line, y", "world"),
                        "s": _series("m", "arc length of each centre-line point from the lane's start", "lane"),
                        "width": _num("m", "lane width"),
                        "length": _num("m", "arc length of the centre line"),
                        "speed_limit": _num("m/s", "speed limit"),
                        "successors": {"type": "array", "description": "lanes that continue this one at its end",
                                       "items": LANE_ID_SCHEMA},
                        "left": {**LANE_ID_SCHEMA, "description": "the adjacent lane on the left, same road and "
                                 "direction ([] for none)"},
                        "right": {**LANE_ID_SCHEMA, "description": "the adjacent lane on the right ([] for none)"},
                        "change_left": {"type": "boolean", "description": "a lane change to the left lane is allowed"},
                        "change_right": {"type": "boolean", "description": "a lane change to the right lane is allowed"},
                        "junction": {"type": "boolean", "description": "the lane is inside a junction"},
                    },
                },
            },
            "stop_lines": {
                "type": "array",
                "description": "stop lines controlled by traffic lights",
                "items": {
                    "type": "object",
                    "description": "one stop line",
                    "properties": {
                        "lane": LANE_ID_SCHEMA,
                        "s": _num("m", "position of the stop line along the lane", "lane"),
                        "x": _num("m", "where the stop line crosses the lane's centre line, x", "world"),
                        "y": _num("m", "... y", "world"),
                        "light_id": _str("the traffic light controlling it (traffic_light.lights[].id)"),
                    },
                },
            },
            "lights": {"type": "array", "description": "ids of the traffic lights", "items": _str("light id")},
        },
        "deft_gym.Map", "the road map as data (lanes as polylines with widths, successors and neighbours, stop "
        "lines, light ids); published once at start-up with the route (latched)",
    ),
    "localization": _obj(
        {
            "x": _num("m", "ego position, x", "vehicle_centre"),
            "y": _num("m", "ego position, y", "vehicle_centre"),
            "heading": _num("rad", "ego heading", "world"),
            "v": _num("m/s", "ego speed (>= 0)"),
            "a": _num("m/s^2", "ego acceleration along its heading"),
            "yaw_rate": _num("rad/s", "rate of change of the heading"),
        },
        "deft_gym.LocalizationEstimate", "the ego's pose (ground truth plus seeded noise)",
    ),
    "chassis": _obj(
        {
            "speed": _num("m/s", "wheel speed"),
            "steering": _num("rad", "front-wheel steering angle, positive towards +heading (right on screen)"),
            "acceleration": _num("m/s^2", "longitudinal acceleration"),
        },
        "deft_gym.Chassis", "the vehicle's own sensors",
    ),
    "perception_obstacles": _obj(
        {
            "obstacles": {
                "type": "array",
                "description": "obstacles within perception range",
                "items": {
                    "type": "object",
                    "description": "one obstacle",
                    "properties": {
                        "id": _int("obstacle id, stable over the episode"),
                        "type": _str("obstacle type", enum=OBSTACLE_TYPES),
                        "x": _num("m", "position, x", "vehicle_centre"),
                        "y": _num("m", "position, y", "vehicle_centre"),
                        "heading": _num("rad", "heading", "world"),
                        "v": _num("m/s", "speed (>= 0)"),
                        **_box("obstacle"),
                    },
                },
            }
        },
        "deft_gym.PerceptionObstacles", "perceived obstacles at header.stamp",
    ),
    "traffic_light": _obj(
        {
            "lights": {
                "type": "array",
                "description": "every traffic light of the map (empty where there are none)",
                "items": {
                    "type": "object",
                    "description": "one light",
                    "properties": {
                        "id": _str("light id (map.stop_lines[].light_id)"),
                        "color": _str("the light's colour", enum=LIGHT_COLORS),
                    },
                },
            }
        },
        "deft_gym.TrafficLightDetection", "detected light colours at header.stamp",
    ),
    "prediction": _obj(
        {
            "perception_stamp": _num("s", "header.stamp of the perception message predicted from", "sim_time",
                                     **{"x-brittle": True}),
            "obstacles": {
                "type": "array",
                "description": "predicted obstacles",
                "items": {
                    "type": "object",
                    "description": "one obstacle and its predicted path",
                    "properties": {  # in the order the prediction module writes them (the binary layout's)
                        "id": _int("obstacle id (as in perception)"),
                        "type": _str("obstacle type", enum=OBSTACLE_TYPES),
                        **_box("obstacle"),
                        "t0": _num("s", "time of the first predicted point, absolute (the perception stamp)",
                                   "sim_time"),
                        "dt": _num("s", "time between predicted points", "relative"),
                        "v": _num("m/s", "current speed (>= 0)"),
                        "is_static": {"type": "boolean", "description": "predicted not to move (one point)"},
                        "x": _series("m", "predicted position at t0 + k dt, x (held at the last point after the "
                                     "end)", "vehicle_centre"),
                        "y": _series("m", "predicted position at t0 + k dt, y", "vehicle_centre"),
                        "heading": _series("rad", "predicted heading at t0 + k dt", "world"),
                        "intent": _str("optional: the lane change predicted for it (left, right); absent for none"),
                    },
                    "required": ["id", "type", "length", "width", "t0", "dt", "v", "is_static", "x", "y", "heading"],
                },
            },
        },
        "deft_gym.PredictionObstacles", "predicted obstacle paths; triggers planning",
    ),
    "planning": _obj(
        {
            "trajectory": TRAJECTORY_SCHEMA,
            "decision": {
                "type": "object",
                "description": "optional, planner-defined: what the planner chose, in its own terms (compared by "
                               "the extracted tests like the trajectory). The keys below are the reference "
                               "planner's",
                "x-planner-defined": True,
                "properties": {
                    "behavior": _str("reference planner: the behaviour of the chosen plan", enum=BEHAVIORS),
                    "lane": {**LANE_ID_SCHEMA, "description": "reference planner: the lane it located the ego on"},
                    "target_lane": {**LANE_ID_SCHEMA, "description": "reference planner: the lane it plans to end in"},
                    "stitched": {"type": "boolean", "description": "reference planner: the plan starts on the previous "
                                 "plan (trajectory stitching) rather than at the localization pose"},
                    "cost": _num("", "reference planner: the chosen candidate's cost (-1: none feasible)"),
                },
            },
            "debug": {
                "type": "object",
                "description": "optional: input_seqs maps each input role to the sequence "
                "number of the message the planner consumed (Apollo's debug field)",
            },
        },
        "deft_gym.ADCTrajectory", "the planner's output; header.stamp is the frame time",
        optional=("debug", "decision"),
    ),
    "control": _obj(
        {
            "steering": _num("rad", "front-wheel steering angle command"),
            "acceleration": _num("m/s^2", "longitudinal acceleration command"),
            "trajectory_seq": _int("header.seq of the planning message being tracked (-1: none)",
                                   **{"x-brittle": True}),
        },
        "deft_gym.ControlCommand", "the control command applied by the simulator",
    ),
}
