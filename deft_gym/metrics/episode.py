"""Per-episode driving-quality metrics (docs/metrics.md) from a :class:`~deft_gym.search.trace.Trace`.

>>> ctx = MetricsContext.of_scenario(scenario)            # map, lights, route (or an expert path)
>>> m = episode_metrics(trace, ctx, collision)            # -> EpisodeMetrics
>>> m.score, m.violations()

Everything is computed once per episode, vectorised over the trace's world steps (numpy and
shapely); nothing here runs during the simulation.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import shapely

from deft_gym.scenarios.scenario import Scenario, destination_xy, pose_xyh
from deft_gym.search.nods import EGO_LENGTH, EGO_WIDTH, collision_fault, ego_distances, trigger_type
from deft_gym.search.trace import Trace
from deft_gym.sim.oracles import held_by_light
from deft_gym.world.geometry import box_corners
from deft_gym.world.roadmap import RoadMap, lane_surface, shared_roadmap
from deft_gym.world.traffic_lights import TrafficLights

# -- thresholds (nuPlan's closed-loop metric defaults unless said otherwise) ---------------------
TTC_BOUND = 1.5  # [s] time to collision below this is a violation (nuPlan: 0.95 s)
STOPPED_SPEED = 0.05  # [m/s] nuPlan: no TTC for a stopped ego
NEAR_MISS = 0.5  # [m] a TTC under 2 x TTC_BOUND counts only where the ego's footprint then came this close to its
NEAR_MISS_HORIZON = 3.0  # [s] ... within this time
DRIVABLE_TOLERANCE = 0.3  # [m] footprint this far outside the road is a violation (nuPlan)
DIRECTION_OK = 2.0  # [m] against the lane's direction within any 1 s: compliant (nuPlan)
DIRECTION_BAD = 6.0  # [m] more than this: violation, between: half score (nuPlan)
DIRECTION_WINDOW = 1.0  # [s]
OVERSPEED_NORM = 2.23  # [m/s] nuPlan's max_overspeed_value_threshold (normalises the integral)
OVERSPEED_BAD = 1.0  # [m/s] over the limit by more than this is a speed-limit violation
PROGRESS_MIN = 5.0  # [m] an expert/route progress below this makes progress trivially met
STANDING = 0.5  # [m/s] slower than this the ego stands (as deft_gym.sim.oracles)
STANDSTILL_BOUND = 5.0  # [s] standing unrequired longer than this is a violation (docs/search.md: 5.05 s)
QUEUE_GAP = 10.0  # [m] standing this close behind a vehicle in the ego's path is required
# following: ISO 15622 (ACC) lets a driver choose time gaps down to 0.8 s in steady state; after a
# cut-in an ACC reopens the gap within seconds, so only a stretch longer than HEADWAY_HOLD counts
HEADWAY_BOUND = 0.8  # [s] bumper gap to a leader over the ego's speed below this is too close
HEADWAY_HOLD = 3.0  # [s] ... for longer than this at a stretch: a violation
HEADWAY_MIN_SPEED = 2.0  # [m/s] no headway for a slower ego (queues, stopping behind a car)
LEADER_SPEED = 1.0  # [m/s] a leader moves along the ego's heading at least this fast
LEADER_ALIGN = 0.7  # cos of the largest heading difference of a leader to the ego
HEADWAY_OPENING = 1.0  # [m/s] a leader pulling away faster than this (a car that merged ahead) is no tailgating
SMOOTH = 0.5  # [s] moving-average window of the comfort signals
STARTUP = 1.0  # [s] comfort ignores the start, before the ADS's first control command took hold
# nuPlan ego_is_comfortable bounds: [m/s^2], [m/s^3], [rad/s], [rad/s^2]
COMFORT_BOUNDS = {"lon_accel": (-4.05, 2.40), "lat_accel": (-4.89, 4.89), "lon_jerk": (-4.13, 4.13),
                  "jerk": (0.0, 8.37), "yaw_rate": (-0.95, 0.95), "yaw_accel": (-1.93, 1.93)}
# nuPlan's weighted-average metrics and their weights
WEIGHTS = {"ttc": 5.0, "progress": 5.0, "speed_limit": 4.0, "comfort": 2.0}


@dataclass
class MetricsContext:
    """What the metrics read besides the trace: the map, the lights (None without), the route
    as a polyline [m] from the ego's start to its destination (or an expert's path) and the
    progress the expert made along it [m] (None: the route's whole length)."""

    roadmap: RoadMap
    lights: TrafficLights | None
    route: np.ndarray
    expert_progress: float | None = None
    _line: Any = None
    _area: Any = None

    @property
    def line(self) -> shapely.LineString:
        if self._line is None:
            self._line = shapely.LineString(self.route)
        return self._line

    @property
    def area(self) -> shapely.Geometry:
        """The drivable area: :func:`drivable_area` of the map (prepared, built once per map)."""
        if self._area is None:
            self._area = drivable_area(self.roadmap)
        return self._area

    @classmethod
    def of_scenario(cls, sc: Scenario, roadmap: RoadMap | None = None, expert: Trace | None = None) -> MetricsContext:
        """The context of a scenario: its lights, and its route - the expert's path when
        ``expert`` (a reference run) is given (nuPlan's progress along the expert route), else
        the lane route from the ego's start to its destination."""
        roadmap = roadmap or shared_roadmap(sc.map.model_dump())
        lights = TrafficLights(roadmap.light_groups, sc.lights) if roadmap.light_groups else None
        if expert is not None and len(expert.xy) > 1:
            line = shapely.LineString(expert.xy)
            prog = float(line.project(shapely.Point(expert.xy[-1])) - line.project(shapely.Point(expert.xy[0])))
            return cls(roadmap, lights, np.asarray(expert.xy, dtype=float), prog)
        return cls(roadmap, lights, route_polyline(roadmap, sc))


_AREAS: dict[int, tuple[RoadMap, shapely.Geometry]] = {}


def drivable_area(roadmap: RoadMap) -> shapely.Geometry:
    """The map's drivable surface: every lane's surface and, in junctions, the convex hull of
    each junction lane's surface - a junction is paved, its lanes are only the paths across it,
    so a turn that cuts inside its lane's curve stays on the road (nuPlan's drivable area holds
    the intersection polygons too). Prepared; memoised per map."""
    hit = _AREAS.get(id(roadmap))
    if hit is not None and hit[0] is roadmap:
        return hit[1]
    hulls = [shapely.convex_hull(roadmap_lane_surface(roadmap, lid)) for lid in roadmap.lane_ids
             if tuple(lid[:2]) in roadmap.junction_roads]
    area = shapely.union_all([roadmap.drivable_area, *hulls])
    shapely.prepare(area)
    _AREAS[id(roadmap)] = (roadmap, area)
    return area


def roadmap_lane_surface(roadmap: RoadMap, lid: Any) -> shapely.Polygon:
    """One lane's surface (polygon [m])."""
    g = roadmap.geom(lid)
    return lane_surface(g, np.linspace(0.0, g.length, max(2, int(g.length / 1.0) + 1)), g.width / 2)


def route_polyline(roadmap: RoadMap, sc: Scenario, step: float = 1.0) -> np.ndarray:
    """The centre line [m] of the lane route from the ego's start to its destination: on each
    road the lane the route leaves it by (lane changes are lateral, they add no length), the
    last road up to the destination's station."""
    xy0, h0 = pose_xyh(roadmap, sc.ego)
    start = tuple(sc.ego.lane) if sc.ego.lane else roadmap.locate(np.asarray(xy0), h0)[0]
    goal = tuple(sc.ego.destination.lane)
    lanes = roadmap.lane_route(start, goal) or [start, goal]
    by_road: dict[tuple[str, str], Any] = {}
    for lid in lanes:
        by_road[tuple(lid[:2])] = lid  # the last lane of each road: where the route leaves it
    _, dest_s = destination_xy(roadmap, sc.ego.destination)
    pts = []
    chain = list(by_road.values())
    for i, lid in enumerate(chain):
        g = roadmap.geom(lid)
        s1 = dest_s if i == len(chain) - 1 else g.length
        s0 = float(g.frenet(np.asarray(xy0))[0]) if i == 0 else 0.0
        s = np.linspace(max(0.0, min(s0, s1)), s1, max(2, math.ceil(abs(s1 - s0) / step) + 1))
        pts.append(g.xy(s))
    return np.concatenate(pts)


@dataclass
class EpisodeMetrics:
    """The metrics of one episode (units in the names' docs; docs/metrics.md)."""

    duration: float = 0.0  #: [s] simulated time the trace covers
    at_fault_collision: bool = False  #: nuPlan no_ego_at_fault_collisions (inverted)
    collision_how: str = ""  #: collision_fault's answer (rear_end, lateral, cut_in, ...)
    min_ttc: float | None = None  #: [s] nuPlan time_to_collision_within_bound; None: never closing
    ttc_below_s: float = 0.0  #: [s] time with TTC below TTC_BOUND
    ttc_actor: str | None = None  #: the participant of the smallest TTC
    ttc_trigger: str | None = None  #: its kind (cone, parked, vehicle; seed:... for a seed's)
    off_road_max: float = 0.0  #: [m] largest distance of a footprint corner outside the road
    off_road_s: float = 0.0  #: [s] time with the footprint more than DRIVABLE_TOLERANCE outside
    wrong_way_m: float = 0.0  #: [m] driven against the direction of every lane the ego was in
    wrong_way_max_1s: float = 0.0  #: [m] the most of it within one DIRECTION_WINDOW
    red_lights: list[dict[str, Any]] = field(default_factory=list)  #: stop lines crossed on red
    progress: float = 0.0  #: [m] along the route (or expert path)
    progress_ratio: float = 1.0  #: ego progress / route (or expert) progress, in [0, 1]
    comfort: dict[str, float] = field(default_factory=dict)  #: worst value of each COMFORT_BOUNDS signal
    uncomfortable: list[str] = field(default_factory=list)  #: the signals outside their bounds
    overspeed_integral: float = 0.0  #: [m] integral of speed above the lane's limit
    max_overspeed: float = 0.0  #: [m/s]
    standstill_s: float = 0.0  #: [s] standing (< STANDING) neither held by a light nor queued
    standstill_max_s: float = 0.0  #: [s] the longest such stretch
    min_headway: float | None = None  #: [s] smallest bumper gap to a leader / ego speed; None: never following
    headway_below_max_s: float = 0.0  #: [s] the longest stretch with headway below HEADWAY_BOUND
    headway_actor: str | None = None  #: the leader of the longest such stretch (else of min_headway)
    headway_trigger: str | None = None  #: its kind (vehicle; seed:vehicle for a seed's)
    cpu_s: float = 0.0  #: [s] process CPU time computing these

    # -- sub-scores (nuPlan) -------------------------------------------------------------------
    @property
    def ttc_score(self) -> float:
        return 0.0 if self.ttc_below_s > 0.0 else 1.0

    @property
    def drivable_score(self) -> float:
        return 0.0 if self.off_road_max > DRIVABLE_TOLERANCE else 1.0

    @property
    def direction_score(self) -> float:
        w = self.wrong_way_max_1s
        return 1.0 if w <= DIRECTION_OK else 0.5 if w <= DIRECTION_BAD else 0.0

    @property
    def speed_score(self) -> float:
        return max(0.0, 1.0 - self.overspeed_integral / (OVERSPEED_NORM * max(self.duration, 1e-9)))

    @property
    def comfort_score(self) -> float:
        return 0.0 if self.uncomfortable else 1.0

    @property
    def score(self) -> float:
        """nuPlan-like score in [0, 1]: the gates (no at-fault collision, drivable area, driving
        direction, no red light) times the weighted average of TTC, progress, speed limit and
        comfort (:data:`WEIGHTS`)."""
        gate = (0.0 if self.at_fault_collision else 1.0) * self.drivable_score * self.direction_score \
            * (0.0 if self.red_lights else 1.0)
        parts = {"ttc": self.ttc_score, "progress": self.progress_ratio, "speed_limit": self.speed_score,
                 "comfort": self.comfort_score}
        return gate * sum(WEIGHTS[k] * parts[k] for k in WEIGHTS) / sum(WEIGHTS.values())

    def violations(self) -> list[str]:
        """The metric oracles this episode violates (names of :data:`deft_gym.metrics.oracle.ORACLES`)."""
        out = []
        if self.at_fault_collision:
            out.append("collision")
        if self.ttc_below_s > 0.0:
            out.append("ttc")
        if self.off_road_max > DRIVABLE_TOLERANCE:
            out.append("drivable_area")
        if self.wrong_way_max_1s > DIRECTION_OK:
            out.append("direction")
        if self.red_lights:
            out.append("red_light")
        if self.uncomfortable:
            out.append("comfort")
        if self.max_overspeed > OVERSPEED_BAD:
            out.append("speed_limit")
        if self.standstill_max_s > STANDSTILL_BOUND:
            out.append("standstill")
        if self.headway_below_max_s > HEADWAY_HOLD:
            out.append("headway")
        return out

    def as_dict(self) -> dict[str, Any]:
        """Plain, rounded values plus ``score`` and ``violations`` (summary.json, records)."""
        d = asdict(self)
        for k, v in d.items():
            if isinstance(v, float):
                d[k] = round(v, 4) if math.isfinite(v) else None
        d["comfort"] = {k: round(v, 3) for k, v in self.comfort.items()}
        d["score"] = round(self.score, 4)
        d["violations"] = self.violations()
        return d


# -- the computation -----------------------------------------------------------------------------
def episode_metrics(trace: Trace, ctx: MetricsContext, collision: dict[str, Any] | None = None) -> EpisodeMetrics:
    """All metrics of one episode. ``collision``: the episode's collision record (``Outcome``'s
    ``collision.as_dict()``), judged by :func:`deft_gym.search.nods.collision_fault`."""
    import time

    c0 = time.process_time()
    m = EpisodeMetrics()
    ego = np.asarray(trace.ego, dtype=float)
    n = len(ego)
    dt = float(trace.world_dt)
    if n == 0:
        return m
    t = trace.t
    m.duration = float(t[-1] - t[0]) if n > 1 else 0.0
    if collision is not None and trace.outcome == "collision":
        def road_heading(x: float, y: float, h: float) -> float:
            loc = ctx.roadmap.locate(np.array([x, y]), h)
            return h if loc is None else float(ctx.roadmap.geom(loc[0]).heading_point(loc[1]))

        m.at_fault_collision, m.collision_how = collision_fault(trace, collision, road_heading)
    lead_gap, follow_gap, follow_v, follow_actor = _ttc(trace, m, dt)
    _headway(trace, ego, follow_gap, follow_v, follow_actor, m, dt)
    _drivable(ego, ctx, m, dt)
    limits = _lanes(ego, ctx, m, dt)
    _red_lights(ego, t, ctx, m)
    _progress(ego, ctx, m)
    _comfort(ego, dt, m)
    over = np.maximum(ego[:, 3] - limits, 0.0)
    m.overspeed_integral = float(over.sum() * dt)
    m.max_overspeed = float(over.max())
    _standstill(ego, t, lead_gap, ctx, m, dt)
    m.cpu_s = time.process_time() - c0
    return m


def _ttc(trace: Trace, m: EpisodeMetrics, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Longitudinal TTC to participants ahead in the ego's path (ego-at-fault direction only):
    gap along the ego's heading over the closing speed, constant velocities. Returns, at every
    step, the gap [m] to the nearest participant in the path (inf: none), the gap [m] to the
    nearest leader in it (moving along the ego's heading: :data:`LEADER_SPEED`,
    :data:`LEADER_ALIGN`), that leader's speed [m/s] along the ego's heading and its actor index
    (-1: none)."""
    ego, parts = trace.ego, trace.parts
    n = len(ego)
    gap_ahead = np.full(n, np.inf)
    follow_gap, follow_v, follow_actor = np.full(n, np.inf), np.zeros(n), np.full(n, -1)
    if not len(parts):
        return gap_ahead, follow_gap, follow_v, follow_actor
    order = np.lexsort((parts[:, 0], parts[:, 1]))
    p = parts[order]
    same = np.r_[False, (p[1:, 1] == p[:-1, 1])]
    dtk = np.r_[1.0, np.diff(p[:, 0])] * dt
    vx = np.where(same, np.r_[0.0, np.diff(p[:, 2])] / np.maximum(dtk, 1e-9), 0.0)
    vy = np.where(same, np.r_[0.0, np.diff(p[:, 3])] / np.maximum(dtk, 1e-9), 0.0)
    i = np.clip(np.searchsorted(trace.ticks, p[:, 0]), 0, n - 1)
    ex, ey, eh, ev = ego[i, 0], ego[i, 1], ego[i, 2], ego[i, 3]
    c, s = np.cos(eh), np.sin(eh)
    dx, dy = p[:, 2] - ex, p[:, 3] - ey
    lon, lat = dx * c + dy * s, -dx * s + dy * c
    idx = p[:, 1].astype(int)
    length = np.array([a.length for a in trace.actors])[idx]
    width = np.array([a.width for a in trace.actors])[idx]
    dh = p[:, 4] - eh
    half_lon = np.abs(np.cos(dh)) * length / 2 + np.abs(np.sin(dh)) * width / 2
    half_lat = np.abs(np.sin(dh)) * length / 2 + np.abs(np.cos(dh)) * width / 2
    in_path = (lon > 0.0) & (np.abs(lat) < EGO_WIDTH / 2 + half_lat)
    gap = lon - EGO_LENGTH / 2 - half_lon
    closing = ev - (vx * c + vy * s)
    with np.errstate(divide="ignore", invalid="ignore"):
        ttc = np.where(gap <= 0.0, 0.0, gap / closing)
    ttc = np.where(in_path & (closing > 1e-3) & (ev > STOPPED_SPEED), ttc, np.inf)
    np.minimum.at(gap_ahead, i[in_path], np.maximum(gap[in_path], 0.0))
    along = vx * c + vy * s
    lead = np.flatnonzero(in_path & (np.cos(dh) > LEADER_ALIGN) & (along > LEADER_SPEED))
    if len(lead):  # the nearest leader at each step: rows sorted by gap, the first of each step kept
        lead = lead[np.lexsort((gap[lead], i[lead]))]
        first = lead[np.r_[True, i[lead][1:] != i[lead][:-1]]]
        follow_gap[i[first]] = np.maximum(gap[first], 0.0)
        follow_v[i[first]] = along[first]
        follow_actor[i[first]] = idx[first]
    near = np.flatnonzero(ttc < 2 * TTC_BOUND)  # (only these: a longer TTC is no violation, and the check costs)
    ttc[near[~_came_close(trace, p, i, idx, near, length, width, dt)]] = np.inf
    per_step = np.full(n, np.inf)
    np.minimum.at(per_step, i, ttc)
    m.ttc_below_s = float((per_step < TTC_BOUND).sum() * dt)
    if np.isfinite(per_step).any():
        k = int(np.argmin(ttc))
        m.min_ttc = float(ttc[k])
        actor = trace.actors[int(idx[k])]
        m.ttc_actor = actor.id
        m.ttc_trigger = trigger_type(actor)
    return gap_ahead, follow_gap, follow_v, follow_actor


def _headway(trace: Trace, ego: np.ndarray, follow_gap: np.ndarray, follow_v: np.ndarray, follow_actor: np.ndarray,
             m: EpisodeMetrics, dt: float) -> None:
    """Time headway [s] to the leader (bumper gap over the ego's speed, an ego faster than
    :data:`HEADWAY_MIN_SPEED`): its minimum, and the longest stretch below :data:`HEADWAY_BOUND`
    (ISO 15622's shortest steady-state time gap of an ACC) while the leader does not pull away
    (:data:`HEADWAY_OPENING`: a faster car that merged in ahead opens the gap by itself). TTC
    misses a tailgater: at the leader's speed nothing closes."""
    v = ego[:, 3]
    ok = np.isfinite(follow_gap) & (v > HEADWAY_MIN_SPEED)
    if not ok.any():
        return
    hw = np.where(ok, follow_gap / np.maximum(v, 1e-9), np.inf)
    k = int(np.argmin(hw))
    m.min_headway = float(hw[k])
    close = ((hw < HEADWAY_BOUND) & (follow_v - v < HEADWAY_OPENING)).astype(np.int8)
    edges = np.flatnonzero(np.diff(np.r_[0, close, 0]))
    if len(edges):
        runs = edges[1::2] - edges[::2]
        j = int(np.argmax(runs))
        m.headway_below_max_s = float(runs[j] * dt)
        k = int(edges[2 * j])
    actor = trace.actors[int(follow_actor[k])]
    m.headway_actor, m.headway_trigger = actor.id, trigger_type(actor)


def _came_close(trace: Trace, p: np.ndarray, i: np.ndarray, idx: np.ndarray, rows: np.ndarray,
                length: np.ndarray, width: np.ndarray, dt: float) -> np.ndarray:
    """For the participant rows ``p[rows]`` (every row of ``p`` at ego step ``i``, actor ``idx``):
    whether the ego's footprint came within :data:`NEAR_MISS` of the participant's in the next
    :data:`NEAR_MISS_HORIZON` (what both actually did). A heading projected straight ahead sweeps
    across a cone beside a turn or an oncoming car the turning ego waits for; a conflict comes close."""
    ego, n = trace.ego, len(trace.ego)
    out = np.zeros(len(rows), dtype=bool)
    if not len(rows):
        return out
    pose = np.full((len(trace.actors), n, 3), np.nan)  # every actor's pose at every ego step, held after its last
    pose[idx, i] = p[:, 2:5]
    i, idx, length, width = i[rows], idx[rows], length[rows], width[rows]
    for a in range(len(trace.actors)):
        seen = np.flatnonzero(~np.isnan(pose[a, :, 0]))
        if len(seen):
            pose[a, seen[0]:] = pose[a, seen[np.searchsorted(seen, np.arange(seen[0], n), side="right") - 1]]
    window = np.minimum(i[:, None] + np.arange(round(NEAR_MISS_HORIZON / dt) + 1)[None, :], n - 1)
    other = pose[idx[:, None], window]
    centre = np.hypot(other[..., 0] - ego[window, 0], other[..., 1] - ego[window, 1])
    w = window[np.arange(len(rows)), np.argmin(np.where(np.isnan(centre), np.inf, centre), axis=1)]
    at = pose[idx, w]
    ok = ~np.isnan(at[:, 0])
    if ok.any():
        out[ok] = ego_distances(ego[w[ok], :3], at[ok], length[ok], width[ok]) <= NEAR_MISS
    return out


def _drivable(ego: np.ndarray, ctx: MetricsContext, m: EpisodeMetrics, dt: float) -> None:
    """nuPlan drivable_area_compliance (CommonRoad: the road-compliance check of the drivability
    checker): how far the footprint leaves the drivable area (:func:`drivable_area`)."""
    pts = box_corners(ego[:, 0], ego[:, 1], ego[:, 2], EGO_LENGTH, EGO_WIDTH).reshape(-1, 2)
    inside = shapely.contains_xy(ctx.area, pts[:, 0], pts[:, 1])
    out = np.zeros(len(pts))
    if not inside.all():
        out[~inside] = shapely.distance(ctx.area, shapely.points(pts[~inside]))
    per_step = out.reshape(-1, 4).max(axis=1)
    m.off_road_max = float(per_step.max())
    m.off_road_s = float((per_step > DRIVABLE_TOLERANCE).sum() * dt)


def _lanes(ego: np.ndarray, ctx: MetricsContext, m: EpisodeMetrics, dt: float) -> np.ndarray:
    """Driving direction (nuPlan driving_direction_compliance; CommonRoad R_I4-like) and the
    speed limit [m/s] at every step: the lanes whose surface holds the ego's centre; the ego
    drives against the direction when every such lane points the other way (more than 90 deg)."""
    rm = ctx.roadmap
    n = len(ego)
    limit = np.full(n, float(rm.spec.speed_limit))
    pi, li = rm.candidate_lanes(ego[:, :2], radius=rm.spec.lane_width / 2)
    along = np.full(n, -np.inf)  # best cos(lane heading - ego heading) of a lane holding the point
    lane_limit = np.full(n, -np.inf)
    for j in np.unique(li):
        lid = rm.lane_ids[int(j)]
        g = rm.geoms[lid]
        k = pi[li == j]
        s, d = g.frenet(ego[k, :2])
        hold = (np.abs(d) <= g.width / 2) & (s >= -0.5) & (s <= g.length + 0.5)
        k, s = k[hold], s[hold]
        if not len(k):
            continue
        cos = np.cos(g.heading(np.clip(s, 0.0, g.length)) - ego[k, 2])
        np.maximum.at(along, k, cos)
        ok = k[cos >= 0.0]
        np.maximum.at(lane_limit, ok, float(rm.lanes[lid].speed_limit or rm.spec.speed_limit))
    limit = np.where(np.isfinite(lane_limit), lane_limit, limit)
    wrong = np.isfinite(along) & (along < 0.0)
    step = np.r_[0.0, np.hypot(*np.diff(ego[:, :2], axis=0).T)]
    against = np.where(wrong, step, 0.0)
    m.wrong_way_m = float(against.sum())
    w = max(1, round(DIRECTION_WINDOW / dt))
    cum = np.r_[0.0, np.cumsum(against)]
    m.wrong_way_max_1s = float((cum[w:] - cum[:-w]).max()) if n >= w else m.wrong_way_m
    return limit


def _red_lights(ego: np.ndarray, t: np.ndarray, ctx: MetricsContext, m: EpisodeMetrics) -> None:
    """Stop lines the ego's front crossed (driving along their lane) while their light was red
    (CommonRoad traffic rule R_IN1; nuPlan has none)."""
    rm, lights = ctx.roadmap, ctx.lights
    if lights is None or not rm.stop_lines or len(ego) < 2:
        return
    h = ego[:, 2]
    fx = ego[:, 0] + EGO_LENGTH / 2 * np.cos(h)
    fy = ego[:, 1] + EGO_LENGTH / 2 * np.sin(h)
    for sl in rm.stop_lines:
        g = rm.geom(sl.lane)
        cx, cy = (float(v) for v in g.xy(np.array(sl.s)))
        hl = g.heading_point(sl.s)
        u, v = math.cos(hl), math.sin(hl)
        lon = (fx - cx) * u + (fy - cy) * v
        lat = -(fx - cx) * v + (fy - cy) * u
        cross = np.flatnonzero((lon[:-1] < 0.0) & (lon[1:] >= 0.0) & (np.abs(lat[1:]) <= g.width / 2)
                               & (np.cos(h[1:] - hl) > 0.0)) + 1
        for k in cross:
            if lights.color(sl.light_id, float(t[k])) == "RED":
                m.red_lights.append({"light": sl.light_id, "lane": list(sl.lane), "t": round(float(t[k]), 3)})


def _progress(ego: np.ndarray, ctx: MetricsContext, m: EpisodeMetrics) -> None:
    """nuPlan ego_progress_along_expert_route: the ego's progress along the route (or the
    expert's path) [m] over the route's (or the expert's) progress, clipped to [0, 1]."""
    line = ctx.line
    s0 = float(line.project(shapely.Point(ego[0, :2])))
    s1 = float(line.project(shapely.Point(ego[-1, :2])))
    m.progress = s1 - s0
    full = ctx.expert_progress if ctx.expert_progress is not None else float(line.length) - s0
    m.progress_ratio = 1.0 if full < PROGRESS_MIN else float(np.clip(m.progress / full, 0.0, 1.0))


def _smooth(x: np.ndarray, w: int) -> np.ndarray:
    if w <= 1 or len(x) < w:
        return x
    pad = np.pad(x, (w // 2, w - 1 - w // 2), mode="edge")
    return np.convolve(pad, np.ones(w) / w, mode="valid")


def _comfort(ego: np.ndarray, dt: float, m: EpisodeMetrics) -> None:
    """nuPlan ego_is_comfortable: longitudinal and lateral acceleration [m/s^2], longitudinal
    jerk and jerk magnitude [m/s^3], yaw rate [rad/s] and yaw acceleration [rad/s^2], each
    smoothed over SMOOTH s, against :data:`COMFORT_BOUNDS`; the first STARTUP s are left out
    (the ego rolls uncontrolled until the first control command arrives)."""
    if len(ego) < 3:
        return
    w = max(1, round(SMOOTH / dt))
    v = ego[:, 3]
    lon = _smooth(np.gradient(v, dt), w)
    yaw = _smooth(np.gradient(np.unwrap(ego[:, 2]), dt), w)
    lat = v * yaw
    lon_jerk = _smooth(np.gradient(lon, dt), w)
    lat_jerk = _smooth(np.gradient(lat, dt), w)
    sig = {"lon_accel": lon, "lat_accel": lat, "lon_jerk": lon_jerk, "jerk": np.hypot(lon_jerk, lat_jerk),
           "yaw_rate": yaw, "yaw_accel": _smooth(np.gradient(yaw, dt), w)}
    skip = min(len(v) - 1, round(STARTUP / dt))
    for k, x in sig.items():
        x = x[skip:]
        lo, hi = COMFORT_BOUNDS[k]
        low, high = float(x.min()), float(x.max())
        # each extreme against its own bound (they differ: braking -4.05, accelerating +2.40 m/s^2);
        # kept: the one nearer to or farther beyond its bound
        m.comfort[k] = low if lo and low / lo > high / hi else high
        if low < lo or high > hi:
            m.uncomfortable.append(k)


def _standstill(ego: np.ndarray, t: np.ndarray, lead_gap: np.ndarray, ctx: MetricsContext,
                m: EpisodeMetrics, dt: float) -> None:
    """Time [s] the ego stood (< STANDING) while not required to: neither held by a light
    (before its lane's stop line while the light is not green) nor queued (a participant in its
    path within QUEUE_GAP)."""
    standing = (ego[:, 3] < STANDING) & ~(lead_gap < QUEUE_GAP)
    idle = np.flatnonzero(standing)
    if ctx.lights is not None and ctx.roadmap.stop_line_of and len(idle):
        at, loc = None, None
        for k in idle:
            if at is None or math.hypot(*(ego[k, :2] - at)) > 0.1:  # located again only once it moved
                at, loc = ego[k, :2], ctx.roadmap.locate(ego[k, :2], float(ego[k, 2]))
            if held_by_light(ctx.roadmap, ctx.lights, loc, float(t[k])):
                standing[k] = False
    m.standstill_s = float(standing.sum() * dt)
    edges = np.flatnonzero(np.diff(np.r_[0, standing.astype(np.int8), 0]))
    runs = edges[1::2] - edges[::2]
    m.standstill_max_s = float(runs.max() * dt) if len(runs) else 0.0


def simulation_metrics(sim: Any, recorder: Any, result: Any, expert: Trace | None = None) -> EpisodeMetrics:
    """The metrics of a finished :class:`~deft_gym.sim.simulation.Simulation` whose
    :class:`~deft_gym.search.trace.TraceRecorder` ``recorder`` was attached before it started."""
    o = result.outcome
    trace = recorder.trace(o.outcome, o.sim_time)
    ctx = MetricsContext.of_scenario(sim.scenario, sim.roadmap, expert)
    return episode_metrics(trace, ctx, o.collision.as_dict() if o.collision else None)


def aggregate(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per-run figures of several episodes' :meth:`EpisodeMetrics.as_dict`: the mean score, the
    worst (smallest) score, the smallest TTC [s] and how many episodes violated each oracle."""
    rows = [r for r in rows if r]
    if not rows:
        return {}
    counts: dict[str, int] = {}
    for r in rows:
        for v in r.get("violations", []):
            counts[v] = counts.get(v, 0) + 1
    ttcs = [r["min_ttc"] for r in rows if r.get("min_ttc") is not None]
    return {"episodes": len(rows), "mean_score": round(float(np.mean([r["score"] for r in rows])), 4),
            "min_score": round(float(min(r["score"] for r in rows)), 4),
            "min_ttc": round(float(min(ttcs)), 4) if ttcs else None,
            "mean_progress_ratio": round(float(np.mean([r["progress_ratio"] for r in rows])), 4),
            "violations": dict(sorted(counts.items()))}
