"""highway-env's ``Road`` with a vectorised neighbour search.

``Road.neighbour_vehicles`` projects every vehicle and object on the queried lane one by one
(``lane.local_coordinates`` in Python) each time an IDM vehicle asks - the single largest cost of
stepping highway-env. :class:`FastRoad` projects all positions on a lane at once with numpy and
caches the result until the world advances (:meth:`FastRoad.advance`), returning the same
neighbours as highway-env (same on-lane test, same tie-breaking).
"""

from __future__ import annotations

from typing import Any

from highway_env.road.lane import AbstractLane
from highway_env.road.road import LaneIndex, Road
from highway_env.vehicle.objects import Landmark

from deft_gym.geometry import LaneGeom


class FastRoad(Road):
    """A Road whose neighbour queries are vectorised and cached per world step."""

    def __init__(self, *args: Any, geoms: dict[LaneIndex, LaneGeom], **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.geoms = geoms
        self.tick = 0
        self._cache_tick = -1
        self._members: list[Any] = []
        self._xy: list[list[float]] = []  # members' positions [m]
        self._index: dict[int, int] = {}
        self._lane_cache: dict[LaneIndex, tuple[list[float], list[bool]]] = {}

    def advance(self) -> None:
        """Positions changed: forget cached projections."""
        self.tick += 1

    def _refresh(self) -> None:
        if self._cache_tick == self.tick:
            return
        self._members = [v for v in self.vehicles + self.objects if not isinstance(v, Landmark)]
        self._index = {id(m): i for i, m in enumerate(self._members)}
        self._xy = [[float(v.position[0]), float(v.position[1])] for v in self._members]
        self._lane_cache.clear()
        self._cache_tick = self.tick

    def lane_coordinates(self, lane_index: LaneIndex) -> tuple[list[float], list[bool]]:
        """``(s, on_lane)`` of every road member on ``lane_index`` (cached per step)."""
        if self._cache_tick != self.tick:
            self._refresh()
        out = self._lane_cache.get(lane_index)
        if out is None:
            geom = self.geoms[lane_index]
            s, lat = geom.frenet_list(self._xy)
            L = AbstractLane.VEHICLE_LENGTH
            half, end = geom.width / 2 + 1.0, geom.length + L
            on = [abs(d) <= half and -L <= s_v < end for s_v, d in zip(s, lat, strict=True)]
            out = (s, on)
            self._lane_cache[lane_index] = out
        return out

    def index_of(self, vehicle: Any) -> int:
        """Position of ``vehicle`` among the cached road members (-1 if absent)."""
        if self._cache_tick != self.tick:
            self._refresh()
        return self._index.get(id(vehicle), -1)

    def neighbour_vehicles(self, vehicle: Any, lane_index: LaneIndex = None) -> tuple[Any, Any]:
        """Preceding and following member on ``lane_index`` (highway-env's semantics)."""
        lane_index = lane_index or vehicle.lane_index
        if not lane_index:
            return None, None
        s_all, on = self.lane_coordinates(lane_index)
        me = self._index.get(id(vehicle), -1)
        s = s_all[me] if me >= 0 else float(self.geoms[lane_index].frenet_point(*vehicle.position)[0])
        s_front = s_rear = None
        i_front = i_rear = -1
        for i, s_v in enumerate(s_all):
            if i == me or not on[i]:
                continue
            if s <= s_v and (s_front is None or s_v <= s_front):
                s_front, i_front = s_v, i
            if s_v < s and (s_rear is None or s_v > s_rear):
                s_rear, i_rear = s_v, i
        members = self._members
        return (members[i_front] if i_front >= 0 else None, members[i_rear] if i_rear >= 0 else None)
