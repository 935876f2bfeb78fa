"""The way back: an exported ``.xosc`` or CommonRoad ``.xml`` to a scenario YAML whose rerun on
the same jitter seed reproduces the episode.

The ego starts where and as fast as the file says, towards its destination (the DeFT-Gym
properties: the scenario's own ego, kept when it starts where the file's ego starts); static
objects stay where they are; every other participant - scripted or reactive when it ran -
becomes a scripted vehicle that replays its trajectory. A scripted vehicle moves in straight
lines between timed waypoints and faces the way it moves, while a reactive one (a kinematic
bicycle) faces a little off its motion when it steers; so each world step ``t`` gets two
waypoints: the recorded position at ``t`` and, half a step later, the point the vehicle reaches
from there along its recorded heading at its recorded speed. The world samples every
participant only at its steps, where the replay then has the recorded position, heading and
speed (to rounding) - but before the first world step: DeFT-Gym's scripted vehicles are placed at
the steps and stand still until the first one, so a vehicle moving at t = 0 would be seen
standing by the first perception frame and predicted static for a second (``static_hold``); it
enters the replay at the first world step instead, so that only that first frame (before any step)
misses it. A static object an adversary added mid-run comes back as a standing scripted
vehicle of its size from then (a scenario's static objects are there from the start); for a
parked vehicle that is the same to the planner, a cone is then called a vehicle (a wider berth).
``reactive=True`` brings reactive participants back as they were (their scenario entry, from the
file's DeFT-Gym description): a rerun then simulates them again, as the original did. What does
not come back at all: a vehicle's future beyond the recorded end.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.export.episode import Actor

MOVING_SPEED = 1e-3  #: [m/s] a vehicle this fast at t = 0 enters the replay at the first world step
STANDING_SPEED = 1e-4  #: [m/s] the half-step point of a standing vehicle (so the replay keeps its heading)
MATCH_TOL = 1e-3  #: [m] the scenario's ego (from the file's properties) is used where it starts this close


def replay_waypoints(rows: np.ndarray, dt: float) -> list[dict[str, float]]:
    """Timed waypoints ``{t, x, y}`` (world frame) under which a scripted vehicle has, at each
    row's time, the row's position, heading and speed (see the module docstring)."""
    out: list[dict[str, float]] = []
    for i, (t, x, y, h, v) in enumerate(rows):
        t, x, y, h, v = float(t), float(x), float(y), float(h), float(v)
        out.append({"t": t, "x": x, "y": y, **({"heading": h} if i == 0 else {})})  # the heading before it moves
        gap = (float(rows[i + 1, 0]) - t) if i + 1 < len(rows) else dt
        half = min(dt, gap) / 2
        if half <= 0:
            continue
        speed = v if abs(v) > STANDING_SPEED else STANDING_SPEED
        out.append({"t": t + half, "x": x + speed * half * math.cos(h), "y": y + speed * half * math.sin(h)})
    return out


def participant_spec(a: Actor, dt: float, recorded: dict[str, Any] | None = None) -> dict[str, Any]:
    """The scenario entry of one imported participant; ``recorded``: its scenario entry as the
    file's description has it (a reactive vehicle's), used instead of its trajectory."""
    if recorded is not None:
        return dict(recorded)
    if a.kind == "static" and a.appear <= 1e-9:
        _t, x, y, h, _ = (float(v) for v in a.rows[0])
        return {"id": a.id, "type": "static", "x": x, "y": y, "heading": h,
                "obstacle": a.obstacle if a.obstacle in ("CONE", "STATIC_VEHICLE") else "STATIC_VEHICLE",
                "length": a.length, "width": a.width}
    # a moving participant, or a static one added mid-run (a scenario's static objects are there
    # from the start): a scripted vehicle from when it appeared
    rows = a.rows if a.kind != "static" else a.rows[:1]
    if len(rows) > 1 and rows[0, 0] <= 1e-9 and abs(rows[0, 4]) > MOVING_SPEED:
        rows = rows[1:]  # moving at t = 0: it enters at the first world step (see the module docstring)
    return {"id": a.id, "type": "scripted", "length": a.length, "width": a.width,
            "waypoints": replay_waypoints(rows, dt)}


def scenario_data(meta: dict[str, Any], ego: Actor, participants: list[Actor], dt: float,
                  end_time: float | None, name: str | None = None, reactive: bool = False) -> dict[str, Any]:
    """A scenario (plain data, :func:`deft_gym.scenarios.scenario.scenario_from_dict`) from an
    imported episode: ``meta`` the file's DeFT-Gym description (:meth:`ExportEpisode.meta`);
    ``reactive``: reactive participants come back reactive (their scenario entry from the
    description) instead of replaying their trajectories."""
    from deft_gym.scenarios.scenario import pose_xyh
    from deft_gym.world.roadmap import shared_roadmap

    if not meta.get("map"):
        raise ValueError("the file carries no DeFT-Gym map description (not a DeFT-Gym export); "
                         "a scenario needs one of the map families (docs/interop.md)")
    if not len(ego.rows):
        raise ValueError("the file has no start pose for the ego")
    roadmap = shared_roadmap(meta["map"])
    _t0, x0, y0, h0, v0 = (float(v) for v in ego.rows[0])
    ego_spec = dict(meta.get("ego") or {})
    if not ego_spec.get("destination"):
        raise ValueError("the file does not say where the ego was going (its destination)")
    kept = False
    if ego_spec.get("lane") is not None or ego_spec.get("x") is not None:
        from deft_gym.scenarios.scenario import Pose

        pose = Pose.model_validate({k: ego_spec[k] for k in ("lane", "s", "d", "x", "y", "heading") if k in ego_spec})
        xy, h = pose_xyh(roadmap, pose)
        kept = math.hypot(xy[0] - x0, xy[1] - y0) < MATCH_TOL and abs(math.remainder(h - h0, math.tau)) < MATCH_TOL
    if not kept:
        ego_spec = {"x": x0, "y": y0, "heading": h0, "destination": ego_spec["destination"],
                    **({"cruise_speed": ego_spec["cruise_speed"]} if ego_spec.get("cruise_speed") else {})}
    ego_spec["speed"] = max(0.0, v0) if not kept else ego_spec.get("speed", max(0.0, v0))
    duration = float(meta.get("duration") or ((end_time or 40.0) + 1.0))
    recorded = {p["id"]: p["spec"] for p in meta.get("participants") or [] if p.get("spec")}
    data: dict[str, Any] = {
        "name": name or f"{meta.get('scenario_name', 'imported')}-import",
        "description": f"imported from an export of {meta.get('scenario_name', '?')} ({meta.get('failure') or meta.get('outcome')}"
                       + (f", jitter seed {meta['jitter_seed']}" if meta.get("jitter_seed") is not None else "") + ")",
        "map": meta["map"], "ego": ego_spec,
        "participants": [participant_spec(a, dt, recorded.get(a.id) if reactive else None)
                         for a in participants if len(a.rows)],
        "duration": duration, "seed": int(meta.get("scenario_seed", 0)),
        "stuck_time": float(meta.get("stuck_time", 30.0))}
    if meta.get("lights"):
        data["lights"] = meta["lights"]
    return data


def import_file(path: Path | str, reactive: bool = False) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(scenario data, meta)`` of an exported ``.xosc`` or CommonRoad ``.xml`` (``reactive``:
    see :func:`scenario_data`)."""
    path = Path(path)
    if path.suffix == ".xosc":
        from deft_gym.export.openscenario import read_xosc

        got = read_xosc(path)
        meta = got["meta"]
        if got["xodr"] is not None and Path(got["xodr"]).exists():
            from deft_gym.export.opendrive import read_map_spec

            spec = read_map_spec(got["xodr"])
            if spec is not None and meta.get("map") and _spec(spec) != _spec(meta["map"]):
                raise ValueError(f"{path}: its road network ({got['xodr']}) is not the map its properties name")
            if spec is not None and not meta.get("map"):
                meta["map"] = spec
        actors = got["actors"]
        end = got["end_time"]
    elif path.suffix == ".xml":
        from deft_gym.export.commonroad import read_commonroad

        got = read_commonroad(path)
        meta, actors, end = got["meta"], got["actors"], got["end_time"]
    else:
        raise ValueError(f"{path}: expected an OpenSCENARIO .xosc or a CommonRoad .xml file")
    ego = next((a for a in actors if a.kind == "ego"), None)
    if ego is None:
        raise ValueError(f"{path}: no ego in the file")
    parts = [a for a in actors if a is not ego]
    order = [p["id"] for p in meta.get("participants") or []]
    parts.sort(key=lambda a: order.index(a.id) if a.id in order else len(order))
    dt = float(meta.get("dt") or _median_step(ego.rows))
    return scenario_data(meta, ego, parts, dt, end, reactive=reactive), meta


def _spec(spec: dict[str, Any]) -> dict[str, Any]:
    from deft_gym.world.roadmap import MapSpec

    return MapSpec.model_validate(spec).model_dump()


def _median_step(rows: np.ndarray) -> float:
    return float(np.median(np.diff(rows[:, 0]))) if len(rows) > 1 else 0.05
