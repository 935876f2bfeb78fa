"""Traffic participants on highway-env's road: static obstacles, scripted NPCs, reactive NPCs.

- :class:`StaticObstacle` - a cone or a parked vehicle (highway-env ``Obstacle``).
- :class:`ScriptedVehicle` - follows timed waypoints exactly, ignoring everybody (this is how an
  adversary adds vehicles); present only from its first waypoint time.
- :class:`ReactiveVehicle` - highway-env's IDM/MOBIL vehicle, which also stops for red lights.
  Its hot paths are rewritten without numpy scalar calls and with a local lane search; the
  behaviour (IDM, MOBIL, lane following) is highway-env's own.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from typing import TYPE_CHECKING, Any

import numpy as np
from highway_env.road.road import Road
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.kinematics import Vehicle
from highway_env.vehicle.objects import Obstacle

if TYPE_CHECKING:
    from deft_gym.world.roadmap import RoadMap
    from deft_gym.world.traffic_lights import TrafficLights

SIZES = {"CONE": (0.6, 0.6), "STATIC_VEHICLE": (4.8, 2.0), "VEHICLE": (4.8, 2.0)}


class StaticObstacle(Obstacle):
    """A cone or a parked vehicle. ``LENGTH``/``WIDTH`` [m] are per instance."""

    def __init__(self, road: Road, position: np.ndarray, heading: float, obstacle_type: str,
                 length: float | None = None, width: float | None = None) -> None:
        self.LENGTH, self.WIDTH = (length, width) if length else SIZES[obstacle_type]
        super().__init__(road, position, heading, 0.0)
        self.obstacle_type = obstacle_type
        self.check_collisions = False


def motion_headings(x: np.ndarray, y: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Heading at each sample as a :class:`ScriptedVehicle` has it: the direction of the segment
    to the next sample (standing still keeps the previous heading, the first sample's
    ``fallback``; the last sample keeps the last segment's)."""
    dx, dy = np.diff(x), np.diff(y)
    moving = np.hypot(dx, dy) > 1e-6
    h = np.array(fallback, dtype=float)
    seg = np.where(moving, np.arctan2(dy, dx), np.nan)
    for i in range(len(seg)):
        h[i] = seg[i] if moving[i] else (h[i - 1] if i > 0 else h[i])
    if len(seg):
        h[-1] = h[-2]
    return h


class ScriptedVehicle(Vehicle):
    """A vehicle that replays timed waypoints ``(t [s], x [m], y [m])`` exactly.

    Between waypoints it moves in a straight line at constant speed; its heading is the
    direction of motion (kept when it stands still). Before the first waypoint time it is absent;
    after the last one it stays parked at the last waypoint. It starts with its first segment's
    speed, so that a vehicle moving from the start is perceived moving in the first frame."""

    obstacle_type = "VEHICLE"

    def __init__(self, road: Road, waypoints: np.ndarray, heading0: float,
                 length: float = 4.8, width: float = 2.0) -> None:
        self.LENGTH, self.WIDTH = length, width
        self.set_waypoints(waypoints, heading0)
        # its speed until the first place(): perception's first frame comes before it (at 0, a
        # truck driving at 6 m/s was perceived standing and predicted parked for static_hold)
        speed0 = math.hypot(*self.seg_v[0]) if len(self.seg_v) else 0.0
        super().__init__(road, self.wp_xy[0].copy(), heading0, speed0)
        self.check_collisions = False
        self.spawn_time = self.wp_t[0]

    def set_waypoints(self, waypoints: np.ndarray, heading0: float) -> None:
        """Replace the timed waypoints ``(t [s], x [m], y [m])``; ``heading0`` [rad] is the
        heading kept while the vehicle stands still before its first move."""
        wp = np.asarray(waypoints, dtype=float)
        if wp.ndim != 2 or wp.shape[1] != 3 or len(wp) < 1:
            raise ValueError("waypoints must be an (n, 3) array of (t, x, y)")
        if np.any(np.diff(wp[:, 0]) <= 0):
            raise ValueError("waypoint times must increase strictly")
        self.wp_t = wp[:, 0].tolist()
        self.wp_xy = wp[:, 1:]
        seg = np.diff(self.wp_xy, axis=0)
        dt = np.diff(wp[:, 0])
        self.seg_v = (seg / dt[:, None]) if len(wp) > 1 else np.zeros((0, 2))
        self.seg_heading = motion_headings(wp[:, 1], wp[:, 2], np.full(len(wp), float(heading0)))[:-1].tolist()

    def place(self, t: float) -> None:
        """Set the state at time ``t`` [s] (kinematic replay)."""
        i = bisect_right(self.wp_t, t) - 1
        if i < 0:
            i = 0
            t = self.wp_t[0]
        if i >= len(self.wp_t) - 1:
            self.position = self.wp_xy[-1].copy()
            self.speed = 0.0
            return
        v = self.seg_v[i]
        self.position = self.wp_xy[i] + v * (t - self.wp_t[i])
        self.speed = math.hypot(v[0], v[1])
        self.heading = self.seg_heading[i]

    def act(self, action=None) -> None:
        pass

    def step(self, dt: float) -> None:
        pass


def _not_zero(x: float, eps: float = 1e-2) -> float:
    if abs(x) > eps:
        return x
    return eps if x >= 0 else -eps


def _wrap(x: float) -> float:
    return ((x + math.pi) % (2 * math.pi)) - math.pi


def bicycle_step(v: Vehicle, dt: float) -> None:
    """highway-env's ``Vehicle.step`` (kinematic bicycle) in scalar math; identical equations,
    without the per-call numpy overhead. ``v.clip_actions()`` runs first, as in highway-env."""
    v.clip_actions()
    delta_f = v.action["steering"]
    beta = math.atan(0.5 * math.tan(delta_f))
    speed, heading = v.speed, v.heading
    x, y = v.position.tolist()  # floats: the same arithmetic as on numpy scalars, faster
    x += speed * math.cos(heading + beta) * dt
    y += speed * math.sin(heading + beta) * dt
    v.position = np.array([x, y]) if v.impact is None else np.array([x, y]) + v.impact
    if v.impact is not None:
        v.crashed = True
        v.impact = None
    v.heading = heading + speed * math.sin(beta) / (v.LENGTH / 2) * dt
    v.speed = speed + v.action["acceleration"] * dt
    v.on_state_update()


class ReactiveVehicle(IDMVehicle):
    """highway-env's IDM/MOBIL vehicle that also respects traffic lights.

    It stops before a stop line whose light is red, or yellow when it can still stop at
    ``COMFORT_ACC_MIN``, by adding a virtual standing leader at the line to IDM.

    ``act``, ``acceleration``, ``steering_control`` and ``step`` are highway-env's formulas
    written with scalar math, and neighbours come from :class:`deft_gym.world.road.FastRoad`; the test
    suite checks the trajectories against stock highway-env. MOBIL (``change_lane_policy``,
    ``mobil``) is highway-env's own code.
    """

    obstacle_type = "VEHICLE"
    STOP_GAP = 2.0  # [m] standstill distance before the stop line

    def __init__(self, road: Road, roadmap: RoadMap, lights: TrafficLights | None,
                 clock: list[float], *args, **kwargs) -> None:
        self.roadmap = roadmap
        self.lights = lights
        self.clock = clock  # shared one-element list holding the world time
        super().__init__(road, *args, **kwargs)

    # -- lane coordinates of the current position, computed once per position ---------------
    _fc_key: tuple[Any, float, float] | None = None
    _fc_val: tuple[float, float] = (0.0, 0.0)

    def _frenet(self, lane_index: Any) -> tuple[float, float]:
        """``(s, lateral)`` of the vehicle on ``lane_index`` (cached for the current position)."""
        x, y = self.position.tolist()
        key = (lane_index, x, y)
        if key != self._fc_key:
            self._fc_key, self._fc_val = key, self.roadmap.geoms[lane_index].frenet_point(x, y)
        return self._fc_val

    _end_key: Any = None
    _end_s: float = 0.0

    def follow_road(self) -> None:
        """highway-env's ``follow_road``: at the end of the target lane, switch to the next one."""
        target = self.target_lane_index
        if target != self._end_key:  # the lane's switching point, kept while the target lane is
            lane = self.road.network.get_lane(target)
            self._end_key, self._end_s = target, lane.length - lane.VEHICLE_LENGTH / 2
        if self._frenet(target)[0] > self._end_s:
            self.target_lane_index = self.road.network.next_lane(
                self.target_lane_index, route=self.route, position=self.position, np_random=self.road.np_random)

    # -- traffic lights ---------------------------------------------------------------------
    def _light_acceleration(self) -> float | None:
        if self.lights is None:
            return None
        sl = self.roadmap.stop_line_of.get(self.lane_index)
        if sl is None:
            return None
        color = self.lights.color(sl.light_id, self.clock[0])
        if color == "GREEN":
            return None
        s, _ = self._frenet(self.lane_index)
        gap = sl.s - s - self.LENGTH / 2 - self.STOP_GAP
        if gap < -self.STOP_GAP:
            return None  # already past the line
        if color == "YELLOW" and gap < self.speed**2 / (2 * -self.COMFORT_ACC_MIN):
            return None  # too close to stop comfortably: go
        gap = max(gap, 0.1)
        v0 = max(self.target_speed, 0.1)
        d_star = 0.5 + self.speed * self.TIME_WANTED + self.speed**2 / (
            2 * math.sqrt(-self.COMFORT_ACC_MAX * self.COMFORT_ACC_MIN))
        return self.COMFORT_ACC_MAX * (1 - (max(self.speed, 0.0) / v0) ** self.DELTA - (d_star / gap) ** 2)

    def act(self, action=None) -> None:
        """IDM/MOBIL (highway-env's ``IDMVehicle.act``), then the red-light constraint."""
        if self.crashed:
            return
        self.follow_road()
        # highway-env's change_lane_policy returns at once, touching nothing, when no lane change
        # is under way and its timer has not passed LANE_CHANGE_DELAY (utils.do_every): that
        # test is made here, without the call
        if self.enable_lane_change and (self.lane_index != self.target_lane_index
                                        or self.timer > self.LANE_CHANGE_DELAY):
            self.change_lane_policy()
        lane_index, target_lane_index = self.lane_index, self.target_lane_index
        steering = self.steering_control(target_lane_index)
        road = self.road
        if lane_index and hasattr(road, "neighbours"):
            front, rear, gap = road.neighbours(self, lane_index)
            # the front vehicle's distance along the current lane, as lane_distance_to has it
            acc = self._idm(self, front, gap) if gap == gap or front is None else self.acceleration(self, front, rear)
        else:
            front, rear = road.neighbour_vehicles(self, lane_index)
            acc = self.acceleration(self, front, rear)
        if lane_index != target_lane_index:
            front, rear = road.neighbour_vehicles(self, target_lane_index)
            acc = min(acc, self.acceleration(self, front, rear))
        # max(-a, min(a, x)) as comparisons, with the builtins' choices (NaN -> a, ties -> first)
        a = self.ACC_MAX
        acc = acc if acc < a else a
        acc = acc if acc > -a else -a
        if self.lights is not None:
            acc_light = self._light_acceleration()
            if acc_light is not None and acc_light < acc:
                acc = max(acc_light, -a)
        m = self.MAX_STEERING_ANGLE
        steering = steering if steering < m else m
        self.action = {"steering": steering if steering > -m else -m, "acceleration": acc}

    def _idm(self, ego_vehicle: Vehicle, front: Vehicle | None, d: float) -> float:
        """highway-env's IDM acceleration [m/s^2] of ``ego_vehicle`` behind ``front`` at lane
        distance ``d`` [m] (the same operations)."""
        target = getattr(ego_vehicle, "target_speed", 0)
        lane = ego_vehicle.lane
        if lane and lane.speed_limit is not None:
            target = 0.0 if target < 0.0 else (lane.speed_limit if target > lane.speed_limit else target)
        speed = ego_vehicle.speed
        if -1e-2 <= target <= 1e-2:
            target = 1e-2 if target >= 0 else -1e-2
        acc = self.COMFORT_ACC_MAX * (1 - ((speed if speed > 0 else 0) / abs(target)) ** self.DELTA)
        if front:
            if -1e-2 <= d <= 1e-2:
                d = 1e-2 if d >= 0 else -1e-2
            acc -= self.COMFORT_ACC_MAX * (self.desired_gap(ego_vehicle, front) / d) ** 2
        return acc

    def acceleration(self, ego_vehicle: Vehicle, front_vehicle: Vehicle = None,
                     rear_vehicle: Vehicle = None) -> float:
        """highway-env's IDM acceleration [m/s^2]."""
        if ego_vehicle is None or not hasattr(ego_vehicle, "speed") or not hasattr(ego_vehicle, "action"):
            return 0
        d = ego_vehicle.lane_distance_to(front_vehicle) if front_vehicle else math.nan
        return self._idm(ego_vehicle, front_vehicle, d)

    def desired_gap(self, ego_vehicle: Vehicle, front_vehicle: Vehicle = None, projected: bool = True) -> float:
        """highway-env's IDM desired gap [m]."""
        v = ego_vehicle.speed
        if projected:
            h = ego_vehicle.heading
            fh, fv = front_vehicle.heading, front_vehicle.speed
            c, s = math.cos(h), math.sin(h)
            dv = (v * c - fv * math.cos(fh)) * c + (v * s - fv * math.sin(fh)) * s
        else:
            dv = v - front_vehicle.speed
        return self.DISTANCE_WANTED + v * self.TIME_WANTED + v * dv / self._two_sqrt_ab

    _two_sqrt_ab = 2 * math.sqrt(-IDMVehicle.COMFORT_ACC_MAX * IDMVehicle.COMFORT_ACC_MIN)

    def steering_control(self, target_lane_index) -> float:
        """highway-env's lane-following steering (lateral P + heading P) [rad]."""
        geom = self.roadmap.geoms[target_lane_index]
        s, lat = self._frenet(target_lane_index)
        speed = self.speed
        nz = speed if (speed > 1e-2 or speed < -1e-2) else (1e-2 if speed >= 0 else -1e-2)
        future_heading = geom.heading_point(s + speed * self.TAU_PURSUIT)
        r = -self.KP_LATERAL * lat / nz
        heading_cmd = math.asin(-1.0 if r < -1.0 else (1.0 if r > 1.0 else r))
        q = math.pi / 4
        heading_ref = future_heading + (-q if heading_cmd < -q else (q if heading_cmd > q else heading_cmd))
        rate_cmd = self.KP_HEADING * (((heading_ref - self.heading) + math.pi) % (2 * math.pi) - math.pi)
        r = self.LENGTH / 2 / nz * rate_cmd
        slip = math.asin(-1.0 if r < -1.0 else (1.0 if r > 1.0 else r))
        steer = math.atan(2 * math.tan(slip))
        m = self.MAX_STEERING_ANGLE
        return -m if steer < -m else (m if steer > m else steer)

    def step(self, dt: float) -> None:
        self.timer += dt
        bicycle_step(self, dt)
        if self.speed < 0.0:  # IDM brakes to a standstill, never into reverse (highway-env's lets speed go
            self.speed = 0.0  # negative when a leader is nearer than the standstill gap)

    def clip_actions(self) -> None:
        a = self.action
        if self.crashed:
            a["steering"] = 0
            a["acceleration"] = -1.0 * self.speed
        if type(a["steering"]) is not float:  # act's are floats already
            a["steering"] = float(a["steering"])
        if type(a["acceleration"]) is not float:
            a["acceleration"] = float(a["acceleration"])
        if self.speed > self.MAX_SPEED:
            a["acceleration"] = min(a["acceleration"], 1.0 * (self.MAX_SPEED - self.speed))
        elif self.speed < self.MIN_SPEED:
            a["acceleration"] = max(a["acceleration"], 1.0 * (self.MIN_SPEED - self.speed))

    def lane_distance_to(self, other, lane=None) -> float:
        if not other:
            return math.nan
        lane_index = self.lane_index if lane is None else None
        road = self.road
        if lane_index is not None and hasattr(road, "lane_s"):
            s_all = road.lane_s(lane_index)
            i, j = road.index_of(other), road.index_of(self)
            if i >= 0 and j >= 0:
                return float(s_all[i] - s_all[j])
        return super().lane_distance_to(other, lane)

    # -- faster versions of highway-env hot paths (same results) ---------------------------
    def on_state_update(self) -> None:
        """Track the current lane among the previous lane, its neighbours and successors
        (highway-env searches every lane of the map at every step)."""
        lane_index = self.lane_index
        if lane_index is None:
            return super().on_state_update()
        g = self.roadmap.geoms[lane_index]
        s, r = self._frenet(lane_index)
        if lane_index == self.target_lane_index and abs(r) < g.width / 2 - 0.3 and 0.0 <= s <= g.length - 0.5:
            return  # well inside the current lane: it stays the closest one
        x, y = self.position.tolist()
        cand = [self.lane_index, *self.roadmap.successors.get(self.lane_index, ())]
        cand += self.road.network.side_lanes(self.lane_index)
        if self.target_lane_index not in cand:
            cand.append(self.target_lane_index)
        best, best_d = self.lane_index, math.inf
        for idx in cand:  # highway-env's distance_with_heading, scalar
            g = self.roadmap.geoms[idx]
            s, r = g.frenet_point(x, y)
            d = abs(r) + max(s - g.length, 0) + max(0 - s, 0) + abs(_wrap(self.heading - g.heading_point(s)))
            if d < best_d:
                best, best_d = idx, d
        self.lane_index = best
        self.lane = self.road.network.get_lane(best)
