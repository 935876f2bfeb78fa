"""Road maps: highway-env road networks plus what an HD map adds (connectivity, stop lines,
lane-change permissions, routing) and fast spatial queries.

Three map families (``intersection``, ``highway``, ``uturn``) cover Decictor's six seed scenarios and the DeFT Figure 1 pattern:

- ``intersection``: four approaches with ``lanes`` in and out, a traffic light per approach,
  left turns from the inner lane (id 0), right turns from the outer lane, straight from all;
- ``highway``: a straight multi-lane road with an exit ramp leaving from the rightmost lane;
- ``uturn``: a divided road with a U-turn bay from the inner lane at its end;
- ``merge``: a straight road whose rightmost lane ends, fed by an on-ramp (``ramp``, default) or
  a lane of the road itself (a lane drop); written for hand-made scenarios, no seed uses it.

``turn_lanes`` (default 1) makes the left turns of an intersection, or the U-turn, leave from
that many inner lanes, lane k into lane k of the road it turns onto (double left-turn lanes, a
two-lane U-turn): a vehicle that is in the second lane when it reaches the junction turns from
there. ``right_turn_lanes`` (default 1) does the same for the right turns of an intersection,
from that many outer lanes. With the defaults the maps are exactly the single-turn-lane ones.

Lane ids follow highway-env: id 0 is the leftmost lane of a road, ids grow to the right.
Node names: ``o<c>`` outer end and ``ir<c>`` inner end of approach ``c`` (0 south, 1 west,
2 north, 3 east), ``il<c>`` the start of the exit road towards ``c``, as in highway-env's
intersection env.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Literal

import numpy as np
import shapely
from highway_env.road.lane import CircularLane, LineType, StraightLane
from highway_env.road.road import RoadNetwork
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    model_serializer,
    model_validator,
)

from deft_gym.world.geometry import LaneGeom, ReferenceLine, wrap_angle

LaneId = tuple[str, str, int]

N, C, S, CL = LineType.NONE, LineType.CONTINUOUS, LineType.STRIPED, LineType.CONTINUOUS_LINE


class MapSpec(BaseModel):
    """Which map to build and its dimensions [m], speed limit [m/s]."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    type: Literal["intersection", "highway", "uturn", "merge"]
    lanes: int = Field(default=2, ge=1, le=5)
    lane_width: float = Field(default=3.5, gt=2.0, le=5.0)
    length: float = Field(default=120.0, gt=20.0, le=2000.0, description="approach/road length")
    speed_limit: float = Field(default=12.0, gt=0.0, le=40.0)
    junction_margin: float = Field(default=5.0, ge=0.0, le=20.0)
    exit_at: float = Field(default=0.6, gt=0.1, lt=0.95, description="highway: exit position as a share of length")
    median: float = Field(default=12.0, ge=2.0, le=40.0, description="uturn: median width")
    turn_lanes: int = Field(default=1, ge=1, le=5, description="intersection: left turns, uturn: U-turns, from "
                            "this many inner lanes (lane k into lane k of the road turned onto)")
    right_turn_lanes: int = Field(default=1, ge=1, le=5, description="intersection: right turns from this many "
                                  "outer lanes (lane k into lane k of the road turned onto)")
    ramp: bool = Field(default=True, description="merge: an on-ramp feeds the ending lane (false: a lane drop)")
    merge_at: float = Field(default=0.4, gt=0.0, lt=0.9, description="merge: where the ending lane's last "
                            "section begins, as a share of length")
    merge_length: float = Field(default=80.0, ge=20.0, le=500.0, description="merge: length [m] of the "
                                "section along which the ending lane runs beside the others")

    @model_validator(mode="after")
    def _turn_lanes_exist(self) -> MapSpec:
        for name in ("turn_lanes", "right_turn_lanes"):
            if getattr(self, name) > self.lanes:
                raise ValueError(f"{name}: {getattr(self, name)} turning lanes but only {self.lanes} lanes")
        if self.type == "merge":
            if self.lanes < 2:
                raise ValueError("lanes: a merge needs at least 2 lanes (the ending lane and one that goes on)")
            if self.length * self.merge_at + self.merge_length > self.length - 20.0:
                raise ValueError(f"merge_length: the section ends {self.length * self.merge_at + self.merge_length:g} m "
                                 f"along a {self.length:g} m road; expected at least 20 m of road after it")
        return self

    @model_serializer(mode="wrap")
    def _without_default_turn_lanes(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """``turn_lanes``, ``right_turn_lanes`` and the merge options are written only when they are
        not their defaults, so a map without the options dumps as before they existed (logs,
        generated tests, cache keys)."""
        data = handler(self)
        for name, default in (("turn_lanes", 1), ("right_turn_lanes", 1), ("ramp", True), ("merge_at", 0.4),
                              ("merge_length", 80.0)):
            if getattr(self, name) == default:
                data.pop(name, None)
        return data


@dataclass
class StopLine:
    """A stop line at the end of ``lane`` (at ``s`` [m]) controlled by light ``light_id``."""

    lane: LaneId
    s: float
    light_id: str


@dataclass
class MapInfo:
    network: RoadNetwork
    stop_lines: list[StopLine] = field(default_factory=list)
    light_groups: dict[str, int] = field(default_factory=dict)  # light id -> phase group
    junction_roads: set[tuple[str, str]] = field(default_factory=set)


def _rot(angle: float) -> Callable[[list[float]], np.ndarray]:
    """Rotation by ``angle`` [rad] about the origin, written out (a matrix product would go to
    BLAS, whose CPU-specific kernels may fuse multiply-adds)."""
    c, s = float(np.cos(angle)), float(np.sin(angle))
    return lambda p: np.array([c * p[0] - s * p[1], s * p[0] + c * p[1]])


def build_intersection(spec: MapSpec) -> MapInfo:
    """Four-way junction, ``spec.lanes`` lanes in and out per approach, lights per approach."""
    w, n_l = spec.lane_width, spec.lanes
    outer = n_l * w + spec.junction_margin  # distance centre -> stop line
    L, v = spec.length, spec.speed_limit
    net = RoadNetwork()
    info = MapInfo(net)
    for c in range(4):
        rotate = _rot(np.pi / 2 * c)
        for k in range(n_l):
            x = w / 2 + k * w
            left = CL if k == 0 else S
            right = CL if k == n_l - 1 else N
            net.add_lane(f"o{c}", f"ir{c}", StraightLane(rotate([x, outer + L]), rotate([x, outer]),
                                                          line_types=[left, right], speed_limit=v, width=w))
        for k in range(n_l):
            x = -(w / 2 + k * w)
            left = CL if k == 0 else S
            right = CL if k == n_l - 1 else N
            net.add_lane(f"il{c}", f"o{c}", StraightLane(rotate([x, outer]), rotate([x, outer + L]),
                                                          line_types=[left, right], speed_limit=v, width=w))
        # straight through, lane k -> lane k of the opposite exit
        for k in range(n_l):
            x = w / 2 + k * w
            net.add_lane(f"ir{c}", f"il{(c + 2) % 4}", StraightLane(rotate([x, outer]), rotate([x, -outer]),
                                                                    line_types=[N, N], speed_limit=v, width=w))
        # right turns from the outer lane(s) into the exit lane(s) of the same index
        for k in range(n_l - spec.right_turn_lanes, n_l):
            net.add_lane(f"ir{c}", f"il{(c - 1) % 4}",
                         CircularLane(rotate([outer, outer]), outer - (w / 2 + k * w), np.pi / 2 * c + np.pi,
                                      np.pi / 2 * c + 1.5 * np.pi, clockwise=True,
                                      line_types=[N, N], speed_limit=v, width=w))
        # left turns from the inner lane(s) into the exit lane(s) of the same index
        for k in range(spec.turn_lanes):
            net.add_lane(f"ir{c}", f"il{(c + 1) % 4}",
                         CircularLane(rotate([-outer, outer]), outer + w / 2 + k * w, np.pi / 2 * c,
                                      np.pi / 2 * c - np.pi / 2, clockwise=False,
                                      line_types=[N, N], speed_limit=v, width=w))
        for k in range(n_l):
            info.stop_lines.append(StopLine((f"o{c}", f"ir{c}", k), L, f"tl{c}"))
        info.light_groups[f"tl{c}"] = c % 2
        for to in ((c + 2) % 4, (c - 1) % 4, (c + 1) % 4):
            info.junction_roads.add((f"ir{c}", f"il{to}"))
    return info


def build_highway(spec: MapSpec) -> MapInfo:
    """Straight road a->b->c with an exit ramp b->x->y from the rightmost lane."""
    w, n_l, L, v = spec.lane_width, spec.lanes, spec.length, spec.speed_limit
    net = RoadNetwork()
    info = MapInfo(net)
    xb = L * spec.exit_at
    for k in range(n_l):
        y = k * w
        left = CL if k == 0 else S
        right = CL if k == n_l - 1 else N
        net.add_lane("a", "b", StraightLane([0.0, y], [xb, y], line_types=[left, right], speed_limit=v, width=w))
        net.add_lane("b", "c", StraightLane([xb, y], [L, y], line_types=[left, right], speed_limit=v, width=w))
    # exit: a right-curving arc (radius 60 m, 25 deg) then a straight ramp
    y_r = (n_l - 1) * w
    radius, ang = 60.0, np.radians(25.0)
    center = np.array([xb, y_r + radius])
    net.add_lane("b", "x", CircularLane(center, radius, -np.pi / 2, -np.pi / 2 + ang, clockwise=True,
                                        line_types=[N, CL], speed_limit=v * 0.7, width=w))
    p0 = center + radius * np.array([np.cos(-np.pi / 2 + ang), np.sin(-np.pi / 2 + ang)])
    direction = np.array([np.cos(ang), np.sin(ang)])
    net.add_lane("x", "y", StraightLane(p0, p0 + direction * 80.0, line_types=[CL, CL], speed_limit=v * 0.7, width=w))
    info.junction_roads.add(("b", "x"))
    return info


def build_uturn(spec: MapSpec) -> MapInfo:
    """Divided road a->b heading +x, U-turn bay b->c from the inner lane(s), return road c->d."""
    w, n_l, L, v = spec.lane_width, spec.lanes, spec.length, spec.speed_limit
    m = spec.median / 2
    net = RoadNetwork()
    info = MapInfo(net)
    for k in range(n_l):
        left = CL if k == 0 else S
        right = CL if k == n_l - 1 else N
        y = m + w / 2 + k * w
        net.add_lane("a", "b", StraightLane([0.0, y], [L, y], line_types=[left, right], speed_limit=v, width=w))
        net.add_lane("c", "d", StraightLane([L, -y], [0.0, -y], line_types=[left, right], speed_limit=v, width=w))
    for k in range(spec.turn_lanes):  # lane k of a-b into lane k of c-d
        r = m + w / 2 + k * w
        net.add_lane("b", "c", CircularLane([L, 0.0], r, np.pi / 2, -np.pi / 2, clockwise=False,
                                            line_types=[N, N], speed_limit=min(v, 6.0), width=w))
    info.junction_roads.add(("b", "c"))
    return info


def build_merge(spec: MapSpec) -> MapInfo:
    """Straight road a->b->c->d heading +x whose rightmost lane (id ``lanes - 1``) ends at c: on
    b->c (``merge_length`` [m] from ``merge_at`` x length) it runs beside the others behind a
    striped line, and c->d has one lane less. With ``ramp`` an on-ramp j->k->b (a straight then
    a left-curving arc, radius 60 m, 20 deg) feeds it (a merge; a->b has ``lanes - 1`` lanes);
    without, it is a lane of a->b that drops (a lane drop)."""
    w, n_l, L, v = spec.lane_width, spec.lanes, spec.length, spec.speed_limit
    net = RoadNetwork()
    info = MapInfo(net)
    xb = L * spec.merge_at
    xc = xb + spec.merge_length
    for a, b, x0, x1, count in (("a", "b", 0.0, xb, n_l - 1 if spec.ramp else n_l), ("b", "c", xb, xc, n_l),
                                ("c", "d", xc, L, n_l - 1)):
        for k in range(count):
            left = CL if k == 0 else S
            right = CL if k == count - 1 else N
            net.add_lane(a, b, StraightLane([x0, k * w], [x1, k * w], line_types=[left, right], speed_limit=v, width=w))
    if spec.ramp:  # ends at b on the ending lane's centre, heading +x
        y_e = (n_l - 1) * w
        radius, ang = 60.0, np.radians(20.0)
        center = np.array([xb, y_e + radius])
        net.add_lane("k", "b", CircularLane(center, radius, -np.pi / 2 - ang, -np.pi / 2, clockwise=True,
                                            line_types=[CL, CL], speed_limit=v, width=w))
        p1 = center + radius * np.array([np.cos(-np.pi / 2 - ang), np.sin(-np.pi / 2 - ang)])
        direction = np.array([np.cos(ang), -np.sin(ang)])
        net.add_lane("j", "k", StraightLane(p1 - direction * 80.0, p1, line_types=[CL, CL], speed_limit=v, width=w))
    return info


BUILDERS = {"intersection": build_intersection, "highway": build_highway, "uturn": build_uturn, "merge": build_merge}


class RoadMap:
    """A road network with geometry caches, connectivity, routing and spatial lookup."""

    CONNECT_TOL = 0.05  # [m] lane end -> lane start distance that counts as connected

    def __init__(self, spec: MapSpec | dict[str, Any]) -> None:
        self.spec = spec if isinstance(spec, MapSpec) else MapSpec.model_validate(spec)
        info = BUILDERS[self.spec.type](self.spec)
        self.network = info.network
        self.stop_lines = info.stop_lines
        self.light_groups = info.light_groups
        self.junction_roads = info.junction_roads
        self.lanes: dict[LaneId, Any] = dict(self.network.lanes_dict())
        self.lane_ids: list[LaneId] = list(self.lanes)
        self.geoms: dict[LaneId, LaneGeom] = {i: LaneGeom(lane) for i, lane in self.lanes.items()}
        self.successors: dict[LaneId, list[LaneId]] = {i: [] for i in self.lane_ids}
        ends = {i: (g.xy(np.array(g.length)), g.heading(np.array(g.length))) for i, g in self.geoms.items()}
        starts = {i: (g.xy(np.array(0.0)), g.heading(np.array(0.0))) for i, g in self.geoms.items()}
        for a, (pa, ha) in ends.items():
            for b, (pb, hb) in starts.items():
                if a[1] == b[0] and np.linalg.norm(pa - pb) < self.CONNECT_TOL and abs(wrap_angle(ha - hb)) < 0.05:
                    self.successors[a].append(b)
        self.stop_line_of: dict[LaneId, StopLine] = {sl.lane: sl for sl in self.stop_lines}
        self._around: dict[LaneId, tuple[LaneId, ...]] = {}
        self._tree = shapely.STRtree([shapely.LineString(g.xy(np.linspace(0, g.length, 12)))
                                      for g in self.geoms.values()])

    # -- lookups ----------------------------------------------------------------------------
    def has_lane(self, lane_id: LaneId) -> bool:
        return tuple(lane_id) in self.lanes

    def geom(self, lane_id: LaneId) -> LaneGeom:
        return self.geoms[tuple(lane_id)]  # type: ignore[index]

    def road_lanes(self, road: tuple[str, str]) -> list[LaneId]:
        return [(road[0], road[1], k) for k in range(len(self.network.graph[road[0]][road[1]]))]

    def changeable_neighbours(self, lane_id: LaneId) -> list[LaneId]:
        """Lanes of the same road reachable by a lane change (striped line, not in a junction)."""
        a, b, k = lane_id
        if (a, b) in self.junction_roads:
            return []
        out = []
        n = len(self.network.graph[a][b])
        for j in (k - 1, k + 1):
            if 0 <= j < n:
                line = self.lanes[(a, b, min(j, k) + 1)].line_types[0]
                if line == S:
                    out.append((a, b, j))
        return out

    def around(self, lane_id: LaneId) -> tuple[LaneId, ...]:
        """The lane, its successors and its changeable neighbours, in that order: where a vehicle
        on it can be a moment later (what trackers search first; cached, the map is static)."""
        out = self._around.get(lane_id)
        if out is None:
            out = self._around[lane_id] = (lane_id, *self.successors[lane_id], *self.changeable_neighbours(lane_id))
        return out

    def straight_successor(self, lane_id: LaneId) -> LaneId | None:
        """The successor with the least heading change (what a naive predictor assumes)."""
        succ = self.successors[tuple(lane_id)]  # type: ignore[index]
        if not succ:
            return None
        g = self.geoms[tuple(lane_id)]  # type: ignore[index]
        h_end = float(g.heading(np.array(g.length)))

        def turn(b: LaneId) -> float:
            gb = self.geoms[b]
            return abs(float(wrap_angle(gb.heading(np.array(gb.length)) - h_end)))

        return min(succ, key=turn)

    def default_chain(self, lane_id: LaneId, min_length: float) -> list[LaneId]:
        """``lane_id`` followed by straight successors until ``min_length`` [m] is covered."""
        chain = [tuple(lane_id)]
        total = self.geoms[chain[0]].length
        while total < min_length:
            nxt = self.straight_successor(chain[-1])  # type: ignore[arg-type]
            if nxt is None or nxt in chain:
                break
            chain.append(nxt)
            total += self.geoms[nxt].length
        return chain  # type: ignore[return-value]

    def reference_line(self, chain: list[LaneId]) -> ReferenceLine:
        return ReferenceLine(chain, [self.geoms[tuple(i)] for i in chain])  # type: ignore[index]

    def candidate_lanes(self, xy: np.ndarray, radius: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
        """Index pairs ``(point_idx, lane_idx)`` of lanes within ``radius`` of each point."""
        pts = shapely.points(np.atleast_2d(xy))
        res = self._tree.query(pts, predicate="dwithin", distance=radius)
        return res[0], res[1]

    def locate(self, xy: np.ndarray, heading: float | None = None, radius: float = 3.0) -> tuple[LaneId, float, float] | None:
        """The best-matching lane of one position: ``(lane_id, s, d)``, or None when off-road.

        Lanes are scored by lateral offset plus a heading mismatch penalty (so an opposite lane
        or a crossing junction lane loses to the lane a vehicle is actually driving along)."""
        xy = np.asarray(xy, dtype=float)
        _, idx = self.candidate_lanes(xy, radius)
        best = None
        for j in idx:
            lane_id = self.lane_ids[j]
            g = self.geoms[lane_id]
            s, d = g.frenet(xy)
            s, d = float(s), float(d)
            over = max(0.0, -s, s - g.length)
            score = abs(d) + 2.0 * over
            if heading is not None:
                score += 4.0 * abs(float(wrap_angle(heading - float(g.heading(np.array(min(max(s, 0.0), g.length)))))))
            if best is None or score < best[0]:
                best = (score, lane_id, s, d)
        return None if best is None else best[1:]

    # -- routing ----------------------------------------------------------------------------
    def lane_route(self, start: LaneId, goal: LaneId) -> list[LaneId] | None:
        """Shortest lane sequence from ``start`` to ``goal`` by successor links and lane changes
        (Dijkstra on length, lane changes cost 20 m). None if unreachable."""
        import heapq

        start, goal = tuple(start), tuple(goal)  # type: ignore[assignment]
        dist = {start: 0.0}
        prev: dict[LaneId, LaneId] = {}
        heap = [(0.0, start)]
        while heap:
            dcur, cur = heapq.heappop(heap)
            if cur == goal:
                break
            if dcur > dist.get(cur, np.inf):
                continue
            edges = [(b, self.geoms[cur].length) for b in self.successors[cur]]
            edges += [(b, 20.0) for b in self.changeable_neighbours(cur)]
            for b, cost in edges:
                nd = dcur + cost
                if nd < dist.get(b, np.inf):
                    dist[b] = nd
                    prev[b] = cur
                    heapq.heappush(heap, (nd, b))
        if goal not in dist:
            return None
        path = [goal]
        while path[-1] != start:
            path.append(prev[path[-1]])
        return path[::-1]  # type: ignore[return-value]

    def route_segments(self, start: LaneId, goal: LaneId) -> list[dict[str, Any]] | None:
        """The routing answer: road segments in order, each with the lanes from which the route
        continues (Apollo's passages, simplified)."""
        lanes = self.lane_route(start, goal)
        if lanes is None:
            return None
        roads: list[tuple[str, str]] = []
        for a, b, _ in lanes:
            if not roads or roads[-1] != (a, b):
                roads.append((a, b))
        segments = []
        for i, road in enumerate(roads):
            if i + 1 < len(roads):
                nxt = roads[i + 1]
                ok = [lid[2] for lid in self.road_lanes(road) if any(s[:2] == nxt for s in self.successors[lid])]
            else:
                ok = [goal[2]]
            segments.append({"road": list(road), "lanes": ok})
        return segments

    def as_data(self, step: float = 0.5) -> dict[str, Any]:
        """The map as plain data (the ``map`` message, :data:`deft_gym.bus.messages.SCHEMAS`):
        every lane's centre line as a polyline (its two ends for a straight lane, points at most
        ``step`` [m] apart otherwise, exact at the points) with its arc lengths, width, length,
        speed limit, successors, left/right neighbours and whether a change to them is allowed;
        stop lines and light ids. A fresh copy on every call."""
        lanes = []
        for lid in self.lane_ids:
            g = self.geoms[lid]
            n = 2 if g.kind == "straight" else max(2, math.ceil(g.length / step) + 1)
            s = np.linspace(0.0, g.length, n)
            xy = g.xy(s)
            a, b, k = lid
            n_road = len(self.network.graph[a][b])
            left = (a, b, k - 1) if k > 0 else None
            right = (a, b, k + 1) if k + 1 < n_road else None
            change = self.changeable_neighbours(lid)
            lanes.append({
                "id": list(lid), "x": xy[:, 0].tolist(), "y": xy[:, 1].tolist(), "s": s.tolist(),
                "width": float(g.width), "length": float(g.length),
                "speed_limit": float(self.lanes[lid].speed_limit or self.spec.speed_limit),
                "successors": [list(x) for x in self.successors[lid]],
                "left": list(left) if left else [], "right": list(right) if right else [],
                "change_left": left in change, "change_right": right in change,
                "junction": (a, b) in self.junction_roads})
        stops = []
        for sl in self.stop_lines:
            x, y = self.geoms[sl.lane].xy(np.array(sl.s)).tolist()
            stops.append({"lane": list(sl.lane), "s": float(sl.s), "x": x, "y": y, "light_id": sl.light_id})
        return {"name": self.spec.type, "lanes": lanes, "stop_lines": stops,
                "lights": sorted({sl.light_id for sl in self.stop_lines})}

    @cached_property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of all lane centre lines [m]."""
        pts = np.concatenate([g.xy(np.linspace(0, g.length, 8)) for g in self.geoms.values()])
        return float(pts[:, 0].min()), float(pts[:, 1].min()), float(pts[:, 0].max()), float(pts[:, 1].max())

    @cached_property
    def drivable_area(self) -> shapely.Geometry:
        """Union of all lane surfaces (shapely), for feasibility checks and plots."""
        return shapely.union_all([lane_surface(g, np.linspace(0.0, g.length, max(2, int(g.length / 2.0) + 1)),
                                               g.width / 2) for g in self.geoms.values()])


def lane_surface(g: LaneGeom, s: np.ndarray, half_width: float) -> shapely.Polygon:
    """The surface of a lane between its edges at ``half_width`` [m] from the centre line,
    sampled at arc lengths ``s`` [m]."""
    return shapely.Polygon(np.concatenate([g.xy(s, -half_width), g.xy(s, half_width)[::-1]]))


_SHARED: dict[str, RoadMap] = {}


def shared_roadmap(spec: MapSpec | dict[str, Any]) -> RoadMap:
    """A :class:`RoadMap` per map spec, built once per process (maps are immutable)."""
    spec = spec if isinstance(spec, MapSpec) else MapSpec.model_validate(spec)
    key = spec.model_dump_json()
    rm = _SHARED.get(key)
    if rm is None:
        rm = _SHARED[key] = RoadMap(spec)
    return rm
