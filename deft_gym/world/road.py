"""highway-env's ``Road`` with a vectorised neighbour search.

``Road.neighbour_vehicles`` projects every vehicle and object on the queried lane one by one
(``lane.local_coordinates`` in Python) each time an IDM vehicle asks - the single largest cost of
stepping highway-env. :class:`FastRoad` projects all positions on a lane at once and caches the
result until the world advances (:meth:`FastRoad.advance`), returning the same neighbours as
highway-env (same on-lane test, same tie-breaking). The road members (vehicles and objects, in
order) are rebuilt only when ``vehicles`` or ``objects`` change; their positions are read once a
step.
"""

from __future__ import annotations

import math
from typing import Any

from highway_env.road.lane import AbstractLane
from highway_env.road.road import LaneIndex, Road
from highway_env.vehicle.objects import Landmark

from deft_gym.world.geometry import LaneGeom

# one lane's projection of the members: s [m] of every member, and (index, s) of those on the lane
_Projection = tuple[list[float], list[tuple[int, float]]]


class FastRoad(Road):
    """A Road whose neighbour queries are vectorised and cached per world step."""

    def __init__(self, *args: Any, geoms: dict[LaneIndex, LaneGeom], **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.geoms = geoms
        self.tick = 0
        self._cache_tick = -1
        self._src: tuple[list[Any], list[Any]] = ([], [])  # the lists the members were built from
        self._members: list[Any] = []
        self._xy: list[list[float]] = []  # members' positions [m]
        self._index: dict[int, int] = {}
        self._lane_cache: dict[LaneIndex, _Projection] = {}

    def advance(self) -> None:
        """Positions changed: forget cached projections."""
        self.tick += 1

    def _refresh(self) -> None:
        if self._cache_tick == self.tick:
            return
        vehicles, objects = self.vehicles, self.objects
        src_v, src_o = self._src
        if vehicles != src_v or objects != src_o:  # identity per element: cheap when unchanged
            self._src = (list(vehicles), list(objects))
            self._members = [v for v in vehicles + objects if not isinstance(v, Landmark)]
            self._index = {id(m): i for i, m in enumerate(self._members)}
        # float64 positions: ``tolist`` gives the same floats as ``float(position[k])``
        self._xy = [v.position.tolist() for v in self._members]
        self._lane_cache.clear()
        self._cache_tick = self.tick

    def _projection(self, lane_index: LaneIndex) -> _Projection:
        """``(s, on-lane (index, s))`` of the members on ``lane_index`` (cached per step)."""
        if self._cache_tick != self.tick:
            self._refresh()
        out = self._lane_cache.get(lane_index)
        if out is not None:
            return out
        geom = self.geoms[lane_index]
        L = AbstractLane.VEHICLE_LENGTH
        half, lo, end = geom.width / 2 + 1.0, -L, geom.length + L
        s, lat = geom.frenet_list(self._xy)
        near = [(i, s_v) for i, s_v in enumerate(s) if abs(lat[i]) <= half and lo <= s_v < end]
        out = self._lane_cache[lane_index] = (s, near)
        return out

    def lane_s(self, lane_index: LaneIndex) -> list[float]:
        """``s`` [m] of every road member on ``lane_index`` (cached per step)."""
        return self._projection(lane_index)[0]

    def index_of(self, vehicle: Any) -> int:
        """Position of ``vehicle`` among the cached road members (-1 if absent)."""
        if self._cache_tick != self.tick:
            self._refresh()
        return self._index.get(id(vehicle), -1)

    def neighbours(self, vehicle: Any, lane_index: LaneIndex) -> tuple[Any, Any, float]:
        """Preceding and following member on ``lane_index`` (highway-env's semantics), and the
        preceding one's ``s`` minus the vehicle's: its ``lane_distance_to`` on that lane (NaN
        without one, or when the vehicle is no road member: its lane distance is then not taken
        from these projections)."""
        s_all, near = self._projection(lane_index)
        me = self._index.get(id(vehicle), -1)
        s = s_all[me] if me >= 0 else float(self.geoms[lane_index].frenet_point(*vehicle.position)[0])
        # on-lane members have finite s in [-L, end): the infinite starts never win a comparison
        s_front, s_rear = math.inf, -math.inf
        i_front = i_rear = -1
        for i, s_v in near:
            if i == me:
                continue
            if s <= s_v and s_v <= s_front:  # ties: the last member in order, as highway-env
                s_front, i_front = s_v, i
            if s_v < s and s_v > s_rear:  # ties: the first member
                s_rear, i_rear = s_v, i
        members = self._members
        rear = members[i_rear] if i_rear >= 0 else None
        if i_front < 0:
            return None, rear, math.nan
        return members[i_front], rear, (s_front - s if me >= 0 else math.nan)

    def neighbour_vehicles(self, vehicle: Any, lane_index: LaneIndex = None) -> tuple[Any, Any]:
        """Preceding and following member on ``lane_index`` (highway-env's semantics)."""
        lane_index = lane_index or vehicle.lane_index
        if not lane_index:
            return None, None
        front, rear, _ = self.neighbours(vehicle, lane_index)
        return front, rear
