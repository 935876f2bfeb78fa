"""The road map drawn with matplotlib (:func:`draw_map`: lane surfaces, centre lines, stop
lines), for pictures of live worlds such as the adversary env's. Pictures of recorded episodes
are :mod:`deft_gym.viz.episode`."""

from __future__ import annotations

from typing import Any

import numpy as np

from deft_gym.world.roadmap import RoadMap


def draw_map(ax: Any, roadmap: RoadMap) -> None:
    """Lane surfaces and centre lines of a road map."""
    for g in roadmap.geoms.values():
        s = np.linspace(0.0, g.length, max(2, int(g.length / 2.0) + 1))
        left, right = g.xy(s, -g.width / 2), g.xy(s, g.width / 2)
        poly = np.concatenate([left, right[::-1]])
        ax.fill(poly[:, 0], poly[:, 1], color="0.88", lw=0)
        c = g.xy(s)
        ax.plot(c[:, 0], c[:, 1], color="0.75", lw=0.5, ls="--")
    for sl in roadmap.stop_lines:
        g = roadmap.geom(sl.lane)
        a, b = g.xy(np.array(sl.s), -g.width / 2), g.xy(np.array(sl.s), g.width / 2)
        ax.plot([a[0], b[0]], [a[1], b[1]], color="k", lw=1.5)


def _box(ax: Any, x: float, y: float, h: float, length: float, width: float, **kw: Any) -> None:
    c, s = np.cos(h), np.sin(h)
    pts = np.array([[-length / 2, -width / 2], [length / 2, -width / 2], [length / 2, width / 2],
                    [-length / 2, width / 2]]) @ np.array([[c, s], [-s, c]]) + [x, y]
    ax.fill(pts[:, 0], pts[:, 1], zorder=4, **kw)
