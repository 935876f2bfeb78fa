"""Scenario files: schema, validation against the map, and building the world from them.

A scenario (``configs/scenarios/*.yaml``) names a map, the ego's start and destination, the
participants and a duration. Loading validates everything - unknown keys, wrong types, lanes
that do not exist, positions off the lane, unreachable destinations - and reports each problem
as ``file: field.path: what was expected``.
"""

from __future__ import annotations

import copy
import itertools
import math
from collections import Counter
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, field_validator, model_validator

from deft_gym.config import CONFIG_DIR, ConfigError, load_yaml, validate
from deft_gym.world.geometry import box_gap_point
from deft_gym.world.participants import SIZES, ReactiveVehicle, ScriptedVehicle, StaticObstacle
from deft_gym.world.roadmap import MapSpec, RoadMap, shared_roadmap
from deft_gym.world.traffic_lights import LightPlan, TrafficLights
from deft_gym.world.world import World

SCENARIO_DIR = CONFIG_DIR / "scenarios"


MAX_OFFSET = 50.0  #: largest lateral offset d [m] of a lane position
MIN_GAP = 2.0  #: a participant starting closer [m] to the ego's start lies on it
MIN_DURATION = 1.0  #: the shortest episode [s]: shorter ones end before the planner's first cycle
#: most participants of a scenario: every world step, sensor frame and message handles each one
#: (1000 run at about 3x real time on one core; 5000 at a third of real time)
MAX_PARTICIPANTS = 1000
MAX_SCENARIO_BYTES = 2_000_000  #: largest scenario file (1000 participants take about 90 kB)
MAX_PROBLEMS = 10  #: problems listed per scenario (then how many more)

class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)  # NaN/inf positions are no scenario


class Pose(_Strict):
    """A position either on a lane (``lane``, ``s`` [m], ``d`` [m] to the right) or in world
    coordinates (``x``, ``y`` [m], ``heading`` [rad])."""

    lane: tuple[str, str, int] | None = None
    s: float | None = None
    d: float = Field(default=0.0, ge=-MAX_OFFSET, le=MAX_OFFSET)
    x: float | None = None
    y: float | None = None
    heading: float | None = None

    @model_validator(mode="after")
    def _one_form(self) -> Pose:
        on_lane = self.lane is not None or self.s is not None
        in_world = self.x is not None or self.y is not None
        if on_lane == in_world:
            raise ValueError("give either lane + s (+ d) or x + y (+ heading)")
        if on_lane and (self.lane is None or self.s is None):
            raise ValueError("a lane position needs both 'lane' and 's'")
        if in_world and (self.x is None or self.y is None):
            raise ValueError("a world position needs both 'x' and 'y'")
        return self


class Destination(_Strict):
    lane: tuple[str, str, int]
    s: float | None = Field(default=None, description="default: 10 m before the lane end")


class EgoSpec(Pose):
    speed: float = Field(default=0.0, ge=0.0, le=40.0)
    destination: Destination
    cruise_speed: float | None = Field(default=None, gt=0.0, le=40.0)


class StaticSpec(Pose):
    id: str
    type: Literal["static"]
    obstacle: Literal["CONE", "STATIC_VEHICLE"] = "STATIC_VEHICLE"
    length: float | None = Field(default=None, gt=0.0, le=20.0)
    width: float | None = Field(default=None, gt=0.0, le=5.0)


class Waypoint(Pose):
    t: float = Field(ge=0.0)


class ScriptedSpec(_Strict):
    id: str
    type: Literal["scripted"]
    waypoints: list[Waypoint] = Field(min_length=1)
    length: float = Field(default=4.8, gt=0.0, le=20.0)
    width: float = Field(default=2.0, gt=0.0, le=5.0)

    @model_validator(mode="after")
    def _increasing(self) -> ScriptedSpec:
        ts = [w.t for w in self.waypoints]
        if any(b <= a for a, b in itertools.pairwise(ts)):
            raise ValueError("waypoint times must increase strictly")
        return self


class ReactiveSpec(Pose):
    id: str
    type: Literal["reactive"]
    speed: float = Field(default=8.0, ge=0.0, le=40.0)
    target_speed: float | None = Field(default=None, gt=0.0, le=40.0)
    destination: Destination | None = None
    lane_change: bool = True


ParticipantSpec = Annotated[StaticSpec | ScriptedSpec | ReactiveSpec, Field(discriminator="type")]


class Scenario(_Strict):
    """A system-level scenario test."""

    name: str = Field(min_length=1, max_length=200)
    description: str = ""
    map: MapSpec
    lights: LightPlan | None = None
    ego: EgoSpec
    participants: list[ParticipantSpec] = Field(default_factory=list)
    duration: float = Field(default=40.0, ge=MIN_DURATION, le=600.0)
    seed: int = Field(default=0, ge=0, le=2**32 - 1, description="scenario randomness (sensor noise, NPC behaviour)")
    stuck_time: float = Field(default=30.0, gt=0.0, description="standstill [s] that counts as stuck")

    source: str | None = Field(default=None, exclude=True)

    @field_validator("name")
    @classmethod
    def _folder_name(cls, v: str) -> str:
        """The name names output folders (``runs/run/<name>``): one folder name, never a path."""
        bad = sorted({c for c in v if c in '/\\' or ord(c) < 32 or ord(c) == 127})
        if bad or v in (".", "..") or v.startswith(".") or v != v.strip():
            shown = ", ".join(repr(c) for c in bad) or "a leading dot or space"
            raise ValueError(f"{v[:80]!r} cannot name a folder ({shown}); expected a name such as 'left_turn' "
                             "(no path separators, control characters or leading dot)")
        return v

    @field_validator("participants", mode="before")
    @classmethod
    def _not_too_many(cls, v: Any) -> Any:
        if isinstance(v, list) and len(v) > MAX_PARTICIPANTS:  # before validating each of them
            raise ValueError(f"{len(v)} participants; expected at most {MAX_PARTICIPANTS} "
                             "(deft_gym.scenarios.scenario.MAX_PARTICIPANTS)")
        return v

    @model_validator(mode="after")
    def _unique_ids(self) -> Scenario:
        dup = sorted(i for i, n in Counter(p.id for p in self.participants).items() if n > 1)  # O(n)
        if dup:
            raise ValueError(f"participant ids must be unique, repeated: {dup}")
        return self


# ---------------------------------------------------------------------------------------------
def load_scenario(path: Path | str) -> Scenario:
    """Load, validate and check a scenario YAML against its map."""
    path = Path(path)
    if not path.exists() and not path.suffix and (SCENARIO_DIR / f"{path}.yaml").exists():
        path = SCENARIO_DIR / f"{path}.yaml"
    try:
        size = path.stat().st_size
    except OSError:
        size = 0  # load_yaml names the problem
    if size > MAX_SCENARIO_BYTES:
        raise ConfigError(f"{path}: {size / 1e6:.1f} MB; expected a scenario file of at most "
                          f"{MAX_SCENARIO_BYTES / 1e6:g} MB (at most {MAX_PARTICIPANTS} participants)")
    data = load_yaml(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    sc = scenario_from_dict(data, source=str(path))
    errors = vehicle_overlaps(sc, shared_roadmap(sc.map))
    if errors:
        raise ConfigError("\n".join(f"{path}: {e}" for e in errors))
    return sc


def vehicle_overlaps(sc: Scenario, roadmap: RoadMap, limit: int = MAX_PROBLEMS) -> list[str]:
    """Vehicles (static, scripted and reactive; not cones) present at the start whose boxes
    overlap each other: two cars in one place are no scenario (checked for scenario files; the
    search's own placements are judged by its feasibility rules)."""
    boxes = []
    for i, p in enumerate(sc.participants):
        if isinstance(p, StaticSpec):
            if p.obstacle == "CONE":
                continue
            pose = p
            length, width = (p.length, p.width or SIZES[p.obstacle][1]) if p.length else SIZES[p.obstacle]
        elif isinstance(p, ScriptedSpec):
            pose, length, width = p.waypoints[0], p.length, p.width
            if pose.t > 0:
                continue  # appears later
        else:
            pose, (length, width) = p, SIZES["VEHICLE"]
        xy, h = pose_xyh(roadmap, pose)
        boxes.append((i, p.id, float(xy[0]), float(xy[1]), float(h), float(length), float(width)))
    cell = 25.0  # > the longest diagonal: overlapping boxes share a cell or touch neighbours
    grid: dict[tuple[int, int], list[int]] = {}
    for k, b in enumerate(boxes):
        grid.setdefault((int(b[2] // cell), int(b[3] // cell)), []).append(k)
    errs = []
    for k, (i, pid, x, y, h, length, width) in enumerate(boxes):
        cx, cy = int(x // cell), int(y // cell)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for m in grid.get((cx + dx, cy + dy), ()):
                    if m <= k:
                        continue
                    j, qid, x2, y2, h2, l2, w2 = boxes[m]
                    if box_gap_point(x, y, h, length, width, x2, y2, h2, l2, w2) < 0.0:
                        errs.append(f"participants.{j}: {qid!r} overlaps participants.{i} ({pid!r}) at the start "
                                    "(two vehicles in one place)")
                        if len(errs) >= limit:
                            return errs
    return errs


def scenario_from_dict(data: dict[str, Any], source: str = "<scenario>") -> Scenario:
    """Validate a scenario given as a dict (``source`` names it in errors)."""
    sc = validate(Scenario, data, source)
    sc.source = source
    errors = check_against_map(sc, shared_roadmap(sc.map))
    if errors:
        more = [f"... and {len(errors) - MAX_PROBLEMS} more problem(s)"] if len(errors) > MAX_PROBLEMS else []
        raise ConfigError("\n".join(f"{source}: {e}" for e in errors[:MAX_PROBLEMS] + more))
    return sc


def scenario_to_dict(sc: Scenario) -> dict[str, Any]:
    """Plain-data form of a scenario (what goes into logs and generated tests)."""
    return sc.model_dump(mode="json", exclude_none=True)


def with_participants(sc: Scenario, name: str, specs: list[dict[str, Any]]) -> dict[str, Any]:
    """Plain data of ``sc`` renamed ``name``, with (copies of) ``specs`` appended to its
    participants - a mutated or injected variant, ready for :func:`scenario_from_dict`."""
    data = scenario_to_dict(sc)
    data["name"] = name
    data.setdefault("participants", []).extend(copy.deepcopy(specs))
    return data


def _lane_problem(roadmap: RoadMap, lane: tuple[str, str, int] | None, s: float | None) -> str | None:
    if lane is None:
        return None
    if not roadmap.has_lane(lane):
        known = ", ".join("-".join(map(str, i)) for i in roadmap.lane_ids[:12])
        more = ", ..." if len(roadmap.lane_ids) > 12 else ""
        return f"lane {list(lane)} does not exist on map '{roadmap.spec.type}' (lanes: {known}{more})"
    length = roadmap.geom(lane).length
    if s is not None and not (0.0 <= s <= length):
        return f"s = {s} is outside lane {list(lane)} (expected 0 <= s <= {length:.1f})"
    return None


class _LaneChecker:
    """Collects ``field: problem`` lines for lane references."""

    def __init__(self, roadmap: RoadMap) -> None:
        self.roadmap = roadmap
        self.errs: list[str] = []

    def __call__(self, field: str, lane: Any, s: Any) -> None:
        p = _lane_problem(self.roadmap, lane, s)
        if p:
            self.errs.append(f"{field}: {p}")


def check_against_map(sc: Scenario, roadmap: RoadMap) -> list[str]:
    """Every lane reference exists, positions lie on their lanes, destinations are reachable."""
    chk = _LaneChecker(roadmap)
    errs = chk.errs
    chk("ego.lane", sc.ego.lane, sc.ego.s)
    chk("ego.destination.lane", sc.ego.destination.lane, sc.ego.destination.s)
    if not errs and sc.ego.lane is not None and roadmap.lane_route(sc.ego.lane, sc.ego.destination.lane) is None:
        errs.append(f"ego.destination.lane: {list(sc.ego.destination.lane)} is not reachable from {list(sc.ego.lane)}")
    errs += _participant_errors(sc, roadmap)
    if not errs:
        errs += _overlap_errors(sc, roadmap)
    if sc.lights is not None and not roadmap.stop_lines:
        errs.append(f"lights: map '{roadmap.spec.type}' has no traffic lights")
    return errs


def _overlap_errors(sc: Scenario, roadmap: RoadMap) -> list[str]:
    """A participant that starts on the ego (centres closer than :data:`MIN_GAP`) is no test."""
    if not sc.participants:
        return []
    exy, _ = pose_xyh(roadmap, sc.ego)
    errs = []
    for i, p in enumerate(sc.participants):
        pose = p.waypoints[0] if isinstance(p, ScriptedSpec) else p
        if isinstance(pose, Waypoint) and pose.t > 0:
            continue  # appears later, when the ego has left its start
        xy, _ = pose_xyh(roadmap, pose)
        gap = float(np.hypot(*(xy - exy)))
        if gap < MIN_GAP:
            errs.append(f"participants.{i}: {p.id!r} starts {gap:.2f} m from the ego's start (expected >= {MIN_GAP} m)")
            if len(errs) >= 5:
                break
    return errs


def _participant_errors(sc: Scenario, roadmap: RoadMap) -> list[str]:
    chk = _LaneChecker(roadmap)
    errs = chk.errs

    for i, p in enumerate(sc.participants):
        base = f"participants.{i}"
        if isinstance(p, ScriptedSpec):
            for j, w in enumerate(p.waypoints):
                chk(f"{base}.waypoints.{j}.lane", w.lane, w.s)
        else:
            chk(f"{base}.lane", p.lane, p.s)
        if isinstance(p, ReactiveSpec):
            if p.lane is None:
                errs.append(f"{base}: a reactive vehicle needs a lane position (lane + s)")
            elif p.destination is not None:
                chk(f"{base}.destination.lane", p.destination.lane, p.destination.s)
                if roadmap.has_lane(p.lane) and roadmap.has_lane(p.destination.lane) and \
                        roadmap.lane_route(p.lane, p.destination.lane) is None:
                    errs.append(f"{base}.destination.lane: not reachable from {list(p.lane)}")
    return errs


# ---------------------------------------------------------------------------------------------
def pose_xyh(roadmap: RoadMap, pose: Pose) -> tuple[np.ndarray, float]:
    """World position [m] and heading [rad] of a pose."""
    if pose.lane is not None:
        g = roadmap.geom(pose.lane)
        s = np.array(float(pose.s))
        xy = g.xy(s, pose.d)
        h = float(g.heading(s)) if pose.heading is None else pose.heading
        return np.asarray(xy, dtype=float), h
    return np.array([pose.x, pose.y], dtype=float), float(pose.heading or 0.0)


def destination_xy(roadmap: RoadMap, dest: Destination) -> tuple[np.ndarray, float]:
    g = roadmap.geom(dest.lane)
    s = dest.s if dest.s is not None else max(0.0, g.length - 10.0)
    return np.asarray(g.xy(np.array(s)), dtype=float), float(s)


def scripted_waypoints(roadmap: RoadMap, spec: ScriptedSpec, step: float = 0.5) -> tuple[np.ndarray, float]:
    """Dense ``(t, x, y)`` waypoints: between two lane waypoints on one lane chain the vehicle
    follows the lanes; otherwise it moves in a straight line."""
    rows: list[tuple[float, float, float]] = []
    poses = [pose_xyh(roadmap, w) for w in spec.waypoints]
    for i, w in enumerate(spec.waypoints):
        rows.append((w.t, *poses[i][0]))
        if i + 1 == len(spec.waypoints):
            break
        nxt = spec.waypoints[i + 1]
        if w.lane is None or nxt.lane is None:
            continue
        route = roadmap.lane_route(w.lane, nxt.lane)
        if route is None or any(a[:2] == b[:2] for a, b in itertools.pairwise(route)):
            continue  # no lane chain without lane changes: straight line
        ref = roadmap.reference_line(route)
        s0, s1 = float(w.s), ref.offsets[-1] + float(nxt.s)
        n = max(1, math.ceil((nxt.t - w.t) / step))
        for k in range(1, n):
            f = k / n
            xy = ref.xy(np.array(s0 + f * (s1 - s0)), w.d + f * (nxt.d - w.d))
            rows.append((w.t + f * (nxt.t - w.t), float(xy[0]), float(xy[1])))
    return np.array(rows), poses[0][1]


def build_world(sc: Scenario, roadmap: RoadMap | None = None) -> World:
    """The world at t = 0: ego, participants and lights of the scenario."""
    roadmap = roadmap or shared_roadmap(sc.map)
    lights = TrafficLights(roadmap.light_groups, sc.lights) if roadmap.light_groups else None
    world = World(roadmap, lights, seed=sc.seed)
    xy, h = pose_xyh(roadmap, sc.ego)
    world.add_ego(xy, h, sc.ego.speed)
    for p in sc.participants:
        add_participant(world, p)
    return world


_PARTICIPANT = TypeAdapter(ParticipantSpec)


def parse_participant(spec: dict[str, Any] | StaticSpec | ScriptedSpec | ReactiveSpec, roadmap: RoadMap,
                      source: str = "participant") -> StaticSpec | ScriptedSpec | ReactiveSpec:
    """Validate one participant description (the scenario's schema) against the map."""
    if not isinstance(spec, dict):
        return spec
    p = validate(_PARTICIPANT, spec, source)
    probe = Scenario.model_construct(participants=[p], lights=None)
    errs = [e for e in _participant_errors(probe, roadmap)]
    if errs:
        raise ConfigError("\n".join(f"{source}: {e}" for e in errs))
    return p


def add_participant(world: World, p: StaticSpec | ScriptedSpec | ReactiveSpec) -> Any:
    """Create the road object of a participant and put it in the world (also mid-episode: a
    scripted vehicle appears at its first waypoint time, others at once)."""
    roadmap, lights = world.roadmap, world.lights
    if isinstance(p, StaticSpec):
        xy, h = pose_xyh(roadmap, p)
        length, width = (p.length, p.width or SIZES[p.obstacle][1]) if p.length else SIZES[p.obstacle]
        obj = StaticObstacle(world.road, xy, h, p.obstacle, length, width)
    elif isinstance(p, ScriptedSpec):
        wp, h = scripted_waypoints(roadmap, p)
        obj = ScriptedVehicle(world.road, wp, h, p.length, p.width)
    else:
        xy, h = pose_xyh(roadmap, p)
        route = None
        if p.destination is not None:
            lanes = roadmap.lane_route(p.lane, p.destination.lane) or [p.lane]
            route = []
            for lid in lanes:  # collapse lane changes: one entry per road, last lane wins
                if route and route[-1][:2] == lid[:2]:
                    route[-1] = lid
                else:
                    route.append(lid)
        v0 = p.target_speed or roadmap.geom(p.lane).lane.speed_limit
        obj = ReactiveVehicle(world.road, roadmap, lights, world.clock, xy, h, p.speed,
                              target_lane_index=tuple(p.lane), target_speed=v0, route=route,
                              enable_lane_change=p.lane_change)
        obj.lane_index = tuple(p.lane)
        obj.lane = roadmap.lanes[tuple(p.lane)]
    return world.add_participant(p.id, p.type, obj)


def list_scenarios() -> list[Path]:
    """The seed scenarios shipped in ``configs/scenarios`` (not the groups in its subfolders)."""
    return sorted(SCENARIO_DIR.glob("*.yaml"))


#: evaluation-only scenario groups, one subfolder of ``configs/scenarios`` each; ``handwritten``:
#: scenarios written as users write them (never trained on, see :func:`is_group_scenario`)
SCENARIO_GROUPS = ("handwritten",)


def group_scenarios(group: str) -> list[str]:
    """The specs ``<group>/<name>`` of a scenario group, sorted (ValueError for an unknown group)."""
    if group not in SCENARIO_GROUPS:
        raise ValueError(f"unknown scenario group {group!r}; expected one of {list(SCENARIO_GROUPS)}")
    return [f"{group}/{p.stem}" for p in sorted((SCENARIO_DIR / group).glob("*.yaml"))]


def group_path(spec: str) -> Path | None:
    """The file of a group scenario spec ``<group>/<name>`` (an existing one), else None."""
    group, sep, name = str(spec).partition("/")
    if not sep or group not in SCENARIO_GROUPS or not name or "/" in name or "\\" in name or name.startswith("."):
        return None
    path = SCENARIO_DIR / group / f"{name}.yaml"
    return path if path.is_file() else None


def is_group_scenario(spec: str | Path) -> bool:
    """Does ``spec`` (a ``<group>/<name>`` spec or a path) name a scenario of an evaluation-only
    group? Training refuses them."""
    if group_path(str(spec)) is not None:
        return True
    try:
        path = Path(spec).resolve()
    except (OSError, RuntimeError):
        return False
    return any(path.parent == (SCENARIO_DIR / g).resolve() for g in SCENARIO_GROUPS)


def expand_groups(specs: list[str]) -> list[str]:
    """``specs`` with each group name (``handwritten``) replaced by the group's scenarios, in order,
    without repeats."""
    out: list[str] = []
    for s in specs:
        out += group_scenarios(s) if s in SCENARIO_GROUPS else [s]
    return list(dict.fromkeys(out))
