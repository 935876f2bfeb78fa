"""The road map as roads, lanes and junctions in the export frame.

DeFT-Gym's world is highway-env's: y points down on screen, so in a right-handed frame with y up
its traffic would keep left. OpenDRIVE, OpenSCENARIO and CommonRoad assume y up, and every
picture of an episode (``deft-gym render``, Foxglove) shows it with y pointing down; the export
frame is that picture: ``X = x``, ``Y = -y``, ``H = -heading`` (:func:`to_export`,
:func:`from_export`), right-hand traffic.

Every road of the map (a highway-env edge ``(a, b)``: its parallel lanes, lane 0 leftmost) is
one OpenDRIVE road whose reference line is lane 0's left edge; lane ``k`` is OpenDRIVE lane
``-(k + 1)`` (right of the reference line, driven along it). Roads inside a junction (the map's
junction roads, and the roads a road forks into) are connecting roads of a junction, grouped by
the nodes they share (an intersection is one junction; a highway exit another). Stop lines and
their lights are signals on the road that ends at them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from deft_gym.world.roadmap import LaneId, RoadMap

ROAD_ID0 = 1  #: OpenDRIVE id of the first road
JUNCTION_ID0 = 1000  #: OpenDRIVE id of the first junction
LIGHT_ID0 = 100  #: OpenDRIVE signal id of the first traffic light
STOP_ID0 = 200  #: OpenDRIVE signal id of the first stop line
GEOMETRY_TOL = 1e-6  #: [m] lanes of one road must be this parallel (they are exactly, by construction)


def to_export(x: Any, y: Any, h: Any = 0.0) -> tuple[Any, Any, Any]:
    """World (highway-env) coordinates to the export frame: ``(x, -y, -h)`` (floats or arrays)."""
    return x, -y, -h


def from_export(x: Any, y: Any, h: Any = 0.0) -> tuple[Any, Any, Any]:
    """The export frame back to world coordinates (the same mirror)."""
    return x, -y, -h


def wrap(a: float) -> float:
    """An angle in (-pi, pi]."""
    return math.atan2(math.sin(a), math.cos(a))


@dataclass
class RefLine:
    """A road's reference line in the export frame: a line or an arc from ``(x, y)`` at heading
    ``hdg`` [rad], ``length`` [m] long, ``curvature`` [1/m] (0 for a line; positive: left)."""

    x: float
    y: float
    hdg: float
    length: float
    curvature: float = 0.0

    @property
    def kind(self) -> str:
        return "line" if self.curvature == 0.0 else "arc"

    def point(self, s: float, t: float = 0.0) -> tuple[float, float, float]:
        """``(x, y, heading)`` at ``s`` along the line and ``t`` to its left [m]."""
        k = self.curvature
        if k == 0.0:
            h = self.hdg
            x, y = self.x + s * math.cos(h), self.y + s * math.sin(h)
        else:
            h = self.hdg + k * s
            x = self.x + (math.sin(h) - math.sin(self.hdg)) / k
            y = self.y - (math.cos(h) - math.cos(self.hdg)) / k
        return x - t * math.sin(h), y + t * math.cos(h), h


@dataclass
class Road:
    """One OpenDRIVE road: the map's lanes of one edge ``key``, lane ``k`` as OpenDRIVE lane
    ``-(k + 1)``."""

    id: int
    key: tuple[str, str]
    lanes: list[LaneId]
    width: float
    speed_limit: float
    ref: RefLine
    junction: int = -1
    predecessors: list[int] = field(default_factory=list)
    successors: list[int] = field(default_factory=list)
    #: OpenDRIVE lane id -> the ``(road id, lane id)`` of every lane it continues from / into
    lane_pred: dict[int, list[tuple[int, int]]] = field(default_factory=dict)
    lane_succ: dict[int, list[tuple[int, int]]] = field(default_factory=dict)
    marks: list[str] = field(default_factory=list)  #: border 0 (reference line) .. n: solid | broken | none
    name: str = ""

    @property
    def n(self) -> int:
        return len(self.lanes)


@dataclass
class Signal:
    """A traffic light (``kind`` ``light``) or a stop line (``stop``) on a road at ``s``."""

    id: int
    kind: str
    road: int
    s: float
    t: float
    light_id: str
    lanes: list[int]  # OpenDRIVE lane ids it applies to


@dataclass
class Network:
    roads: list[Road]
    junctions: dict[int, list[int]]  #: junction id -> its connecting roads
    lane_of: dict[LaneId, tuple[int, int]]  #: map lane -> (road id, OpenDRIVE lane id)
    signals: list[Signal]
    roadmap: RoadMap

    def road(self, rid: int) -> Road:
        return self.roads[rid - ROAD_ID0]


_MARK = {0: "none", 1: "broken", 2: "solid", 3: "solid"}  # highway-env LineType: NONE, STRIPED, CONTINUOUS(_LINE)


def _border_mark(left_of_next: int | None, right_of_prev: int | None) -> str:
    kinds = {_MARK.get(int(v), "none") for v in (left_of_next, right_of_prev) if v is not None}
    for k in ("broken", "solid"):
        if k in kinds:
            return k
    return "none"


def _ref_line(roadmap: RoadMap, lane0: LaneId) -> tuple[RefLine, float]:
    """Reference line (lane 0's left edge) in the export frame and the ratio of its length to
    lane 0's centre line."""
    g = roadmap.geom(lane0)
    w = g.width
    x, y = (float(v) for v in g.xy(np.array(0.0), -w / 2))
    h = float(g.heading(np.array(0.0)))
    if g.kind == "straight":
        return RefLine(x, -y, wrap(-h), g.length), 1.0
    if g.kind != "circular":
        raise ValueError(f"lane {lane0}: a {g.kind} lane has no OpenDRIVE geometry here (lines and arcs only)")
    r_ref = g.radius + (w / 2) * g.sense
    ratio = r_ref / g.radius
    return RefLine(x, -y, wrap(-h), g.length * ratio, -g.sense / r_ref), ratio


def _check_parallel(roadmap: RoadMap, lanes: list[LaneId]) -> None:
    """Lane k of a road lies k widths right of lane 0 along all its length."""
    g0 = roadmap.geom(lanes[0])
    for k, lid in enumerate(lanes):
        g = roadmap.geom(lid)
        if abs(g.width - g0.width) > GEOMETRY_TOL:
            raise ValueError(f"road {lid[:2]}: lanes of different widths")
        pts = g.xy(np.linspace(0.0, g.length, 5))
        _, d = g0.frenet(pts)
        if np.max(np.abs(np.asarray(d) - k * g0.width)) > GEOMETRY_TOL:
            raise ValueError(f"road {lid[:2]}: lane {k} is not {k} lane widths right of lane 0")


def build_network(roadmap: RoadMap) -> Network:
    """The roads, junctions and signals of ``roadmap`` (see the module docstring)."""
    keys: list[tuple[str, str]] = []
    for a, b, _ in roadmap.lane_ids:
        if (a, b) not in keys:
            keys.append((a, b))
    lanes_of = {key: roadmap.road_lanes(key) for key in keys}
    succ_roads = {key: sorted({s[:2] for lid in lanes_of[key] for s in roadmap.successors[lid]}, key=keys.index)
                  for key in keys}
    pred_roads: dict[tuple[str, str], list[tuple[str, str]]] = {key: [] for key in keys}
    for key in keys:
        for s in succ_roads[key]:
            pred_roads[s].append(key)
    in_junction = set(roadmap.junction_roads)
    for key in keys:  # a fork (or a merge) is a junction: the roads it splits into are connecting roads
        if len(succ_roads[key]) > 1:
            in_junction.update(succ_roads[key])
        if len(pred_roads[key]) > 1:
            in_junction.update(pred_roads[key])
    # junctions: connecting roads that share a node
    parent: dict[tuple[str, str], tuple[str, str]] = {k: k for k in keys if k in in_junction}

    def find(k: tuple[str, str]) -> tuple[str, str]:
        while parent[k] != k:
            k = parent[k]
        return k

    jkeys = list(parent)
    for i, ka in enumerate(jkeys):
        for kb in jkeys[i + 1:]:
            if set(ka) & set(kb):
                parent[find(kb)] = find(ka)
    roots: list[tuple[str, str]] = []
    for k in jkeys:
        if find(k) not in roots:
            roots.append(find(k))
    junction_of = {k: JUNCTION_ID0 + roots.index(find(k)) for k in jkeys}

    roads: list[Road] = []
    lane_of: dict[LaneId, tuple[int, int]] = {}
    for i, key in enumerate(keys):
        lanes = lanes_of[key]
        _check_parallel(roadmap, lanes)
        ref, _ = _ref_line(roadmap, lanes[0])
        g0 = roadmap.geom(lanes[0])
        hw = [roadmap.lanes[lid] for lid in lanes]
        marks = [_border_mark(hw[0].line_types[0], None)]
        marks += [_border_mark(hw[k + 1].line_types[0], hw[k].line_types[1]) for k in range(len(lanes) - 1)]
        marks.append(_border_mark(None, hw[-1].line_types[1]))
        speed = float(hw[0].speed_limit or roadmap.spec.speed_limit)
        road = Road(ROAD_ID0 + i, key, list(lanes), g0.width, speed, ref, junction_of.get(key, -1), marks=marks,
                    name=f"{key[0]}-{key[1]}")
        roads.append(road)
        for k, lid in enumerate(lanes):
            lane_of[tuple(lid)] = (road.id, -(k + 1))
    by_key = {r.key: r for r in roads}
    for r in roads:
        r.successors = [by_key[k].id for k in succ_roads[r.key]]
        r.predecessors = [by_key[k].id for k in pred_roads[r.key]]
        for lid in r.lanes:
            own = lane_of[tuple(lid)]
            r.lane_succ[own[1]] = [lane_of[tuple(s)] for s in roadmap.successors[lid]]
            for s in roadmap.successors[lid]:
                by_key[s[:2]].lane_pred.setdefault(lane_of[tuple(s)][1], []).append(own)
    junctions: dict[int, list[int]] = {}
    for r in roads:
        if r.junction >= 0:
            junctions.setdefault(r.junction, []).append(r.id)
    signals: list[Signal] = []
    per_road: dict[tuple[int, str], list[Any]] = {}
    for sl in roadmap.stop_lines:
        rid, lane = lane_of[tuple(sl.lane)]
        per_road.setdefault((rid, sl.light_id), []).append((sl, lane))
    for n, ((rid, light), items) in enumerate(per_road.items()):
        road = by_key[roads[rid - ROAD_ID0].key]
        _, ratio = _ref_line(roadmap, road.lanes[0])
        s = float(items[0][0].s) * ratio
        lanes = sorted(lane for _, lane in items)
        signals.append(Signal(LIGHT_ID0 + n, "light", rid, s, -road.n * road.width, light, lanes))
        signals.append(Signal(STOP_ID0 + n, "stop", rid, s, -road.n * road.width / 2, light, lanes))
    return Network(roads, junctions, lane_of, signals, roadmap)


def lane_polyline(roadmap: RoadMap, lane: LaneId, d: float = 0.0, step: float = 1.0) -> np.ndarray:
    """Points ``(n, 2)`` of a lane's centre line (or the line ``d`` [m] right of it) in the export
    frame: its two ends for a straight lane, at most ``step`` [m] apart on an arc."""
    g = roadmap.geom(lane)
    n = 2 if g.kind == "straight" else max(3, math.ceil(g.length / step) + 1)
    xy = g.xy(np.linspace(0.0, g.length, n), d)
    return np.column_stack([xy[:, 0], -xy[:, 1]])
