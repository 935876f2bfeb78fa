"""The simulated world: highway-env road, the ego vehicle, participants, lights, collisions.

The ego is a highway-env kinematic bicycle driven *only* by control commands (steering [rad],
acceleration [m/s^2]) that arrive over the bus. The world is the ground truth the sensor
modules sample and the collision oracle checks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely
from highway_env.vehicle.kinematics import Vehicle
from highway_env.vehicle.objects import RoadObject

from deft_gym.world.geometry import box_gap_point
from deft_gym.world.participants import (
    ReactiveVehicle,
    ScriptedVehicle,
    StaticObstacle,
    bicycle_step,
)
from deft_gym.world.road import FastRoad
from deft_gym.world.roadmap import RoadMap
from deft_gym.world.traffic_lights import TrafficLights


class EgoVehicle(Vehicle):
    """highway-env's bicycle model without reverse gear and without per-step lane search."""

    LENGTH = 4.8
    WIDTH = 2.0
    MAX_STEERING = math.radians(35.0)

    def __init__(self, road: FastRoad, position: np.ndarray, heading: float, speed: float) -> None:
        super().__init__(road, position, heading, speed)
        self.check_collisions = False
        self.accel = 0.0
        self.yaw_rate = 0.0

    def clip_actions(self) -> None:
        a = self.action
        # max(-m, min(m, x)) and max(x, 0.0) as comparisons, with the builtins' choices
        # (NaN -> m, ties -> the first argument)
        m = self.MAX_STEERING
        steering = float(a["steering"])
        steering = steering if steering < m else m
        a["steering"] = steering if steering > -m else -m
        acc = float(a["acceleration"])
        if self.speed <= 0.0 and acc < 0.0:
            acc = 0.0
        a["acceleration"] = acc

    def step(self, dt: float) -> None:
        heading0, speed0 = self.heading, self.speed
        bicycle_step(self, dt)
        if self.speed < 0.0:
            self.speed = 0.0
        if self.speed > self.MAX_SPEED:
            self.speed = self.MAX_SPEED
        self.accel = (self.speed - speed0) / dt
        self.yaw_rate = (self.heading - heading0) / dt

    def on_state_update(self) -> None:
        pass


_CORNERS: dict[tuple[float, float], np.ndarray] = {}


def footprint(obj: RoadObject) -> np.ndarray:
    """``obj.polygon()`` (the closed ring of its corners, shape (5, 2)) with highway-env's own
    operations - the same ``np.cos``/``np.sin``, rotation matrix and matrix product, so the same
    bits - without rebuilding the constant corner array or tiling the position."""
    if type(obj).polygon is not RoadObject.polygon:
        return obj.polygon()
    length, width = obj.LENGTH, obj.WIDTH
    points = _CORNERS.get((length, width))
    if points is None:  # built as highway-env builds it: the transpose of a (4, 2) array
        points = _CORNERS[(length, width)] = np.array(
            [[-length / 2, -width / 2], [-length / 2, +width / 2], [+length / 2, +width / 2],
             [+length / 2, -width / 2]]).T
    c, s = np.cos(obj.heading), np.sin(obj.heading)
    rotation = np.array([[c, -s], [s, c]])
    corners = (rotation @ points).T + obj.position  # broadcast: np.tile's sums
    return np.concatenate((corners, corners[0:1]))


@dataclass
class Participant:
    """A participant of the scenario and the road object that embodies it."""

    id: str
    num: int  # integer id used in perception messages
    kind: str  # static | scripted | reactive
    obj: Any

    @property
    def obstacle_type(self) -> str:
        return self.obj.obstacle_type

    def present(self, t: float) -> bool:
        return self.kind != "scripted" or t >= self.obj.spawn_time


@dataclass
class Collision:
    """What the collision oracle saw."""

    participant: str
    participant_num: int  # the id perception reports for it
    kind: str
    obstacle_type: str
    time: float
    ego_speed: float
    ego_moving: bool
    x: float
    y: float

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


class World:
    """Ground truth: road, ego, participants, lights, time [s]."""

    def __init__(self, roadmap: RoadMap, lights: TrafficLights | None, seed: int = 0) -> None:
        self.roadmap = roadmap
        self.lights = lights
        self.road = FastRoad(network=roadmap.network, np_random=np.random.RandomState(seed),
                             record_history=False, geoms=roadmap.geoms)
        self.clock = [0.0]
        self.ticks = 0
        self.ego: EgoVehicle | None = None
        self.participants: list[Participant] = []
        self.collision: Collision | None = None
        self.min_distance = math.inf
        self._static_polygons: dict[int, shapely.Polygon] = {}

    @property
    def time(self) -> float:
        return self.clock[0]

    # -- building ---------------------------------------------------------------------------
    def add_ego(self, position: np.ndarray, heading: float, speed: float) -> EgoVehicle:
        self.ego = EgoVehicle(self.road, position, heading, speed)
        self.road.vehicles.insert(0, self.ego)
        return self.ego

    def add_participant(self, pid: str, kind: str, obj: Any) -> Participant:
        p = Participant(pid, len(self.participants) + 1, kind, obj)
        self.participants.append(p)
        if kind == "static":
            self.road.objects.append(obj)
        elif kind == "reactive" or (kind == "scripted" and obj.spawn_time <= self.time):
            self.road.vehicles.append(obj)
        return p

    # -- stepping ---------------------------------------------------------------------------
    def step(self, dt: float, steering: float, acceleration: float) -> None:
        """Advance by ``dt`` [s]: NPC decisions, kinematics, then the collision check."""
        road = self.road
        if self._kinds_n != len(self.participants):
            self._sort_participants()
        reactive = self._reactive
        for obj in reactive:  # decisions on the current state, then all move (as highway-env)
            obj.act()
        for obj in reactive:
            obj.step(dt)
        self.ticks += 1
        t = self.ticks * dt  # exact multiples, no accumulated rounding
        self.clock[0] = t
        for obj in self._scripted:
            if t >= obj.spawn_time and obj not in road.vehicles:
                road.vehicles.append(obj)
            obj.place(t)
        ego = self.ego
        ego.act({"steering": steering, "acceleration": acceleration})
        ego.step(dt)
        road.advance()
        self._check_collisions(t)

    _kinds_n = -1  # len(participants) when _reactive/_scripted/_half_diag were made

    def _sort_participants(self) -> None:
        ps = self.participants
        self._reactive = [p.obj for p in ps if p.kind == "reactive"]
        self._scripted = [p.obj for p in ps if p.kind == "scripted"]
        # half diagonals as floats (highway-env keeps numpy scalars: the same values)
        self._half_diag = [float(p.obj.diagonal) / 2 for p in ps]
        self._kinds_n = len(ps)

    def present_participants(self) -> list[Participant]:
        t = self.clock[0]
        return [p for p in self.participants if p.present(t)]

    def _check_collisions(self, t: float) -> None:
        ego = self.ego  # the per-kind lists are current: step made them
        ex, ey = ego.position.tolist()
        half_ego = float(ego.diagonal) / 2
        min_distance = self.min_distance
        # exact polygon distances only where they can lower the minimum (or be a collision):
        # the bounding-circle gap, then the separating-axis gap, are lower bounds of the
        # polygon distance (scalar math: they only decide which pairs get the exact distance).
        # A pair whose circle gap is not below the minimum now never will be in this check
        # (the minimum only falls): only the others are sorted.
        gaps = []
        hypot = math.hypot
        for i, p in enumerate(self.participants):
            if not p.present(t):
                continue
            o = p.obj
            px, py = o.position.tolist()
            gap = hypot(px - ex, py - ey) - self._half_diag[i] - half_ego
            if gap < min_distance:
                gaps.append((gap, i, px, py))
        if not gaps:
            return
        gaps.sort()  # by gap (then index: unique, so positions are never compared)
        eh = float(ego.heading)
        ego_poly = None
        for gap, i, px, py in gaps:
            if gap >= self.min_distance:
                break
            p = self.participants[i]
            o = p.obj
            if box_gap_point(ex, ey, eh, ego.LENGTH, ego.WIDTH, px, py, float(o.heading), o.LENGTH,
                             o.WIDTH) >= self.min_distance + 1e-9:
                continue  # the polygons cannot be closer than the minimum
            if ego_poly is None:
                ego_poly = shapely.polygons(shapely.linearrings(footprint(ego)))
            dist = ego_poly.distance(self._polygon(p))
            self.min_distance = min(self.min_distance, dist)
            if dist <= 0.0 and self.collision is None:
                self.collision = Collision(p.id, p.num, p.kind, p.obstacle_type, t, float(ego.speed),
                                           bool(ego.speed > 0.1), float(ego.position[0]),
                                           float(ego.position[1]))

    def _polygon(self, p: Participant) -> shapely.Polygon:
        """A participant's footprint; static obstacles' never change and are kept."""
        if p.kind != "static":
            return shapely.polygons(shapely.linearrings(footprint(p.obj)))
        poly = self._static_polygons.get(p.num)
        if poly is None:
            poly = self._static_polygons[p.num] = shapely.polygons(shapely.linearrings(footprint(p.obj)))
        return poly

    # -- ground truth for sensors -----------------------------------------------------------
    def ego_state(self) -> dict[str, float]:
        e = self.ego
        return {"x": float(e.position[0]), "y": float(e.position[1]), "heading": float(e.heading),
                "v": float(e.speed), "a": float(e.accel), "yaw_rate": float(e.yaw_rate),
                "steering": float(e.action["steering"])}

    def obstacles(self) -> list[dict[str, Any]]:
        """Ground-truth state of every present participant."""
        out = []
        for p in self.present_participants():
            o = p.obj
            out.append({"id": p.num, "type": p.obstacle_type, "x": float(o.position[0]),
                        "y": float(o.position[1]), "heading": float(o.heading),
                        "v": float(o.speed), "length": float(o.LENGTH), "width": float(o.WIDTH)})
        return out

    def light_colors(self) -> list[dict[str, str]]:
        if self.lights is None:
            return []
        t = self.clock[0]
        return [{"id": lid, "color": self.lights.color(lid, t)} for lid in self.lights.ids]


__all__ = ["Collision", "EgoVehicle", "Participant", "ReactiveVehicle", "ScriptedVehicle",
           "StaticObstacle", "World"]
