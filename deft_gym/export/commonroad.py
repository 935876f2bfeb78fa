"""CommonRoad XML (format 2020a) of an episode with ``commonroad-io``, its reader, and the
drivability checker's collision test.

What the file holds (export frame of :mod:`.network`; time step = the world step):

- the lanelet network: one lanelet per lane of the map (left, centre and right polylines; arcs
  sampled every metre), predecessors and successors, left and right neighbours (the same road:
  same direction; the two directions of an intersection approach: opposite), line markings
  from the map's line types, lanelet types (intersection, highway, exit ramp, urban), the speed
  limit as a ``MAX_SPEED`` traffic sign, each approach's stop line and traffic light with its
  cycle (``time_offset`` from the plan's offset), and the intersection (incomings with their
  left, straight and right successors);
- every participant as an obstacle with its size (a rectangle): a static object present from
  the start as a static obstacle (a cone as a construction zone, a parked vehicle as a parked
  vehicle); every other one as a dynamic obstacle with its recorded trajectory at every step
  (position, orientation, velocity), from the step it appeared;
- the ego's planning problem: its start (position, orientation, speed) and a goal region from the
  route - the destination with the radius the episode oracle counts as reached, on the
  destination lane's lanelet, within the scenario's duration;
- a leading XML comment ``deft_gym: {...}`` (:meth:`~.episode.ExportEpisode.meta`) with what the
  way back needs (CommonRoad readers skip comments).

:func:`first_collision_step` asks the drivability checker (``commonroad-drivability-checker``)
when a trajectory of the ego first collides with the file's obstacles.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.export.episode import Actor, ExportEpisode
from deft_gym.export.network import lane_polyline

OBSTACLE_ID0 = 1000  #: obstacle id of perception id 0 (participant i is OBSTACLE_ID0 + i + 1)
SIGN_ID0, LIGHT_ID0, INTERSECTION_ID0, INCOMING_ID0 = 500, 600, 700, 800
PLANNING_PROBLEM_ID = 2000
DECIMALS = 10  #: decimals the file keeps (commonroad-io's default of 4 would round to 0.1 mm)
META_PREFIX = "deft_gym: "
HOLD_DISTANCE = 10_000.0  #: [m] where an obstacle that appears later waits (below the map) before it appears
REACH_RADIUS = 3.0  #: [m] the episode oracle's destination radius (deft_gym.sim.oracles.EpisodeOracle)


def _lanelet_ids(roadmap: Any) -> dict[tuple[str, str, int], int]:
    return {tuple(lid): i + 1 for i, lid in enumerate(roadmap.lane_ids)}


def _marking(line_type: int) -> Any:
    from commonroad.scenario.lanelet import LineMarking

    return {1: LineMarking.DASHED, 2: LineMarking.SOLID, 3: LineMarking.SOLID}.get(int(line_type), LineMarking.NO_MARKING)


def lanelet_network(roadmap: Any, lights: dict[str, Any] | None, dt: float) -> Any:
    """The CommonRoad ``LaneletNetwork`` of ``roadmap`` (see the module docstring)."""
    from commonroad.scenario.intersection import Intersection, IntersectionIncomingElement
    from commonroad.scenario.lanelet import (
        Lanelet,
        LaneletNetwork,
        LaneletType,
        LineMarking,
        StopLine,
    )
    from commonroad.scenario.traffic_light import (
        TrafficLight,
        TrafficLightCycle,
        TrafficLightCycleElement,
        TrafficLightState,
    )
    from commonroad.scenario.traffic_sign import (
        TrafficSign,
        TrafficSignElement,
        TrafficSignIDZamunda,
    )

    ids = _lanelet_ids(roadmap)
    preds: dict[int, list[int]] = {i: [] for i in ids.values()}
    for lid, succ in roadmap.successors.items():
        for s in succ:
            preds[ids[tuple(s)]].append(ids[tuple(lid)])
    # speed limits: one virtual MAX_SPEED sign per value, on the lanelets that have it
    speeds: dict[float, list[int]] = {}
    for lid in roadmap.lane_ids:
        speeds.setdefault(float(roadmap.lanes[lid].speed_limit or roadmap.spec.speed_limit), []).append(ids[tuple(lid)])
    signs, sign_of = [], {}
    for n, (v, lanelets) in enumerate(sorted(speeds.items())):
        first = lane_polyline(roadmap, roadmap.lane_ids[lanelets[0] - 1])[0]
        signs.append(TrafficSign(SIGN_ID0 + n, [TrafficSignElement(TrafficSignIDZamunda.MAX_SPEED, [repr(v)])],
                                 set(lanelets), np.array(first), virtual=True))
        for i in lanelets:
            sign_of[i] = SIGN_ID0 + n
    # lights: one per light id, at its stop lines' right end
    light_objs, light_of = [], {}
    if roadmap.stop_lines:
        from deft_gym.world.traffic_lights import LightPlan, TrafficLights

        tl = TrafficLights(roadmap.light_groups, LightPlan.model_validate(lights or {}))
        p = tl.plan
        steps = lambda s: round(s / dt)  # noqa: E731
        for n, light in enumerate(sorted(roadmap.light_groups)):
            g = roadmap.light_groups[light]
            elems = [TrafficLightCycleElement(TrafficLightState.GREEN, steps(p.green))]
            if p.yellow > 0:
                elems.append(TrafficLightCycleElement(TrafficLightState.YELLOW, steps(p.yellow)))
            elems.append(TrafficLightCycleElement(TrafficLightState.RED, steps(tl.cycle - p.green - p.yellow)))
            offset = steps((g * tl.half - p.offset) % tl.cycle) % sum(e.duration for e in elems)
            lines = [sl for sl in roadmap.stop_lines if sl.light_id == light]
            last = max(lines, key=lambda sl: sl.lane[2])
            g_l = roadmap.geom(last.lane)
            x, y = (float(v) for v in g_l.xy(np.array(last.s), g_l.width / 2))
            light_objs.append(TrafficLight(LIGHT_ID0 + n, np.array([x, -y]), TrafficLightCycle(elems, offset)))
            light_of[light] = LIGHT_ID0 + n
    stop_of = {tuple(sl.lane): sl for sl in roadmap.stop_lines}
    lanelets = []
    for lid in roadmap.lane_ids:
        i = ids[tuple(lid)]
        g = roadmap.geom(lid)
        w = g.width
        hw = roadmap.lanes[lid]
        left, centre, right = (lane_polyline(roadmap, lid, d) for d in (-w / 2, 0.0, w / 2))
        a, b, k = lid
        n_road = len(roadmap.road_lanes((a, b)))
        adj_l = ids[(a, b, k - 1)] if k > 0 else None
        adj_r = ids[(a, b, k + 1)] if k + 1 < n_road else None
        same_l = True if adj_l else None
        if adj_l is None:
            adj_l = _opposite(roadmap, lid, ids)
            same_l = False if adj_l else None
        kinds = set()
        if (a, b) in roadmap.junction_roads:
            kinds.add(LaneletType.INTERSECTION if roadmap.spec.type == "intersection" else
                      LaneletType.EXIT_RAMP if roadmap.spec.type == "highway" else LaneletType.URBAN)
        elif roadmap.spec.type == "highway":
            kinds.add(LaneletType.EXIT_RAMP if (a, b) == ("x", "y") else LaneletType.HIGHWAY)
        else:
            kinds.add(LaneletType.URBAN)
        stop = None
        lights_here: set[int] = set()
        if tuple(lid) in stop_of:
            sl = stop_of[tuple(lid)]
            p0 = g.xy(np.array(sl.s), -w / 2)
            p1 = g.xy(np.array(sl.s), w / 2)
            lights_here = {light_of[sl.light_id]} if sl.light_id in light_of else set()
            stop = StopLine(np.array([p0[0], -p0[1]]), np.array([p1[0], -p1[1]]), LineMarking.SOLID,
                            traffic_light_ref=set(lights_here))
        lanelets.append(Lanelet(left, centre, right, i, predecessor=preds[i],
                                successor=[ids[tuple(s)] for s in roadmap.successors[lid]],
                                adjacent_left=adj_l, adjacent_left_same_direction=same_l,
                                adjacent_right=adj_r, adjacent_right_same_direction=True if adj_r else None,
                                line_marking_left_vertices=_marking(hw.line_types[0]),
                                line_marking_right_vertices=_marking(hw.line_types[1]),
                                stop_line=stop, lanelet_type=kinds, traffic_signs={sign_of[i]},
                                traffic_lights=lights_here or None))
    net = LaneletNetwork()
    for ll in lanelets:
        net.add_lanelet(ll)
    for s in signs:
        net.add_traffic_sign(s, set())
    for t in light_objs:
        net.add_traffic_light(t, set())
    if roadmap.spec.type == "intersection":
        incomings = []
        for n, road in enumerate(sorted({tuple(sl.lane[:2]) for sl in roadmap.stop_lines})):
            lanes = roadmap.road_lanes(road)
            turns: dict[str, set[int]] = {"left": set(), "straight": set(), "right": set()}
            for lid in lanes:
                for s in roadmap.successors[lid]:
                    turns[_turn(roadmap, lid, s)].add(ids[tuple(s)])
            incomings.append(IntersectionIncomingElement(INCOMING_ID0 + n, {ids[tuple(lid)] for lid in lanes},
                                                         turns["right"], turns["straight"], turns["left"]))
        net.add_intersection(Intersection(INTERSECTION_ID0, incomings))
    return net


def _turn(roadmap: Any, lane: Any, succ: Any) -> str:
    """left / straight / right of a junction lane, in the export frame (the world's mirror)."""
    g = roadmap.geom(succ)
    dh = float(g.heading(np.array(g.length)) - g.heading(np.array(0.0)))
    dh = -math.atan2(math.sin(dh), math.cos(dh))  # mirrored: left is positive
    return "straight" if abs(dh) < 0.3 else ("left" if dh > 0 else "right")


def _opposite(roadmap: Any, lid: Any, ids: dict[Any, int]) -> int | None:
    """The lane of the opposite direction whose left edge is this lane's left edge (the two
    directions of an intersection approach), or None."""
    if tuple(lid[:2]) in roadmap.junction_roads:
        return None
    g = roadmap.geom(lid)
    mine = g.xy(np.array([0.0, g.length]), -g.width / 2)
    for other in roadmap.lane_ids:
        if other[2] != 0 or other[:2] == lid[:2] or tuple(other[:2]) in roadmap.junction_roads:
            continue
        go = roadmap.geom(other)
        theirs = go.xy(np.array([go.length, 0.0]), -go.width / 2)
        if np.max(np.abs(mine - theirs)) < 1e-6:
            return ids[tuple(other)]
    return None


def _state(cls: Any, step: int, row: Any, **extra: Any) -> Any:
    _, x, y, h, v = (float(u) for u in row)
    return cls(time_step=step, position=np.array([x, -y]), orientation=-h, velocity=v, **extra)


def _obstacle(a: Actor, num: int, dt: float, end_step: int) -> Any:
    from commonroad.geometry.shape import Rectangle
    from commonroad.prediction.prediction import TrajectoryPrediction
    from commonroad.scenario.obstacle import DynamicObstacle, ObstacleType, StaticObstacle
    from commonroad.scenario.state import CustomState, InitialState
    from commonroad.scenario.trajectory import Trajectory

    kind = {"CONE": ObstacleType.CONSTRUCTION_ZONE, "STATIC_VEHICLE": ObstacleType.PARKED_VEHICLE}.get(
        a.obstacle, ObstacleType.CAR)
    shape = Rectangle(a.length, a.width)
    steps = np.rint(a.rows[:, 0] / dt).astype(int)
    extra = {"acceleration": 0.0, "yaw_rate": 0.0, "slip_angle": 0.0}
    oid = OBSTACLE_ID0 + num
    if a.kind == "static" and steps[0] == 0:
        return StaticObstacle(oid, kind, shape, _state(InitialState, 0, a.rows[0], **extra))
    rows, st = a.rows, steps
    if a.kind == "static":  # added mid-run: standing from then to the end, a dynamic obstacle's type
        kind = ObstacleType.CAR if a.obstacle == "STATIC_VEHICLE" else ObstacleType.UNKNOWN
        st = np.arange(steps[0], max(end_step, steps[0] + 1) + 1)
        rows = np.repeat(a.rows[:1], len(st), axis=0)
    if st[0] > 0:  # CommonRoad 2020a starts every obstacle at step 0: it waits far away until it appears
        wait = np.repeat(a.rows[:1], st[0], axis=0)
        wait[:, 2] += HOLD_DISTANCE  # world y: HOLD_DISTANCE below the map in the export frame
        wait[:, 4] = 0.0
        rows = np.concatenate([wait, rows])
        st = np.concatenate([np.arange(st[0]), st])
    init = _state(InitialState, int(st[0]), rows[0], **extra)
    states = [_state(CustomState, int(k), r) for k, r in zip(st[1:], rows[1:])]
    if not states:  # present for one step only: stand there one more
        states = [_state(CustomState, int(st[0]) + 1, rows[0])]
    return DynamicObstacle(oid, kind, shape, init, TrajectoryPrediction(Trajectory(int(st[0]) + 1, states), shape))


def scenario_and_problem(e: ExportEpisode) -> tuple[Any, Any]:
    """The CommonRoad ``Scenario`` and ``PlanningProblemSet`` of ``e``."""
    from commonroad.common.util import Interval
    from commonroad.geometry.shape import Circle
    from commonroad.planning.goal import GoalRegion
    from commonroad.planning.planning_problem import PlanningProblem, PlanningProblemSet
    from commonroad.scenario.scenario import Location, Scenario, ScenarioID, Tag
    from commonroad.scenario.state import CustomState, InitialState

    from deft_gym.scenarios.scenario import Destination, destination_xy

    dt = e.dt
    rm = e.roadmap
    name = re.sub(r"[^A-Za-z0-9]+", "", e.name.title()) or "DeftGym"
    sid = ScenarioID(country_id="ZAM", map_name=name[:40], map_id=1, configuration_id=1, obstacle_behavior="T",
                     prediction_id=1)
    tags = {Tag.CRITICAL, Tag.SIMULATED} | ({Tag.INTERSECTION, Tag.URBAN} if rm.spec.type == "intersection" else
                                          {Tag.HIGHWAY} if rm.spec.type == "highway" else {Tag.URBAN})
    if rm.spec.lanes > 1:
        tags.add(Tag.MULTI_LANE)
    sc = Scenario(dt, sid, author="DeFT-Gym", tags=tags, affiliation="DeFT-Gym",
                  source=f"DeFT-Gym export: {e.summary()}", location=Location())
    sc.add_objects(lanelet_network(rm, e.lights, dt))
    end_step = round(e.sim_time / dt)
    for i, a in enumerate(e.participants):
        if len(a.rows):
            sc.add_objects(_obstacle(a, i + 1, dt, end_step))
    ego0 = e.ego.rows[0]
    init = _state(InitialState, 0, ego0, acceleration=0.0, yaw_rate=0.0, slip_angle=0.0)
    dest = Destination.model_validate(e.scenario["ego"]["destination"])
    xy, _ = destination_xy(rm, dest)
    horizon = round(float(e.scenario.get("duration", 40.0)) / dt)
    goal = GoalRegion([CustomState(time_step=Interval(0, horizon),
                                   position=Circle(REACH_RADIUS, np.array([float(xy[0]), -float(xy[1])])))],
                      {0: [_lanelet_ids(rm)[tuple(dest.lane)]]})
    problems = PlanningProblemSet([PlanningProblem(PLANNING_PROBLEM_ID, init, goal)])
    return sc, problems


def write_commonroad(e: ExportEpisode, path: Path | str) -> Path:
    """Write ``e`` as CommonRoad XML to ``path`` (with the DeFT-Gym comment)."""
    from commonroad.common.file_writer import CommonRoadFileWriter, OverwriteExistingFile

    from deft_gym.files import write_atomic

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sc, problems = scenario_and_problem(e)
    tmp = path.with_name(path.name + ".cr.tmp")
    CommonRoadFileWriter(sc, problems, author="DeFT-Gym", affiliation="DeFT-Gym", source=sc.source, tags=sc.tags,
                         location=sc.location, decimal_precision=DECIMALS).write_to_file(str(tmp), OverwriteExistingFile.ALWAYS)
    text = tmp.read_text()
    tmp.unlink()
    comment = "<!-- " + META_PREFIX + json.dumps(e.meta(), sort_keys=True).replace("--", "- -") + " -->\n"
    head, sep, rest = text.partition("?>")
    text = (head + sep + "\n" + comment + rest.lstrip("\n")) if sep else comment + text
    write_atomic(path, text)
    return path


# -- reading ----------------------------------------------------------------------------------------
def read_meta(path: Path | str) -> dict[str, Any]:
    """The DeFT-Gym comment of an exported CommonRoad file ({} when there is none)."""
    text = Path(path).read_text()
    m = re.search(r"<!-- " + re.escape(META_PREFIX) + r"(.*?) -->", text, re.S)
    if not m:
        return {}
    return json.loads(m.group(1).replace("- -", "--"))


def read_commonroad(path: Path | str) -> dict[str, Any]:
    """An exported CommonRoad file back (read with ``commonroad-io``): ``{"meta", "end_time",
    "actors", "scenario", "problems"}``, actors in the world frame; the ego's only row is its
    planning problem's initial state."""
    from commonroad.common.file_reader import CommonRoadFileReader

    sc, problems = CommonRoadFileReader(str(path)).open()
    meta = read_meta(path)
    dt = float(sc.dt)
    names = [p["id"] for p in meta.get("participants") or []]
    info = {p["id"]: p for p in meta.get("participants") or []}
    actors: list[Actor] = []
    for ob in sorted(sc.obstacles, key=lambda o: o.obstacle_id):
        i = ob.obstacle_id - OBSTACLE_ID0 - 1
        name = names[i] if 0 <= i < len(names) else f"obstacle{ob.obstacle_id}"
        states = [ob.initial_state]
        traj = getattr(getattr(ob, "prediction", None), "trajectory", None)
        if traj is not None:
            states += list(traj.state_list)
        rows = np.array([_row(s, dt) for s in states], float)
        # the rows far below the map are the wait before it appears
        rows = rows[np.abs(rows[:, 2] - rows[-1, 2]) < HOLD_DISTANCE / 2]
        kind = info.get(name, {}).get("kind") or ("static" if ob.obstacle_type.value in ("parkedVehicle",
                                                                                      "constructionZone") else "scripted")
        obstacle = info.get(name, {}).get("obstacle") or {"parkedVehicle": "STATIC_VEHICLE",
                                                           "constructionZone": "CONE"}.get(ob.obstacle_type.value,
                                                                                           "VEHICLE")
        a = Actor(name, kind, obstacle, float(ob.obstacle_shape.length), float(ob.obstacle_shape.width), rows)
        if rows[0, 0] > 0:
            a.added = float(rows[0, 0])
        actors.append(a)
    pp = next(iter(problems.planning_problem_dict.values()))
    ego_size = (meta.get("ego_size") or {})
    ego = Actor("ego", "ego", "EGO", float(ego_size.get("length", 4.8)), float(ego_size.get("width", 2.0)),
                np.array([_row(pp.initial_state, dt)], float))
    end = meta.get("sim_time")
    return {"meta": meta, "end_time": end, "actors": [ego, *actors], "scenario": sc, "problems": problems}


def _row(state: Any, dt: float) -> tuple[float, float, float, float, float]:
    x, y = (float(v) for v in state.position)
    v = float(getattr(state, "velocity", 0.0) or 0.0)
    return state.time_step * dt, x, -y, -float(state.orientation), v


# -- the drivability checker -------------------------------------------------------------------------
def first_collision_step(scenario: Any, ego_rows: np.ndarray, length: float, width: float,
                         dt: float) -> int | None:
    """The first time step at which the ego (``rows`` ``(t, x, y, heading, ...)``, world frame)
    collides with an obstacle of the CommonRoad ``scenario``, by CommonRoad's drivability
    checker (``commonroad_dc``); None if it never does."""
    from commonroad_dc import pycrcc
    from commonroad_dc.collision.collision_detection.pycrcc_collision_dispatch import (
        create_collision_checker,
    )

    cc = create_collision_checker(scenario)
    for t, x, y, h, *_ in ego_rows:
        k = round(float(t) / dt)
        box = pycrcc.RectOBB(length / 2, width / 2, -float(h), float(x), -float(y))
        if cc.time_slice(k).collide(box):
            return k
    return None

