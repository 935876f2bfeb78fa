"""Non-invasive feasible areas (Decictor eq. 3-4) with shapely.

Time is cut into windows ``[k dt, (k+1) dt]`` (``dt`` = 2 s in the paper). For every window the
reference run (the seed scenario's optimal run, :func:`deft_gym.search.trace.reference_run`) gives
the *motion areas* R^p(pi(s*), dt): the area the ego's box sweeps along its reference path
from ``late_window`` seconds before the window to ``early_window`` after it (all of the path once
the reference run has ended, on to the destination itself: :func:`deft_gym.search.nods.reserved_path`),
inflated by ``margin`` - the same reservation the validity check
(:func:`deft_gym.search.nods.clearances`) applies - and the areas the seed participants sweep, inflated by
``participant_margin``. A new participant is non-invasive when, in every window it exists in,
the area it sweeps stays out of all of them (eq. 3-4) and out of the areas of the participants
already added; a static obstacle never intersects any of them in any window, nor the whole
path inflated by ``static_margin``, nor the lanes the path drives in (``static_lane_depth``): out
of the ego's lane, a departure from the paper, whose 0.5 m lets a parked car stand inside the
lane, where a planner goes round it by design.

:class:`MotionAreas` holds the per-window areas of one reference run (prepared shapely
geometries, built once per process and reference). :class:`Layout` adds the participants placed
so far and answers the two questions the mutation operators and the adversary env ask, vectorised
over candidates: "may these static boxes go here?" and "in which window does this trajectory
first invade?". Swept areas are unions of the convex hulls of consecutive box poses sampled every
``sample_dt`` (exact for straight motion at constant heading, tight otherwise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import shapely
from pydantic import BaseModel, ConfigDict, Field

from deft_gym.search.nods import EGO_LENGTH, EGO_WIDTH, lane_strips
from deft_gym.search.trace import Trace
from deft_gym.world.geometry import box_corners, box_polygon
from deft_gym.world.roadmap import RoadMap, lane_surface


class FeasibleConfig(BaseModel):
    """Parameters of the feasible-area computation (m, s)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    dt: float = Field(2.0, gt=0.0, le=10.0, description="window length (paper: 2 s)")
    margin: float = Field(0.5, ge=0.0, le=3.0, description="[m] inflation of the ego's reference motion area: "
                          "the paper's safe distance; never below the planner's own hard buffer")
    static_margin: float = Field(0.75, ge=0.0, le=3.0, description="[m] the same for static objects (cones, parked "
                                 "vehicles), never below margin: out of the ego's lane (a centred ego in a 3.5 m lane "
                                 "has 0.75 m each side). A planner may rightly go round an object standing in its "
                                 "lane - the reference's parked-vehicle buffer does so from 0.7 m - so one placed "
                                 "there changes the optimal decision by design and finds no failure")
    static_lane_depth: float | None = Field(0.0, ge=0.0, le=1.0, description="[m] static objects stand no "
                                            "deeper than this in a lane the optimal path drives in (within 8 m "
                                            "of where it is in it; 0: not in it at all - the reference's "
                                            "parked-vehicle buffer blocks a 3.5 m lane for any car that enters "
                                            "it); null: no lane test (the paper)")
    tolerance: float = Field(0.05, ge=0.0, le=0.5, description="[m] extra inflation of the ego's motion area "
                             "covering what sampling its poses every sample_dt can miss, so that a feasible "
                             "placement keeps the full margin from every pose")
    participant_margin: float = Field(0.3, ge=0.0, le=3.0, description="[m] inflation of other participants' areas")
    idm_zones: bool = Field(True, description="reactive participants also claim the stretch of their lane "
                            "ahead that their car-following reacts to within the window: what they can "
                            "reach in it plus the IDM gap (jam distance + time gap x speed)")
    idm_gap: float = Field(10.0, ge=0.0, le=50.0, description="[m] IDM jam distance (highway-env: 5 m + length)")
    idm_time_gap: float = Field(1.5, ge=0.0, le=5.0, description="[s] IDM time gap (highway-env: 1.5 s)")
    roi: float = Field(15.0, gt=0.0, le=100.0, description="placements within this distance of the reference path")
    shoulder: float = Field(1.0, ge=0.0, le=5.0, description="[m] static objects may stand this far beyond the "
                            "drivable area (on the shoulder, where cones and parked cars are found)")
    sample_dt: float = Field(0.25, gt=0.0, le=1.0, description="pose sampling of swept areas")
    spawn_distance: float = Field(15.0, ge=0.0, le=100.0, description="min distance of a new participant to the ego")
    early_window: float = Field(1.0, ge=0.0, le=30.0, description="[s] the optimal path is reserved from this "
                                "long before the reference ego is there (a mutated ego this much early still finds "
                                "it free)")
    late_window: float = Field(3.0, ge=0.0, le=30.0, description="[s] ... until this long after it left (a mutated "
                               "ego this much late still finds it free); all of it once the reference run has ended")


#: Decictor's own rule: static objects, like moving ones, 0.5 m from the optimal path (a parked car
#: may stand inside the ego's lane; the evaluations before 2026-11-26 ran under it)
PAPER = FeasibleConfig(static_margin=0.5, static_lane_depth=None)


def swept_hulls(corners: np.ndarray) -> np.ndarray:
    """Convex hulls of consecutive box poses, ``corners`` shape (n, 4, 2) -> n-1 polygons (or the
    single box for n == 1)."""
    if len(corners) == 1:
        return shapely.polygons(corners)
    pairs = np.concatenate([corners[:-1], corners[1:]], axis=1)
    return shapely.convex_hull(shapely.multipoints(pairs))


def swept_area(x: np.ndarray, y: np.ndarray, h: np.ndarray, length: float, width: float) -> shapely.Geometry:
    """Union of the area swept by a box through the given poses."""
    return shapely.union_all(swept_hulls(box_corners(x, y, h, length, width)))


def _in_window(t: np.ndarray, t0: float, t1: float) -> np.ndarray:
    """Indices of the samples of ``t`` in [t0, t1] (1 ns tolerance at both ends)."""
    return np.flatnonzero((t >= t0 - 1e-9) & (t <= t1 + 1e-9))


def _window_samples(t: np.ndarray, t0: float, t1: float, step: float) -> np.ndarray:
    """Indices of samples of ``t`` in [t0, t1], thinned to about ``step`` apart (ends kept)."""
    idx = _in_window(t, t0, t1)
    if len(idx) <= 2:
        return idx
    span = t[idx[-1]] - t[idx[0]]
    n = max(2, round(span / step) + 1)
    keep = np.unique(np.round(np.linspace(0, len(idx) - 1, n)).astype(int))
    return idx[keep]


class MotionAreas:
    """Per-window motion areas of the ego and the seed participants of one reference run."""

    def __init__(self, ref: Trace, roadmap: RoadMap, cfg: FeasibleConfig, horizon: float) -> None:
        self.ref, self.roadmap, self.cfg = ref, roadmap, cfg
        self.n_windows = max(1, math.ceil(horizon / cfg.dt - 1e-9))
        dt, m, pm = cfg.dt, cfg.margin + cfg.tolerance, cfg.participant_margin
        t = ref.t
        e = ref.ego
        self.ego: list[shapely.Geometry] = []
        self.seed: list[shapely.Geometry] = []
        tracks = [(a, ref.track(i)) for i, a in enumerate(ref.actors)]
        whole: shapely.Geometry | None = None  # the whole path: reserved once the reference has ended
        for k in range(self.n_windows):
            t0, t1 = k * dt, (k + 1) * dt
            if t1 > t[-1] + 1e-9:
                if whole is None:
                    idx = _window_samples(t, t[0], t[-1], cfg.sample_dt)
                    whole = swept_area(e[idx, 0], e[idx, 1], e[idx, 2], EGO_LENGTH + 2 * m, EGO_WIDTH + 2 * m)
                self.ego.append(whole)
            else:  # a participant in the window meets an ego up to late_window late or early_window early
                idx = _window_samples(t, t0 - cfg.late_window, t1 + cfg.early_window, cfg.sample_dt)
                self.ego.append(swept_area(e[idx, 0], e[idx, 1], e[idx, 2], EGO_LENGTH + 2 * m, EGO_WIDTH + 2 * m))
            parts = []
            for a, tr in tracks:
                if not len(tr):
                    continue
                tt = tr[:, 0] * ref.world_dt
                j = _window_samples(tt, t0, t1, cfg.sample_dt)
                if len(j) == 0:
                    if a.kind == "scripted" and tt[0] > t1:
                        continue  # not there yet
                    j = np.array([len(tt) - 1]) if tt[-1] < t0 else np.array([0])
                parts.append(swept_area(tr[j, 1], tr[j, 2], tr[j, 3], a.length + 2 * pm, a.width + 2 * pm))
                if a.kind == "reactive" and cfg.idm_zones:
                    parts.extend(self._idm_zone(tr[j], ref.world_dt, a.length))
            self.seed.append(shapely.union_all(parts) if parts else shapely.Polygon())
        self.forbidden = [shapely.union(a, b) for a, b in zip(self.ego, self.seed)]
        for g in self.forbidden:
            shapely.prepare(g)
        sm = max(cfg.static_margin, cfg.margin) + cfg.tolerance
        idx = _window_samples(t, t[0], t[-1], cfg.sample_dt)
        static_path = swept_area(e[idx, 0], e[idx, 1], e[idx, 2], EGO_LENGTH + 2 * sm, EGO_WIDTH + 2 * sm)
        # the lanes the path drives in (the validity check's ``ego_lanes`` too); None: no lane test
        self.ego_lanes = None if cfg.static_lane_depth is None else lane_strips(ref, roadmap, cfg.static_lane_depth)
        if self.ego_lanes is not None:
            shapely.prepare(self.ego_lanes)
        lanes = [] if self.ego_lanes is None else [self.ego_lanes]
        self.static_forbidden = shapely.union_all([*self.forbidden, static_path, *lanes])
        shapely.prepare(self.static_forbidden)
        self.ref_line = shapely.LineString(ref.xy)
        self.ground = roadmap.drivable_area.buffer(cfg.shoulder) if cfg.shoulder > 0 else roadmap.drivable_area
        self.roi = shapely.intersection(self.ground, self.ref_line.buffer(cfg.roi))
        shapely.prepare(self.roi)
        shapely.prepare(self.ground)
        self._near_static: dict[float, shapely.Geometry] = {}

    def near_static_forbidden(self, reach: float) -> shapely.Geometry:
        """A prepared area holding every point within ``reach`` [m] of :attr:`static_forbidden`
        (its buffer, 2 % + 1 mm wider than ``reach``: the buffer's arcs are chords, inside the
        true circle by under 0.5 %), built once per ``reach``. A box whose centre lies outside it
        cannot meet the forbidden area."""
        near = self._near_static.get(reach)
        if near is None:
            near = self._near_static[reach] = self.static_forbidden.buffer(1.02 * reach + 1e-3, quad_segs=8)
            shapely.prepare(near)
        return near

    def _idm_zone(self, rows: np.ndarray, world_dt: float, length: float) -> list[shapely.Geometry]:
        """What a reactive (IDM) participant at these poses ``(tick, x, y, h)`` reacts to in the
        window: its lane from where it is to where it gets by the end of the window plus its IDM
        gap (jam distance + time gap x speed), 1 m wider on each side (highway-env's on-lane
        test) - so that area is claimed too."""
        cfg = self.cfg
        if len(rows) >= 2:
            span = max(float(rows[-1, 0] - rows[0, 0]) * world_dt, 1e-6)
            v = float(np.hypot(rows[-1, 1] - rows[0, 1], rows[-1, 2] - rows[0, 2])) / span
        else:
            v = 0.0
        ahead = length / 2 + cfg.idm_gap + cfg.idm_time_gap * v
        first: dict[tuple[str, str, int], tuple[float, float]] = {}
        for _, x, y, h in rows:
            loc = self.roadmap.locate(np.array([x, y]), float(h))
            if loc is not None:
                lane, s, _ = loc
                lo, hi = first.get(lane, (math.inf, -math.inf))
                first[lane] = (min(lo, float(s)), max(hi, float(s)))
        return [_lane_strip(self.roadmap, lane, lo, hi + ahead) for lane, (lo, hi) in first.items()]

    def window(self, t: float) -> int:
        return min(max(math.floor(t / self.cfg.dt + 1e-9), 0), self.n_windows - 1)


_STRIPS: dict[tuple[Any, ...], shapely.Geometry] = {}


def _lane_strip(roadmap: RoadMap, lane: tuple[str, str, int], s0: float, s1: float) -> shapely.Geometry:
    """Lane surface from ``s0`` to ``s1`` (rounded out to 1 m, clipped to the lane), 1 m wider on
    each side."""
    geom = roadmap.geom(lane)
    a = min(max(math.floor(s0), 0.0), geom.length)
    b = min(max(math.ceil(s1), a), geom.length)
    key = (id(roadmap), lane, a, b)
    g = _STRIPS.get(key)
    if g is None:
        ss = np.linspace(a, b, max(2, int((b - a) / 2.0) + 2))
        g = lane_surface(geom, ss, geom.width / 2 + 1.0)
        if len(_STRIPS) > 20000:
            _STRIPS.clear()
        _STRIPS[key] = g
    return g


_AREAS: dict[tuple[Any, ...], MotionAreas] = {}


def motion_areas(ref: Trace, roadmap: RoadMap, cfg: FeasibleConfig, horizon: float) -> MotionAreas:
    """:class:`MotionAreas`, memoised per process (reference, map, config, horizon)."""
    key = (id(ref), id(roadmap), cfg, round(horizon, 6))
    ma = _AREAS.get(key)
    if ma is None:
        if len(_AREAS) > 64:
            _AREAS.clear()
        ma = _AREAS[key] = MotionAreas(ref, roadmap, cfg, horizon)
    return ma


# ---------------------------------------------------------------------------------------------
@dataclass
class Placed:
    """A participant placed by a mutation or the adversary, with its occupied areas."""

    id: str
    kind: str  # static | scripted
    spec: dict[str, Any]
    windows: dict[int, shapely.Geometry] = field(default_factory=dict)  # scripted: window -> area
    area: shapely.Geometry | None = None  # static: footprint (inflated)
    traj: Any = None  # scripted: the trajectory (deft_gym.search.vehicles.Trajectory)


class Layout:
    """The participants added so far on top of a reference run, and feasibility queries."""

    def __init__(self, areas: MotionAreas) -> None:
        self.areas = areas
        self.cfg = areas.cfg
        self.placed: list[Placed] = []
        self._static_union: shapely.Geometry | None = None
        self._window_union: dict[int, shapely.Geometry] = {}

    # -- bookkeeping --------------------------------------------------------------------------
    def add(self, p: Placed) -> None:
        self.placed.append(p)
        self._invalidate()

    def remove(self, pid: str) -> Placed | None:
        for i, p in enumerate(self.placed):
            if p.id == pid:
                self._invalidate()
                return self.placed.pop(i)
        return None

    def replace(self, p: Placed) -> None:
        for i, q in enumerate(self.placed):
            if q.id == p.id:
                self.placed[i] = p
                self._invalidate()
                return
        self.add(p)

    def _invalidate(self) -> None:
        self._static_union = None
        self._window_union = {}

    def _added_in_window(self, k: int, skip: str | None) -> shapely.Geometry | None:
        if skip is None and k in self._window_union:
            return self._window_union[k]
        geoms = [p.area if p.kind == "static" else p.windows.get(k) for p in self.placed if p.id != skip]
        geoms = [g for g in geoms if g is not None]
        g = shapely.union_all(geoms) if geoms else None
        if g is not None:
            shapely.prepare(g)
        if skip is None:
            self._window_union[k] = g
        return g

    def _added_any(self) -> shapely.Geometry | None:
        if self._static_union is None:
            geoms = [p.area for p in self.placed if p.kind == "static"]
            geoms += [g for p in self.placed if p.kind != "static" for g in p.windows.values()]
            self._static_union = shapely.union_all(geoms) if geoms else shapely.Polygon()
            shapely.prepare(self._static_union)
        return None if self._static_union.is_empty else self._static_union

    # -- queries ------------------------------------------------------------------------------
    def static_ok(self, x: np.ndarray, y: np.ndarray, h: np.ndarray, length: float, width: float,
                  on_road: bool = True) -> np.ndarray:
        """Boolean per candidate box: never intersects the reference motion areas (all windows)
        nor any added participant, and (``on_road``) has its centre on the drivable area or its
        shoulder."""
        # the cheap point test first; the box tests only for the boxes still in the running
        # (each box is judged alone: the same answer as testing every box, at less cost)
        ok = shapely.contains_xy(self.areas.ground, x, y) if on_road else np.ones(len(x), dtype=bool)
        idx = np.flatnonzero(ok)
        if len(idx):
            corners = box_corners(x[idx], y[idx], h[idx], length, width)
            # the box test only where the centres leave it open: a centre inside the forbidden
            # area puts the box in it, one farther from it than the box's half-diagonal keeps the
            # box out (the same answer as the box test, at a fraction of its cost)
            forbidden, cx, cy = self.areas.static_forbidden, x[idx], y[idx]
            near = shapely.contains_xy(self.areas.near_static_forbidden(0.5 * math.hypot(length, width)), cx, cy)
            open_ = near & ~shapely.contains_xy(forbidden, cx, cy)
            free = ~near
            if open_.any():
                free[open_] = ~shapely.intersects(shapely.polygons(corners[open_]), forbidden)
            other = self._added_any()
            if other is not None and free.any():
                free[free] = ~shapely.intersects(shapely.polygons(corners[free]), other)
            ok[idx] = free
        return ok

    def first_conflict(self, t: np.ndarray, x: np.ndarray, y: np.ndarray, h: np.ndarray, length: float,
                       width: float, skip: str | None = None, k_from: int = 0,
                       k_to: int | None = None) -> int:
        """The first window (>= ``k_from``) in which the box moving through the poses ``(t, x, y,
        h)`` invades a motion area, or -1 if it never does. ``skip``: an added participant to
        ignore (the one being changed)."""
        areas, dt = self.areas, self.cfg.dt
        k_end = areas.n_windows if k_to is None else min(k_to, areas.n_windows)
        k0 = max(k_from, areas.window(float(t[0])))
        corners = box_corners(x, y, h, length, width)
        for k in range(k0, k_end):
            t0, t1 = k * dt, (k + 1) * dt
            if t[0] > t1 + 1e-9:
                continue
            parked = t[-1] < t0 - 1e-9  # after its last pose it stays there
            idx = np.array([len(t) - 1]) if parked else _in_window(t, t0, t1)
            hulls = swept_hulls(corners[idx])
            if self._hits(hulls, k, skip):
                return k
            if parked:
                return next((kk for kk in range(k + 1, k_end) if self._hits(hulls, kk, skip)), -1)
        return -1

    def _hits(self, geoms: np.ndarray, k: int, skip: str | None) -> bool:
        if shapely.intersects(geoms, self.areas.forbidden[k]).any():
            return True
        other = self._added_in_window(k, skip)
        return other is not None and bool(shapely.intersects(geoms, other).any())

    def window_areas(self, t: np.ndarray, x: np.ndarray, y: np.ndarray, h: np.ndarray, length: float,
                     width: float) -> dict[int, shapely.Geometry]:
        """Per-window swept areas of a trajectory, inflated by ``participant_margin`` (what a
        placed vehicle occupies for later placements)."""
        areas, dt, pm = self.areas, self.cfg.dt, self.cfg.participant_margin
        corners = box_corners(x, y, h, length + 2 * pm, width + 2 * pm)
        out: dict[int, shapely.Geometry] = {}
        for k in range(areas.window(float(t[0])), areas.n_windows):
            t0, t1 = k * dt, (k + 1) * dt
            idx = _in_window(t, t0, t1)
            if len(idx) == 0:
                idx = np.array([len(t) - 1])
            g = shapely.union_all(swept_hulls(corners[idx]))
            shapely.prepare(g)
            out[k] = g
        return out

    def static_footprint(self, x: float, y: float, h: float, length: float, width: float) -> shapely.Geometry:
        pm = self.cfg.participant_margin
        g = box_polygon(x, y, h, length + 2 * pm, width + 2 * pm)
        shapely.prepare(g)
        return g


def reachable_area(roadmap: RoadMap, lane: tuple[str, str, int], s: float, v: float, dt: float,
                   v_max: float, a_max: float = 3.0, d_max: float = 4.0) -> shapely.Geometry:
    """Eq. 3's R(y_t) for a lane-bound vehicle: the lane surface between the distances it can
    cover in ``dt`` (speed in [max(0, v - d_max dt), min(v_max, v + a_max dt)]), on its lane and
    the changeable neighbours (for rendering; the mutation operators sample controls from the
    same set)."""
    lo = s + max(0.0, v - 0.5 * d_max * dt) * dt if v > d_max * dt else s
    hi = s + min(v_max, v + 0.5 * a_max * dt) * dt
    polys = []
    for lid in [lane, *roadmap.changeable_neighbours(lane)]:
        g = roadmap.geom(lid)
        ss = np.linspace(max(0.0, min(lo, g.length)), max(0.0, min(hi, g.length)), 8)
        if ss[-1] - ss[0] < 1e-3:
            continue
        polys.append(lane_surface(g, ss, g.width / 2))
    return shapely.union_all(polys) if polys else shapely.Polygon()
