"""System-level oracles: collision, task completion, timeout and stuck; and the outcomes of a
run that did not get that far: ``crash`` (a module raised, or published a NaN or an infinity on
the planning or control topic: reason ``non-finite output``), ``hang`` (a module call ran past the
wall-clock watchdog), ``no_plan`` (the ego reached its destination without ever receiving a plan).

The collision check itself runs in the world at every step (ego polygon against every
participant); :class:`EpisodeOracle` turns the world state into the episode outcome.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from deft_gym.world.geometry import LaneGeom
from deft_gym.world.roadmap import RoadMap
from deft_gym.world.traffic_lights import TrafficLights
from deft_gym.world.world import Collision, World

OUTCOMES = ("collision", "completed", "timeout", "stuck", "crash", "hang", "no_plan")
STANDING_SPEED = 0.5  # [m/s] slower than this, the ego may be waiting at a light
REACH_RADIUS = 3.0  # [m] the destination counts as reached this near (:class:`EpisodeOracle`)
LEVEL_LANES = 1.5  # [lane widths] at most this far beside the destination's lane is "a lane over"


def level_with_destination(along: float, beside: float, lane_width: float,
                           reach_radius: float = REACH_RADIUS) -> bool:
    """Whether a point ``along`` [m] past the destination on its lane (negative: short of it) and
    ``beside`` [m] from that lane's centre line is level with it (within ``reach_radius`` [m]
    along) and at most a lane beside it (``LEVEL_LANES`` widths of ``lane_width`` [m])."""
    return abs(along) <= reach_radius and abs(beside) <= LEVEL_LANES * lane_width


def held_by_light(roadmap: RoadMap, lights: TrafficLights | None, loc: tuple[Any, float, float] | None,
                  t: float) -> bool:
    """Whether a vehicle at ``loc`` (``roadmap.locate``'s ``(lane, s, d)``) is held by a light at
    time ``t`` [s]: before the stop line of its lane (or within 1 m past it) while that light is
    not green."""
    if lights is None or loc is None:
        return False
    line = roadmap.stop_line_of.get(loc[0])
    return line is not None and loc[1] <= line.s + 1.0 and lights.color(line.light_id, t) != "GREEN"


@dataclass
class Outcome:
    """How an episode ended."""

    outcome: str
    sim_time: float
    collision: Collision | None
    min_distance: float
    failure: dict[str, Any] | None = None  #: crash / hang: {"kind", "module", "exception", "time"}
    arrival: str | None = None  #: completed: "radius" (within reach_radius) or "a lane over"

    @property
    def task_completed(self) -> bool:
        return self.outcome == "completed"

    def as_dict(self) -> dict[str, Any]:
        out = {"outcome": self.outcome, "sim_time": self.sim_time,
               "collision": self.collision.as_dict() if self.collision else None,
               "task_completed": self.task_completed,
               "min_distance": self.min_distance if math.isfinite(self.min_distance) else None}
        if self.failure is not None:
            out["failure"] = dict(self.failure)
        if self.arrival == "a lane over":  # the usual arrival leaves the record as it always was
            out["arrival"] = self.arrival
        return out


class EpisodeOracle:
    """Watches the world after every step and decides when the episode is over.

    ``reach_radius`` [m]: the destination counts as reached within this distance - or, given the
    destination's lane (``destination_lane``, at ``destination_s`` [m] along it), standing (slower
    than ``STANDING_SPEED``) level with it (within ``reach_radius`` along that lane) at most a lane
    beside it (1.5 lane widths from its centre line): stopped at its destination, one lane over
    (a 3 m radius in a 3.5 m lane would call that ego stuck, and count a timeout or stuck failure
    that no driver would);
    ``stuck_time`` [s]: moving less than ``stuck_distance`` [m] for this long is stuck. Time the
    ego spends held by a light (standing before the stop line of its lane while that light is not
    green, queued or first in line) never counts: the standstill is measured from when the light
    turns green, so ``stuck_time`` need not outlast a red phase.
    """

    def __init__(self, world: World, destination: np.ndarray, duration: float,
                 reach_radius: float = REACH_RADIUS, stuck_time: float = 30.0, stuck_distance: float = 0.5,
                 stop_on_collision: bool = True, destination_lane: LaneGeom | None = None,
                 destination_s: float = 0.0) -> None:
        self.world = world
        self.destination = np.asarray(destination, dtype=float)
        self._destination = (float(self.destination[0]), float(self.destination[1]))
        self.destination_lane, self.destination_s = destination_lane, destination_s
        beside = LEVEL_LANES * destination_lane.width if destination_lane is not None else 0.0
        self._level_radius = math.hypot(reach_radius, beside)  # nearer than this: level-with test
        self.arrival: str | None = None  #: how it arrived: "radius" or "a lane over"
        self.duration = duration
        self.reach_radius = reach_radius
        self.stuck_time = stuck_time
        self.stuck_distance = stuck_distance
        self.stop_on_collision = stop_on_collision
        self._track: deque[tuple[float, float, float]] = deque()
        self._lane: tuple[float, float, Any] = (math.nan, math.nan, None)  # (x, y, located lane) cache
        self.result: str | None = None

    def held_by_light(self) -> bool:
        """:func:`held_by_light` for the ego now (its lane located again only once it moved)."""
        w = self.world
        if w.lights is None or not w.roadmap.stop_line_of:
            return False
        ex, ey = w.ego.position
        cx, cy, loc = self._lane
        if not math.hypot(ex - cx, ey - cy) <= 0.1:  # moved (or never located)
            loc = w.roadmap.locate(np.array([ex, ey]), w.ego.heading)
            self._lane = (ex, ey, loc)
        return held_by_light(w.roadmap, w.lights, loc, w.time)

    def check(self) -> str | None:
        """The outcome if the episode is over now, else None."""
        w = self.world
        t = w.time
        if w.collision is not None and self.stop_on_collision:
            self.result = "collision"
        else:
            ex, ey = w.ego.position.tolist()  # floats: the same values as the array's, cheaper arithmetic
            dx, dy = self._destination
            dist = math.hypot(ex - dx, ey - dy)
            if dist <= self.reach_radius:
                self.result, self.arrival = "completed", "radius"
            elif dist <= self._level_radius and w.ego.speed < STANDING_SPEED and self._level(ex, ey):
                self.result, self.arrival = "completed", "a lane over"
            else:
                tr = self._track
                if w.ego.speed < STANDING_SPEED and self.held_by_light():
                    tr.clear()  # waiting for the light: the standstill counts from green on
                tr.append((t, ex, ey))
                while tr and tr[0][0] < t - self.stuck_time:
                    tr.popleft()
                t0, x0, y0 = tr[0]
                if t - t0 >= self.stuck_time - 1e-9 and math.hypot(ex - x0, ey - y0) < self.stuck_distance:
                    self.result = "stuck"
                elif t >= self.duration - 1e-9:
                    self.result = "timeout"
        return self.result

    def _level(self, x: float, y: float) -> bool:
        """Whether ``(x, y)`` is level with the destination (within ``reach_radius`` along its
        lane) and at most a lane beside it."""
        assert self.destination_lane is not None
        s, d = self.destination_lane.frenet_point(x, y)
        return level_with_destination(s - self.destination_s, d, self.destination_lane.width, self.reach_radius)

    def outcome(self) -> Outcome:
        w = self.world
        return Outcome(self.result or ("collision" if w.collision else "timeout"), w.time,
                       w.collision, w.min_distance, arrival=self.arrival)
