"""Modules that sample the world: localization, obstacle perception, traffic-light perception.

They stand in for Apollo's localization and perception (which a simulator bridge feeds with
near-perfect data, as in Decictor's setup): ground truth plus small, seeded noise.
"""

from __future__ import annotations

import random
from typing import Any

from deft_gym.bus.ads import ModuleConfig
from deft_gym.bus.bus import Node, header
from deft_gym.bus.messages import NS_PER_S
from deft_gym.world.world import World


def _period_ns(cfg: ModuleConfig) -> int:
    return round(NS_PER_S / cfg.rate_hz)


class LocalizationNode(Node):
    """Ego pose from ground truth with Gaussian noise (``params``: ``xy_std`` [m],
    ``heading_std`` [rad], ``speed_std`` [m/s]), seeded by the scenario seed."""

    def __init__(self, world: World, cfg: ModuleConfig, topic: str, seed: int) -> None:
        super().__init__("localization", [], period_ns=_period_ns(cfg), processing=cfg.processing)
        self.world, self.topic = world, topic
        self.xy_std = float(cfg.params.get("xy_std", 0.02))
        self.h_std = float(cfg.params.get("heading_std", 0.002))
        self.v_std = float(cfg.params.get("speed_std", 0.02))
        self.rng = random.Random(seed * 1_000_003 + 11)

    def compute(self, now_ns: int) -> list[tuple[str, dict[str, Any]]]:
        e = self.world.ego
        g = self.rng.gauss
        v = float(e.speed)
        payload = {
            "header": header(now_ns / NS_PER_S, self.name),
            "x": float(e.position[0]) + g(0.0, self.xy_std),
            "y": float(e.position[1]) + g(0.0, self.xy_std),
            "heading": float(e.heading) + g(0.0, self.h_std),
            "v": max(0.0, v + g(0.0, self.v_std)) if v > 0 else 0.0,
            "a": float(e.accel),
            "yaw_rate": float(e.yaw_rate),
        }
        return [(self.topic, payload)]


class PerceptionNode(Node):
    """Obstacles within ``params.range`` [m] of the ego (default 120 m), ground truth."""

    def __init__(self, world: World, cfg: ModuleConfig, topic: str) -> None:
        super().__init__("perception", [], period_ns=_period_ns(cfg), processing=cfg.processing)
        self.world, self.topic = world, topic
        self.range2 = float(cfg.params.get("range", 120.0)) ** 2

    def compute(self, now_ns: int) -> list[tuple[str, dict[str, Any]]]:
        ex, ey = self.world.ego.position
        obs = [o for o in self.world.obstacles() if (o["x"] - ex) ** 2 + (o["y"] - ey) ** 2 <= self.range2]
        return [(self.topic, {"header": header(now_ns / NS_PER_S, self.name), "obstacles": obs})]


class TrafficLightNode(Node):
    """Colour of every light of the map (Apollo's traffic-light perception)."""

    def __init__(self, world: World, cfg: ModuleConfig, topic: str) -> None:
        super().__init__("traffic_light", [], period_ns=_period_ns(cfg), processing=cfg.processing)
        self.world, self.topic = world, topic

    def compute(self, now_ns: int) -> list[tuple[str, dict[str, Any]]]:
        return [(self.topic, {"header": header(now_ns / NS_PER_S, self.name),
                              "lights": self.world.light_colors()})]
