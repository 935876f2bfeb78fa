"""Foxglove-ready pictures of the world in the episode log: a scene topic the 3D panel draws.

Beside the bus messages a recorded episode gets three viewer-only topics (no ``role``: readers
of bus messages skip them; :data:`deft_gym.bus.messages.VIEWER_TOPICS`):

- ``/deft_gym/scene`` (``foxglove.SceneUpdate``, :data:`SCENE_HZ` Hz): the ego, every
  participant with its id and speed (ground truth, coloured by kind), the planned trajectory
  the planner published last and, at the end, the collision with its time;
- ``/deft_gym/scene/map`` (``foxglove.SceneUpdate``, at the start and every
  :data:`MAP_EVERY_S` s): lane edges, centre lines and stop lines;
- ``/deft_gym/tf`` (``foxglove.FrameTransform``): the ``ego`` frame in ``map``, for a camera
  that follows the ego (``configs/foxglove/layout.json``).

The scene is drawn in the ``map`` frame with y and headings negated (highway-env's world frame
has y pointing down on screen; Foxglove's is right-handed with z up), so the 3D panel shows
what ``deft-gym render`` shows. Writing the scene reads the world and draws no random numbers,
so the bus messages of a run are the same with or without it; ``DEFT_GYM_SCENE_HZ=0`` turns it
off. Timestamps are the log's epoch times (``log_start_ns`` + sim time).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from math import cos, isfinite, sin
from operator import neg
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.bus.messages import NS_PER_S, SCENE_MAP_TOPIC, SCENE_TOPIC, TF_TOPIC, Message
from deft_gym.files import checked_kernel
from deft_gym.record.textformat import format_bytes

try:  # the scene's values compiled (setup.py): the same tuple, without a Python frame per value
    from deft_gym.record import _scene_c
except ImportError:  # pragma: no cover - the build is optional
    _scene_c = None
# a kernel built before scene.py or _scene_c.c was edited is not used (the edit must count)
_scene_c = None if os.environ.get("DEFT_GYM_PURE_PYTHON") else checked_kernel(
    _scene_c, Path(__file__).with_name("_scene_c.c"), Path(__file__))

SCENE_HZ = 5.0
MAP_EVERY_S = 10.0
PLAN_POINTS = 16  # the planned trajectory is drawn with at most this many points
FRAME = "map"
KIND_COLORS = {"ego": (0.12, 0.47, 0.71), "static": (0.85, 0.65, 0.13), "scripted": (0.58, 0.40, 0.74),
               "reactive": (0.17, 0.63, 0.17), "plan": (0.0, 0.75, 1.0), "collision": (0.84, 0.15, 0.16)}


def scene_hz() -> float:
    """Scene messages per simulated second (``DEFT_GYM_SCENE_HZ``, default :data:`SCENE_HZ`; 0: none)."""
    try:
        return max(0.0, float(os.environ.get("DEFT_GYM_SCENE_HZ", SCENE_HZ)))
    except ValueError:
        return SCENE_HZ


# -- JSON schemas (Foxglove's, for the fields written here) -------------------------------------------
def _o(props: dict[str, Any], title: str | None = None, optional: tuple[str, ...] = ()) -> dict[str, Any]:
    out: dict[str, Any] = {"type": "object", "properties": props, "required": [k for k in props if k not in optional]}
    if title:
        out["title"] = title
    return out


def _nums(*names: str) -> dict[str, Any]:
    return {n: {"type": "number"} for n in names}


_TIME = _o({"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}},
           "time")
_VEC = _o(_nums("x", "y", "z"), "foxglove.Vector3")
_POINT = _o(_nums("x", "y", "z"), "foxglove.Point3")
_QUAT = _o(_nums("x", "y", "z", "w"), "foxglove.Quaternion")
_POSE = _o({"position": _VEC, "orientation": _QUAT}, "foxglove.Pose")
_COLOR = _o(_nums("r", "g", "b", "a"), "foxglove.Color")


def _arr(items: dict[str, Any]) -> dict[str, Any]:
    return {"type": "array", "items": items}


def scene_update_schema() -> dict[str, Any]:
    """JSON schema of ``foxglove.SceneUpdate`` (every field of an entity, its primitive arrays
    optional; the primitives this module writes in full, the others as arrays)."""
    prim = {"type": "object"}
    entity = _o({
        "timestamp": _TIME, "frame_id": {"type": "string"}, "id": {"type": "string"},
        "lifetime": _o({"sec": {"type": "integer"}, "nsec": {"type": "integer", "minimum": 0}}, "duration"),
        "frame_locked": {"type": "boolean"},
        "metadata": _arr(_o({"key": {"type": "string"}, "value": {"type": "string"}}, "foxglove.KeyValuePair")),
        "arrows": _arr(prim),
        "cubes": _arr(_o({"pose": _POSE, "size": _VEC, "color": _COLOR}, "foxglove.CubePrimitive")),
        "spheres": _arr(_o({"pose": _POSE, "size": _VEC, "color": _COLOR}, "foxglove.SpherePrimitive")),
        "cylinders": _arr(prim),
        "lines": _arr(_o({"type": {"type": "integer", "enum": [0, 1, 2]}, "pose": _POSE, "thickness": {"type": "number"},
                          "scale_invariant": {"type": "boolean"}, "points": _arr(_POINT), "color": _COLOR,
                          "colors": _arr(_COLOR), "indices": _arr({"type": "integer", "minimum": 0})},
                         "foxglove.LinePrimitive")),
        "triangles": _arr(prim),
        "texts": _arr(_o({"pose": _POSE, "billboard": {"type": "boolean"}, "font_size": {"type": "number"},
                          "scale_invariant": {"type": "boolean"}, "color": _COLOR, "text": {"type": "string"}},
                         "foxglove.TextPrimitive")),
        "models": _arr(prim),
    }, "foxglove.SceneEntity", optional=("metadata", "arrows", "cubes", "spheres", "cylinders", "lines", "triangles",
                                         "texts", "models"))
    deletion = _o({"timestamp": _TIME, "type": {"type": "integer", "enum": [0, 1]}, "id": {"type": "string"}},
                  "foxglove.SceneEntityDeletion")
    return {**_o({"deletions": _arr(deletion), "entities": _arr(entity)}, "foxglove.SceneUpdate"),
            "description": "An update to the entities displayed in a 3D scene (DeFT-Gym: the episode's world, "
                           "y and headings negated)"}


def frame_transform_schema() -> dict[str, Any]:
    """JSON schema of ``foxglove.FrameTransform``."""
    return _o({"timestamp": _TIME, "parent_frame_id": {"type": "string"}, "child_frame_id": {"type": "string"},
               "translation": _VEC, "rotation": _QUAT}, "foxglove.FrameTransform")


def viewer_channels() -> list[tuple[str, str, str, bytes]]:
    """``(topic, role "", schema name, JSON schema)`` of the viewer topics, for the recorder."""
    scene = json.dumps(scene_update_schema()).encode()
    return [(SCENE_TOPIC, "", "foxglove.SceneUpdate", scene), (SCENE_MAP_TOPIC, "", "foxglove.SceneUpdate", scene),
            (TF_TOPIC, "", "foxglove.FrameTransform", json.dumps(frame_transform_schema()).encode())]


# -- primitives ---------------------------------------------------------------------------------------
def _time(ns: int) -> dict[str, int]:
    return {"sec": ns // NS_PER_S, "nsec": ns % NS_PER_S}


def _pose(x: float, y: float, z: float = 0.0, heading: float = 0.0) -> dict[str, Any]:
    """A pose in the scene frame from world coordinates (y and heading negated; mm, 1e-6)."""
    half = -0.5 * heading
    return {"position": {"x": round(x, 3), "y": round(-y, 3), "z": z},
            "orientation": {"x": 0, "y": 0, "z": round(math.sin(half), 6), "w": round(math.cos(half), 6)}}


def _color(rgb: tuple[float, float, float], a: float = 1.0) -> dict[str, float]:
    return {"r": rgb[0], "g": rgb[1], "b": rgb[2], "a": a}


def _entity(ns: int, eid: str, **prims: Any) -> dict[str, Any]:
    """An entity; primitive arrays that would be empty are left out (Foxglove reads them as
    empty: the schema does not require them), which keeps the log small."""
    ent: dict[str, Any] = {"timestamp": _time(ns), "frame_id": FRAME, "id": eid, "lifetime": {"sec": 0, "nsec": 0},
                           "frame_locked": False}
    for key, value in prims.items():
        if key == "metadata":
            ent[key] = [{"key": k, "value": str(v)} for k, v in value.items()]
        elif value:
            ent[key] = value
    return ent


def _text(x: float, y: float, text: str, rgb: tuple[float, float, float] = (1.0, 1.0, 1.0), z: float = 2.5,
          size: float = 14.0) -> dict[str, Any]:
    return {"pose": _pose(x, y, z), "billboard": True, "font_size": size, "scale_invariant": True,
            "color": _color(rgb), "text": text}


def _line(xs: Any, ys: Any, rgb: tuple[float, float, float], thickness: float = 0.15, z: float = 0.05,
          a: float = 1.0, kind: int = 0) -> dict[str, Any]:
    return {"type": kind, "pose": _pose(0.0, 0.0), "thickness": thickness, "scale_invariant": False,
            "points": [{"x": round(float(x), 3), "y": round(-float(y), 3), "z": z} for x, y in zip(xs, ys)],
            "color": _color(rgb, a), "colors": [], "indices": []}


def _num(x: float, nd: int = 3) -> str:
    """A JSON number rounded to ``nd`` decimals (0 for a non-finite value: the world's states
    are finite, this only keeps the text valid JSON)."""
    return ("%.*f" % (nd, x)) if math.isfinite(x) else "0"  # noqa: UP031 - the fastest formatting here


def _position_text(x: float, y: float, z: float) -> str:
    return '{"x":%s,"y":%s,"z":%s}' % (_num(x), _num(-y), _num(z))  # noqa: UP031


def _orientation_text(heading: float) -> str:
    half = -0.5 * heading if math.isfinite(heading) else 0.0
    return '{"x":0,"y":0,"z":%.6f,"w":%.6f}' % (math.sin(half), math.cos(half))  # noqa: UP031


def _pose_text(x: float, y: float, z: float, heading: float) -> str:
    """A pose's JSON text in the scene frame (y and heading negated; mm, 1e-6)."""
    return f'{{"position":{_position_text(x, y, z)},"orientation":{_orientation_text(heading)}}}'


def _color_text(rgb: tuple[float, float, float], a: float) -> str:
    return f'{{"r":{rgb[0]},"g":{rgb[1]},"b":{rgb[2]},"a":{a}}}'


_WHITE = _color_text((1.0, 1.0, 1.0), 1.0)
_KIND_TEXT = {k: (_color_text(rgb, 0.9), json.dumps([{"key": "kind", "value": k}])) for k, rgb in KIND_COLORS.items()}
_VEHICLE = ('{"timestamp":{"sec":%d,"nsec":%d},"frame_id":"' + FRAME + '","id":%s,"lifetime":{"sec":0,"nsec":0},'
            '"frame_locked":false,"cubes":[{"pose":{"position":{"x":%.3f,"y":%.3f,"z":%s},"orientation":'
            '{"x":0,"y":0,"z":%.6f,"w":%.6f}},"size":{"x":%.3f,"y":%.3f,"z":%s},"color":%s}],"texts":[{"pose":'
            '{"position":{"x":%.3f,"y":%.3f,"z":%s},"orientation":{"x":0,"y":0,"z":0,"w":1}},"billboard":true,'
            '"font_size":14.0,"scale_invariant":true,"color":' + _WHITE + ',"text":%s}],"metadata":%s}')


def _head(ns: int, eid: str) -> str:
    return (f'{{"timestamp":{{"sec":{ns // NS_PER_S},"nsec":{ns % NS_PER_S}}},"frame_id":"{FRAME}","id":{eid},'
            f'"lifetime":{{"sec":0,"nsec":0}},"frame_locked":false,')


def vehicle_entity(ns: int, eid: str, label: str, kind: str, x: float, y: float, heading: float, speed: float,
                   length: float, width: float) -> str:
    """A vehicle (or obstacle) as a box labelled with its id and speed: the entity's JSON text
    (one format operation: a scene message per 0.2 s must cost the simulation little)."""
    color, meta = _KIND_TEXT.get(kind) or (_color_text((0.5, 0.5, 0.5), 0.9), json.dumps([{"key": "kind",
                                                                                           "value": kind}]))
    if not all(map(math.isfinite, (x, y, heading, length, width))):  # keeps the text valid JSON
        x, y, heading, length, width = (v if math.isfinite(v) else 0.0 for v in (x, y, heading, length, width))
    height = "0.6" if kind == "static" and length < 1.0 else "1.5"
    half = -0.5 * heading
    text = json.dumps(f"{label} {speed:.1f} m/s" if math.isfinite(speed) else label)
    return _VEHICLE % (ns // NS_PER_S, ns % NS_PER_S, json.dumps(eid), x, -y, "0.3" if height == "0.6" else "0.75",
                       math.sin(half), math.cos(half), length, width, height, color, x, -y,
                       "1.6" if height == "0.6" else "2.5", text, meta)


_TEMPLATES: dict[tuple[str, str, float, float], str] = {}  # vehicle_entity's text per (id, kind, size)
_PLAIN_ID = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-. /:")


def _vehicle_template(eid: str, kind: str, length: float, width: float) -> str:
    """:func:`vehicle_entity`'s text of one vehicle with its moving parts as ``%`` fields (sec,
    nsec, x, -y, the orientation's z and w, x, -y, speed): the same bytes for finite values at a
    third of the cost; "" where the id or kind needs JSON escapes or the size is not finite."""
    if not (set(eid) <= _PLAIN_ID and set(kind) <= _PLAIN_ID and isfinite(length) and isfinite(width)):
        return ""
    probe = vehicle_entity(_PROBE_NS, eid if eid == "ego" else f"participant/{eid}", eid, kind, 0.0, 0.0, 0.0, 0.0,
                           length, width)
    # the fields of the probe, in order: time, position, orientation, label position, speed text
    parts = probe.replace("%", "%%").split(_PROBE_TIME, 1)
    if len(parts) != 2:
        return ""
    head, rest = parts[0] + '"sec":%d,"nsec":%d', parts[1]
    cube, rest = rest.split('{"x":0.000,"y":-0.000,"z":', 1)
    z1, rest = rest.split("}", 1)
    orient, rest = rest.split('{"x":0,"y":0,"z":-0.000000,"w":1.000000}', 1)
    label, rest = rest.split('{"x":0.000,"y":-0.000,"z":', 1)
    z2, rest = rest.split("}", 1)
    text = f" {0.0:.1f} m/s"
    before, after = rest.split(json.dumps(f"{eid} {0.0:.1f} m/s")[:-1 - len(text)] + text + '"', 1)
    out = (head + cube + '{"x":%.3f,"y":%.3f,"z":' + z1 + "}" + orient + '{"x":0,"y":0,"z":%.6f,"w":%.6f}' + label
           + '{"x":%.3f,"y":%.3f,"z":' + z2 + "}" + before + json.dumps(eid)[:-1] + ' %.1f m/s"' + after)
    return out


_PLAN_POINT = '{"x":%.3f,"y":%.3f,"z":0.2}'


def plan_entity(ns: int, plan: dict[str, Any]) -> str | None:
    """The planned trajectory (``planning`` payload) as a line (its JSON text), or None without one."""
    tr = (plan or {}).get("trajectory") or {}
    xs, ys = tr.get("x") or [], tr.get("y") or []
    if len(xs) < 2 or len(xs) != len(ys):
        return None
    try:
        ok = [(float(x), float(y)) for x, y in zip(xs, ys) if math.isfinite(float(x)) and math.isfinite(float(y))]
    except (TypeError, ValueError):  # a payload mutated by a robustness test
        return None
    if len(ok) < 2:
        return None
    step = max(1, math.ceil((len(ok) - 1) / (PLAN_POINTS - 1)))
    ok = ok[::step] + ([ok[-1]] if (len(ok) - 1) % step else [])
    points = ",".join([_PLAN_POINT % (x, -y) for x, y in ok])  # finite: _num's text
    stamp = (plan.get("header") or {}).get("stamp", "")
    return (_head(ns, '"plan"')
            + f'"lines":[{{"type":0,"pose":{_pose_text(0.0, 0.0, 0.0, 0.0)},"thickness":0.3,"scale_invariant":false,'
              f'"points":[{points}],"color":{_color_text(KIND_COLORS["plan"], 1.0)},"colors":[],"indices":[]}}],'
              f'"metadata":[{{"key":"frame_time_s","value":{json.dumps(str(stamp))}}}]}}')


def collision_entity(ns: int, collision: dict[str, Any]) -> dict[str, Any]:
    """The collision point with a label: who was hit, when."""
    x, y = float(collision["x"]), float(collision["y"])
    sphere = {"pose": _pose(x, y, 1.0), "size": {"x": 2.5, "y": 2.5, "z": 2.5},
              "color": _color(KIND_COLORS["collision"], 0.8)}
    label = f"collision with {collision.get('participant')} at {float(collision.get('time', 0.0)):.2f} s"
    return _entity(ns, "collision", spheres=[sphere], texts=[_text(x, y, label, KIND_COLORS["collision"], 4.0, 16.0)],
                   metadata={"participant": collision.get("participant"), "time_s": collision.get("time")})


_MAP_LINES: dict[int, tuple[Any, list[dict[str, Any]]]] = {}


def map_entities(ns: int, roadmap: Any) -> list[dict[str, Any]]:
    """Lane edges and centre lines, stop lines (drawn once per road map)."""
    cached = _MAP_LINES.get(id(roadmap))
    if cached is None or cached[0] is not roadmap:
        cached = _MAP_LINES[id(roadmap)] = (roadmap, _map_lines(roadmap))
    return [_entity(ns, "lanes", lines=cached[1])]


def _map_lines(roadmap: Any) -> list[dict[str, Any]]:
    lines = []
    for g in roadmap.geoms.values():
        s = np.linspace(0.0, g.length, 2 if g.kind == "straight" else max(2, int(g.length / 2.0) + 1))
        for d, rgb, th, a in ((-g.width / 2, (0.8, 0.8, 0.8), 0.12, 1.0), (g.width / 2, (0.8, 0.8, 0.8), 0.12, 1.0),
                              (0.0, (0.5, 0.5, 0.5), 0.05, 0.6)):
            pts = g.xy(s, d)
            lines.append(_line(np.round(pts[:, 0], 3), np.round(pts[:, 1], 3), rgb, th, 0.0, a))
    for sl in roadmap.stop_lines:
        g = roadmap.geom(sl.lane)
        a, b = g.xy(np.array(sl.s), -g.width / 2), g.xy(np.array(sl.s), g.width / 2)
        lines.append(_line([a[0], b[0]], [a[1], b[1]], (0.95, 0.95, 0.95), 0.4, 0.02))
    return lines


# -- the compact state and its expansion (in the log's writer) -------------------------------------------
COMPACT = "$scene"  # the key of a compact scene state (a SceneWriter's message before expand)


def expand(ns: int, seq: int, payload: Any, start_ns: int) -> list[tuple[str, int, bytes, int]] | None:
    """The log entries ``(topic, publish ns, JSON, seq)`` of a compact scene state published at
    sim time ``ns``: the SceneUpdate and the ego's FrameTransform; None when ``payload`` is not
    one (then it is written as it is)."""
    if not (isinstance(payload, dict) and COMPACT in payload):
        return None
    rows, xs, ys, stamp, collision = payload[COMPACT]
    t = start_ns + ns
    sec, nsec = t // NS_PER_S, t % NS_PER_S
    texts = None if collision else _scene_texts(sec, nsec, rows, xs, ys, stamp)
    if texts is None:  # a collision, a non-finite value, an id that needs escapes: entity by entity
        ents = _entities(t, rows, xs, ys, stamp)
        if collision:
            ents.append(json.dumps(collision_entity(t, collision)))
        # participants that left the world are deleted: every message replaces the whole scene
        scene = (_SCENE_HEAD % (sec, nsec) + ",".join(ents) + "]}").encode()
        _, _, x, y, h = rows[0][:5]
        tf = (f'{{"timestamp":{{"sec":{sec},"nsec":{nsec}}},"parent_frame_id":"{FRAME}","child_frame_id":"ego",'
              f'"translation":{_position_text(x, y, 0.0)},"rotation":{_orientation_text(h)}}}').encode()
    else:
        scene, tf = texts
    return [(SCENE_TOPIC, ns, scene, seq), (TF_TOPIC, ns, tf, seq)]


_SCENE_HEAD = '{"deletions":[{"timestamp":{"sec":%d,"nsec":%d},"type":1,"id":""}],"entities":['
# the ego's transform of a finite pose, as expand writes it (sec, nsec, x, -y, sin and cos of -heading/2)
_TF = ('{"timestamp":{"sec":%d,"nsec":%d},"parent_frame_id":"' + FRAME + '","child_frame_id":"ego",'
       '"translation":{"x":%.3f,"y":%.3f,"z":0.000},"rotation":{"x":0,"y":0,"z":%.6f,"w":%.6f}}')


def _entities(t: int, rows: list[tuple[Any, ...]], xs: list[Any], ys: list[Any], stamp: Any) -> list[str]:
    """The entities' JSON texts of a compact state at log time ``t`` [ns], one by one: its
    vehicles (:func:`vehicle_entity`, through their templates where they have one) and its plan
    (:func:`plan_entity`)."""
    sec, nsec = t // NS_PER_S, t % NS_PER_S
    ents = []
    for eid, kind, x, y, h, v, length, width in rows:
        tmpl = _template_of(eid, kind, length, width)
        if tmpl and isfinite(x) and isfinite(y) and isfinite(h) and isfinite(v):
            half = -0.5 * h
            ents.append(tmpl % (sec, nsec, x, -y, sin(half), cos(half), x, -y, v))
        else:  # a non-finite value, or an id that needs JSON escapes: the general formatting
            ents.append(vehicle_entity(t, eid if eid == "ego" else f"participant/{eid}", eid, kind, x, y, h, v,
                                       length, width))
    plan = plan_entity(t, {"trajectory": {"x": xs, "y": ys}, "header": {"stamp": stamp}})
    if plan is not None:
        ents.append(plan)
    return ents


def _template_of(eid: str, kind: str, length: float, width: float) -> str:
    """:func:`_vehicle_template`, made once per (id, kind, size)."""
    key = (eid, kind, length, width)
    tmpl = _TEMPLATES.get(key)
    if tmpl is None:
        if len(_TEMPLATES) > 4096:  # ids of many generated scenarios: start afresh
            _TEMPLATES.clear()
        tmpl = _TEMPLATES[key] = _vehicle_template(eid, kind, length, width)
    return tmpl


_SCENES: dict[tuple[Any, ...], str] = {}  # _scene_template's text per (vehicles, plan points)
_PROBE_NS = 1234567 * NS_PER_S + 7654321
_PROBE_TIME = '"sec":1234567,"nsec":7654321'


def _scene_template(vehicles: tuple[tuple[str, str, float, float], ...], points: int) -> str:
    """A scene without a collision as one ``%`` template (fields: sec and nsec of its deletion,
    each vehicle's fields, with ``points`` >= 2 the plan line's: sec, nsec, x and -y of each
    point, the stamp's JSON string): the vehicles' templates (``(id, kind, length, width)`` in
    order) and the plan's; "" when a vehicle has none."""
    parts = [_template_of(*key) for key in vehicles]
    if not all(parts):
        return ""
    if points >= 2:
        probe = plan_entity(_PROBE_NS, {"trajectory": {"x": [0.0] * points, "y": [0.0] * points},
                                        "header": {"stamp": "S"}})
        zeros = ",".join([_PLAN_POINT % (0.0, -0.0)] * points)
        head, rest = probe.replace("%", "%%").split(_PROBE_TIME, 1)
        line, meta = rest.split(zeros, 1)
        before, after = meta.split('"value":"S"', 1)
        parts.append(head + '"sec":%d,"nsec":%d' + line + ",".join([_PLAN_POINT] * points) + before + '"value":%s'
                     + after)
    return _SCENE_HEAD + ",".join(parts) + "]}"


def _scene_texts(sec: int, nsec: int, rows: list[tuple[Any, ...]], xs: list[Any], ys: list[Any],
                 stamp: Any) -> tuple[bytes, bytes] | None:
    """The scene's and the ego transform's JSON as :func:`expand` writes them, for a state whose
    values are all finite and whose ids need no escapes, with one format operation each
    (:func:`~deft_gym.record.textformat.format_bytes`: the scene's ~90 numbers at a fraction of
    ``%``'s cost); None for any other state."""
    points = len(xs)
    if points != len(ys) or points > PLAN_POINTS:
        return None
    key = (tuple([(r[0], r[1], r[6], r[7]) for r in rows]), points if points >= 2 else 0)
    tmpl = _SCENES.get(key)
    if tmpl is None:
        if len(_SCENES) > 4096:
            _SCENES.clear()
        tmpl = _SCENES[key] = _scene_template(*key)
    if not tmpl:
        return None
    plan = key[1] > 0
    args = NotImplemented if _scene_c is None else _scene_c.scene_args(sec, nsec, rows, xs, ys, stamp, plan)
    if args is NotImplemented:  # (no kernel, or a state outside what it takes)
        args = scene_args(sec, nsec, rows, xs, ys, stamp, plan)
    if args is None:
        return None
    return format_bytes(tmpl, args), format_bytes(_TF, args[2:8])


def scene_args(sec: int, nsec: int, rows: list[tuple[Any, ...]], xs: list[Any], ys: list[Any], stamp: Any,
               plan: bool) -> tuple[Any, ...] | None:
    """The values of a scene template (:func:`_scene_template`): sec and nsec, each vehicle's
    (sec, nsec, x, -y, sin and cos of -heading/2, x, -y, speed) and, with ``plan``, the plan
    line's (sec, nsec, then x and -y of each point, the stamp's JSON string); None when one is
    not finite (or not a number). Compiled in ``_scene_c.c`` (the same tuple)."""
    args: list[Any] = [sec, nsec]
    try:
        for _, _, x, y, h, v, _, _ in rows:
            half = -0.5 * h
            args += (sec, nsec, x, -y, sin(half), cos(half), x, -y, v)
        finite = sum(args[4::9]) + sum(args[5::9]) + sum(args[6::9]) + sum(args[10::9])
        if plan:
            line = [0.0] * (2 * len(xs))
            line[::2] = map(float, xs)  # as plan_entity reads them
            line[1::2] = map(neg, map(float, ys))
            finite += sum(line)
            args += (sec, nsec, *line, json.dumps(str(stamp)))
        if not isfinite(finite):  # (or a sum beyond the floats: then entity by entity, as well)
            return None
    except (TypeError, ValueError, OverflowError):
        return None
    return tuple(args)


# -- the writer ---------------------------------------------------------------------------------------
class SceneWriter:
    """Hooks a :class:`~deft_gym.sim.simulation.Simulation` and writes the viewer topics through
    ``write`` (the recorder's tap) at ``hz`` per simulated second."""

    def __init__(self, sim: Any, write: Callable[[Message], None], start_ns: int, hz: float = SCENE_HZ) -> None:
        self.sim, self.write, self.start_ns = sim, write, start_ns
        self.every = max(1, round(sim.ads.world_hz / hz))
        self.map_every = max(1, round(MAP_EVERY_S * sim.ads.world_hz))
        self.plan: dict[str, Any] | None = None
        self._n = 0
        self._seq = {SCENE_TOPIC: 0, SCENE_MAP_TOPIC: 0, TF_TOPIC: 0}
        t_plan = sim.ads.topic("planning")
        sim.on_step.append(self._on_step)

        def keep(m: Message) -> None:
            if m.topic == t_plan:
                self.plan = m.payload

        sim.bus.taps.append(keep)
        self._map(0)

    def _map(self, ns: int) -> None:
        ents = map_entities(self.start_ns + ns, self.sim.roadmap)
        self.write(Message(SCENE_MAP_TOPIC, self._seq[SCENE_MAP_TOPIC], ns, {"deletions": [], "entities": ents}))
        self._seq[SCENE_MAP_TOPIC] += 1

    def _on_step(self, sim: Any) -> None:
        n = self._n
        self._n += 1
        if n % self.every:
            return
        ns = sim.bus.now_ns
        if n and n % self.map_every == 0:
            self._map(ns)
        self.scene(ns)

    def scene(self, ns: int, collision: dict[str, Any] | None = None) -> None:
        """Hand the world as it is now (sim time ``ns``), with ``collision`` if given, to the
        log: a compact state of plain values (:data:`COMPACT`), which the log's tap turns into
        the scene and frame-transform messages (:func:`expand`: one format operation each)."""
        world = self.sim.world
        e = world.ego
        ex, ey = map(float, e.position.tolist())
        rows = [("ego", "ego", ex, ey, float(e.heading), float(e.speed), float(e.LENGTH), float(e.WIDTH))]
        for p in world.present_participants():
            o = p.obj
            x, y = map(float, o.position.tolist())  # the same floats as float(o.position[i]), fewer calls
            rows.append((str(p.id), p.kind, x, y, float(o.heading), float(getattr(o, "speed", 0.0)), float(o.LENGTH),
                         float(o.WIDTH)))
        plan = self.plan if isinstance(self.plan, dict) else {}
        tr = plan.get("trajectory") if isinstance(plan.get("trajectory"), dict) else {}
        xs, ys = tr.get("x"), tr.get("y")  # (a robustness test may have put anything there)
        if not (isinstance(xs, list) and isinstance(ys, list) and len(xs) == len(ys)):
            xs = ys = []
        if len(xs) > PLAN_POINTS:  # every k-th point and the last, as plan_entity draws them
            step = math.ceil((len(xs) - 1) / (PLAN_POINTS - 1))
            last = slice(-1, None) if (len(xs) - 1) % step else slice(0, 0)
            xs, ys = xs[::step] + xs[last], ys[::step] + ys[last]
        header = plan.get("header")
        stamp = header.get("stamp", "") if isinstance(header, dict) else ""
        self.write(Message(SCENE_TOPIC, self._seq[SCENE_TOPIC], ns,
                           {COMPACT: [rows, list(xs), list(ys), stamp, collision]}))
        self._seq[SCENE_TOPIC] += 1

    def finish(self, collision: dict[str, Any] | None) -> None:
        """The last scene, at the end of the episode, with the collision if there was one."""
        self.scene(self.sim.bus.now_ns, collision)
