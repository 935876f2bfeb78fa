"""Routing: answers the scenario's routing request once, at start-up."""

from __future__ import annotations

from typing import Any

from deft_gym.bus.ads import ModuleConfig
from deft_gym.bus.bus import Node, header
from deft_gym.bus.messages import NS_PER_S
from deft_gym.world.roadmap import LaneId, RoadMap


class RoutingNode(Node):
    """Publishes the lane-level route from the ego's start lane to its destination and, with it,
    the map it routes on as data (on ``map_topic``), for planners that read the ``map`` role."""

    def __init__(self, roadmap: RoadMap, start: LaneId, dest: LaneId, dest_s: float,
                 cruise_speed: float | None, cfg: ModuleConfig, topic: str, map_topic: str | None = None) -> None:
        super().__init__("routing", [], processing=cfg.processing)
        self.roadmap, self.start_lane, self.dest, self.dest_s = roadmap, start, dest, dest_s
        self.cruise, self.topic, self.map_topic = cruise_speed, topic, map_topic

    def start(self) -> None:
        self.bus.schedule(0, self._begin)

    def compute(self, now_ns: int) -> list[tuple[str, dict[str, Any]]]:
        segments = self.roadmap.route_segments(self.start_lane, self.dest) or []
        payload: dict[str, Any] = {
            "header": header(now_ns / NS_PER_S, self.name),
            "segments": segments,
            "destination": {"lane": list(self.dest), "s": float(self.dest_s)},
            "cruise_speed": float(self.cruise or self.roadmap.spec.speed_limit),
        }
        out = [(self.topic, payload)]
        if self.map_topic is not None:
            out.append((self.map_topic, {"header": header(now_ns / NS_PER_S, self.name), **self.roadmap.as_data()}))
        return out
