"""Oracle transformation (DeFT section 4.5): from a system-level collision to a faulty plan.

A collision seen by the simulator becomes a planning-module oracle: a planned trajectory is
*faulty* when one of its points puts the ego box, at the planned time, onto the box of the
participant it collided with, at that participant's recorded position at the same time
(interpolated between perception messages, extrapolated briefly past the last one). Of all
faulty outputs published before the collision, P_faulty is the last one whose start (its first
point) is still collision-free: the last plan with which the planner could still have avoided
the collision and chose not to, so reproducing it is reproducing the failing decision.

Everything here is numpy over all points of all outputs at once; the same functions check the
reproduced output in the generated failure tests (:mod:`extract.runtime`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

#: how far past the last observation a participant's position is extrapolated [s]
MAX_EXTRAPOLATION = 0.3
DEFAULT_EGO = (4.8, 2.0)


@dataclass
class Track:
    """A participant's recorded states: time [s], centre, heading, speed and size."""

    participant: str
    num: int
    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    v: np.ndarray
    length: float
    width: float

    def as_dict(self) -> dict[str, Any]:
        return {"participant": self.participant, "num": self.num, "t": self.t.tolist(), "x": self.x.tolist(),
                "y": self.y.tolist(), "heading": self.heading.tolist(), "v": self.v.tolist(),
                "length": self.length, "width": self.width}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Track:
        return cls(d["participant"], int(d["num"]), *(np.asarray(d[k], dtype=float) for k in
                                                       ("t", "x", "y", "heading", "v")),
                   float(d["length"]), float(d["width"]))

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Centre x, y, heading at times ``t`` and whether the participant is known there."""
        t = np.asarray(t, dtype=float)
        h = np.unwrap(self.heading)
        x, y, hh = np.interp(t, self.t, self.x), np.interp(t, self.t, self.y), np.interp(t, self.t, h)
        after = np.maximum(t - self.t[-1], 0.0)
        x = x + after * self.v[-1] * np.cos(h[-1])
        y = y + after * self.v[-1] * np.sin(h[-1])
        known = (t >= self.t[0]) & (t <= self.t[-1] + MAX_EXTRAPOLATION)
        return x, y, hh, known


def participant_track(messages: Iterable[Mapping[str, Any] | None], num: int, participant: str = "") -> Track | None:
    """The states of obstacle ``num`` in perception-obstacle payloads (``header.stamp``,
    ``obstacles[].{id, x, y, heading, v, length, width}``), or None when it never appears."""
    track = participant_tracks(messages, {num}).get(num)
    if track is not None:
        track.participant = participant
    return track


def participant_tracks(messages: Iterable[Mapping[str, Any] | None], nums: set[int] | None = None
                       ) -> dict[int, Track]:
    """The tracks of every obstacle of perception-obstacle payloads (of ``nums`` only, when
    given), by id, in one pass; each named by its id and ``type`` (``"3 (CONE)"``)."""
    rows: dict[int, dict[float, tuple[float, float, float, float, float, float]]] = {}
    kinds: dict[int, str] = {}
    for m in messages:
        if not m:
            continue
        stamp = (m.get("header") or {}).get("stamp")
        if stamp is None:
            continue
        for ob in m.get("obstacles") or ():
            try:
                num = int(ob["id"])
            except (KeyError, TypeError, ValueError):
                continue
            if nums is not None and num not in nums:
                continue
            rows.setdefault(num, {}).setdefault(float(stamp), (ob["x"], ob["y"], ob.get("heading", 0.0),
                                                               ob.get("v", 0.0), ob.get("length", 0.0),
                                                               ob.get("width", 0.0)))
            kinds.setdefault(num, str(ob.get("type", "")))
    tracks = {}
    for num, by_time in rows.items():
        ts = sorted(by_time)
        a = np.array([by_time[t] for t in ts], dtype=float)
        tracks[num] = Track(f"{num} ({kinds[num]})" if kinds[num] else str(num), num, np.array(ts), a[:, 0],
                            a[:, 1], a[:, 2], a[:, 3], float(a[-1, 4]), float(a[-1, 5]))
    return tracks


def boxes_overlap(ax: np.ndarray, ay: np.ndarray, ah: np.ndarray, a_len: float, a_wid: float,
                  bx: np.ndarray, by: np.ndarray, bh: np.ndarray, b_len: float, b_wid: float) -> np.ndarray:
    """Whether oriented boxes A and B overlap (touching counts), element-wise; separating-axis
    test on the four box axes."""
    la, wa, lb, wb = a_len / 2, a_wid / 2, b_len / 2, b_wid / 2
    ca, sa, cb, sb = np.cos(ah), np.sin(ah), np.cos(bh), np.sin(bh)
    dx, dy = bx - ax, by - ay
    crel = np.abs(ca * cb + sa * sb)
    srel = np.abs(sa * cb - ca * sb)
    return ((np.abs(dx * ca + dy * sa) <= la + lb * crel + wb * srel)
            & (np.abs(dy * ca - dx * sa) <= wa + lb * srel + wb * crel)
            & (np.abs(dx * cb + dy * sb) <= lb + la * crel + wa * srel)
            & (np.abs(dy * cb - dx * sb) <= wb + la * srel + wa * crel))


def box_corners(x: np.ndarray, y: np.ndarray, heading: np.ndarray, size: tuple[float, float]) -> np.ndarray:
    """Corners ``(..., 4, 2)`` [m], in order around each box, of boxes of ``size`` (length, width
    [m]) centred at ``x``, ``y`` [m] with ``heading`` [rad]."""
    c, s = np.cos(heading), np.sin(heading)
    ux, uy, vx, vy = c * size[0] / 2, s * size[0] / 2, -s * size[1] / 2, c * size[1] / 2
    cx = np.stack([x + ux + vx, x + ux - vx, x - ux - vx, x - ux + vx], axis=-1)
    cy = np.stack([y + uy + vy, y + uy - vy, y - uy - vy, y - uy + vy], axis=-1)
    return np.stack([cx, cy], axis=-1)


def box_gaps(ax: np.ndarray, ay: np.ndarray, ah: np.ndarray, a_size: tuple[float, float],
             bx: np.ndarray, by: np.ndarray, bh: np.ndarray, b_size: tuple[float, float]) -> np.ndarray:
    """Distance [m] between oriented boxes A and B (sizes: length, width [m]), element-wise; 0
    where they touch or overlap (shapely)."""
    import shapely

    if not len(ax):
        return np.zeros(0)
    a = shapely.polygons(box_corners(ax, ay, ah, a_size))
    b = shapely.polygons(box_corners(bx, by, bh, b_size))
    return np.asarray(shapely.distance(a, b), dtype=float)


def overlapping_points(trajectory: Mapping[str, Sequence[float]], track: Track, ego: tuple[float, float]) -> np.ndarray:
    """Indices of the planned points whose ego box overlaps the participant at the planned time."""
    t = np.asarray(trajectory["t"], dtype=float)
    if t.size == 0:
        return np.zeros(0, dtype=np.int64)
    px, py, ph, known = track.at(t)
    hit = boxes_overlap(np.asarray(trajectory["x"], dtype=float), np.asarray(trajectory["y"], dtype=float),
                        np.asarray(trajectory["heading"], dtype=float), ego[0], ego[1],
                        px, py, ph, track.length, track.width)
    return np.flatnonzero(hit & known)


def first_overlaps(trajectories: Sequence[Mapping[str, Sequence[float]]], track: Track,
                   ego: tuple[float, float]) -> np.ndarray:
    """For each trajectory, the index of its first point overlapping the participant, or -1;
    all points of all trajectories in one vectorised pass (rows padded to the longest)."""
    if not trajectories:
        return np.zeros(0, dtype=np.int64)
    width = max(len(tr["t"]) for tr in trajectories)
    arr = np.full((4, len(trajectories), width), np.nan)
    for i, tr in enumerate(trajectories):
        m = len(tr["t"])
        for c, key in enumerate(("t", "x", "y", "heading")):
            arr[c, i, :m] = tr[key]
    t, x, y, h = arr
    px, py, ph, known = track.at(np.nan_to_num(t, nan=-np.inf))
    hit = boxes_overlap(x, y, h, ego[0], ego[1], px, py, ph, track.length, track.width) & known & ~np.isnan(t)
    return np.where(hit.any(axis=1), hit.argmax(axis=1), -1)


@dataclass
class Faulty:
    """P_faulty: the frame whose recorded output plans the ego into the collision."""

    index: int
    time: float
    publish_time: float
    planning_seq: int
    point: int
    point_time: float
    x: float
    y: float
    participant: str
    participant_num: int
    collision_time: float
    faulty_outputs: int  #: outputs before the collision that plan into it
    distance: float  #: extraction's distance of the reproduced output from P_faulty
    perceived: bool = True  #: the participant had been perceived by the frame time
    replay_from: int = 0  #: the failure test replays frames replay_from..index (see extract.minimize)
    seeded: bool = False  #: ... from a planner seeded with its recorded state at ``index`` (replays one frame)

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def find_faulty(outputs: Sequence[tuple[int, float, float, int, Mapping[str, Any]]], distances: Sequence[float],
                track: Track, ego: tuple[float, float], collision_time: float, theta: float) -> Faulty | None:
    """P_faulty: the last output published before ``collision_time`` that plans into the
    participant from a collision-free start.

    ``outputs``: ``(index, frame time, publish time, seq, payload)`` per frame. Outputs planned
    before the participant was first perceived are used only when no other is faulty (the
    planner could not have known it). An output whose first planned point already overlaps was made when the collision could no longer be avoided
    (the ego is in it at the frame time), so it counts only when no other output is faulty.
    Outputs whose reproduction was not within ``theta`` are used only when no reproduced one is
    faulty, since the failure test must reproduce P_faulty to fail."""
    n = sum(1 for o in outputs if o[2] <= collision_time + 1e-9)
    first = first_overlaps([o[4]["trajectory"] for o in outputs[:n]], track, ego)
    faulty = [(k, int(p), bool(p > 0), bool(track.t[0] <= outputs[k][1]))
              for k, p in enumerate(first.tolist()) if p >= 0]
    if not faulty:
        return None

    def rank(f: tuple[int, int, bool, bool]) -> tuple[bool, bool, bool, int]:
        return (f[3], distances[f[0]] <= theta, f[2], f[0])

    k, p, _, seen = max(faulty, key=rank)
    index, t_f, pub, seq, payload = outputs[k]
    tr = payload["trajectory"]
    return Faulty(index, t_f, pub, seq, p, float(tr["t"][p]), float(tr["x"][p]), float(tr["y"][p]),
                  track.participant, track.num, collision_time, len(faulty), float(distances[k]), seen)


def ego_size(override: tuple[float | None, float | None], logged: Mapping[str, Any] | None
             ) -> tuple[tuple[float, float], str | None]:
    """Ego box [m] and a warning when it had to be assumed: the mapping's values, else the
    log's (the ``ego`` entry of the episode record: ``length``, ``width`` of the simulated
    vehicle), else 4.8 x 2.0."""
    logged = logged if isinstance(logged, Mapping) else {}
    length = override[0] or _positive(logged.get("length"))
    width = override[1] or _positive(logged.get("width"))
    note = None
    if not (length and width):
        note = (f"the log states no ego size (episode record 'ego') and the mapping sets none (ego:); "
                f"the collision oracle assumes {DEFAULT_EGO[0]} x {DEFAULT_EGO[1]} m")
    return (float(length or DEFAULT_EGO[0]), float(width or DEFAULT_EGO[1])), note


def _positive(v: Any) -> float | None:
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) and v > 0 else None


# -- non-optimal decisions: leaving the optimal path ---------------------------------------------
# (a search run writes the optimal path it is judged against into its log: the metadata record
# named by the mapping's optimal_path_metadata, with ``x``, ``y`` [m] and ``limit`` [m], half a lane)


def optimal_path(record: Mapping[str, Any] | None) -> tuple[np.ndarray, float] | None:
    """``(path (n x 2) [m], limit [m])`` of an optimal-path record (the log's metadata, or the
    frames header's ``optimal_path``), or None when it holds no path."""
    if not isinstance(record, Mapping) or not isinstance(record.get("x"), list) or len(record["x"]) < 2:
        return None
    return np.column_stack([np.asarray(record["x"], float), np.asarray(record["y"], float)]), \
        float(record.get("limit", 1.75))


def path_distances(x: Sequence[float], y: Sequence[float], path: np.ndarray) -> np.ndarray:
    """Distance [m] of each point ``(x[i], y[i])`` to the polyline ``path`` (n x 2), as the search's
    NoDS oracle measures it (shapely, ``NoDSOracle.distances``)."""
    import shapely  # here: the programs' --help imports this module and stays fast

    points = shapely.points(np.column_stack([np.asarray(x, float), np.asarray(y, float)]))
    return np.asarray(shapely.distance(points, shapely.LineString(path)), float)


def off_path(trajectory: Mapping[str, Any], path: np.ndarray, limit: float) -> tuple[int, float] | None:
    """``(point index, distance [m])`` of the first planned point farther than ``limit`` from the
    optimal path, else None."""
    if not trajectory.get("x"):
        return None
    d = path_distances(trajectory["x"], trajectory["y"], path)
    far = np.flatnonzero(d > limit)
    return (int(far[0]), float(d[far[0]])) if len(far) else None


def find_departure(outputs: Sequence[tuple[int, float, Mapping[str, Any]]], path: np.ndarray,
                   limit: float) -> dict[str, Any] | None:
    """P_departure, the plan that took the ego off the optimal path: among the planning outputs
    ``(index, time, payload)`` in order, the first plan of the unbroken run of plans that leave
    the path (a planned point farther than ``limit``) which ends with the first plan that starts
    off it (the ego left). None when no plan starts off the path (the ego kept to it)."""
    left = next((k for k, (_, _, out) in enumerate(outputs)
                 if (tr := out.get("trajectory") or {}).get("x")
                 and path_distances(tr["x"][:1], tr["y"][:1], path)[0] > limit), None)
    if left is None:
        return None
    k = left
    while k > 0 and off_path(outputs[k - 1][2].get("trajectory") or {}, path, limit) is not None:
        k -= 1
    index, t, out = outputs[k]
    hit = off_path(out.get("trajectory") or {}, path, limit)
    point, dist = hit if hit is not None else (0, 0.0)
    return {"index": int(index), "time": float(t), "point": point, "distance": dist, "limit": float(limit),
            "left_at": float(outputs[left][1])}


# -- driving against the lane direction: the driving-direction metric on a plan ------------------
# (docs/metrics.md's ``direction``: a point is wrong-way when every lane whose surface holds it points
# more than 90 degrees away from its heading; nuPlan's driving_direction_compliance allows 2 m)

WRONG_WAY_LIMIT = 2.0  #: [m] of a plan's path in wrong-way lanes before the plan counts (P_wrong_way)


def _map_polylines(map_payload: Mapping[str, Any] | None) -> Iterable[tuple[np.ndarray, float, Mapping[str, Any]]]:
    """``(centre line (n x 2) [m], half width [m], the lane's record)`` of every lane of a ``map``
    message that has a finite polyline of at least two points and a positive width."""
    for lane in (map_payload or {}).get("lanes") or []:
        try:
            xy = np.column_stack([np.asarray(lane["x"], float), np.asarray(lane["y"], float)])
            half = 0.5 * float(lane["width"])
        except (KeyError, TypeError, ValueError):
            continue
        if len(xy) >= 2 and np.isfinite(xy).all() and half > 0:
            yield xy, half, lane


def map_lanes(map_payload: Mapping[str, Any] | None) -> list[tuple[np.ndarray, float]]:
    """``(centre line (n x 2) [m], half width [m])`` of every lane of a ``map`` message that has a
    polyline of at least two points (none without a map)."""
    return [(xy, half) for xy, half, _ in _map_polylines(map_payload)]


def wrong_way_flags(trajectory: Mapping[str, Any], lanes: Sequence[tuple[np.ndarray, float]]) -> np.ndarray:
    """Per planned point: True where at least one lane's surface holds it and every such lane
    points more than 90 degrees away from the point's ``heading``."""
    import shapely

    x, y = np.asarray(trajectory.get("x") or [], float), np.asarray(trajectory.get("y") or [], float)
    heading = np.asarray(trajectory.get("heading") or [0.0] * len(x), float)
    agree, against = np.zeros(len(x), bool), np.zeros(len(x), bool)
    if not len(x):
        return against
    points = shapely.points(np.column_stack([x, y]))
    for xy, half in lanes:
        line = shapely.LineString(xy)
        inside = np.flatnonzero(shapely.distance(points, line) <= half)
        if not len(inside):
            continue
        seg = np.diff(xy, axis=0)
        cum = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
        s = shapely.line_locate_point(line, points[inside])
        j = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
        lane_heading = np.arctan2(seg[j, 1], seg[j, 0])
        same = np.cos(heading[inside] - lane_heading) >= 0.0
        agree[inside[same]] = True
        against[inside[~same]] = True
    return against & ~agree


def wrong_way_length(trajectory: Mapping[str, Any], lanes: Sequence[tuple[np.ndarray, float]]) -> tuple[int, float]:
    """``(first wrong-way point index or -1, length [m] of the planned path whose end points are
    wrong-way)``."""
    flags = wrong_way_flags(trajectory, lanes)
    if not flags.any():
        return -1, 0.0
    x, y = np.asarray(trajectory["x"], float), np.asarray(trajectory["y"], float)
    step = np.hypot(np.diff(x), np.diff(y))
    return int(np.flatnonzero(flags)[0]), float(step[flags[1:]].sum())


def find_wrong_way(outputs: Sequence[tuple[int, float, Mapping[str, Any]]], lanes: Sequence[tuple[np.ndarray, float]],
                   limit: float = WRONG_WAY_LIMIT) -> dict[str, Any] | None:
    """P_wrong_way, the plan that took the ego against the lane direction: find the first plan that
    starts at a wrong-way point (the ego is there), then walk back through the unbroken run of
    plans before it that each plan at least ``limit`` m of path wrong-way; the first of that run.
    None when the ego never drove wrong-way or no plan before it planned it (the vehicle left its
    plan, as CommonRoad's ego cutting a left turn's corner does: DeFT's criterion for P_faulty)."""
    if not lanes:
        return None
    starts = [k for k, (_, _, out) in enumerate(outputs) if (out.get("trajectory") or {}).get("x")]
    firsts = {key: [(outputs[k][2]["trajectory"].get(key) or [0.0])[0] for k in starts] for key in ("x", "y", "heading")}
    flags = wrong_way_flags(firsts, lanes)  # every plan's first point at once (each point is judged alone)
    if not flags.any():
        return None
    entered = starts[int(np.argmax(flags))]

    def planned(k: int) -> tuple[int, float]:
        return wrong_way_length(outputs[k][2].get("trajectory") or {}, lanes)

    k = entered
    while k > 0 and planned(k - 1)[1] >= limit:
        k -= 1
    if k == entered:  # no plan before took it there (plans from there on only bring it back)
        return None
    point, length = planned(k)
    index, t, _ = outputs[k]
    return {"index": int(index), "time": float(t), "point": point, "length": length, "limit": float(limit),
            "entered_at": float(outputs[entered][1])}


# -- leaving the road: the drivable-area metric on a plan ----------------------------------------
# (docs/metrics.md's ``drivable_area``: a corner of the ego's box more than 0.3 m outside every lane's
# surface and, in junctions, each junction lane's convex hull; nuPlan's drivable_area_compliance)

OFF_ROAD_LIMIT = 0.3  #: [m] a box corner farther outside the drivable area counts (the metric's tolerance)
OFF_ROAD_RADIUS = 5.0  #: [m] a plan counts where it leaves the road this close to where the ego left it


def map_area(map_payload: Mapping[str, Any] | None) -> Any:
    """The drivable area (shapely, prepared) of a ``map`` message as the metric builds it from the
    roadmap: every lane's surface (its centre line offset by half its width along the normals)
    and the convex hull of each junction lane's surface; None without lanes."""
    import shapely

    parts = []
    for xy, half, lane in _map_polylines(map_payload):
        tangent = np.gradient(xy, axis=0)
        normal = np.column_stack([-tangent[:, 1], tangent[:, 0]]) / np.hypot(tangent[:, 0], tangent[:, 1])[:, None]
        surface = shapely.make_valid(shapely.Polygon(np.concatenate([xy - half * normal, (xy + half * normal)[::-1]])))
        parts.append(shapely.convex_hull(surface) if lane.get("junction") else surface)
    if not parts:
        return None
    area = shapely.union_all(parts)
    shapely.prepare(area)
    return area


def off_road_depths(trajectory: Mapping[str, Any], area: Any, ego: tuple[float, float]) -> np.ndarray:
    """Per planned point: how far [m] the ego's box there reaches outside ``area`` (its farthest
    corner; 0 inside)."""
    import shapely

    x, y = np.asarray(trajectory.get("x") or [], float), np.asarray(trajectory.get("y") or [], float)
    h = np.asarray(trajectory.get("heading") or [0.0] * len(x), float)
    if not len(x):
        return np.zeros(0)
    corners = box_corners(x, y, h, ego)
    cx, cy = corners[..., 0].ravel(), corners[..., 1].ravel()
    depth = np.zeros(len(cx))
    outside = ~shapely.contains_xy(area, cx, cy)
    if outside.any():
        depth[outside] = shapely.distance(area, shapely.points(cx[outside], cy[outside]))
    return depth.reshape(-1, 4).max(axis=1)


def off_road_near(trajectory: Mapping[str, Any], area: Any, ego: tuple[float, float], place: Sequence[float],
                  radius: float = OFF_ROAD_RADIUS) -> tuple[int, float]:
    """``(index, depth [m])`` of the planned point within ``radius`` of ``place`` (x, y [m]) whose
    box reaches farthest outside ``area``; ``(-1, 0.0)`` when no planned point is that close."""
    x, y = np.asarray(trajectory.get("x") or [], float), np.asarray(trajectory.get("y") or [], float)
    near = np.flatnonzero(np.hypot(x - place[0], y - place[1]) <= radius)
    if not len(near):
        return -1, 0.0
    depth = off_road_depths({k: np.asarray(trajectory[k])[near].tolist() for k in ("x", "y", "heading")
                             if trajectory.get(k) is not None}, area, ego)
    j = int(np.argmax(depth))
    return int(near[j]), float(depth[j])


def left_road(poses: Mapping[str, Sequence[float]], area: Any, ego: tuple[float, float],
              limit: float = OFF_ROAD_LIMIT) -> tuple[int, np.ndarray] | None:
    """Where the ego left the road: the index of the first pose (``poses``: ``x``, ``y`` [m],
    ``heading`` [rad]) whose box reaches more than ``limit`` [m] outside ``area``, and every pose's
    depth [m]; None when none does (or there is no area or no pose)."""
    if area is None or not len(poses.get("x") or ()):
        return None
    depth = off_road_depths(poses, area, ego)
    out_at = np.flatnonzero(depth > limit)
    return (int(out_at[0]), depth) if len(out_at) else None


def find_off_road(outputs: Sequence[tuple[int, float, Mapping[str, Any]]], poses: Mapping[str, Sequence[float]],
                  area: Any, ego: tuple[float, float], limit: float = OFF_ROAD_LIMIT,
                  radius: float = OFF_ROAD_RADIUS) -> dict[str, Any] | None:
    """P_off_road, the plan that took the ego off the road: find the first ego pose (``poses``:
    ``t`` [s], ``x``, ``y`` [m], ``heading`` [rad], the localization messages) whose box reaches
    more than ``limit`` outside the drivable area - where and when the ego left the road - then,
    from the last plan published before that, walk back through the unbroken run of plans that
    each put the box more than ``limit`` outside within ``radius`` of that place; the first of that
    run. Tied to where the ego left the road, so a long plan run off the end of a road that the
    next plans correct does not count. None when the ego never left the road or the last plan
    before did not take it there (the vehicle left its plan: DeFT's criterion for P_faulty)."""
    left = left_road(poses, area, ego, limit)
    if left is None:
        return None
    p, depth = left
    t_left, place = float(poses["t"][p]), (float(poses["x"][p]), float(poses["y"][p]))

    def planned(k: int) -> tuple[int, float]:
        return off_road_near(outputs[k][2].get("trajectory") or {}, area, ego, place, radius)

    first = None  # (plan, (point, depth)) of the earliest plan of the run so far
    k = sum(1 for _, t, _ in outputs if t < t_left) - 1  # the last plan before the ego left
    while k >= 0 and (hit := planned(k))[1] > limit:
        first, k = (k, hit), k - 1
    if first is None:
        return None
    (index, t, _), (point, reach) = outputs[first[0]], first[1]
    return {"index": int(index), "time": float(t), "point": point, "depth": reach, "limit": float(limit),
            "radius": float(radius), "place": list(place), "ego": {"length": ego[0], "width": ego[1]},
            "left_at": t_left, "left_depth": float(depth[p])}


# -- a stuck ego: the plans that stand ------------------------------------------------------------
STALL_LIMIT = 0.5  #: [m] a plan whose path is shorter stands (the episode oracle's stuck distance)


def planned_travel(trajectory: Mapping[str, Any]) -> float:
    """Length [m] of a plan's path."""
    x, y = np.asarray(trajectory.get("x") or [], float), np.asarray(trajectory.get("y") or [], float)
    return float(np.hypot(np.diff(x), np.diff(y)).sum()) if len(x) > 1 else 0.0


def find_stall(outputs: Sequence[tuple[int, float, Mapping[str, Any]]], limit: float = STALL_LIMIT,
               free: Sequence[bool] | None = None) -> dict[str, Any] | None:
    """P_stall, the plan that left a stuck ego standing: the first plan shorter than ``limit``
    (its path) of the stretch at the end of the episode in which every plan stands, or moves but
    was never followed - the ego stood where that plan starts until the end (a planner that
    flickers between a standstill and a plan it drops at the next cycle). For an episode the
    simulation ended as ``stuck``: the ego stood, no light holding it. With ``free`` (per output:
    no light held the ego then, :func:`light_holds`), only such plans count - for an episode that
    timed out standing at a light through its green phases. None when no plan of that stretch
    stands (free)."""
    def start(k: int) -> tuple[float, float] | None:
        tr = outputs[k][2].get("trajectory") or {}
        return (float(tr["x"][0]), float(tr["y"][0])) if tr.get("x") and tr.get("y") else None

    if not outputs:
        return None
    travel = [planned_travel(out.get("trajectory") or {}) for _, _, out in outputs]
    end = start(len(outputs) - 1)
    k = len(outputs)
    while k > 0:
        s = start(k - 1)
        followed = s is None or end is None or math.hypot(s[0] - end[0], s[1] - end[1]) >= limit
        if travel[k - 1] >= limit and followed:
            break
        k -= 1
    standing = [i for i in range(k, len(outputs)) if travel[i] < limit and (free is None or free[i])]
    if not standing:
        return None
    index, t, _ = outputs[standing[0]]
    return {"index": int(index), "time": float(t), "travel": travel[standing[0]],
            "limit": float(limit), "standing_plans": len(standing), "timed_out": free is not None,
            "dropped_plans": len(outputs) - standing[0] - len(standing), "last_time": float(outputs[-1][1])}


# -- passing too close: a near miss ----------------------------------------------------------------
NEAR_MISS_CLEARANCE = 0.5  #: [m] boxes closer than this pass too close (the TTC metric's near miss, NEAR_MISS)
NEAR_MISS_SPEED = 2.0  #: [m/s] ... while their velocities differ by more than this (a queue, a follower: no near miss)
NEAR_MISS_SUBSTEPS = 4  #: states checked between two of a plan's points or poses


def near_gaps(states: Mapping[str, Sequence[float]], track: Track, ego: tuple[float, float],
              speed: float = NEAR_MISS_SPEED, reach: float = NEAR_MISS_CLEARANCE,
              substeps: int = NEAR_MISS_SUBSTEPS) -> np.ndarray:
    """Per ego state (``t`` [s], ``x``, ``y`` [m], ``heading`` [rad], ``v`` [m/s]: a plan's points or
    the localization poses): the smallest gap [m] between the ego's box and the participant's
    recorded box from that state to the next, both interpolated at ``substeps`` times between
    (a car passing at 6 m/s moves 1.2 m between the 0.2 s points of a plan); inf where the
    participant is not known then, their velocities differ by ``speed`` or less, or their centres
    are too far apart for a gap under ``reach``."""
    n = len(states.get("t") or ())
    if not n:
        return np.zeros(0)
    at = np.linspace(0.0, n - 1.0, (n - 1) * substeps + 1)
    grid = np.arange(n, dtype=float)

    def fine(key: str, unwrap: bool = False) -> np.ndarray:
        values = np.asarray(states.get(key) or [0.0] * n, float)
        return np.interp(at, grid, np.unwrap(values) if unwrap else values)

    t, x, y, h, v = fine("t"), fine("x"), fine("y"), fine("heading", True), fine("v")
    px, py, ph, known = track.at(t)
    pv = np.interp(t, track.t, track.v)
    relative = np.hypot(v * np.cos(h) - pv * np.cos(ph), v * np.sin(h) - pv * np.sin(ph))
    reach_c = (math.hypot(*ego) + math.hypot(track.length, track.width)) / 2 + reach
    near = np.flatnonzero(known & (relative > speed) & (np.hypot(px - x, py - y) < reach_c))
    gaps = np.full(len(t), np.inf)
    gaps[near] = box_gaps(x[near], y[near], h[near], ego, px[near], py[near], ph[near],
                          (track.length, track.width))
    return np.minimum.reduceat(gaps, np.arange(n) * substeps)


def find_near_miss(outputs: Sequence[tuple[int, float, Mapping[str, Any]]], poses: Mapping[str, Sequence[float]],
                   tracks: Iterable[Track], ego: tuple[float, float], clearance: float = NEAR_MISS_CLEARANCE,
                   speed: float = NEAR_MISS_SPEED) -> dict[str, Any] | None:
    """P_near_miss, the plan that took the ego past a participant too close: find the first ego pose
    (``poses``: ``t`` [s], ``x``, ``y`` [m], ``heading`` [rad], ``v`` [m/s], the localization
    messages) whose box came within ``clearance`` of a participant's (``tracks``, perceived) while
    their velocities differed by more than ``speed``; then, from the last plan published before it,
    walk back through the unbroken run of plans that each put the ego's box that close to the same
    participant at its recorded position at the planned time; the first of that run (as
    :func:`find_off_road`). None when the ego never came that close, or the last plan before did
    not plan it (the vehicle left its plan, or the participant moved into the ego's way unforeseen
    by the plans' times)."""
    close = None  # (time, pose, gap, track) of the earliest close approach
    for track in tracks:
        gaps = near_gaps(poses, track, ego, speed, clearance)
        hit = np.flatnonzero(gaps < clearance)
        if len(hit) and (close is None or poses["t"][hit[0]] < close[0]):
            close = (float(poses["t"][hit[0]]), int(hit[0]), float(gaps[hit[0]]), track)
    if close is None:
        return None
    t_close, pose, gap_close, track = close

    def planned(k: int) -> tuple[int, float]:
        gaps = near_gaps(outputs[k][2].get("trajectory") or {}, track, ego, speed, clearance)
        j = int(np.argmin(gaps)) if len(gaps) else -1
        return j, float(gaps[j]) if j >= 0 else math.inf

    first = None  # (plan, (point, gap)) of the earliest plan of the run so far
    k = sum(1 for _, t, _ in outputs if t < t_close) - 1  # the last plan before the ego came close
    while k >= 0 and (hit := planned(k))[1] < clearance:
        first, k = (k, hit), k - 1
    if first is None:
        return None
    (index, t, out), (point, gap) = outputs[first[0]], first[1]
    tr = out["trajectory"]
    return {"index": int(index), "time": float(t), "point": point, "point_time": float(tr["t"][point]),
            "gap": gap, "clearance": float(clearance), "speed": float(speed), "participant": track.participant,
            "track": track.as_dict(), "ego": {"length": ego[0], "width": ego[1]}, "close_at": t_close,
            "close_gap": gap_close, "close_x": float(poses["x"][pose]), "close_y": float(poses["y"][pose])}


# -- running a red light ---------------------------------------------------------------------------
def map_stop_lines(map_payload: Mapping[str, Any] | None) -> list[dict[str, Any]]:
    """The stop lines of a ``map`` message (``stop_lines[].{lane, x, y, light_id}``), each with its
    lane's heading there (of the lane polyline's segment nearest to it) [rad] and half width [m]:
    ``{"light", "x", "y", "heading", "half_width"}``; lines whose lane is not in the map are left out."""
    lanes = {tuple(lane["id"]) if isinstance(lane.get("id"), list) else lane.get("id"): lane
             for lane in (map_payload or {}).get("lanes") or ()}
    out = []
    for sl in (map_payload or {}).get("stop_lines") or ():
        lane = lanes.get(tuple(sl["lane"]) if isinstance(sl.get("lane"), list) else sl.get("lane"))
        if lane is None or len(lane.get("x") or ()) < 2:
            continue
        xy = np.column_stack([lane["x"], lane["y"]]).astype(float)
        k = int(np.argmin(np.hypot(xy[:, 0] - sl["x"], xy[:, 1] - sl["y"])))
        a, b = xy[max(k - 1, 0)], xy[min(k + 1, len(xy) - 1)]
        out.append({"light": str(sl["light_id"]), "x": float(sl["x"]), "y": float(sl["y"]),
                    "heading": math.atan2(b[1] - a[1], b[0] - a[0]), "half_width": 0.5 * float(lane["width"])})
    return out


def light_timeline(messages: Iterable[Mapping[str, Any] | None]) -> dict[str, dict[str, list[Any]]]:
    """Each light's recorded colours from traffic-light payloads (``header.stamp``,
    ``lights[].{id, color}``): ``{light: {"t": [s, ...], "color": [...]}}``, the changes only."""
    out: dict[str, dict[str, list[Any]]] = {}
    for m in messages:
        stamp = ((m or {}).get("header") or {}).get("stamp")
        for lt in (m or {}).get("lights") or ():
            row = out.setdefault(str(lt["id"]), {"t": [], "color": []})
            if stamp is not None and (not row["color"] or row["color"][-1] != lt["color"]):
                row["t"].append(float(stamp))
                row["color"].append(str(lt["color"]))
    return out


def colour_at(timeline: Mapping[str, Sequence[Any]], t: float) -> str | None:
    """The light's colour recorded last at or before ``t`` [s] (None before its first record)."""
    k = int(np.searchsorted(np.asarray(timeline["t"], float), t, side="right")) - 1
    return str(timeline["color"][k]) if k >= 0 else None


def line_coords(line: Mapping[str, Any], fx: Any, fy: Any) -> tuple[Any, Any]:
    """Where the point(s) ``fx``, ``fy`` [m] (the ego's front) stand to stop ``line``: how far before
    it along its lane's heading [m] (negative: past it) and how far beside its centre [m] (signed);
    floats or numpy arrays."""
    u, v = math.cos(line["heading"]), math.sin(line["heading"])
    return (line["x"] - fx) * u + (line["y"] - fy) * v, -(fx - line["x"]) * v + (fy - line["y"]) * u


def red_crossings(states: Mapping[str, Sequence[float]], line: Mapping[str, Any], timeline: Mapping[str, Sequence[Any]],
                  ego_length: float) -> np.ndarray:
    """Indices of the ego states (``t`` [s], ``x``, ``y`` [m], ``heading`` [rad]: a plan's points or
    the poses) at which the ego's front has just crossed the stop ``line`` (from before it, within
    its lane's width, driving along the lane) while its light's recorded colour is RED - the
    metric's red-light rule (CommonRoad's R_IN1)."""
    t = np.asarray(states.get("t") or [], float)
    if len(t) < 2:
        return np.zeros(0, dtype=np.int64)
    h = np.asarray(states["heading"], float)
    fx = np.asarray(states["x"], float) + ego_length / 2 * np.cos(h)
    fy = np.asarray(states["y"], float) + ego_length / 2 * np.sin(h)
    ahead, beside = line_coords(line, fx, fy)
    cross = np.flatnonzero((ahead[:-1] > 0.0) & (ahead[1:] <= 0.0) & (np.abs(beside[1:]) <= line["half_width"])
                           & (np.cos(h[1:] - line["heading"]) > 0.0)) + 1
    return np.array([k for k in cross if colour_at(timeline, float(t[k])) == "RED"], dtype=np.int64)


def first_red_crossing(poses: Mapping[str, Sequence[float]], lines: Sequence[Mapping[str, Any]],
                       timelines: Mapping[str, Mapping[str, Sequence[Any]]],
                       ego_length: float) -> tuple[float, Mapping[str, Any]] | None:
    """``(time [s], stop line)`` of the first ego pose whose front crossed a stop line at red
    (:func:`red_crossings`), or None."""
    crossed = None
    for line in lines:
        timeline = timelines.get(line["light"])
        hits = red_crossings(poses, line, timeline, ego_length) if timeline else ()
        if len(hits) and (crossed is None or poses["t"][hits[0]] < crossed[0]):
            crossed = (float(poses["t"][hits[0]]), line)
    return crossed


def find_red_light(outputs: Sequence[tuple[int, float, Mapping[str, Any]]], poses: Mapping[str, Sequence[float]],
                   lines: Sequence[Mapping[str, Any]], timelines: Mapping[str, Mapping[str, Sequence[Any]]],
                   ego_length: float) -> dict[str, Any] | None:
    """P_red_light, the plan that ran a red light: find the first ego pose (``poses``: ``t`` [s],
    ``x``, ``y`` [m], ``heading`` [rad]) at which its front crossed a stop line (``lines``,
    :func:`map_stop_lines`) at red (``timelines``, :func:`light_timeline`); then, from the last plan
    published before it, walk back through the unbroken run of plans that each planned to cross
    that line at red (the light's recorded colours at the planned times) and were made while it
    showed yellow or red (the planner had seen it change: a plan made at green that the light
    caught is no plan to run it); the first of that run. None when the ego never ran a red light
    or the last plan before did not plan it."""
    crossed = first_red_crossing(poses, lines, timelines, ego_length)
    if crossed is None:
        return None
    t_cross, line = crossed
    timeline = timelines[line["light"]]

    def planned(k: int) -> np.ndarray:
        return red_crossings(outputs[k][2].get("trajectory") or {}, line, timeline, ego_length)

    first = None  # (plan, point) of the earliest plan of the run so far
    k = sum(1 for _, t, _ in outputs if t < t_cross) - 1  # the last plan before the ego crossed
    while k >= 0 and colour_at(timeline, outputs[k][1]) in ("YELLOW", "RED") and len(hit := planned(k)):
        first, k = (k, int(hit[0])), k - 1
    if first is None:
        return None
    (index, t, out), point = outputs[first[0]], first[1]
    return {"index": int(index), "time": float(t), "point": point, "point_time": float(out["trajectory"]["t"][point]),
            "light": line["light"], "colour": colour_at(timeline, t), "line": dict(line),
            "timeline": {"t": list(timeline["t"]), "color": list(timeline["color"])}, "ego_length": float(ego_length),
            "crossed_at": t_cross}


GREEN_REACTION = 1.0  #: [s] a light green for less than this still holds a standing ego (moving off takes a moment)
HOLD_REACH = 15.0  #: [m] a stop line this far ahead of the ego's front, or less, is the one its light holds it at


def light_holds(outputs: Sequence[tuple[int, float, Mapping[str, Any]]], lines: Sequence[Mapping[str, Any]],
                timelines: Mapping[str, Mapping[str, Sequence[Any]]], ego_length: float,
                reaction: float = GREEN_REACTION, reach: float = HOLD_REACH) -> list[bool]:
    """Per output ``(index, frame time, payload)``: whether a light holds the ego at its plan's start
    - a stop line up to ``reach`` ahead of its front (or 0.5 m behind it), in its lane and
    direction, whose light was not green at the frame time, or had been green for less than
    ``reaction``."""
    held = []
    for _, t, out in outputs:
        tr = out.get("trajectory") or {}
        if not tr.get("x"):
            held.append(False)
            continue
        h = float(tr["heading"][0])
        fx, fy = tr["x"][0] + ego_length / 2 * math.cos(h), tr["y"][0] + ego_length / 2 * math.sin(h)
        hold = False
        for line in lines:
            ahead, beside = line_coords(line, fx, fy)
            timeline = timelines.get(line["light"])
            if timeline is None or not (-0.5 <= ahead <= reach and abs(beside) <= line["half_width"]
                                        and math.cos(h - line["heading"]) > 0.0):
                continue
            hold = hold or colour_at(timeline, t) != "GREEN" or colour_at(timeline, t - reaction) != "GREEN"
        held.append(hold)
    return held


YELLOW_DECEL = 3.0  #: [m/s^2] a yellow light this gentle a stop can still be made for must be (ITE's yellow-interval deceleration)


def yellow_stop(trajectory: Mapping[str, Sequence[float]], lines: Sequence[Mapping[str, Any]], ego_length: float,
                decel: float = YELLOW_DECEL) -> tuple[float, bool, bool]:
    """For a plan approaching the stop lines ``lines`` (those of one light): ``(distance [m] of its
    first point's front to the line, whether a stop before the line at ``decel`` was possible
    there, whether the plan gives it up - it crosses the line, or ends where stopping before it
    takes more than ``decel``)``; the line is the one laterally nearest to the plan's start."""
    if not trajectory.get("t") or not trajectory.get("v") or not lines:
        return math.inf, False, False

    def front_to_line(k: int, line: Mapping[str, Any]) -> tuple[float, float]:
        h = float(trajectory["heading"][k])
        ahead, beside = line_coords(line, trajectory["x"][k] + ego_length / 2 * math.cos(h),
                                    trajectory["y"][k] + ego_length / 2 * math.sin(h))
        return ahead, abs(beside)

    line = min(lines, key=lambda ln: front_to_line(0, ln)[1])
    ahead0, ahead_end = front_to_line(0, line)[0], front_to_line(len(trajectory["t"]) - 1, line)[0]
    v0, v_end = float(trajectory["v"][0]), float(trajectory["v"][-1])
    possible = ahead0 > 0.0 and v0 * v0 <= 2.0 * decel * ahead0
    given_up = ahead_end <= 0.0 or v_end * v_end > 2.0 * decel * ahead_end
    return ahead0, possible, given_up


def find_yellow(outputs: Sequence[tuple[int, float, Mapping[str, Any]]], poses: Mapping[str, Sequence[float]],
                lines: Sequence[Mapping[str, Any]], timelines: Mapping[str, Mapping[str, Sequence[Any]]],
                ego_length: float, decel: float = YELLOW_DECEL) -> dict[str, Any] | None:
    """P_yellow, the plan that gave up a stop it could make: for a run whose ego crossed a stop line
    at red (:func:`first_red_crossing`), the first plan made while that light showed yellow, before
    the crossing, from whose start a stop before the line at ``decel`` was possible and which gives
    it up (:func:`yellow_stop`). The planner saw the yellow and could stop gently; the plan drove on
    into the red. None when every such plan kept the stop possible (the yellow came too late to
    stop for: a dilemma the planner did not make)."""
    crossed = first_red_crossing(poses, lines, timelines, ego_length)
    if crossed is None:
        return None
    t_cross, line = crossed
    timeline = timelines[line["light"]]
    same_light = [ln for ln in lines if ln["light"] == line["light"]]
    for index, t, out in outputs:
        if t >= t_cross:
            break
        if colour_at(timeline, t) != "YELLOW":
            continue
        tr = out.get("trajectory") or {}
        ahead, possible, given_up = yellow_stop(tr, same_light, ego_length, decel)
        if possible and given_up:
            return {"index": int(index), "time": float(t), "light": line["light"], "ahead": ahead,
                    "v0": float(tr["v"][0]), "v_end": float(tr["v"][-1]), "decel": float(decel),
                    "lines": [dict(ln) for ln in same_light], "ego_length": float(ego_length), "crossed_at": t_cross}
    return None
