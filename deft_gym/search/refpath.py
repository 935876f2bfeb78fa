"""The reference path as a coordinate frame: arc length sigma along it, lateral offset from it.

Placements and observations of the adversary are expressed in this frame (a point ``along`` m
ahead of the ego's projection on the path, ``lateral`` m to its right), which is what lets one
policy act on every scenario and on variants it never saw.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np

from deft_gym.search.trace import Trace
from deft_gym.world.roadmap import RoadMap


class RefPath:
    """Arc length, tangents and the lane structure along a reference run's ego path."""

    def __init__(self, ref: Trace, roadmap: RoadMap) -> None:
        xy = ref.xy
        step = np.hypot(*np.diff(xy, axis=0).T)
        keep = np.concatenate([[True], step > 0.05])  # drop standstill duplicates
        self.xy = xy[keep]
        self.t = ref.t[keep]
        self.v = ref.ego[keep, 3]
        seg = np.diff(self.xy, axis=0)
        self.sigma = np.concatenate([[0.0], np.cumsum(np.hypot(*seg.T))])
        self.length = float(self.sigma[-1])
        h = np.arctan2(seg[:, 1], seg[:, 0])
        self.heading = np.unwrap(np.concatenate([h, h[-1:]]))
        self.roadmap = roadmap

    def at(self, sigma: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Points (n, 2) and headings (n,) at arc lengths (clipped to the path; beyond its ends
        the path is extended straight)."""
        s = np.atleast_1d(np.asarray(sigma, dtype=float))
        sc = np.clip(s, 0.0, self.length)
        x = np.interp(sc, self.sigma, self.xy[:, 0])
        y = np.interp(sc, self.sigma, self.xy[:, 1])
        h = np.interp(sc, self.sigma, self.heading)
        extra = s - sc
        return np.stack([x + extra * np.cos(h), y + extra * np.sin(h)], axis=1), h

    def offset(self, sigma: np.ndarray | float, lateral: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """World points at ``lateral`` m to the right of the path at ``sigma``, and the path
        heading there."""
        p, h = self.at(sigma)
        lat = np.asarray(lateral, dtype=float)
        return np.stack([p[:, 0] - lat * np.sin(h), p[:, 1] + lat * np.cos(h)], axis=-1), h

    def project(self, xy: np.ndarray, hint: int | None = None, window: int = 400) -> tuple[float, float, int]:
        """Arc length and signed lateral offset (right +) of one point, searching near ``hint``
        (a point index) first. Returns ``(sigma, lateral, index)``."""
        p = np.asarray(xy, dtype=float)
        n = len(self.xy)
        lo, hi = (0, n) if hint is None else (max(0, hint - window // 4), min(n, hint + window))
        seg_a = self.xy[lo:max(hi - 1, lo + 1)]
        seg_b = self.xy[lo + 1:max(hi, lo + 2)]
        if len(seg_b) == 0:
            return 0.0, 0.0, 0
        m = min(len(seg_a), len(seg_b))
        seg_a, seg_b = seg_a[:m], seg_b[:m]
        d = seg_b - seg_a
        ll = np.maximum((d**2).sum(axis=1), 1e-12)
        u = np.clip(((p - seg_a) * d).sum(axis=1) / ll, 0.0, 1.0)
        q = seg_a + u[:, None] * d
        dist = np.hypot(*(p - q).T)
        j = int(np.argmin(dist))
        i = lo + j
        cross = d[j, 0] * (p[1] - seg_a[j, 1]) - d[j, 1] * (p[0] - seg_a[j, 0])
        lat = float(np.sign(cross) * dist[j])
        return float(self.sigma[i] + u[j] * np.sqrt(ll[j])), lat, i

    def sigma_at_time(self, t: float) -> float:
        """Where the reference ego was at time ``t`` [s]."""
        return float(np.interp(t, self.t, self.sigma))

    def speed_at(self, sigma: float) -> float:
        return float(np.interp(sigma, self.sigma, self.v))

    @cached_property
    def lanes_beside(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """On a 2 m grid of sigma: how many same-direction lanes lie to the left and to the right
        of the path (``grid, left, right``)."""
        grid = np.arange(0.0, self.length + 2.0, 2.0)
        pts, hs = self.at(grid)
        left, right = np.zeros(len(grid)), np.zeros(len(grid))
        for i, (p, h) in enumerate(zip(pts, hs)):
            loc = self.roadmap.locate(p, float(h))
            if loc is None:
                continue
            a, b, k = loc[0]
            n = len(self.roadmap.network.graph[a][b])
            left[i], right[i] = k, n - 1 - k
        return grid, left, right
