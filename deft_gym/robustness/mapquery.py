"""Map facts that invariants need: lane speed limits, stop lines, the drivable area.

Every query is total: non-finite or absurd inputs give a neutral answer (the map speed limit,
no stop line, off-road) instead of raising, so an invariant is judged on the system's values,
never broken by them.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import shapely

from deft_gym.world.geometry import wrap_angle
from deft_gym.world.roadmap import RoadMap, shared_roadmap

EGO_HALF_LENGTH = 2.4  # [m]
_FAR = 1e6  # [m] coordinates beyond this are not on any map


def _ok(*xs: Any) -> bool:
    return all(isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) and abs(x) < _FAR
               for x in xs)


class MapQuery:
    """Queries on one road map (``map_spec`` as in a scenario or the log's episode record)."""

    def __init__(self, map_spec: dict[str, Any] | RoadMap) -> None:
        self.map = map_spec if isinstance(map_spec, RoadMap) else shared_roadmap(map_spec)
        self.default_limit = float(self.map.spec.speed_limit)
        self._road: dict[float, Any] = {}

    def lane_speed_limit(self, x: float, y: float, heading: float) -> float:
        """Speed limit [m/s] of the lane at ``(x, y)`` (the map's limit when off every lane)."""
        if not _ok(x, y, heading):
            return self.default_limit
        loc = self.map.locate(np.array([x, y]), heading)
        if loc is None:
            return self.default_limit
        return float(self.map.lanes[loc[0]].speed_limit or self.default_limit)

    def stop_line(self, x: float, y: float, heading: float) -> dict[str, Any] | None:
        """The stop line the ego's front approaches or just passed: ``{id, gap, light}`` with
        ``gap`` [m] the distance from the front bumper to the line (negative once past it), or
        None when no stop line is within 60 m ahead / 6 m behind on the ego's lane."""
        if not _ok(x, y, heading):
            return None
        fx, fy = x + EGO_HALF_LENGTH * math.cos(heading), y + EGO_HALF_LENGTH * math.sin(heading)
        best = None
        for sl in self.map.stop_lines:
            g = self.map.geoms[sl.lane]
            s, d = g.frenet_point(fx, fy)
            gap = sl.s - s
            if not (-6.0 <= gap <= 60.0) or abs(d) > g.width / 2 + 0.5:
                continue
            if abs(float(wrap_angle(heading - g.heading_point(min(max(s, 0.0), g.length))))) > 1.0:
                continue
            if best is None or abs(d) < best[0]:
                best = (abs(d), {"id": f"{sl.lane[0]}-{sl.lane[1]}-{sl.lane[2]}", "gap": float(gap),
                                 "light": sl.light_id})
        return None if best is None else best[1]

    def on_road(self, x: float, y: float, margin: float = 0.5) -> bool:
        """``(x, y)`` lies within ``margin`` [m] of the drivable area."""
        if not _ok(x, y):
            return False
        road = self._road.get(margin)
        if road is None:
            road = self._road[margin] = self.map.drivable_area.buffer(margin)
            shapely.prepare(road)
        return bool(shapely.contains_xy(road, x, y))
