"""ASAM OpenSCENARIO 1.2 of an episode (``scenariogeneration``'s ``xosc``), and its reader.

What the file holds (all in the export frame of :mod:`.network`, the reference point of every
entity its geometric centre):

- the road network: the ``.xodr`` beside it (:mod:`.opendrive`), and the light plan as a traffic
  signal controller whose phases cover one cycle from t = 0 (states ``red;yellow;green`` lamps,
  e.g. ``off;off;on`` green) for the OpenDRIVE signals of every approach;
- the ego and every participant with its size (a vehicle, or a cone as a misc object), kind and
  perception type as properties;
- ``Init``: each entity present at t = 0 teleported to its start pose at its start speed;
- one story: for every entity that appears later an ``AddEntityAction`` at that time, and for
  every entity that moves a ``FollowTrajectoryAction`` along what it did - a polyline with a
  vertex at every world step and absolute times (time reference ``absolute``, following mode
  ``position``: a replay, not a controller's target);
- a stop trigger at the episode's end;
- the failure (collision time, participant and place; or the non-optimal decision's root cause)
  in the file header's description and properties, with everything the way back needs
  (property ``deft_gym``, JSON: :meth:`~.episode.ExportEpisode.meta`).

:func:`read_xosc` reads such a file back into actors and the episode's description.
"""

from __future__ import annotations

import itertools
import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.export.episode import Actor, ExportEpisode
from deft_gym.export.network import Network, build_network

META_PROPERTY = "deft_gym"  #: file header property holding :meth:`ExportEpisode.meta` (JSON)
LAMPS = {"RED": "on;off;off", "YELLOW": "off;on;off", "GREEN": "off;off;on"}  #: red;yellow;green lamps
HEIGHT = {"EGO": 1.5, "VEHICLE": 1.5, "STATIC_VEHICLE": 1.5, "CONE": 0.6}


def light_phases(plan: dict[str, Any], groups: dict[str, int]) -> list[tuple[float, dict[str, str]]]:
    """One cycle of the light plan from t = 0 as ``(duration [s], {light id: colour})`` phases
    (consecutive instants where no light changes colour)."""
    from deft_gym.world.traffic_lights import LightPlan, TrafficLights

    lights = TrafficLights(groups, LightPlan.model_validate(plan or {}))
    p, cycle = lights.plan, lights.cycle
    edges = {0.0, cycle}
    for g in set(groups.values()):
        for e in (p.green, p.green + p.yellow, cycle):
            edges.add((e - p.offset + g * lights.half) % cycle)
    times = sorted(edges)
    out = []
    for a, b in itertools.pairwise(times):
        if b - a > 1e-9:
            mid = (a + b) / 2
            out.append((b - a, {lid: lights.color(lid, mid) for lid in sorted(groups)}))
    return out


def _entity(xosc: Any, a: Actor) -> Any:
    h = HEIGHT.get(a.obstacle, 1.5)
    bb = xosc.BoundingBox(a.width, a.length, h, 0.0, 0.0, h / 2)
    if a.obstacle == "CONE":
        obj = xosc.MiscObject(a.id, 1.0, xosc.MiscObjectCategory.obstacle, bb)
    else:
        front = xosc.Axle(0.6, 0.7, a.width * 0.85, a.length * 0.3, 0.35)
        rear = xosc.Axle(0.0, 0.7, a.width * 0.85, -a.length * 0.3, 0.35)
        obj = xosc.Vehicle(a.id, xosc.VehicleCategory.car, bb, front, rear, 40.0, 10.0, 10.0)
    obj.add_property("deft_gym:kind", a.kind)
    obj.add_property("deft_gym:obstacle", a.obstacle)
    return obj


def _pos(xosc: Any, row: Any) -> Any:
    _t, x, y, h, _ = (float(v) for v in row)
    return xosc.WorldPosition(x, -y, 0.0, -h)


def _at(xosc: Any, name: str, t: float) -> Any:
    return xosc.ValueTrigger(name, 0, xosc.ConditionEdge.none,
                             xosc.SimulationTimeCondition(float(t), xosc.Rule.greaterOrEqual))


def _description(e: ExportEpisode) -> str:
    text = f"DeFT-Gym failure: {e.summary()}"
    if e.verdict and e.verdict.get("signature"):
        text += f"; root cause {e.verdict['signature']}"
    return text


def scenario(e: ExportEpisode, xodr_name: str, net: Network | None = None) -> Any:
    """The ``xosc.Scenario`` of ``e`` with its road network in ``xodr_name`` (a path relative to
    the ``.xosc``)."""
    from scenariogeneration import xosc

    net = net or build_network(e.roadmap)
    road = xosc.RoadNetwork(roadfile=xodr_name)
    if e.lights is not None and net.signals:
        ctrl = xosc.TrafficSignalController("lights")
        ids = {s.light_id: str(s.id) for s in net.signals if s.kind == "light"}
        for i, (dur, colours) in enumerate(light_phases(e.lights, e.roadmap.light_groups)):
            ph = xosc.Phase(f"phase{i}: " + ", ".join(f"{k} {v.lower()}" for k, v in colours.items()), dur)
            for lid, colour in colours.items():
                if lid in ids:
                    ph.add_signal_state(ids[lid], LAMPS[colour])
            ctrl.add_phase(ph)
        road.add_traffic_signal_controller(ctrl)
    entities = xosc.Entities()
    init = xosc.Init()
    story = xosc.Story("replay")
    act = xosc.Act("what happened", _at(xosc, "episode start", 0.0))
    actors = [e.ego, *e.participants]
    for a in actors:
        entities.add_scenario_object(a.id, _entity(xosc, a))
        if not len(a.rows):
            continue
        late = a.appear > 1e-9
        if not late:
            init.add_init_action(a.id, xosc.TeleportAction(_pos(xosc, a.rows[0])))
            if a.obstacle != "CONE":
                init.add_init_action(a.id, xosc.AbsoluteSpeedAction(float(a.rows[0, 4]), xosc.TransitionDynamics(
                    xosc.DynamicsShapes.step, xosc.DynamicsDimension.time, 0.0)))
        man = xosc.Maneuver(f"{a.id} replay")
        if late:
            ev = xosc.Event(f"{a.id} appears", xosc.Priority.parallel)
            ev.add_action(f"add {a.id}", xosc.AddEntityAction(a.id, _pos(xosc, a.rows[0])))
            ev.add_trigger(_at(xosc, f"{a.id} appears at {a.appear:g} s", a.appear))
            man.add_event(ev)
        if a.moves or (a.kind != "static" and len(a.rows) > 1):
            traj = xosc.Trajectory(f"{a.id} trajectory", False)
            traj.add_shape(xosc.Polyline([float(t) for t in a.rows[:, 0]], [_pos(xosc, r) for r in a.rows]))
            ev = xosc.Event(f"{a.id} follows its trajectory", xosc.Priority.parallel)
            ev.add_action(f"{a.id} trajectory", xosc.FollowTrajectoryAction(
                traj, xosc.FollowingMode.position, xosc.ReferenceContext.absolute, 1.0, 0.0))
            ev.add_trigger(_at(xosc, f"{a.id} starts at {a.appear:g} s", a.appear))
            man.add_event(ev)
        if man.events:
            mg = xosc.ManeuverGroup(f"{a.id}")
            mg.add_actor(a.id)
            mg.add_maneuver(man)
            act.add_maneuver_group(mg)
    story.add_act(act)
    stop = xosc.ValueTrigger("episode end", 0, xosc.ConditionEdge.none,
                             xosc.SimulationTimeCondition(float(e.sim_time), xosc.Rule.greaterOrEqual), "stop")
    sb = xosc.StoryBoard(init, stop)
    sb.add_story(story)
    props = xosc.Properties()
    props.add_property("deft_gym:failure", str(e.failure or "none"))
    props.add_property("deft_gym:outcome", e.outcome)
    props.add_property("deft_gym:end_time", repr(float(e.sim_time)))
    if e.collision:
        for k in ("participant", "time", "x", "y", "ego_speed"):
            v = e.collision.get(k)
            if k in ("x", "y") and v is not None:
                v = float(v) if k == "x" else -float(v)  # the export frame
            props.add_property(f"deft_gym:collision.{k}", str(v))
    if e.jitter_seed is not None:
        props.add_property("deft_gym:jitter_seed", str(e.jitter_seed))
    props.add_property(META_PROPERTY, json.dumps(e.meta(), sort_keys=True))
    return xosc.Scenario(e.name, "DeFT-Gym", xosc.ParameterDeclarations(), entities, sb, road, xosc.Catalog(),
                         osc_minor_version=2, header_properties=props)


def write_xosc(e: ExportEpisode, path: Path | str, xodr_path: Path | str) -> Path:
    """Write ``e`` as OpenSCENARIO to ``path`` referring to the OpenDRIVE file ``xodr_path`` (by
    its path relative to ``path``)."""
    import os

    from deft_gym.files import write_atomic

    path, xodr_path = Path(path), Path(xodr_path)
    rel = os.path.relpath(xodr_path, path.parent)
    root = scenario(e, rel).get_element()
    header = root.find("FileHeader")
    if header is not None:
        header.set("description", _description(e))
    ET.indent(root)
    write_atomic(path, b'<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="utf-8"))
    return path


# -- reading ----------------------------------------------------------------------------------------
def _world(pos: ET.Element | None) -> tuple[float, float, float]:
    """World (highway-env) ``(x, y, heading)`` of an OpenSCENARIO ``Position`` element (a
    ``WorldPosition`` in the export frame)."""
    wp = None if pos is None else pos.find("WorldPosition")
    if wp is None:
        raise ValueError("expected a WorldPosition (this reader reads DeFT-Gym's exports)")
    return float(wp.get("x", 0)), -float(wp.get("y", 0)), -float(wp.get("h", 0) or 0.0)


def speeds(rows: np.ndarray, dt_max: float | None = None) -> np.ndarray:
    """Speeds [m/s] of a trajectory ``(t, x, y, h)``: the distance to the next vertex over the
    time to it, signed by the heading (a world step moves a vehicle by its speed at the step
    times the step), the last vertex keeping the one before."""
    if len(rows) < 2:
        return np.zeros(len(rows))
    d = np.diff(rows[:, 1:3], axis=0)
    dt = np.diff(rows[:, 0])
    v = np.hypot(d[:, 0], d[:, 1]) / dt
    sign = np.sign(d[:, 0] * np.cos(rows[:-1, 3]) + d[:, 1] * np.sin(rows[:-1, 3]))
    v = np.where(sign < 0, -v, v)
    return np.append(v, v[-1])


def read_xosc(path: Path | str) -> dict[str, Any]:
    """An exported ``.xosc`` back: ``{"meta", "xodr", "end_time", "actors"}`` where ``actors``
    are :class:`~.episode.Actor` (world frame; ``rows`` from the start pose or the appearance,
    then every trajectory vertex; speeds from the ``Init`` speed and the vertices)."""
    path = Path(path)
    root = ET.parse(path).getroot()
    meta: dict[str, Any] = {}
    for prop in root.iterfind("FileHeader/Properties/Property"):
        if prop.get("name") == META_PROPERTY:
            meta = json.loads(prop.get("value") or "{}")
    logic = root.find("RoadNetwork/LogicFile")
    xodr = (path.parent / logic.get("filepath", "")).resolve() if logic is not None else None
    actors: dict[str, Actor] = {}
    for so in root.iterfind("Entities/ScenarioObject"):
        name = so.get("name", "")
        obj = so.find("Vehicle")
        if obj is None:
            obj = so.find("MiscObject")
        if obj is None:
            continue
        dims = obj.find("BoundingBox/Dimensions")
        props = {p.get("name"): p.get("value") for p in obj.iterfind("Properties/Property")}
        kind = props.get("deft_gym:kind") or ("static" if obj.tag == "MiscObject" else "scripted")
        obstacle = props.get("deft_gym:obstacle") or ("CONE" if obj.tag == "MiscObject" else "VEHICLE")
        actors[name] = Actor(name, kind, obstacle, float(dims.get("length")), float(dims.get("width")),
                             np.zeros((0, 5)))
    start: dict[str, list[float]] = {}
    for priv in root.iterfind("Storyboard/Init/Actions/Private"):
        ref = priv.get("entityRef", "")
        for pa in priv.iterfind("PrivateAction"):
            tele = pa.find("TeleportAction/Position")
            if tele is not None:
                x, y, h = _world(tele)
                start.setdefault(ref, [0.0, x, y, h, 0.0])[1:4] = [x, y, h]
            sp = pa.find("LongitudinalAction/SpeedAction/SpeedActionTarget/AbsoluteTargetSpeed")
            if sp is not None:
                start.setdefault(ref, [0.0, 0.0, 0.0, 0.0, 0.0])[4] = float(sp.get("value", 0))
    appear: dict[str, list[float]] = {}
    traj: dict[str, np.ndarray] = {}
    for ev in root.iter("Event"):
        cond = ev.find(".//StartTrigger//SimulationTimeCondition")
        t0 = float(cond.get("value", 0)) if cond is not None else 0.0
        for action in ev.iterfind("Action"):
            add = action.find("GlobalAction/EntityAction")
            if add is not None and add.find("AddEntityAction") is not None:
                x, y, h = _world(add.find("AddEntityAction/Position"))
                appear[add.get("entityRef", "")] = [t0, x, y, h, 0.0]
            ft = action.find("PrivateAction/RoutingAction/FollowTrajectoryAction")
            if ft is not None:
                owner = _actor_of(root, ev)
                rows = []
                for v in ft.iterfind(".//Trajectory/Shape/Polyline/Vertex"):
                    x, y, h = _world(v.find("Position"))
                    rows.append((float(v.get("time", 0)), x, y, h))
                if rows:
                    traj[owner] = np.array(rows, float)
    for name, a in actors.items():
        if name in traj:
            r = traj[name]
            v = speeds(r)
            if name in start and abs(r[0, 0]) < 1e-9:
                v[0] = start[name][4]
            a.rows = np.column_stack([r, v])
        elif name in start:
            a.rows = np.array([start[name]], float)
        elif name in appear:
            a.rows = np.array([appear[name]], float)
        if name in appear:
            a.added = appear[name][0]
    stop = root.find("Storyboard/StopTrigger//SimulationTimeCondition")
    end = float(stop.get("value")) if stop is not None else None
    return {"meta": meta, "xodr": xodr, "end_time": end, "actors": list(actors.values())}


def _actor_of(root: ET.Element, event: ET.Element) -> str:
    """The actor of the maneuver group an event belongs to."""
    for mg in root.iter("ManeuverGroup"):
        if any(ev is event for ev in mg.iter("Event")):
            ref = mg.find("Actors/EntityRef")
            return ref.get("entityRef", "") if ref is not None else ""
    return ""


def heading_error(a: float, b: float) -> float:
    return abs(math.atan2(math.sin(a - b), math.cos(a - b)))
