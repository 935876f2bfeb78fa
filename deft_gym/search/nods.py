"""Decictor's oracles and feedback for non-optimal decisions (NoDS), on ground-truth traces.

- **Task check**: a collision is a safety failure; a timeout or a stuck ego is a task failure;
  neither is a non-optimal decision.
- **Consistency check** (paper eq. 5-6): the ego paths of the reference run and of a mutated run
  are mapped to the 2 m cells they cover; the scenario is a NoDS when the task completed and the
  IoU of the two cell sets is <= ``threshold`` (0.6). Cells are lane-aligned by default
  (``grid="lane"``: each lane cut into 2 m slices across its full width, as Decictor's
  implementation does), so a path drifting inside its lane never changes cells and the check does
  not depend on where a square grid happens to fall; ``grid="world"`` is the paper's literal
  square grid over (x, y).
- **Local check** (a separate column, never merged into the headline): the longest stretch of
  the mutated path farther than half a lane from the reference path (``off_length`` [m]); a
  completed run with ``off_length >= local_length`` (20 m) is a *local* non-optimal decision.
- **Feedback** (eq. 7-9): ``f_p`` the mean distance of the mutated path to the reference path
  (exact point-to-polyline distance), ``f_b`` the maximum mean discrepancy between the
  distributions of the ego's behaviour (heading, speed, acceleration) per reference lane, with a
  Gaussian kernel whose bandwidth is the median pairwise distance of the reference behaviour
  (fixed per seed, so children compare on one scale); heading enters as (cos, sin) so that it
  has no wrap-around jump at +-pi.
- **Validity** (%Mutation): the reference ego path is replayed against the participants of the
  mutated run. An added participant closer than ``clearance`` (0.5 m, the paper's safe distance
  and the planner's own hard buffer) to the reference ego box while that stretch of the path is
  reserved - from ``EARLY_WINDOW`` (1 s) before the reference ego is there until ``LATE_WINDOW``
  (3 s) after it left, and all of the path once the reference run has ended, on to the destination
  itself (:func:`reserved_path`: the reference ends within 3 m of it; a static one at any time) -
  makes the mutation invasive. So does a static one (cone, parked vehicle) closer than
  ``static_clearance`` (0.75 m) or standing in a lane the optimal path drives in
  (:func:`lane_strips`): inside the ego's lane, where a planner goes round it by design. So does
  one that appears within ``SPAWN_DISTANCE`` (15 m) of the live ego, or a seed participant (which
  may react to what was added) overlapping the reference ego.
- **Fault**: a collision is the ego's when the ego closed the gap (:func:`collision_fault`).
- **Findings**: every failure carries its root cause (:class:`Finding`): the trigger (the added
  object the planner's decision names: cone, parked vehicle, vehicle), its clearance band to the
  optimal path (in the ego's lane < 0.75 m, near 0.75-1.0 m, far) and the mechanism (which rule of
  the ADS's decisions fired, :meth:`DecisionOracle.explain`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
import shapely

from deft_gym.search.trace import Actor, Trace
from deft_gym.world.geometry import PolylineDistance, box_corners, box_gap, box_polygon
from deft_gym.world.roadmap import RoadMap, lane_surface
from deft_gym.world.world import EgoVehicle

GRID = 2.0  # [m] cell size
THRESHOLD = 0.6  # IoU <= threshold: non-optimal
CLEARANCE = 0.5  # [m] validity: the reference path keeps this far from every added object
STATIC_CLEARANCE = 0.75  # [m] ... and this far from every added static one (out of the ego's lane)
LOCAL_LENGTH = 20.0  # [m] local check: this long farther than half a lane from the reference
_SLICES = 100_000  # cell id = lane index * _SLICES + slice


# -- cells --------------------------------------------------------------------------------------
class LaneCells:
    """Maps positions to lane-aligned cells (and lane memberships) of one road map."""

    def __init__(self, roadmap: RoadMap, grid: float = GRID) -> None:
        self.roadmap, self.grid = roadmap, grid
        self.geoms = [roadmap.geoms[i] for i in roadmap.lane_ids]
        boxes = []
        for g in self.geoms:
            pts = g.xy(np.linspace(0.0, g.length, max(2, int(g.length / 2.0) + 1)))
            r = g.width / 2 + 0.5
            boxes.append((pts[:, 0].min() - r, pts[:, 1].min() - r, pts[:, 0].max() + r, pts[:, 1].max() + r))
        self.boxes = np.array(boxes)

    def membership(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every (point, lane) pair with the point on the lane surface: ``(point_idx, lane_idx,
        s)`` arrays."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if not len(xy):
            e = np.zeros(0, dtype=np.int64)
            return e, e, np.zeros(0)
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        b = self.boxes
        cand = np.flatnonzero((b[:, 0] <= hi[0]) & (b[:, 2] >= lo[0]) & (b[:, 1] <= hi[1]) & (b[:, 3] >= lo[1]))
        pi, li, ss = [], [], []
        for j in cand:
            g = self.geoms[j]
            s, d = g.frenet(xy)
            on = (s >= 0.0) & (s <= g.length) & (np.abs(d) <= g.width / 2)
            if on.any():
                idx = np.flatnonzero(on)
                pi.append(idx)
                li.append(np.full(len(idx), j))
                ss.append(s[idx])
        if not pi:
            e = np.zeros(0, dtype=np.int64)
            return e, e, np.zeros(0)
        return np.concatenate(pi), np.concatenate(li), np.concatenate(ss)

    def cells(self, xy: np.ndarray) -> np.ndarray:
        """Sorted unique cell ids covered by the points."""
        _, li, s = self.membership(xy)
        return np.unique(li.astype(np.int64) * _SLICES + np.floor(s / self.grid).astype(np.int64))


def world_cells(xy: np.ndarray, grid: float = GRID) -> np.ndarray:
    """The paper's square grid: sorted unique ids of the (x, y) cells of the points."""
    ij = np.floor(np.asarray(xy, dtype=float).reshape(-1, 2) / grid).astype(np.int64)
    return np.unique(ij[:, 0] * 1_000_003 + ij[:, 1])


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two sorted unique id arrays (1.0 when both are empty)."""
    inter = len(np.intersect1d(a, b, assume_unique=True))
    union = len(a) + len(b) - inter
    return 1.0 if union == 0 else inter / union


# -- feedback -----------------------------------------------------------------------------------
BEHAVIOUR_WEIGHTS = (1.0, 0.5, 0.5)  # heading, speed, acceleration (as Decictor's code)
SPEED_RANGE, ACCEL_RANGE = 12.0, 10.0  # normalisation [m/s], [m/s^2] (as Decictor's code)


def behaviour_features(ego: np.ndarray) -> np.ndarray:
    """Normalised, weighted behaviour features (cos h, sin h, v, a) of ego rows."""
    wh, wv, wa = BEHAVIOUR_WEIGHTS
    h = ego[:, 2]
    return np.stack([0.5 * wh * np.cos(h), 0.5 * wh * np.sin(h), wv * ego[:, 3] / SPEED_RANGE,
                     wa * ego[:, 4] / ACCEL_RANGE], axis=1)


def mmd_linear(x: np.ndarray, y: np.ndarray) -> float:
    """Linear-kernel MMD^2 of two samples = squared distance of their means (exact)."""
    return float(np.sum((x.mean(axis=0) - y.mean(axis=0)) ** 2))


MMD_POINTS = 200  # behaviour samples per side (evenly strided), bounding the O(n^2) kernel cost


def _thin(x: np.ndarray, n: int = MMD_POINTS) -> np.ndarray:
    """At most ``n`` rows of ``x``, evenly strided (deterministic)."""
    if len(x) <= n:
        return x
    return x[np.round(np.linspace(0, len(x) - 1, n)).astype(np.int64)]


def median_bandwidth(x: np.ndarray) -> float:
    """The median pairwise distance of the rows of ``x`` (the usual MMD bandwidth; 1 if zero)."""
    x = _thin(x)
    if len(x) < 2:
        return 1.0
    d = np.sqrt(((x[:, None, :] - x[None, :, :]) ** 2).sum(-1))
    med = float(np.median(d[np.triu_indices(len(x), 1)]))
    return med if med > 1e-9 else 1.0


def mean_kernel(a: np.ndarray, b: np.ndarray, bandwidth: float) -> float:
    """Mean of the Gaussian kernel ``exp(-|a-b|^2 / (2 bw^2))`` over all row pairs of ``a``, ``b``."""
    g = -0.5 / (bandwidth * bandwidth)
    return float(np.exp(g * ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)).mean())


def mmd_rbf(x: np.ndarray, y: np.ndarray, bandwidth: float, kxx: float | None = None) -> float:
    """Biased MMD^2 of two samples with the Gaussian kernel ``exp(-|a-b|^2 / (2 bw^2))``, in
    [0, 2]: 0 for equal distributions; an empty sample is as far as it gets (1). ``kxx``: the
    :func:`mean_kernel` of ``_thin(x)`` with itself, when the caller keeps it (the same float)."""
    if not len(x) or not len(y):
        return 1.0
    x, y = _thin(x), _thin(y)
    if kxx is None:
        kxx = mean_kernel(x, x, bandwidth)
    return max(kxx + mean_kernel(y, y, bandwidth) - 2.0 * mean_kernel(x, y, bandwidth), 0.0)


# -- validity -----------------------------------------------------------------------------------
EGO_LENGTH, EGO_WIDTH = EgoVehicle.LENGTH, EgoVehicle.WIDTH
# [s] the optimal path stays reserved from EARLY_WINDOW before the reference ego is there until
# LATE_WINDOW after it left: a mutated ego up to 1 s early or 3 s late still finds it free (a lagging
# ego is what detours make; nothing makes one much earlier, and a symmetric 3 s would outlaw every
# leader within 3 s headway, the most ordinary traffic there is)
EARLY_WINDOW, LATE_WINDOW = 1.0, 3.0
SPAWN_DISTANCE = 15.0  # [m] a participant appears at least this far from the live ego
_REACH = 2.5  # [m] clearances are computed exactly up to this distance (farther: inf)


def ego_distances(ego: np.ndarray, boxes: np.ndarray, length: float | np.ndarray,
                  width: float | np.ndarray) -> np.ndarray:
    """Exact distances [m] between the ego's footprints at ``ego`` (n, 3: x, y, h) and participant
    boxes ``boxes`` (n, 3) of ``length`` x ``width`` [m], paired row by row (0: they touch)."""
    return shapely.distance(shapely.polygons(box_corners(ego[:, 0], ego[:, 1], ego[:, 2], EGO_LENGTH, EGO_WIDTH)),
                            shapely.polygons(box_corners(boxes[:, 0], boxes[:, 1], boxes[:, 2], length, width)))


def _exact_min(ego: np.ndarray, boxes: np.ndarray, gap: np.ndarray, dims: np.ndarray) -> float:
    """Smallest exact distance [m] between ego boxes ``ego`` (n, 3: x, y, h) and participant boxes
    ``boxes`` (n, 3) paired row by row, whose separating-axis gaps ``gap`` are lower bounds:
    pairs are tried in order of their bound, in blocks, until no bound is below the best."""
    order = np.argsort(gap, kind="stable")
    best = math.inf
    for a in range(0, len(order), 256):
        blk = order[a:a + 256]
        if gap[blk[0]] >= best:
            break
        best = min(best, float(ego_distances(ego[blk], boxes[blk], dims[0], dims[1]).min()))
    return best


def reserved_path(ref: Trace, destination: np.ndarray, step: float = 0.5) -> Trace:
    """The reference run with the rest of its way: the ego's box moved on from its last pose to
    ``destination`` (x, y) [m] every ``step`` [m], at the last pose's heading, standing, ticked at
    the last tick. The reference ends once within the episode's ``reach_radius`` (3 m) of the
    destination, so without it the destination itself - where a mutated ego that lags still drives
    - would be free to stand on once the reference has ended."""
    last = ref.ego[-1]
    gap = float(math.hypot(destination[0] - last[0], destination[1] - last[1]))
    n = math.ceil(gap / step)
    if n == 0:
        return ref
    f = np.arange(1, n + 1) / n
    tail = np.repeat(last[None, :], n, axis=0)
    tail[:, 0] = last[0] + f * (destination[0] - last[0])
    tail[:, 1] = last[1] + f * (destination[1] - last[1])
    tail[:, 3:] = 0.0
    ticks = np.concatenate([ref.ticks, np.full(n, ref.ticks[-1], dtype=ref.ticks.dtype)])
    return replace(ref, ticks=ticks, ego=np.concatenate([ref.ego, tail]))


def clearances(ref: Trace, trace: Trace, window: tuple[float, float] = (EARLY_WINDOW, LATE_WINDOW),
               reach: float = _REACH) -> dict[int, float]:
    """Per added participant of ``trace`` (actor index): its smallest distance [m] to the
    reference ego's box while that stretch of the optimal path is reserved - from ``window[0]``
    seconds before the reference ego is there until ``window[1]`` seconds after it left, and
    all of the path once the reference run has ended (a mutated ego that lags meets what stands
    there then); a static participant at any time. Exact (shapely) up to ``reach`` metres,
    ``inf`` beyond. ``ref``: the reference run, or its :func:`reserved_path`."""
    out: dict[int, float] = {}
    added = [i for i, a in enumerate(trace.actors) if a.added]
    if not added or not len(trace.parts):
        return out
    from scipy.spatial import cKDTree

    rt = ref.ticks.astype(np.int64)
    last = int(rt[-1])
    early, late = round(window[0] / ref.world_dt), round(window[1] / ref.world_dt)
    tree = cKDTree(ref.xy)
    ego_r = 0.5 * math.hypot(EGO_LENGTH, EGO_WIDTH)
    parts = trace.parts
    for i in added:
        a = trace.actors[i]
        rows = parts[parts[:, 1] == i]
        if not len(rows):
            continue
        if a.kind == "static":
            rows = rows[:1]
        r = ego_r + 0.5 * math.hypot(a.length, a.width) + reach
        near = tree.query_ball_point(rows[:, 2:4], r)
        n = np.fromiter((len(x) for x in near), dtype=np.int64, count=len(near))
        if not n.sum():
            out[i] = math.inf
            continue
        ri = np.repeat(np.arange(len(rows)), n)
        ei = np.fromiter((j for x in near for j in x), dtype=np.int64, count=int(n.sum()))
        if a.kind != "static":  # moving: only while that stretch of the path is reserved
            t = rows[ri, 0].astype(np.int64)
            # the reference ego is there from `late` ticks before the participant to `early` after
            keep = ((rt[ei] >= t - late) & (rt[ei] <= t + early)) | (t > last)
            ri, ei = ri[keep], ei[keep]
        if not len(ri):
            out[i] = math.inf
            continue
        e, b = ref.ego[ei, :3], rows[ri, 2:5]
        gap = box_gap(e[:, 0], e[:, 1], e[:, 2], EGO_LENGTH, EGO_WIDTH, b[:, 0], b[:, 1], b[:, 2], a.length, a.width)
        close = gap < reach
        out[i] = _exact_min(e[close], b[close], gap[close], (a.length, a.width)) if close.any() else math.inf
        if out[i] >= reach:
            out[i] = math.inf
    return out


def seed_overlaps(ref: Trace, trace: Trace) -> list[int]:
    """Seed participants of ``trace`` (which may react to what was added) that overlap the
    reference ego at the same instant (actor indices)."""
    parts = trace.parts
    seed = np.array([not a.added for a in trace.actors], dtype=bool)
    if not len(parts) or not seed.any():
        return []
    rows = parts[seed[parts[:, 1].astype(np.int64)]]
    k = np.searchsorted(ref.ticks, rows[:, 0].astype(np.int64))
    k = np.clip(k, 0, len(ref.ticks) - 1)
    ok = ref.ticks[k] == rows[:, 0]
    rows, k = rows[ok], k[ok]
    if not len(rows):
        return []
    e = ref.ego[k]
    idx = rows[:, 1].astype(np.int64)
    dims = np.array([(a.length, a.width) for a in trace.actors])
    gap = box_gap(e[:, 0], e[:, 1], e[:, 2], EGO_LENGTH, EGO_WIDTH, rows[:, 2], rows[:, 3], rows[:, 4],
                  dims[idx, 0], dims[idx, 1])
    bad: list[int] = []
    for j in np.flatnonzero(gap <= 0.0):  # the SAT bound says "maybe": confirm exactly
        i = int(idx[j])
        if i in bad:
            continue
        pa = box_polygon(e[j, 0], e[j, 1], e[j, 2], EGO_LENGTH, EGO_WIDTH)
        if pa.intersects(box_polygon(rows[j, 2], rows[j, 3], rows[j, 4], dims[i, 0], dims[i, 1])):
            bad.append(i)
    return bad


def spawned_near(trace: Trace, distance: float = SPAWN_DISTANCE) -> list[int]:
    """Added participants of ``trace`` that appeared during the run closer than ``distance`` [m]
    (centre to centre) to the live ego (actor indices). Whatever the method meant, a vehicle that
    appears beside the ego is no scenario a real road makes. Those present from the start are
    judged by their clearance alone. A participant's first row is one world step after it
    appeared: the distance is taken at that step and allowed the step's motion of both (their
    speeds x the step), so a placement made exactly ``distance`` away is not refused."""
    parts = trace.parts
    bad = []
    for i, a in enumerate(trace.actors):
        if not a.added:
            continue
        rows = parts[parts[:, 1] == i]
        if not len(rows) or rows[0, 0] <= trace.ticks[0]:
            continue
        k = int(np.clip(np.searchsorted(trace.ticks, int(rows[0, 0])), 0, len(trace.ticks) - 1))
        v = math.hypot(rows[1, 2] - rows[0, 2], rows[1, 3] - rows[0, 3]) / trace.world_dt if len(rows) > 1 else 0.0
        slack = (abs(float(trace.ego[k, 3])) + v) * trace.world_dt
        if math.hypot(rows[0, 2] - trace.ego[k, 0], rows[0, 3] - trace.ego[k, 1]) < distance - slack:
            bad.append(i)
    return bad


def lane_strips(ref: Trace, roadmap: RoadMap, depth: float, reach: float = 8.0) -> shapely.Geometry:
    """The lanes the optimal path drives in, each from ``reach`` [m] before the first point the
    reference is in it to ``reach`` after the last, shrunk by ``depth`` [m] each side: a static
    object touching it stands at least ``depth`` inside the ego's lane."""
    spans: dict[Any, tuple[float, float]] = {}
    run = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ref.xy, axis=0).T))])
    for k in np.unique(np.searchsorted(run, np.arange(0.0, run[-1] + 1.0, 1.0)).clip(0, len(run) - 1)):  # every 1 m
        loc = roadmap.locate(ref.xy[k], float(ref.ego[k, 2]))
        if loc is not None:
            lo, hi = spans.get(loc[0], (math.inf, -math.inf))
            spans[loc[0]] = (min(lo, float(loc[1])), max(hi, float(loc[1])))
    strips = []
    for lane, (lo, hi) in spans.items():
        g = roadmap.geom(lane)
        a, b = max(lo - reach, 0.0), min(hi + reach, g.length)
        if b - a > 1e-6 and g.width / 2 > depth:
            strips.append(lane_surface(g, np.linspace(a, b, max(2, int((b - a) / 2.0) + 2)), g.width / 2 - depth))
    return shapely.union_all(strips) if strips else shapely.Polygon()


def in_lanes(trace: Trace, lanes: shapely.Geometry | None) -> list[int]:
    """Added static participants of ``trace`` whose box touches ``lanes`` (:func:`lane_strips`;
    actor indices; none for None)."""
    if lanes is None or lanes.is_empty:
        return []
    out = []
    for i, a in enumerate(trace.actors):
        if not (a.added and a.kind == "static"):
            continue
        rows = trace.parts[trace.parts[:, 1] == i]
        if len(rows) and lanes.intersects(box_polygon(*rows[0, 2:5], a.length, a.width)):
            out.append(i)
    return out


def invasive_why(ref: Trace, trace: Trace, clear: dict[int, float], clearance: float = CLEARANCE,
                 spawn_distance: float = SPAWN_DISTANCE, static_clearance: float = STATIC_CLEARANCE,
                 ego_lanes: shapely.Geometry | None = None) -> dict[str, str]:
    """Participants of ``trace`` that make a mutation invasive, with why: an added one closer
    than ``clearance`` [m] (a static one: ``static_clearance``, never less than ``clearance``) to
    the optimal path while it is reserved (``clear``: :func:`clearances`; ``"path"``), a static
    one touching ``ego_lanes`` (:func:`lane_strips`; ``"lane"``), or one appearing within
    ``spawn_distance`` [m] of the live ego (``"spawn"``); a seed one overlapping the reference ego
    at the same instant (``"seed"``)."""
    static = max(static_clearance, clearance)
    bad = {trace.actors[i].id: "path" for i, c in clear.items()
           if c < (static if trace.actors[i].kind == "static" else clearance)}
    for i in in_lanes(trace, ego_lanes):
        bad.setdefault(trace.actors[i].id, "lane")
    for i in spawned_near(trace, spawn_distance):
        bad.setdefault(trace.actors[i].id, "spawn")
    for i in seed_overlaps(ref, trace):
        bad.setdefault(trace.actors[i].id, "seed")
    return bad


# -- who closed the gap -------------------------------------------------------------------------
APPEAR_WINDOW = 2.0  # [s] a participant that appeared this shortly before a collision appeared on the ego
FAULT_WINDOW = 2.0  # [s] how far back the fault analysis looks for the two side by side


def _intervals(x: float, y: float, h: float, length: float, width: float, h0: float) -> tuple[float, float, float, float]:
    """A box's extent in the frame of heading ``h0``: (lon centre, lon half extent, lat centre,
    lat half extent) [m]."""
    c, s = math.cos(h0), math.sin(h0)
    dh = h - h0
    lon, lat = x * c + y * s, -x * s + y * c
    hl, hw = length / 2, width / 2
    return (lon, hl * abs(math.cos(dh)) + hw * abs(math.sin(dh)),
            lat, hl * abs(math.sin(dh)) + hw * abs(math.cos(dh)))


def collision_fault(trace: Trace, collision: dict[str, Any],
                    road_heading: Callable[[float, float, float], float] | None = None) -> tuple[bool, str]:
    """``(ego_at_fault, how)`` of a collision, by which vehicle closed the gap, seen along the
    road (``road_heading(x, y, heading)`` [rad]: the heading of the lane at the ego; default:
    the ego's own heading):

    - a standing ego, or a participant that appeared less than ``APPEAR_WINDOW`` s before, is
      never at fault (``"standing"``, ``"appeared"``);
    - boxes that overlapped sideways (across the road) for all of the last
      ``FAULT_WINDOW`` s: one ran into the other from behind - the ego is at fault when the
      other is ahead of it (``"rear_end"``, else ``"rear_ended"``);
    - otherwise, from the last moment they were side by side: whoever moved sideways towards the
      other more closed the gap - a car that cuts in beside the ego is not the ego's fault
      (``"cut_in"``), the ego's own lateral move is (``"lateral"``); a participant crossing at
      more than 45 degrees is ``"crossing"``."""
    if not collision.get("ego_moving", True):
        return False, "standing"
    dt = trace.world_dt
    tick = round(float(collision["time"]) / dt)
    try:
        a = trace.actor_index(str(collision["participant"]))
    except StopIteration:
        return True, "unknown"
    actor = trace.actors[a]
    rows = trace.parts[(trace.parts[:, 1] == a) & (trace.parts[:, 0] <= tick)]
    if not len(rows):
        return True, "unknown"
    if (tick - rows[0, 0]) * dt < APPEAR_WINDOW - 1e-9 and rows[0, 0] > trace.ticks[0]:
        return False, "appeared"

    def ego_at(tk: float) -> np.ndarray:
        return trace.ego[int(np.clip(np.searchsorted(trace.ticks, tk), 0, len(trace.ticks) - 1)), :3]

    def other_at(tk: float) -> np.ndarray:
        j = int(np.clip(np.searchsorted(rows[:, 0], tk, side="right") - 1, 0, len(rows) - 1))
        return rows[j, 2:5]

    def sideways(tk: float) -> tuple[tuple[float, ...], tuple[float, ...], float, bool]:
        """(ego extent, other's extent, road heading, overlapping across the road) at tick ``tk``."""
        e, o = ego_at(tk), other_at(tk)
        h = float(e[2]) if road_heading is None else road_heading(float(e[0]), float(e[1]), float(e[2]))
        ego_x, other_x = _intervals(*e, EGO_LENGTH, EGO_WIDTH, h), _intervals(*o, actor.length, actor.width, h)
        return ego_x, other_x, h, abs(other_x[2] - ego_x[2]) < other_x[3] + ego_x[3]

    e1, o1 = ego_at(tick), other_at(tick)
    k0 = tick - round(FAULT_WINDOW / dt)
    apart = next((k for k in range(tick, max(k0, int(rows[0, 0])) - 1, -1) if not sideways(k)[3]), None)
    if apart is None:  # overlapping across the road all along: a rear-end, one way or the other
        ego0, other0, _, _ = sideways(k0)
        ahead = bool(other0[0] > ego0[0])
        return ahead, ("rear_end" if ahead else "rear_ended")
    ego0, other0, h0, _ = sideways(apart)
    ego1 = _intervals(*e1, EGO_LENGTH, EGO_WIDTH, h0)
    other1 = _intervals(*o1, actor.length, actor.width, h0)
    side = math.copysign(1.0, other0[2] - ego0[2])  # where the other is, seen from the ego
    ego_move = side * (ego1[2] - ego0[2])  # [m] the ego's lateral move towards the other
    other_move = -side * (other1[2] - other0[2])  # [m] the other's towards the ego
    at_fault = bool(ego_move >= other_move)
    crossing = abs(math.remainder(float(other_at(apart)[2]) - h0, 2 * math.pi)) > math.pi / 4
    return at_fault, ("crossing" if crossing else "lateral" if at_fault else "cut_in")


def ego_at_fault(trace: Trace, collision: dict[str, Any],
                 road_heading: Callable[[float, float, float], float] | None = None) -> bool:
    """Whether the ego closed the gap (:func:`collision_fault`)."""
    return collision_fault(trace, collision, road_heading)[0]


# -- findings: trigger x band x mechanism ------------------------------------------------------
BANDS = ((0.75, "in_lane"), (1.0, "near"), (math.inf, "far"))  # [m] clearance to the optimal path
IN_LANE = "in_lane"  # an object inside the ego's own lane (< 0.75 m from a lane-centred ego)
MOVING_SPEED = 0.3  # [m/s] a vehicle faster than this is moving (not parked)


def band(clearance: float | None) -> str:
    """The clearance band of a trigger [m]: ``in_lane`` (< 0.75: inside the ego's lane, the
    ego centred in a 3.5 m lane has 0.75 m each side), ``near`` (0.75-1.0) or ``far``; ``-``
    without one (a seed participant). A trigger inside the optimal path's lane is ``in_lane``
    whatever its clearance (:meth:`DecisionOracle._intrudes`)."""
    if clearance is None:
        return "-"
    return next((name for limit, name in BANDS if clearance < limit), BANDS[-1][1])


def trigger_type(actor: Actor) -> str:
    """``cone``, ``parked`` (a static vehicle) or ``vehicle`` (one that moves), prefixed
    ``seed:`` for a participant of the seed scenario."""
    kind = ("cone" if actor.obstacle_type == "CONE" else "parked") if actor.kind == "static" else "vehicle"
    return kind if actor.added else f"seed:{kind}"


def lane_name(lane: list[Any] | tuple[Any, ...]) -> str:
    """A lane id as the planner publishes it (``road-from-to-index``)."""
    return "-".join(map(str, lane))


@dataclass
class Finding:
    """Why a failure happened: the participant(s) that set it off, how close the closest of them
    came to the optimal path, and which rule of the ADS fired (see :meth:`DecisionOracle.explain`)."""

    trigger: str = "none"  # cone | parked | vehicle | seed:<...> | none
    clearance: float | None = None  # [m] the trigger's clearance to the optimal path (added ones)
    mechanism: str = "other"
    trigger_ids: list[str] = field(default_factory=list)
    in_lane: bool = False  # the trigger stood (at least 5 cm) inside the lane the optimal path was in

    @property
    def band(self) -> str:
        if self.trigger == "none" or self.trigger.startswith("seed:"):
            return "-"
        return IN_LANE if self.in_lane else band(self.clearance)

    def key(self, kind: str) -> str:
        """The root cause: ``kind:trigger:band:mechanism``."""
        return f"{kind}:{self.trigger}:{self.band}:{self.mechanism}"


# -- verdict ------------------------------------------------------------------------------------
@dataclass
class Verdict:
    """Everything the oracles say about one mutated episode."""

    outcome: str
    collision: bool
    nods: bool
    iou: float
    f_p: float
    f_b: float
    valid: bool
    invasive: list[str] = field(default_factory=list)
    signature: str = ""  # the root cause of a failure or task failure: kind:trigger:band:mechanism
    collision_detail: dict[str, Any] | None = None
    ego_at_fault: bool = False  # the ego closed the gap (collision_fault)
    off_length: float = 0.0  # [m] longest stretch farther than half a lane from the reference
    nods_local: bool = False  # completed with off_length >= the local length (separate column)
    invasive_why: dict[str, str] = field(default_factory=dict)  # id -> path | spawn | seed
    finding: Finding | None = None
    cut_short: bool = False  # a timeout of the scenario's own duration, before the time rule (no task failure)

    @property
    def failure(self) -> str | None:
        """'collision' | 'nods' | None, counting only valid (non-invasive) mutations and only
        collisions the ego caused (it closed the gap: :func:`collision_fault`)."""
        if not self.valid:
            return None
        if self.collision:
            return "collision" if self.ego_at_fault else None
        return "nods" if self.nods else None

    @property
    def task_failure(self) -> str | None:
        """'timeout' | 'stuck' of a valid mutation (the ego never finished: its own column), or
        None; a timeout the scenario's own duration ended before the time rule (``cut_short``) is
        none: it says only that the ego was slower than the scenario allowed, not that it failed."""
        return self.outcome if self.valid and self.outcome in ("timeout", "stuck") and not self.cut_short else None

    def as_dict(self) -> dict[str, Any]:
        f = self.finding
        return {"outcome": self.outcome, "collision": self.collision, "ego_at_fault": self.ego_at_fault,
                "nods": self.nods,
                "iou": round(self.iou, 4), "f_p": round(self.f_p, 4), "f_b": round(self.f_b, 4),
                "valid": self.valid, "invasive": self.invasive, "invasive_why": self.invasive_why,
                "failure": self.failure, "task_failure": self.task_failure, "cut_short": self.cut_short, "off_length": round(self.off_length, 2),
                "nods_local": self.nods_local, "signature": self.signature,
                "trigger": f.trigger if f else None, "band": f.band if f else None,
                "clearance": None if not f or f.clearance is None or not math.isfinite(f.clearance)
                else round(f.clearance, 3),
                "mechanism": f.mechanism if f else None, "trigger_ids": f.trigger_ids if f else [],
                "collision_detail": self.collision_detail}


class DecisionOracle:
    """The consistency check, feedback and validity check against one reference run."""

    def __init__(self, ref: Trace, roadmap: RoadMap, threshold: float = THRESHOLD, grid: float = GRID,
                 grid_kind: Literal["lane", "world"] = "lane", clearance: float = CLEARANCE,
                 local_length: float = LOCAL_LENGTH, window: tuple[float, float] = (EARLY_WINDOW, LATE_WINDOW),
                 spawn_distance: float = SPAWN_DISTANCE, static_clearance: float = STATIC_CLEARANCE,
                 ego_lanes: shapely.Geometry | None = None, reserved: Trace | None = None,
                 timeouts_count: bool = True) -> None:
        self.ref, self.roadmap = ref, roadmap
        # False: the episodes end at the scenario's own duration before the time rule's (see
        # ``context.seed_context``), so a timeout is no task failure
        self.timeouts_count = timeouts_count
        self.reserved = ref if reserved is None else reserved  # what validity reserves (:func:`reserved_path`)
        self.threshold, self.grid, self.grid_kind = threshold, grid, grid_kind
        self.clearance, self.static_clearance, self.local_length = clearance, static_clearance, local_length
        self.ego_lanes = ego_lanes  # static objects stay out of them (:func:`lane_strips`; None: no lane test)
        self.window, self.spawn_distance = window, spawn_distance
        self.lanes = LaneCells(roadmap, grid)
        self.ref_cells = self.cells(ref.xy)
        self._ref_distance = PolylineDistance(ref.xy)
        # behaviour per reference lane (lanes holding >= 5 % of the reference points)
        pi, li, _ = self.lanes.membership(ref.xy)
        feats = behaviour_features(ref.ego)
        self.bandwidth = median_bandwidth(feats)
        self.ref_lanes: dict[int, np.ndarray] = {}
        for j in np.unique(li):
            pts = pi[li == j]
            if len(pts) >= 0.05 * len(ref.xy):
                self.ref_lanes[int(j)] = feats[pts]
        # each reference lane's kernel with itself: the same in every judgement
        self._ref_kxx = {j: mean_kernel(_thin(f), _thin(f), self.bandwidth) for j, f in self.ref_lanes.items()}

    def cells(self, xy: np.ndarray) -> np.ndarray:
        return self.lanes.cells(xy) if self.grid_kind == "lane" else world_cells(xy, self.grid)

    def road_heading(self, x: float, y: float, heading: float) -> float:
        """The heading [rad] of the lane at ``(x, y)`` best matching ``heading`` (itself
        off the road)."""
        loc = self.roadmap.locate(np.array([x, y]), heading)
        return heading if loc is None else float(self.roadmap.geom(loc[0]).heading_point(loc[1]))

    def iou(self, xy: np.ndarray) -> float:
        return iou(self.ref_cells, self.cells(xy))

    def distances(self, xy: np.ndarray) -> np.ndarray:
        """Exact distance [m] of each point of a path to the reference path."""
        return self._ref_distance(xy)

    @staticmethod
    def f_p(dist: np.ndarray) -> float:
        """Eq. 7: mean over the path's points of the exact distance to the reference path [m]
        (``dist``: :meth:`distances` of the path)."""
        return float(dist.mean()) if len(dist) else 0.0

    def f_b(self, ego: np.ndarray) -> float:
        """Eq. 8: mean over reference lanes of the Gaussian-kernel MMD (the distance, in [0,
        sqrt 2]) between the reference behaviour on that lane and the mutated run's - on the scale
        of f_p's metres, so that neither term of D = f_p + f_b drowns the other."""
        if not self.ref_lanes:
            return 0.0
        pi, li, _ = self.lanes.membership(ego[:, :2])
        feats = behaviour_features(ego)
        vals = [math.sqrt(mmd_rbf(ref_feats, feats[pi[li == j]], self.bandwidth, self._ref_kxx[j]))
                for j, ref_feats in self.ref_lanes.items()]
        return float(np.mean(vals))

    def off_length(self, xy: np.ndarray, dist: np.ndarray) -> float:
        """Longest stretch [m] of the path ``xy`` farther than half a lane from the reference path
        (``dist``: :meth:`distances` of ``xy``)."""
        if len(xy) < 2:
            return 0.0
        far = dist > self.roadmap.spec.lane_width / 2
        step = np.hypot(*np.diff(xy, axis=0).T)
        best = run = 0.0
        for i in range(1, len(xy)):
            run = run + step[i - 1] if (far[i] and far[i - 1]) else 0.0
            best = max(best, run)
        return float(best)

    def judge(self, trace: Trace, collision: dict[str, Any] | None = None) -> Verdict:
        """Task check, consistency check, feedback, validity and the root cause of a failure."""
        outcome = trace.outcome
        xy = trace.xy
        dist = self.distances(xy)  # computed once: f_p, off_length, the finding
        io, fp, fb = self.iou(xy), self.f_p(dist), self.f_b(trace.ego)
        clear = clearances(self.reserved, trace, self.window)
        why = invasive_why(self.ref, trace, clear, self.clearance, self.spawn_distance, self.static_clearance,
                           self.ego_lanes)
        is_collision = outcome == "collision"
        nods = outcome == "completed" and io <= self.threshold
        off = self.off_length(xy, dist)
        fault, how = collision_fault(trace, collision, self.road_heading) if is_collision and collision else (False, "")
        v = Verdict(outcome, is_collision, nods, io, fp, fb, not why, list(why), collision_detail=collision,
                    ego_at_fault=fault, off_length=off, nods_local=outcome == "completed" and off >= self.local_length,
                    invasive_why=why, cut_short=outcome == "timeout" and not self.timeouts_count)
        kind = ("collision" if v.collision else "nods" if v.nods else "local" if v.nods_local
                else v.outcome if v.outcome in ("timeout", "stuck") and not v.cut_short else None)
        if kind is not None:
            v.finding = self.explain(trace, kind, dist, clear, collision, how)
            v.signature = v.finding.key(kind)
        return v

    # -- root causes ----------------------------------------------------------------------------
    def explain(self, trace: Trace, kind: str, dist: np.ndarray, clear: dict[int, float],
                collision: dict[str, Any] | None = None, how: str = "") -> Finding:
        """The root cause of a failure of ``kind`` (collision | nods | local | timeout | stuck):

        - a collision: the participant hit and ``collision:<how>`` (:func:`collision_fault`);
        - otherwise why the ego was not where the reference was when it first got half a lane off
          the optimal path (or, never off it, at its end): a lane borrow away from the optimal
          path's lane that the reference did not make, or that lane kept from the ego - called
          ``blocked`` by one object (``blocked``), by objects on both sides of the path
          (``parallel``), by a vehicle that was moving (``predicted_static``: prediction took it
          for a parked one), or ``tight`` (closer than the comfort gap) - or a lane change into
          it refused, by the gap to a vehicle (``gap:rear``, ``gap:front``, ``gap:alongside``), by
          a vehicle in that lane only by its predicted lane change (``intent``), near a junction
          (``junction``); for an ego that never left, its own lane blocked or tight. ``other``:
          none of these (a planner that publishes no decisions always gives ``other``).

        Of the causes found, the first that names an added participant wins (a seed's object the
        reference also went round is no finding); the trigger is the participant(s) the decision
        names (by perception id), the added ones first; its clearance is their smallest
        (``clear``: :func:`clearances`)."""
        if collision is not None and kind == "collision":
            try:
                i = trace.actor_index(str(collision.get("participant", "")))
            except StopIteration:
                return Finding(mechanism=f"collision:{how or 'unknown'}")
            return self._finding(trace, [i], f"collision:{how or 'unknown'}", clear, float(collision["time"]))
        timeline = trace.meta.get("timeline") or []
        off = np.flatnonzero(dist > self.roadmap.spec.lane_width / 2)
        t_event = float(trace.t[off[0]]) if len(off) else float(trace.t[-1])
        before = [e for e in timeline if e["t"] <= t_event + 1e-9]
        want = self._reference_lanes(t_event - 1.0, t_event + 3.0)
        candidates = [self._borrow_cause(before, t_event), self._kept_from(timeline, want, t_event),
                      self._refusal_cause(timeline, t_event), self._lane_cause(before[-1:])]
        found = [c for c in candidates if c is not None]
        added = {a.num for a in trace.actors if a.added}
        best = next((c for c in found if set(c[0]) & added), found[0] if found else None)
        if best is None:
            k = int(off[0]) if len(off) else len(trace.ticks) - 1
            near = _nearest_added(trace, int(trace.ticks[k]), trace.xy[k])
            return self._finding(trace, [near] if near is not None else [], "other", clear, t_event)
        nums, mechanism, t_cause = best
        idx = [i for i, a in enumerate(trace.actors) if a.num in nums]
        if mechanism == "blocked":
            mechanism = self._blocked_kind(trace, idx, t_cause)
        return self._finding(trace, idx, mechanism, clear, t_cause)

    def _reference_lanes(self, t0: float, t1: float) -> set[str]:
        """The lanes the reference ego drove in between ``t0`` and ``t1`` [s] (sampled every 0.5 s)."""
        ref = self.ref
        k0, k1 = np.searchsorted(ref.t, [max(t0, 0.0), t1])
        out = set()
        for k in range(min(int(k0), len(ref.t) - 1), max(min(int(k1), len(ref.t)), int(k0) + 1), 10):
            loc = self.roadmap.locate(ref.xy[k], float(ref.ego[k, 2]))
            if loc is not None:
                out.add(lane_name(loc[0]))
        return out

    def _borrow_cause(self, before: list[dict[str, Any]], t_event: float,
                      look_back: float = 10.0) -> tuple[list[int], str, float] | None:
        """The state of the lane the ego left when its last lane borrow within ``look_back`` s
        before the event began (``(perception ids, blocked | tight, time)``, looking back from the
        borrow's start to the latest entry that called that lane blocked or tight), unless the
        reference made the same borrow within 3 s of it."""
        start = None
        for j in range(len(before) - 1, -1, -1):
            if before[j]["t"] < t_event - look_back:
                break
            if before[j]["reason"] == "borrow" and (j == 0 or before[j - 1]["reason"] != "borrow"):
                start = j
                break
        if start is None:
            return None
        t_b, lane_b = before[start]["t"], before[start]["lane"]
        ref_tl = self.ref.meta.get("timeline") or []
        if any(e["reason"] == "borrow" and e["lane"] == lane_b and abs(e["t"] - t_b) <= 3.0 for e in ref_tl):
            return None
        lane = lane_name(lane_b)
        for e in reversed(before[:start + 1]):
            found = _lane_state(e, lane)
            if found is not None:
                return found
        return [], "other", t_b

    @staticmethod
    def _kept_from(timeline: list[dict[str, Any]], want: set[str], t_event: float,
                   window: float = 3.0) -> tuple[list[int], str, float] | None:
        """A lane the reference drove in (``want``), other than the ego's own, that the ego's
        planner called blocked or tight nearest in time to the event (within ``window`` s):
        what kept the ego from it."""
        near = [e for e in timeline if abs(e["t"] - t_event) <= window]
        for e in sorted(near, key=lambda e: (abs(e["t"] - t_event), e["t"])):
            for lane in sorted(want - {lane_name(e["lane"])}):
                found = _lane_state(e, lane)
                if found is not None:
                    return found
        return None

    @staticmethod
    def _lane_cause(entries: list[dict[str, Any]]) -> tuple[list[int], str, float] | None:
        """The ego's own lane blocked or tight in the last of ``entries`` (an ego that never left
        the optimal path but stopped or crawled)."""
        return _lane_state(entries[-1], lane_name(entries[-1]["lane"])) if entries else None

    def _refusal_cause(self, timeline: list[dict[str, Any]], t_event: float, look_back: float = 10.0,
                       look_ahead: float = 3.0) -> tuple[list[int], str, float] | None:
        """The refusal that held longest, within ``look_back`` s before the event and
        ``look_ahead`` s after it, of a lane change into a lane the reference ego drove in within
        5 s: ``(perception ids, gap:<why> | intent | junction, when it began)``. Refusals of
        other lanes (the planner weighs every neighbour every cycle) did not keep the ego off the
        optimal path."""
        held: dict[tuple[Any, ...], list[float]] = {}  # (ids, mechanism) -> [seconds, first time]
        for n, e in enumerate(timeline):
            if not (t_event - look_back <= e["t"] <= t_event + look_ahead) or not e["refused"]:
                continue
            want = self._reference_lanes(e["t"], e["t"] + 5.0) - {lane_name(e["lane"])}
            until = timeline[n + 1]["t"] if n + 1 < len(timeline) else e["t"] + 0.1
            for lane in sorted(want & set(e["refused"])):
                why = e["refused"][lane]
                cause = e["causes"].get(lane, {}).get("refused")
                if why == "junction" or not cause:
                    key: tuple[Any, ...] = ((), "junction" if why == "junction" else f"gap:{why.replace('_gap', '')}")
                else:
                    key = ((cause[0],), "intent" if cause[1] == "predicted" else f"gap:{why.replace('_gap', '')}")
                h = held.setdefault(key, [0.0, e["t"]])
                h[0] += until - e["t"]
        if not held:
            return None
        (ids, mechanism), (_, t0) = max(held.items(), key=lambda kv: (kv[1][0], -kv[1][1]))
        return list(ids), mechanism, t0

    def _blocked_kind(self, trace: Trace, idx: list[int], t: float) -> str:
        """``predicted_static`` when a blocking participant was moving at ``t`` [s], ``parallel``
        when the blocking objects stand on both sides of the optimal path, else ``blocked``."""
        tick = round(t / trace.world_dt)
        sides = set()
        for i in idx:
            rows = trace.parts[trace.parts[:, 1] == i]
            if not len(rows):
                continue
            j = int(np.clip(np.searchsorted(rows[:, 0], tick), 0, len(rows) - 1))
            lo, hi = max(j - 5, 0), min(j + 5, len(rows) - 1)
            span = (rows[hi, 0] - rows[lo, 0]) * trace.world_dt
            if trace.actors[i].kind != "static" and span > 0 and \
                    math.hypot(rows[hi, 2] - rows[lo, 2], rows[hi, 3] - rows[lo, 3]) / span > MOVING_SPEED:
                return "predicted_static"
            sides.add(_side(self.ref.xy, rows[j, 2:4]))
        return "parallel" if len(sides) > 1 else "blocked"

    def _finding(self, trace: Trace, idx: list[int], mechanism: str, clear: dict[int, float], t: float) -> Finding:
        """The finding of a mechanism whose decision named the participants ``idx`` at ``t`` [s]:
        the added ones first, the one closest to the optimal path the trigger."""
        if not idx:
            return Finding(mechanism=mechanism)
        added = [i for i in idx if trace.actors[i].added]
        pick = added or idx
        main = min(pick, key=lambda i: (clear.get(i, math.inf), i)) if added else pick[0]
        c = clear.get(main) if added else None
        return Finding(trigger_type(trace.actors[main]), c, mechanism, [trace.actors[i].id for i in pick],
                       bool(added) and self._intrudes(trace, main, t))

    def _intrudes(self, trace: Trace, i: int, t: float, depth: float = 0.05) -> bool:
        """Whether participant ``i`` stood at least ``depth`` [m] inside the lane the optimal path
        was in next to it, at ``t`` [s] (a static one: where it stands) - "inside the ego's own
        lane" also where the reference drove off its lane's centre."""
        rows = trace.parts[trace.parts[:, 1] == i]
        if not len(rows):
            return False
        j = int(np.clip(np.searchsorted(rows[:, 0], round(t / trace.world_dt)), 0, len(rows) - 1))
        x, y, h = rows[j, 2:5]
        ref = self.ref
        k = int(np.argmin(np.hypot(ref.xy[:, 0] - x, ref.xy[:, 1] - y)))
        loc = self.roadmap.locate(ref.xy[k], float(ref.ego[k, 2]))
        if loc is None:
            return False
        g, s0 = self.roadmap.geom(loc[0]), float(loc[1])
        ss = np.linspace(max(s0 - 8.0, 0.0), min(s0 + 8.0, g.length), 9)
        if ss[-1] - ss[0] < 1e-6:
            return False
        a = trace.actors[i]
        return bool(lane_surface(g, ss, g.width / 2 - depth).intersects(box_polygon(x, y, h, a.length, a.width)))

    def decision_change(self, trace: Trace) -> list[str]:
        """Planning decisions the run made that the reference run never did (sorted)."""
        ref = self.ref.meta.get("decisions", {})
        return sorted(k for k in trace.meta.get("decisions", {}) if k not in ref)


def _lane_state(entry: dict[str, Any], lane: str) -> tuple[list[int], str, float] | None:
    """``(perception ids, blocked | tight, time)`` when the decision ``entry`` called ``lane``
    blocked (first) or tight, else None."""
    for rule in ("blocked", "tight"):
        if lane in entry[rule]:
            return list(entry["causes"].get(lane, {}).get(rule, [])), rule, entry["t"]
    return None


def _side(ref_xy: np.ndarray, p: np.ndarray) -> str:
    i = int(np.argmin(np.hypot(*(ref_xy - p).T)))
    j = min(i + 1, len(ref_xy) - 1)
    i = j - 1 if j > 0 else i
    t = ref_xy[j] - ref_xy[i]
    cross = t[0] * (p[1] - ref_xy[i, 1]) - t[1] * (p[0] - ref_xy[i, 0])
    return "right" if cross > 0 else "left"  # y points down: positive cross is to the right


def _nearest_added(trace: Trace, tick: int, p: np.ndarray) -> int | None:
    """The added participant nearest to ``p`` at ``tick`` (actor index), if any is present."""
    rows = trace.parts[trace.parts[:, 0] == tick]
    best, out = math.inf, None
    for r in rows:
        a = trace.actors[int(r[1])]
        d = math.hypot(r[2] - p[0], r[3] - p[1])
        if a.added and d < best:
            best, out = d, int(r[1])
    return out
