"""Vectorised lane geometry: Frenet <-> Cartesian for many points at once.

highway-env's lanes convert one point at a time; the planner and prediction convert hundreds of
points per cycle, so :class:`LaneGeom` re-implements ``position``/``local_coordinates``/
``heading_at`` for arrays, for the two lane shapes DeFT-Gym's maps use (``StraightLane`` and
``CircularLane``) and, for any other ``AbstractLane``, through a dense polyline.

Conventions follow highway-env: ``s`` [m] is the longitudinal coordinate from the lane start,
``d`` [m] is lateral and positive to the *right* of the driving direction (highway-env's y axis
points down the screen), headings [rad] are measured from +x towards +y.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import shapely
from highway_env.road.lane import AbstractLane, CircularLane, StraightLane

TWO_PI = 2.0 * np.pi


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to [-pi, pi) [rad]."""
    return (np.asarray(a) + np.pi) % TWO_PI - np.pi


class LaneGeom:
    """Array versions of one lane's coordinate transforms."""

    def __init__(self, lane: AbstractLane) -> None:
        self.lane = lane
        self.length = float(lane.length)
        self.width = float(lane.width_at(0.0))
        if isinstance(lane, StraightLane) and type(lane) is StraightLane:
            self.kind = "straight"
            self.start = np.asarray(lane.start, dtype=float)
            self.dir = np.asarray(lane.direction, dtype=float)
            self.lat = np.asarray(lane.direction_lateral, dtype=float)
            self.heading0 = float(lane.heading)
            # the same values as plain floats, for the scalar transforms
            self._s0 = (float(self.start[0]), float(self.start[1]))
            self._dir = (float(self.dir[0]), float(self.dir[1]))
            self._lat = (float(self.lat[0]), float(self.lat[1]))
        elif isinstance(lane, CircularLane):
            self.kind = "circular"
            self.center = np.asarray(lane.center, dtype=float)
            self.radius = float(lane.radius)
            self.phase0 = float(lane.start_phase)
            self.sense = float(lane.direction)
            self._c0 = (float(self.center[0]), float(self.center[1]))
        else:
            self.kind = "polyline"
            s = np.linspace(0.0, self.length, max(2, int(self.length / 0.25) + 1))
            self.poly_s = s
            pts = np.array([lane.position(v, 0.0) for v in s])
            self.poly_xy = pts
            self.poly_h = np.unwrap([lane.heading_at(v) for v in s])

    def xy(self, s: np.ndarray, d: np.ndarray | float = 0.0) -> np.ndarray:
        """World positions [m] of lane coordinates, shape ``s.shape + (2,)``."""
        s = np.asarray(s, dtype=float)
        d = np.asarray(d, dtype=float)
        if self.kind == "straight":
            return self.start + s[..., None] * self.dir + d[..., None] * self.lat
        if self.kind == "circular":
            phi = self.sense * s / self.radius + self.phase0
            r = self.radius - d * self.sense
            return self.center + np.stack([r * np.cos(phi), r * np.sin(phi)], axis=-1)
        x = np.interp(s, self.poly_s, self.poly_xy[:, 0])
        y = np.interp(s, self.poly_s, self.poly_xy[:, 1])
        h = np.interp(s, self.poly_s, self.poly_h)
        return np.stack([x - d * np.sin(h), y + d * np.cos(h)], axis=-1)

    def xy_list(self, s: list[float], d: float) -> tuple[list[float], list[float]]:
        """:meth:`xy` of a few stations ``s`` at one lateral offset ``d``, as lists ``(x, y)``:
        scalar math on a straight lane (the same operations, in the same order), numpy otherwise."""
        if self.kind == "straight":
            (sx, sy), (ux, uy), (lx, ly) = self._s0, self._dir, self._lat
            dx, dy = d * lx, d * ly
            return [sx + v * ux + dx for v in s], [sy + v * uy + dy for v in s]
        pts = self.xy(np.array(s, dtype=float), d)
        return pts[:, 0].tolist(), pts[:, 1].tolist()

    def heading(self, s: np.ndarray) -> np.ndarray:
        """Lane heading [rad] at ``s``."""
        s = np.asarray(s, dtype=float)
        if self.kind == "straight":
            return np.full(s.shape, self.heading0)
        if self.kind == "circular":
            return self.sense * s / self.radius + self.phase0 + self.sense * np.pi / 2
        return np.interp(s, self.poly_s, self.poly_h)

    def curvature(self, s: np.ndarray) -> np.ndarray:
        """Signed curvature [1/m] (positive turning right, i.e. increasing heading)."""
        s = np.asarray(s, dtype=float)
        if self.kind == "straight":
            return np.zeros(s.shape)
        if self.kind == "circular":
            return np.full(s.shape, self.sense / self.radius)
        return np.gradient(np.interp(s, self.poly_s, self.poly_h), s) if s.size > 1 else np.zeros(s.shape)

    def heading_point(self, s: float) -> float:
        """Scalar :meth:`heading` [rad]."""
        if self.kind == "straight":
            return self.heading0
        if self.kind == "circular":
            return self.sense * s / self.radius + self.phase0 + self.sense * math.pi / 2
        return float(np.interp(s, self.poly_s, self.poly_h))

    def frenet_point(self, x: float, y: float) -> tuple[float, float]:
        """Scalar :meth:`frenet` for one point (no array overhead)."""
        if self.kind == "straight":
            sx, sy = self._s0
            dx, dy = float(x) - sx, float(y) - sy
            (ux, uy), (lx, ly) = self._dir, self._lat
            return dx * ux + dy * uy, dx * lx + dy * ly
        if self.kind == "circular":
            cx, cy = self._c0
            dx, dy = float(x) - cx, float(y) - cy
            phi = math.atan2(dy, dx)
            phi = self.phase0 + ((phi - self.phase0 + math.pi) % TWO_PI - math.pi)
            r = math.hypot(dx, dy)
            return (float(self.sense * (phi - self.phase0) * self.radius), float(self.sense * (self.radius - r)))
        s, d = self.frenet(np.array([x, y]))
        return float(s), float(d)

    def frenet_list(self, xy: list[list[float]]) -> tuple[list[float], list[float]]:
        """:meth:`frenet` of a few points ``[[x, y], ...]``, as lists: scalar math on a straight
        lane (the same operations, without numpy's per-call overhead), numpy otherwise."""
        if self.kind == "straight":
            (sx, sy), (ux, uy), (lx, ly) = self._s0, self._dir, self._lat
            delta = [(x - sx, y - sy) for x, y in xy]
            return [dx * ux + dy * uy for dx, dy in delta], [dx * lx + dy * ly for dx, dy in delta]
        if not xy:
            return [], []
        s, d = self.frenet(np.array(xy, dtype=float))
        return s.tolist(), d.tolist()

    def frenet(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lane coordinates ``(s, d)`` [m] of world positions ``xy`` (shape ``(..., 2)``)."""
        xy = np.asarray(xy, dtype=float)
        if self.kind == "straight":
            # written out, not ``delta @ self.dir``: a matrix product goes to BLAS, whose kernel
            # (chosen per CPU) may fuse multiply-adds, so its last bit would depend on the machine
            dx, dy = xy[..., 0] - self._s0[0], xy[..., 1] - self._s0[1]
            (ux, uy), (lx, ly) = self._dir, self._lat
            return dx * ux + dy * uy, dx * lx + dy * ly
        if self.kind == "circular":
            delta = xy - self.center
            phi = np.arctan2(delta[..., 1], delta[..., 0])
            phi = self.phase0 + wrap_angle(phi - self.phase0)
            r = np.hypot(delta[..., 0], delta[..., 1])
            return self.sense * (phi - self.phase0) * self.radius, self.sense * (self.radius - r)
        # polyline: nearest vertex, then project on the local tangent
        flat = xy.reshape(-1, 2)
        d2 = ((flat[:, None, :] - self.poly_xy[None, :, :]) ** 2).sum(-1)
        i = d2.argmin(axis=1)
        h = self.poly_h[i]
        delta = flat - self.poly_xy[i]
        ds = delta[:, 0] * np.cos(h) + delta[:, 1] * np.sin(h)
        dd = -delta[:, 0] * np.sin(h) + delta[:, 1] * np.cos(h)
        shape = xy.shape[:-1]
        return (self.poly_s[i] + ds).reshape(shape), dd.reshape(shape)


class ReferenceLine:
    """A chain of lanes driven one after the other, addressed by one arc length ``s``.

    ``s = 0`` is the start of the first lane. Points before the first or after the last lane are
    handled by extending the end lanes' own geometry (a straight lane continues straight).
    """

    def __init__(self, lane_ids: list[tuple[str, str, int]], geoms: list[LaneGeom]) -> None:
        if not geoms:
            raise ValueError("a reference line needs at least one lane")
        self.lane_ids = list(lane_ids)
        self.geoms = geoms
        lengths = np.array([g.length for g in geoms])
        self.offsets = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
        self._offsets: list[float] = self.offsets.tolist()
        self.length = float(lengths.sum())
        self.widths = np.array([g.width for g in geoms])

    def _piece(self, s: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.offsets, s, side="right") - 1, 0, len(self.geoms) - 1)

    def xy(self, s: np.ndarray, d: np.ndarray | float = 0.0) -> np.ndarray:
        """World positions of reference-line coordinates."""
        if len(self.geoms) == 1:
            return self.geoms[0].xy(s, d)
        s = np.asarray(s, dtype=float)
        d = np.broadcast_to(np.asarray(d, dtype=float), s.shape)
        out = np.empty((*s.shape, 2))
        piece = self._piece(s)
        for k, g in enumerate(self.geoms):
            m = piece == k
            if m.any():
                out[m] = g.xy(s[m] - self.offsets[k], d[m])
        return out

    def heading(self, s: np.ndarray) -> np.ndarray:
        s = np.asarray(s, dtype=float)
        if len(self.geoms) == 1:
            return self.geoms[0].heading(s)
        out = np.empty(s.shape)
        piece = self._piece(s)
        for k, g in enumerate(self.geoms):
            m = piece == k
            if m.any():
                out[m] = g.heading(s[m] - self.offsets[k])
        return out

    def curvature(self, s: np.ndarray) -> np.ndarray:
        s = np.asarray(s, dtype=float)
        out = np.empty(s.shape)
        piece = self._piece(s)
        for k, g in enumerate(self.geoms):
            m = piece == k
            if m.any():
                out[m] = g.curvature(s[m] - self.offsets[k])
        return out

    def width(self, s: np.ndarray) -> np.ndarray:
        return self.widths[self._piece(np.asarray(s, dtype=float))]

    def frenet_point(self, x: float, y: float) -> tuple[float, float]:
        """Scalar :meth:`frenet` for one point."""
        best = (math.inf, 0.0, 0.0)
        last = len(self.geoms) - 1
        for k, g in enumerate(self.geoms):
            s, d = g.frenet_point(x, y)
            over = (max(0.0, -s) if k > 0 else 0.0) + (max(0.0, s - g.length) if k < last else 0.0)
            score = abs(d) + 2.0 * over
            if score < best[0]:
                best = (score, s + float(self.offsets[k]), d)
        return best[1], best[2]

    def frenet_list(self, xy: list[list[float]]) -> tuple[list[float], list[float]]:
        """:meth:`frenet` of a few points ``[[x, y], ...]``, as lists: per lane
        :meth:`LaneGeom.frenet_list`, then the same choice in scalar math (NaN handled as numpy
        does: a NaN score never wins, ``np.maximum`` passes a NaN on)."""
        if len(self.geoms) == 1:
            return self.geoms[0].frenet_list(xy)
        n = len(xy)
        best_s, best_d, best_score = [0.0] * n, [0.0] * n, [math.inf] * n
        last = len(self.geoms) - 1
        for k, g in enumerate(self.geoms):
            s_k, d_k = g.frenet_list(xy)
            off = self._offsets[k]
            length = g.length
            for i in range(n):
                s, d = s_k[i], d_k[i]
                before = (-s if (-s > 0.0 or s != s) else 0.0) if k > 0 else 0.0
                after = (s - length if (s - length > 0.0 or s != s) else 0.0) if k < last else 0.0
                score = abs(d) + 2.0 * (before + after)
                if score < best_score[i]:
                    best_score[i], best_s[i], best_d[i] = score, s + off, d
        return best_s, best_d

    def frenet(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(s, d)`` of world positions; each point goes to the piece that contains it
        longitudinally with the smallest lateral offset."""
        xy = np.asarray(xy, dtype=float)
        if len(self.geoms) == 1:
            return self.geoms[0].frenet(xy)
        shape = xy.shape[:-1]
        best_s = np.zeros(shape)
        best_d = np.zeros(shape)
        best_score = np.full(shape, np.inf)
        last = len(self.geoms) - 1
        for k, g in enumerate(self.geoms):
            s, d = g.frenet(xy)
            before = np.maximum(0.0, -s) if k > 0 else 0.0
            after = np.maximum(0.0, s - g.length) if k < last else 0.0
            score = np.abs(d) + 2.0 * (before + after)
            better = score < best_score
            best_score = np.where(better, score, best_score)
            best_s = np.where(better, s + self.offsets[k], best_s)
            best_d = np.where(better, d, best_d)
        return best_s, best_d


# -- oriented boxes (vectorised; scalars work too) -------------------------------------------------
class PolylineDistance:
    """Exact distances [m] from points to a polyline ``xy`` (n, 2), through an STRtree of its
    segments: the same GEOS point-to-segment distance, minimised over the same segments, as
    ``shapely.distance(points, LineString(xy))`` - the same floats - at about a third of its
    cost for a path of a thousand points."""

    def __init__(self, xy: np.ndarray) -> None:
        xy = np.asarray(xy, dtype=float)
        self.line = shapely.LineString(xy)
        self._tree = shapely.STRtree(shapely.linestrings(np.stack([xy[:-1], xy[1:]], axis=1)))

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        """Distance [m] of each point of ``xy`` (n, 2) to the polyline."""
        points = shapely.points(np.asarray(xy, dtype=float).reshape(-1, 2))
        out = np.full(len(points), np.nan)
        if len(points):
            (which, _), dist = self._tree.query_nearest(points, return_distance=True, all_matches=False)
            out[which] = dist
            if len(which) < len(points):  # a point the tree finds nothing for (not finite): as shapely says
                rest = np.setdiff1d(np.arange(len(points)), which)
                out[rest] = shapely.distance(points[rest], self.line)
        return out


def box_corners(x: np.ndarray, y: np.ndarray, h: np.ndarray, length: float | np.ndarray,
                width: float | np.ndarray) -> np.ndarray:
    """Corners (n, 4, 2) of oriented boxes."""
    c, s = np.cos(h), np.sin(h)
    hl, hw = np.asarray(length) / 2, np.asarray(width) / 2
    ux, uy = c * hl, s * hl
    vx, vy = -s * hw, c * hw
    xs = np.stack([x + ux + vx, x + ux - vx, x - ux - vx, x - ux + vx], axis=-1)
    ys = np.stack([y + uy + vy, y + uy - vy, y - uy - vy, y - uy + vy], axis=-1)
    return np.stack([xs, ys], axis=-1)


def box_polygon(x: float, y: float, h: float, length: float, width: float) -> shapely.Polygon:
    """One oriented box as a shapely polygon."""
    return shapely.Polygon(box_corners(np.array([x]), np.array([y]), np.array([h]), length, width)[0])


def _axis_gaps(dx: Any, dy: Any, ca: Any, sa: Any, cb: Any, sb: Any, hal: Any, haw: Any, hbl: Any,
               hbw: Any) -> tuple[Any, Any, Any, Any]:
    """The separating-axis gaps [m] along both boxes' axes, from the centre offset ``(dx, dy)``,
    each box's heading cos/sin and half length/width (plain operators: floats or arrays)."""
    crel = abs(ca * cb + sa * sb)
    srel = abs(sa * cb - ca * sb)
    return (abs(dx * ca + dy * sa) - hal - (hbl * crel + hbw * srel),
            abs(-dx * sa + dy * ca) - haw - (hbl * srel + hbw * crel),
            abs(dx * cb + dy * sb) - hbl - (hal * crel + haw * srel),
            abs(-dx * sb + dy * cb) - hbw - (hal * srel + haw * crel))


def box_gap(ax: np.ndarray, ay: np.ndarray, ah: np.ndarray, al: float | np.ndarray, aw: float | np.ndarray,
            bx: np.ndarray, by: np.ndarray, bh: np.ndarray, bl: np.ndarray, bw: np.ndarray) -> np.ndarray:
    """Separating-axis gap [m] between oriented boxes (centre, heading, length, width),
    vectorised: > 0 apart, <= 0 overlapping. A lower bound of the true distance."""
    g1, g2, g3, g4 = _axis_gaps(bx - ax, by - ay, np.cos(ah), np.sin(ah), np.cos(bh), np.sin(bh),
                                np.asarray(al) / 2, np.asarray(aw) / 2, np.asarray(bl) / 2, np.asarray(bw) / 2)
    return np.maximum(np.maximum(g1, g2), np.maximum(g3, g4))


def box_gap_point(ax: float, ay: float, ah: float, al: float, aw: float,
                  bx: float, by: float, bh: float, bl: float, bw: float) -> float:
    """:func:`box_gap` of one pair of boxes in scalar math (no array overhead) [m]."""
    return max(_axis_gaps(bx - ax, by - ay, math.cos(ah), math.sin(ah), math.cos(bh), math.sin(bh),
                          al / 2, aw / 2, bl / 2, bw / 2))
