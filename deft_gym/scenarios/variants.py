"""Scenario variants: a seed scenario with its participants, ego start and lights perturbed.

Used to calibrate the non-determinism (how many collision scenarios are flaky across reruns)
and as held-out scenarios for the adversary. Every draw comes from the given seed.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from deft_gym.scenarios.scenario import (
    Scenario,
    scenario_from_dict,
    scenario_to_dict,
    with_participants,
)
from deft_gym.world.roadmap import shared_roadmap


def perturb(sc: Scenario, seed: int, strength: float = 1.0) -> Scenario:
    """A variant of ``sc``: positions [m], speeds and timing shifted by amounts that scale with
    ``strength`` (1.0: up to ~10 m, ~20 % speed, 2 s of light offset)."""
    rng = np.random.default_rng(seed)
    roadmap = shared_roadmap(sc.map)
    data = scenario_to_dict(sc)  # a fresh copy
    data["name"] = f"{sc.name}~v{seed}"

    def shift_s(item: dict[str, Any], amount: float) -> None:
        if "lane" in item and "s" in item:
            length = roadmap.geom(tuple(item["lane"])).length
            item["s"] = float(np.clip(item["s"] + rng.uniform(-amount, amount) * strength, 0.0, length))

    def scale(item: dict[str, Any], key: str, rel: float) -> None:
        if key in item and item[key] is not None:
            item[key] = float(max(0.0, item[key] * (1.0 + rng.uniform(-rel, rel) * strength)))

    shift_s(data["ego"], 5.0)
    scale(data["ego"], "speed", 0.15)
    for p in data.get("participants", []):
        if p["type"] == "static":
            shift_s(p, 8.0)
            if "d" in p:
                p["d"] = float(p["d"] + rng.uniform(-0.4, 0.4) * strength)
        elif p["type"] == "reactive":
            shift_s(p, 10.0)
            scale(p, "speed", 0.2)
            scale(p, "target_speed", 0.15)
        else:
            dt = rng.uniform(-1.5, 1.5) * strength
            times = [max(0.0, w["t"] + dt) for w in p["waypoints"]]
            for i in range(1, len(times)):
                times[i] = max(times[i], times[i - 1] + 0.1)
            for w, t in zip(p["waypoints"], times):
                w["t"] = float(t)
                shift_s(w, 3.0)
    if data.get("lights"):
        data["lights"]["offset"] = float(data["lights"].get("offset", 0.0) + rng.uniform(-2.0, 2.0) * strength)
    return scenario_from_dict(data, source=f"{sc.source or sc.name} (variant {seed})")


def inject_cut_in(sc: Scenario, path: np.ndarray, seed: int) -> Scenario:
    """``sc`` plus a scripted vehicle that cuts in ahead of the ego (from its left or right) at a
    random moment of the reference path ``path`` - the manoeuvre a constant-velocity predictor
    sees late. Lateral start offset, lead distance (0-12 m: from unavoidable to easy), timing and
    speeds are drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    moving = path[path[:, 4] > 2.0]
    if len(moving) < 20:
        return sc
    i = int(rng.integers(len(moving) // 5, len(moving) * 4 // 5))
    t_h, x, y, h, v = moving[i]
    c, s_ = np.cos(h), np.sin(h)
    side = rng.choice([-1.0, 1.0]) * rng.uniform(3.0, 4.0)
    lead = rng.uniform(0.0, 12.0)
    dur = rng.uniform(1.0, 3.0)
    v_npc = v * rng.uniform(0.3, 1.0)

    def at(ahead: float, lateral: float) -> tuple[float, float]:
        return float(x + ahead * c - lateral * s_), float(y + ahead * s_ + lateral * c)

    wps = []
    t0 = max(0.0, t_h - dur)
    for k, (tt, ahead, lat) in enumerate([(t0, lead - (t_h - t0) * (v - v_npc) * 0.5, side),
                                          (t_h, lead, 0.0), (t_h + 4.0, lead + 4.0 * v_npc, 0.0)]):
        px, py = at(ahead, lat)
        wps.append({"t": float(tt + 1e-3 * k), "x": px, "y": py})
    return _with_scripted(sc, f"cut{seed}", f"cut_in_{seed}", wps, f"cut-in {seed}")


def inject_hard_brake(sc: Scenario, path: np.ndarray, seed: int) -> Scenario:
    """``sc`` plus a scripted vehicle that appears ahead of the ego on its reference path, drives
    at the ego's speed and then brakes hard to a stop. Gap (6-25 m), braking moment and
    deceleration (4-9 m/s^2) are drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    moving = np.flatnonzero(path[:, 4] > 3.0)
    if len(moving) < 20:
        return sc
    xy = path[:, 1:3]
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    i = int(moving[rng.integers(len(moving) // 5, len(moving) * 3 // 5)])
    t0, v = float(path[i, 0]), float(path[i, 4])
    gap = rng.uniform(6.0, 25.0) + 4.8
    t_brake = t0 + rng.uniform(0.5, 3.0)
    decel = rng.uniform(4.0, 9.0)
    s_at = []  # the vehicle's arc length over time: ego speed until t_brake, then braking
    for k in range(0, 41):
        t = t0 + 0.25 * k
        if t <= t_brake:
            s_v = arc[i] + gap + v * (t - t0)
        else:
            tb = min(t - t_brake, v / decel)
            s_v = arc[i] + gap + v * (t_brake - t0) + v * tb - 0.5 * decel * tb * tb
        s_at.append((t, s_v))
    wps = []
    for t, s_v in s_at:
        if s_v > arc[-1]:
            break
        wps.append({"t": float(t), "x": float(np.interp(s_v, arc, xy[:, 0])), "y": float(np.interp(s_v, arc, xy[:, 1]))})
    if len(wps) < 3:
        return sc
    return _with_scripted(sc, f"brake{seed}", f"brake_{seed}", wps, f"hard brake {seed}")


def _with_scripted(sc: Scenario, suffix: str, pid: str, waypoints: list[dict[str, float]], what: str) -> Scenario:
    """``sc`` named ``<name>~<suffix>`` with one more scripted participant ``pid``."""
    data = with_participants(sc, f"{sc.name}~{suffix}", [{"id": pid, "type": "scripted", "waypoints": waypoints}])
    return scenario_from_dict(data, source=f"{sc.source or sc.name} ({what})")
