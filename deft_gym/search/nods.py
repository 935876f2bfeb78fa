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
  mutated run; a participant closer than ``clearance`` (0.5 m, the paper's safe distance and
  the planner's own hard buffer) to the reference ego box at the same instant (a static one at
  any instant) makes the mutation invasive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import shapely

from deft_gym.search.trace import Trace
from deft_gym.world.geometry import box_gap, box_polygon
from deft_gym.world.roadmap import RoadMap
from deft_gym.world.world import EgoVehicle

GRID = 2.0  # [m] cell size
THRESHOLD = 0.6  # IoU <= threshold: non-optimal
CLEARANCE = 0.5  # [m] validity: the reference path keeps this far from every added object
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


def mmd_rbf(x: np.ndarray, y: np.ndarray, bandwidth: float) -> float:
    """Biased MMD^2 of two samples with the Gaussian kernel ``exp(-|a-b|^2 / (2 bw^2))``, in
    [0, 2]: 0 for equal distributions; an empty sample is as far as it gets (1)."""
    if not len(x) or not len(y):
        return 1.0
    x, y = _thin(x), _thin(y)
    g = -0.5 / (bandwidth * bandwidth)

    def k(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.exp(g * ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)).mean())

    return max(k(x, x) + k(y, y) - 2.0 * k(x, y), 0.0)


# -- validity -----------------------------------------------------------------------------------
EGO_LENGTH, EGO_WIDTH = EgoVehicle.LENGTH, EgoVehicle.WIDTH


def invasive_actors(ref: Trace, trace: Trace, until_tick: int | None = None,
                    clearance: float = CLEARANCE) -> list[str]:
    """Participants of ``trace`` that invade the optimal path: added ones closer than
    ``clearance`` [m] to the reference ego replayed at the same ticks, seed ones (which may react
    to what was added) overlapping it. Static participants are extended to the end of the
    reference run."""
    parts = trace.parts
    if not len(parts):
        return []
    last_ref = int(ref.ticks[-1])
    ticks = parts[:, 0].astype(np.int64)
    rows = parts[ticks <= last_ref]
    # statics are there for good: check them against the whole reference path
    static = [i for i, a in enumerate(trace.actors) if a.kind == "static"]
    extra = []
    if static:
        first = {i: rows[rows[:, 1] == i][:1] for i in static}
        for i, r in first.items():
            if len(r):
                n = len(ref.ticks)
                extra.append(np.column_stack([ref.ticks, np.full(n, i), np.repeat(r[:, 2:], n, axis=0)]))
        rows = np.concatenate([rows[~np.isin(rows[:, 1], static)], *extra]) if extra else rows
    if until_tick is not None:
        rows = rows[rows[:, 0] <= until_tick]
    if not len(rows):
        return []
    tick_index = np.searchsorted(ref.ticks, rows[:, 0].astype(np.int64))
    tick_index = np.clip(tick_index, 0, len(ref.ticks) - 1)
    ok = ref.ticks[tick_index] == rows[:, 0]
    rows, tick_index = rows[ok], tick_index[ok]
    e = ref.ego[tick_index]
    idx = rows[:, 1].astype(np.int64)
    dims = np.array([(a.length, a.width) for a in trace.actors])
    need = np.array([clearance if a.added else 0.0 for a in trace.actors])[idx]
    gap = box_gap(e[:, 0], e[:, 1], e[:, 2], EGO_LENGTH, EGO_WIDTH, rows[:, 2], rows[:, 3], rows[:, 4],
                  dims[idx, 0], dims[idx, 1])
    # the SAT gap is a lower bound of the distance: confirm candidates exactly with shapely
    hit = np.flatnonzero((gap < need) | ((need == 0.0) & (gap <= 0.0)))
    bad: list[str] = []
    for k in hit:
        i = int(idx[k])
        aid = trace.actors[i].id
        if aid in bad:
            continue
        pa = box_polygon(e[k, 0], e[k, 1], e[k, 2], EGO_LENGTH, EGO_WIDTH)
        pb = box_polygon(rows[k, 2], rows[k, 3], rows[k, 4], dims[i, 0], dims[i, 1])
        if (pa.distance(pb) < clearance) if trace.actors[i].added else pa.intersects(pb):
            bad.append(aid)
    return bad


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
    signature: str = ""
    collision_detail: dict[str, Any] | None = None
    ego_at_fault: bool = False  # the ego was moving and the other party was not behind it
    off_length: float = 0.0  # [m] longest stretch farther than half a lane from the reference
    nods_local: bool = False  # completed with off_length >= the local length (separate column)

    @property
    def failure(self) -> str | None:
        """'collision' | 'nods' | None, counting only valid (non-invasive) mutations and only
        collisions the ego drove into (not a participant running into a standing ego or into its
        back)."""
        if not self.valid:
            return None
        if self.collision:
            return "collision" if self.ego_at_fault else None
        return "nods" if self.nods else None

    @property
    def task_failure(self) -> str | None:
        """'timeout' | 'stuck' of a valid mutation (the ego never finished: its own column), or
        None."""
        return self.outcome if self.valid and self.outcome in ("timeout", "stuck") else None

    def as_dict(self) -> dict[str, Any]:
        return {"outcome": self.outcome, "collision": self.collision, "ego_at_fault": self.ego_at_fault,
                "nods": self.nods,
                "iou": round(self.iou, 4), "f_p": round(self.f_p, 4), "f_b": round(self.f_b, 4),
                "valid": self.valid, "invasive": self.invasive, "failure": self.failure,
                "task_failure": self.task_failure, "off_length": round(self.off_length, 2),
                "nods_local": self.nods_local,
                "signature": self.signature, "collision_detail": self.collision_detail}


class DecisionOracle:
    """The consistency check, feedback and validity check against one reference run."""

    def __init__(self, ref: Trace, roadmap: RoadMap, threshold: float = THRESHOLD, grid: float = GRID,
                 grid_kind: Literal["lane", "world"] = "lane", clearance: float = CLEARANCE,
                 local_length: float = LOCAL_LENGTH) -> None:
        self.ref, self.roadmap = ref, roadmap
        self.threshold, self.grid, self.grid_kind = threshold, grid, grid_kind
        self.clearance, self.local_length = clearance, local_length
        self.lanes = LaneCells(roadmap, grid)
        self.ref_cells = self.cells(ref.xy)
        self.ref_line = shapely.LineString(ref.xy)
        shapely.prepare(self.ref_line)
        # behaviour per reference lane (lanes holding >= 5 % of the reference points)
        pi, li, _ = self.lanes.membership(ref.xy)
        feats = behaviour_features(ref.ego)
        self.bandwidth = median_bandwidth(feats)
        self.ref_lanes: dict[int, np.ndarray] = {}
        for j in np.unique(li):
            pts = pi[li == j]
            if len(pts) >= 0.05 * len(ref.xy):
                self.ref_lanes[int(j)] = feats[pts]

    def cells(self, xy: np.ndarray) -> np.ndarray:
        return self.lanes.cells(xy) if self.grid_kind == "lane" else world_cells(xy, self.grid)

    def iou(self, xy: np.ndarray) -> float:
        return iou(self.ref_cells, self.cells(xy))

    def distances(self, xy: np.ndarray) -> np.ndarray:
        """Exact distance [m] of each point of a path to the reference path."""
        return shapely.distance(shapely.points(np.asarray(xy).reshape(-1, 2)), self.ref_line)

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
        vals = [math.sqrt(mmd_rbf(ref_feats, feats[pi[li == j]], self.bandwidth))
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
        """Task check, consistency check, feedback, validity and a failure signature."""
        outcome = trace.outcome
        xy = trace.xy
        dist = self.distances(xy)  # computed once: f_p, off_length, signature
        io, fp, fb = self.iou(xy), self.f_p(dist), self.f_b(trace.ego)
        bad = invasive_actors(self.ref, trace, clearance=self.clearance)
        is_collision = outcome == "collision"
        nods = outcome == "completed" and io <= self.threshold
        off = self.off_length(xy, dist)
        v = Verdict(outcome, is_collision, nods, io, fp, fb, not bad, bad, collision_detail=collision,
                    ego_at_fault=bool(is_collision and collision and ego_at_fault(trace, collision)),
                    off_length=off, nods_local=outcome == "completed" and off >= self.local_length)
        v.signature = self.signature(v, trace, collision, dist)
        return v

    def signature(self, v: Verdict, trace: Trace, collision: dict[str, Any] | None, dist: np.ndarray) -> str:
        """Root-cause signature of a failure, for counting distinct failures: its kind, where
        along the optimal path it happened (10 m buckets), the participant involved (seed or
        added, kind, type) and the decision change (the planning decisions of the run that the
        reference run never made, e.g. ``blocked+reason:borrow`` or ``refused:rear_gap``);
        ``dist``: :meth:`distances` of the run's path."""
        change = "+".join(self.decision_change(trace)) or "-"
        if v.collision and collision:
            who = _actor_key(trace, collision.get("participant", ""))
            where = self._bucket(np.array([collision["x"], collision["y"]]))
            return f"collision@{where}:{who}:{change}"
        if v.nods or v.nods_local or v.task_failure:
            xy = trace.xy
            off = np.flatnonzero(dist > self.roadmap.spec.lane_width / 2)
            k = int(off[0]) if len(off) else int(np.argmax(dist))
            side = _side(self.ref.xy, xy[k])
            who = _nearest_added(trace, int(trace.ticks[k]), xy[k])
            kind = "nods" if v.nods else ("local" if v.nods_local else v.task_failure)
            return f"{kind}@{self._bucket(xy[k])}:{side}:{who}:{change}"
        return ""

    def decision_change(self, trace: Trace) -> list[str]:
        """Planning decisions the run made that the reference run never did (sorted)."""
        ref = self.ref.meta.get("decisions", {})
        return sorted(k for k in trace.meta.get("decisions", {}) if k not in ref)

    def _bucket(self, p: np.ndarray) -> str:
        """Where along the optimal path a point is: a 10 m bucket of its arc length."""
        sigma = float(self.ref_line.project(shapely.Point(float(p[0]), float(p[1]))))
        return f"{int(sigma // 10.0) * 10}m"


def ego_at_fault(trace: Trace, collision: dict[str, Any]) -> bool:
    """The ego was moving and the participant's centre was not behind the ego's rear end - the
    ego drove into it (or cut across it), rather than being run into from behind or standing."""
    if not collision.get("ego_moving", True):
        return False
    tick = round(float(collision["time"]) / trace.world_dt)
    i = int(np.clip(np.searchsorted(trace.ticks, tick), 0, len(trace.ticks) - 1))
    ex, ey, eh = trace.ego[i, :3]
    try:
        a = trace.actor_index(str(collision["participant"]))
    except StopIteration:
        return True
    rows = trace.parts[(trace.parts[:, 1] == a) & (trace.parts[:, 0] <= tick)]
    if not len(rows):
        return True
    px, py = rows[-1, 2], rows[-1, 3]
    lon = (px - ex) * math.cos(eh) + (py - ey) * math.sin(eh)
    return bool(lon > -EGO_LENGTH / 2)


def _cell5(x: float, y: float) -> str:
    return f"{math.floor(x / 5.0)},{math.floor(y / 5.0)}"


def _actor_key(trace: Trace, pid: str) -> str:
    for a in trace.actors:
        if a.id == pid:
            return f"{'added' if a.added else 'seed:' + a.id}:{a.kind}:{a.obstacle_type}"
    return pid


def _side(ref_xy: np.ndarray, p: np.ndarray) -> str:
    i = int(np.argmin(np.hypot(*(ref_xy - p).T)))
    j = min(i + 1, len(ref_xy) - 1)
    i = j - 1 if j > 0 else i
    t = ref_xy[j] - ref_xy[i]
    cross = t[0] * (p[1] - ref_xy[i, 1]) - t[1] * (p[0] - ref_xy[i, 0])
    return "right" if cross > 0 else "left"  # y points down: positive cross is to the right


def _nearest_added(trace: Trace, tick: int, p: np.ndarray) -> str:
    rows = trace.parts[trace.parts[:, 0] == tick]
    best, key = math.inf, "none"
    for r in rows:
        a = trace.actors[int(r[1])]
        dist = math.hypot(r[2] - p[0], r[3] - p[1])
        if dist < best:
            best, key = dist, f"{'added' if a.added else 'seed:' + a.id}:{a.kind}:{a.obstacle_type}"
    return key
