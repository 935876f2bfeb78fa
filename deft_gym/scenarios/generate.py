"""Procedural scenarios: held-out test scenarios for the adversary, each drawn from one seed.

``generate(seed)`` builds the scenario ``gen-<seed>`` (spec string ``gen:<seed>``, see
:func:`resolve`) from one ``np.random.default_rng(seed)``:

- a family: ``highway`` (through, or taking the exit ramp), ``intersection`` (straight, left or
  right, with traffic lights) or ``uturn``; ``merge`` (an on-ramp merge or a lane drop) only when
  its weight ``families.merge`` is set (default 0, which leaves every ``gen:<seed>`` as before);
- a map sized so that the ego's route is 110-240 m long on multi-lane roads, with lane choices
  to make (a lane to reach before a junction or fork, a destination lane other than the start);
- reactive traffic, an optional scripted vehicle, cones and parked vehicles on lane edges,
  shoulders and in lanes - placed so that the route stays passable (a lane is blocked only
  where another lane of the road is free and there is room to change back), every traffic
  vehicle's lanes stay clear of obstacles, and everything keeps clear of the ego's start.

Seeds in :data:`TRAIN_SEEDS` are for training; held-out seeds start at :data:`HELD_OUT_BASE`
(:func:`held_out_seeds`, :func:`disjoint`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Annotated, Any

import numpy as np
import shapely
from pydantic import AfterValidator, Field, model_validator

from deft_gym.config import ConfigError, Strict
from deft_gym.scenarios.scenario import Scenario, scenario_from_dict
from deft_gym.world.participants import SIZES
from deft_gym.world.roadmap import LaneId, shared_roadmap

SPEC_PREFIX = "gen:"  #: scenario spec strings ``gen:<seed>``
NAME_PREFIX = "gen-"  #: generated scenario names ``gen-<seed>``
TRAIN_SEEDS = range(0, 100_000)  #: generator seeds an adversary may train on
HELD_OUT_BASE = 1_000_000  #: the first held-out generator seed
FAMILIES = ("highway", "highway-exit", "intersection-straight", "intersection-left",
            "intersection-right", "uturn")  #: the family labels :func:`build` reports
#: labels of the families that are off unless their weight is set (``families.merge``): on
#: ``merge`` maps, the ego merges from an on-ramp or out of a lane that drops
OPTIONAL_FAMILIES = ("merge-ramp", "lane-drop")


def _ordered(r: tuple[float, float]) -> tuple[float, float]:
    if r[0] > r[1]:
        raise ValueError(f"range {list(r)}: the lower bound exceeds the upper one")
    return r


Range = Annotated[tuple[Annotated[float, Field(ge=0.0)], Annotated[float, Field(ge=0.0)]],
                  AfterValidator(_ordered)]
LaneRange = Annotated[tuple[Annotated[int, Field(ge=2, le=5)], Annotated[int, Field(ge=2, le=5)]],
                      AfterValidator(_ordered)]
CountRange = Annotated[tuple[Annotated[int, Field(ge=0, le=8)], Annotated[int, Field(ge=0, le=8)]],
                       AfterValidator(_ordered)]
Share = Annotated[float, Field(ge=0.0, le=1.0)]
Weight = Annotated[float, Field(ge=0.0)]


class _Weights(Strict):
    @model_validator(mode="after")
    def _some(self) -> _Weights:
        if sum(self.model_dump().values()) <= 0.0:
            raise ValueError("at least one weight must be positive")
        return self


class FamilyWeights(_Weights):
    """Relative weights (no unit) of the map families."""

    highway: Weight = Field(1.0, description="straight multi-lane road with an exit ramp")
    intersection: Weight = Field(1.5, description="signalised four-way junction")
    uturn: Weight = Field(1.0, description="divided road with a U-turn bay")
    merge: Weight = Field(0.0, description="road whose rightmost lane ends, fed by an on-ramp or dropping (off "
                                           "by default: with weight 0 every gen:<seed> is as before)")


class ManoeuvreWeights(_Weights):
    """Relative weights (no unit) of the ego's manoeuvre at an intersection."""

    straight: Weight = 1.0
    left: Weight = 1.0
    right: Weight = 1.0


class StaticWeights(_Weights):
    """Relative weights (no unit) of the kinds of static object."""

    blocker: Weight = Field(0.35, description="parked vehicle or cone in a lane of the route, "
                                              "where another lane of the road is free")
    edge: Weight = Field(0.3, description="cone on a lane edge of the route")
    shoulder: Weight = Field(0.2, description="cone or parked vehicle beyond the outer lane edge")
    off_route: Weight = Field(0.15, description="parked vehicle or cone on a road the route does not use")


class LightRanges(Strict):
    """Traffic-light phase durations [s] and plan offset [s] (intersections)."""

    green: Range = Field((8.0, 14.0), description="[s]")
    yellow: Range = Field((3.0, 4.0), description="[s]")
    all_red: Range = Field((1.0, 2.0), description="[s]")
    offset: Range = Field((0.0, 30.0), description="[s] shift of the plan")


class GeneratorConfig(Strict):
    """Families, weights and ranges of :func:`generate` (ranges are ``[low, high]``)."""

    families: FamilyWeights = FamilyWeights()
    highway_lanes: LaneRange = Field((2, 4), description="highway lane count")
    highway_exit: Share = Field(0.5, description="probability that a highway route takes the exit ramp")
    highway_speed: Range = Field((12.0, 20.0), description="highway speed limit [m/s]")
    highway_tail: Range = Field((25.0, 80.0), description="highway road beyond the destination or fork [m]")
    intersection_lanes: LaneRange = Field((2, 3), description="lanes per intersection approach")
    manoeuvres: ManoeuvreWeights = ManoeuvreWeights()
    intersection_speed: Range = Field((9.0, 13.0), description="intersection speed limit [m/s]")
    merge_ramp: Share = Field(0.5, description="merge family: probability that the ego comes up an on-ramp "
                                               "(else it drives in a lane that drops)")
    merge_section: Range = Field((60.0, 120.0), description="merge family: length [m] of the section the ending "
                                                           "lane runs beside the others")
    uturn_lanes: LaneRange = Field((2, 3), description="lanes per direction of the U-turn road")
    uturn_speed: Range = Field((9.0, 13.0), description="U-turn road speed limit [m/s]")
    uturn_median: Range = Field((10.0, 16.0), description="U-turn median width [m] (below 10 m the "
                                                          "bay is too tight for the reference planner)")
    road_length: Range = Field((70.0, 150.0), description="intersection approach / U-turn road length [m]")
    route_length: Range = Field((110.0, 240.0), description="the ego's route length [m]")
    ego_start: Range = Field((5.0, 30.0), description="highway: ego start s on the first road [m]")
    ego_speed: Range = Field((0.4, 0.9), description="ego start speed [share of the speed limit]")
    dest_other_lane: Share = Field(0.5, description="probability of a destination lane other than the "
                                                    "lane the route arrives in (lane changes needed)")
    change_room: float = Field(40.0, ge=10.0, le=100.0, description="road length kept per lane change [m]")
    traffic: CountRange = Field((0, 4), description="reactive vehicles")
    traffic_speed: Range = Field((0.5, 1.0), description="traffic start and target speed [share of the limit]")
    traffic_lane_change: Share = Field(0.2, description="probability that a reactive vehicle may change lanes")
    scripted: Share = Field(0.25, description="probability of one scripted vehicle")
    statics: CountRange = Field((0, 4), description="static objects")
    static_kinds: StaticWeights = StaticWeights()
    lights: LightRanges = LightRanges()
    start_clearance: float = Field(25.0, ge=5.0, description="no participant closer to the ego's start [m]")
    duration_speed: Share = Field(0.6, gt=0.0, description="duration: route at this share of the limit")
    duration_slack: float = Field(15.0, ge=0.0, description="duration: added slack [s]")


# ---------------------------------------------------------------------------------------------
# seeds and specs
def held_out_seeds(count: int) -> list[int]:
    """The first ``count`` held-out generator seeds (from :data:`HELD_OUT_BASE`)."""
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    return list(range(HELD_OUT_BASE, HELD_OUT_BASE + count))


def disjoint(train: Iterable[int], held: Iterable[int]) -> None:
    """Raise ``ValueError`` naming the shared seeds when ``train`` and ``held`` overlap."""
    if isinstance(train, range) and isinstance(held, range) and train.step == held.step == 1:
        lo, hi = max(train.start, held.start), min(train.stop, held.stop)
        both = range(lo, hi) if lo < hi else range(0)
    else:
        both = sorted(set(train) & set(held))
    if len(both):
        first = ", ".join(str(s) for s in list(both[:5]))
        raise ValueError(f"training and held-out seeds overlap: {len(both)} seed(s) in both "
                         f"(first: {first}); held-out seeds start at {HELD_OUT_BASE}")


def parse_spec(spec: str) -> int | None:
    """The seed of ``gen:<seed>``, None for any other string; ``ConfigError`` for a malformed
    ``gen:`` spec."""
    if not spec.startswith(SPEC_PREFIX):
        return None
    text = spec[len(SPEC_PREFIX):]
    if not text.isdigit():
        raise ConfigError(f"scenario {spec!r}: expected '{SPEC_PREFIX}<seed>' with a seed >= 0")
    return int(text)


def resolve(spec: str) -> Scenario | None:
    """The generated scenario of ``gen:<seed>`` (default config), None for any other spec."""
    seed = parse_spec(str(spec))
    return None if seed is None else generate(seed)


# ---------------------------------------------------------------------------------------------
@dataclass
class Generated:
    """A generated scenario and what the generator chose."""

    scenario: Scenario
    seed: int
    family: str
    lanes: int
    route_length: float  #: [m] along the lane centres, lane changes not counted
    lane_changes: int  #: the fewest lane changes the route needs

    @property
    def counts(self) -> dict[str, int]:
        """Participants by type."""
        out = {"reactive": 0, "scripted": 0, "static": 0}
        for p in self.scenario.participants:
            out[p.type] += 1
        return out


def generate(seed: int, cfg: GeneratorConfig | None = None) -> Scenario:
    """The scenario ``gen-<seed>``: deterministic in ``seed`` (and ``cfg``)."""
    return build(seed, cfg).scenario


def build(seed: int, cfg: GeneratorConfig | None = None) -> Generated:
    """:func:`generate`, with the family, lane count, route length and lane changes."""
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ConfigError(f"generator seed {seed!r}: expected an integer >= 0")
    b = _Builder(int(seed), cfg or GeneratorConfig())
    return b.run()


# ---------------------------------------------------------------------------------------------
def _r(x: float, nd: int = 1) -> float:
    return float(round(float(x), nd))


def _round_up(x: float, step: float = 5.0) -> float:
    return float(math.ceil(x / step - 1e-9) * step)


def _split(rng: np.random.Generator, total: float, lo1: float, hi1: float, lo2: float,
           hi2: float) -> tuple[float, float]:
    """``(a, b)`` with ``a + b`` as close to ``total`` as the bounds allow, ``a`` in
    ``[lo1, hi1]`` and ``b`` in ``[lo2, hi2]``; ``a`` uniform among the choices."""
    total = min(max(total, lo1 + lo2), hi1 + hi2)
    a_lo, a_hi = max(lo1, total - hi2), min(hi1, total - lo2)
    a = float(rng.uniform(a_lo, a_hi)) if a_hi > a_lo else a_lo
    return a, total - a


@dataclass
class _Leg:
    """One road of the ego's route: where the ego drives on it ``[s_from, s_to]`` [m] and the
    lanes from which the route continues."""

    road: tuple[str, str]
    lanes: int
    length: float
    s_from: float
    s_to: float
    junction: bool
    keep: list[int]
    entry: int  #: the lane the route enters this road in (the start lane on the first road)


@dataclass
class _Plan:
    """The ego's route as the generator sees it."""

    family: str
    spec: dict[str, Any]
    start: LaneId
    s0: float
    dest: LaneId
    dest_s: float
    changes: int
    entry: int  #: the lane in which the route is expected to enter its last road
    lights: dict[str, float] | None = None
    legs: list[_Leg] = field(default_factory=list)


class _Builder:
    """Draws one scenario; every random choice comes from ``self.rng``."""

    TRIES = 15

    def __init__(self, seed: int, cfg: GeneratorConfig) -> None:
        self.seed, self.cfg = seed, cfg
        self.rng = np.random.default_rng(seed)
        self.parts: list[dict[str, Any]] = []
        self.static_xy: list[tuple[np.ndarray, bool, float]] = []  # position, blocker?, half extent
        self.npc_xy: list[np.ndarray] = []
        self.npc_chains: list[tuple[list[LaneId], float]] = []

    # -- drawing helpers ----------------------------------------------------------------------
    def uniform(self, r: tuple[float, float]) -> float:
        return float(self.rng.uniform(r[0], r[1])) if r[1] > r[0] else float(r[0])

    def integer(self, r: tuple[int, int]) -> int:
        return int(self.rng.integers(r[0], r[1] + 1))

    def pick(self, weights: dict[str, float]) -> str:
        keys = list(weights)
        w = np.array([weights[k] for k in keys], dtype=float)
        return keys[int(self.rng.choice(len(keys), p=w / w.sum()))]

    def other_lane(self, n: int, lane: int, room: float) -> int:
        """A destination lane: ``lane``, or with probability ``dest_other_lane`` another lane
        of the ``n`` whose lane changes fit in ``room`` [m]."""
        others = [j for j in range(n) if j != lane and 25.0 + self.cfg.change_room * abs(j - lane) <= room]
        if others and self.rng.random() < self.cfg.dest_other_lane:
            return int(others[int(self.rng.integers(len(others)))])
        return lane

    # -- the run ------------------------------------------------------------------------------
    def run(self) -> Generated:
        cfg = self.cfg
        kind = self.pick(cfg.families.model_dump())
        plan = {"highway": self.highway, "intersection": self.intersection, "uturn": self.uturn,
                "merge": self.merge}[kind]()
        plan.s0, plan.dest_s = _r(plan.s0), _r(plan.dest_s)
        self.rm = shared_roadmap(plan.spec)
        self.plan = plan
        self.legs = plan.legs = self.route_legs(plan)
        self.route_length = self.length_of()
        self.route_nodes = {lg.road[0] for lg in self.legs}
        self.ego_junction = self.junction_path()
        self.start_xy = np.asarray(self.rm.geom(plan.start).xy(np.array(plan.s0)), dtype=float)
        self.dest_xy = np.asarray(self.rm.geom(plan.dest).xy(np.array(plan.dest_s)), dtype=float)
        self.statics()
        self.traffic()
        if self.rng.random() < cfg.scripted:
            self.scripted()
        ego_speed = _r(self.uniform(cfg.ego_speed) * plan.spec["speed_limit"])
        data: dict[str, Any] = {
            "name": f"{NAME_PREFIX}{self.seed}",
            "description": self.describe(plan),
            "map": plan.spec,
            "ego": {"lane": list(plan.start), "s": _r(plan.s0), "speed": ego_speed,
                    "destination": {"lane": list(plan.dest), "s": _r(plan.dest_s)}},
            "participants": self.parts,
            "duration": min(math.ceil(self.duration() * 10.0) / 10.0, 600.0),
            "seed": self.seed,
        }
        if plan.lights is not None:
            data["lights"] = plan.lights
        sc = scenario_from_dict(data, source=f"{SPEC_PREFIX}{self.seed}")
        return Generated(sc, self.seed, plan.family, int(plan.spec["lanes"]), _r(self.route_length),
                         plan.changes)

    CURVE_ACCEL = 2.5  #: [m/s^2] lateral acceleration that sets the speed on curved lanes
    CHANGE_TIME = 4.0  #: [s] added per lane change

    def duration(self) -> float:
        """Episode length [s]: each leg at ``duration_speed`` times its speed (the lane's
        limit, lower on tight curves), plus time per lane change, the longest red light and
        ``duration_slack``."""
        cfg, t = self.cfg, 0.0
        for leg in self.legs:
            g = self.rm.geom((*leg.road, leg.entry))  # type: ignore[arg-type]
            v = float(g.lane.speed_limit)
            if g.kind == "circular":
                v = min(v, math.sqrt(self.CURVE_ACCEL * g.radius))
            t += (leg.s_to - leg.s_from) / (cfg.duration_speed * v)
        t += self.CHANGE_TIME * self.plan.changes + cfg.duration_slack
        lt = self.plan.lights
        if lt is not None:  # the longest red: the other group's phases and two all-reds
            t += lt["green"] + lt["yellow"] + 2 * lt["all_red"]
        return t

    def describe(self, plan: _Plan) -> str:
        c = {"reactive": 0, "scripted": 0}
        for p in self.parts:
            c[p["type"]] = c.get(p["type"], 0) + 1
        kinds = [p["id"].rstrip("0123456789").rstrip("_") for p in self.parts if p["type"] == "static"]
        statics = ", ".join(f"{kinds.count(k)} {k}" for k in sorted(set(kinds))) or "no static objects"
        dest = "-".join(map(str, plan.dest))
        return (f"Generated (seed {self.seed}): {plan.family} on a {plan.spec['lanes']}-lane "
                f"{plan.spec['type']} map, speed limit {plan.spec['speed_limit']} m/s; the ego drives "
                f"{self.route_length:.0f} m from lane {plan.start[2]} to {dest} "
                f"({plan.changes} lane change(s) needed); {c['reactive']} reactive and "
                f"{c['scripted']} scripted vehicle(s); {statics}.")

    # -- families -----------------------------------------------------------------------------
    def highway(self) -> _Plan:
        cfg, rng = self.cfg, self.rng
        n = self.integer(cfg.highway_lanes)
        v = _r(self.uniform(cfg.highway_speed) * 2, 0) / 2
        exit_ = bool(rng.random() < cfg.highway_exit)
        route = self.uniform(cfg.route_length)
        s0 = self.uniform(cfg.ego_start)
        k = int(rng.integers(n))
        room = cfg.change_room
        if exit_:
            arc = 60.0 * math.radians(25.0)  # the ramp's curve (roadmap.build_highway)
            post = float(rng.uniform(25.0, 60.0))
            changes = n - 1 - k
            pre = max(route - arc - post, 30.0 + room * changes)
            tail = self.uniform(cfg.highway_tail)
            dest: LaneId = ("x", "y", 0)
        else:
            pre_min = 40.0
            j = self.other_lane(n, k, cfg.route_length[1] - pre_min)
            changes = abs(j - k)
            pre, post = _split(rng, route, pre_min, math.inf, 25.0 + room * changes, math.inf)
            tail = post + self.uniform(cfg.highway_tail)
            dest = ("b", "c", j)
        xb = _round_up(s0 + pre)  # the fork and the length on a 5 m grid: maps repeat across seeds
        length = _round_up(xb + tail)
        spec = {"type": "highway", "lanes": n, "length": length, "speed_limit": v,
                "exit_at": _r(xb / length, 4)}
        s0 = spec["exit_at"] * length - pre  # keep the drawn distance to the fork exactly
        return _Plan("highway-exit" if exit_ else "highway", spec, ("a", "b", k), s0, dest, post, changes,
                     0 if exit_ else k)

    def merge(self) -> _Plan:
        """A road whose rightmost lane ends (map ``merge``): the ego comes up the on-ramp (with
        probability ``merge_ramp``) or drives in the lane that drops, merges into the lane beside
        it on the section [m] where both run, and ends in a lane of the road after it."""
        cfg, rng = self.cfg, self.rng
        n = self.integer(cfg.highway_lanes)
        v = _r(self.uniform(cfg.highway_speed) * 2, 0) / 2
        ramp = bool(rng.random() < cfg.merge_ramp)
        section = _round_up(max(self.uniform(cfg.merge_section), 20.0))
        route = self.uniform(cfg.route_length)
        j = self.other_lane(n - 1, n - 2, cfg.route_length[1] - section)  # destination lane after the end
        post = max(25.0 + cfg.change_room * abs(n - 2 - j), route - section - 60.0)
        if ramp:
            s0 = float(rng.uniform(5.0, 40.0))
            pre = 80.0 - s0 + 60.0 * math.radians(20.0)  # up the ramp to b (roadmap.build_merge)
            xb = _round_up(float(rng.uniform(40.0, 150.0)))
            start: LaneId = ("j", "k", 0)
        else:
            pre = float(rng.uniform(40.0, 120.0))
            s0 = self.uniform(cfg.ego_start)
            xb = _round_up(s0 + pre)
            start = ("a", "b", n - 1)
        post = min(post, max(25.0 + cfg.change_room * abs(n - 2 - j), route - section - pre))
        length = _round_up(xb + section + post + self.uniform(cfg.highway_tail))
        spec = {"type": "merge", "lanes": n, "length": length, "speed_limit": v, "ramp": ramp,
                "merge_at": _r(xb / length, 4), "merge_length": section}
        if not ramp:
            s0 = spec["merge_at"] * length - pre  # keep the drawn distance to the section exactly
        return _Plan("merge-ramp" if ramp else "lane-drop", spec, start, s0, ("c", "d", j), post,
                     1 + abs(n - 2 - j), n - 2)

    def intersection(self) -> _Plan:
        cfg, rng = self.cfg, self.rng
        n = self.integer(cfg.intersection_lanes)
        v = _r(self.uniform(cfg.intersection_speed) * 2, 0) / 2
        man = self.pick(cfg.manoeuvres.model_dump())
        c = int(rng.integers(4))
        k = int(rng.integers(n))
        to, lane_in, entry = {"straight": ((c + 2) % 4, k, k), "left": ((c + 1) % 4, 0, 0),
                              "right": ((c - 1) % 4, n - 1, n - 1)}[man]
        length = _round_up(self.uniform(cfg.road_length))
        spec = {"type": "intersection", "lanes": n, "length": length, "speed_limit": v}
        rm = shared_roadmap(spec)
        junction = rm.geom((f"ir{c}", f"il{to}", lane_in if man == "straight" else 0)).length
        lt = cfg.lights
        lights = {"green": _r(self.uniform(lt.green)), "yellow": _r(self.uniform(lt.yellow)),
                  "all_red": _r(self.uniform(lt.all_red)), "offset": _r(self.uniform(lt.offset))}
        plan = self.two_roads(f"intersection-{man}", spec, (f"o{c}", f"ir{c}", k), abs(k - lane_in),
                              (f"il{to}", f"o{to}"), entry, junction)
        plan.lights = lights
        return plan

    def uturn(self) -> _Plan:
        cfg, rng = self.cfg, self.rng
        n = self.integer(cfg.uturn_lanes)
        v = _r(self.uniform(cfg.uturn_speed) * 2, 0) / 2
        median = _r(self.uniform(cfg.uturn_median), 0)
        k = int(rng.integers(n))
        length = _round_up(self.uniform(cfg.road_length))
        spec = {"type": "uturn", "lanes": n, "length": length, "speed_limit": v, "median": median}
        bay = shared_roadmap(spec).geom(("b", "c", 0)).length
        return self.two_roads("uturn", spec, ("a", "b", k), k, ("c", "d"), 0, bay)

    def two_roads(self, family: str, spec: dict[str, Any], start: LaneId, changes_in: int,
                  exit_road: tuple[str, str], entry: int, junction: float) -> _Plan:
        """A route: ``start`` road, a junction of ``junction`` [m], the exit road entered in
        lane ``entry``; the road length grows when the lane changes need more room."""
        cfg, room = self.cfg, self.cfg.change_room
        n = spec["lanes"]
        route = self.uniform(cfg.route_length)
        pre_min = max(40.0, 30.0 + room * changes_in)
        j = self.other_lane(n, entry, cfg.route_length[1] - junction - pre_min)
        post_min = max(30.0, 25.0 + room * abs(j - entry))
        length = spec["length"] = max(spec["length"], _round_up(pre_min + 5.0), _round_up(post_min + 15.0))
        pre, post = _split(self.rng, route - junction, pre_min, length - 5.0, post_min, length - 15.0)
        return _Plan(family, spec, start, length - pre, (*exit_road, j), post, changes_in + abs(j - entry), entry)

    # -- the route ----------------------------------------------------------------------------
    def route_legs(self, plan: _Plan) -> list[_Leg]:
        rm = self.rm
        lanes = rm.lane_route(plan.start, plan.dest)
        segs = rm.route_segments(plan.start, plan.dest)
        assert lanes is not None and segs is not None, "generated destination unreachable"
        legs: list[_Leg] = []
        for i, seg in enumerate(segs):
            road = (seg["road"][0], seg["road"][1])
            ids = rm.road_lanes(road)
            # the lane the ego enters the road in (the planner changes lanes on the last road)
            entry = plan.entry if 0 < i == len(segs) - 1 else next(lid[2] for lid in lanes if lid[:2] == road)
            legs.append(_Leg(road, len(ids), rm.geom(ids[0]).length, plan.s0 if i == 0 else 0.0,
                             plan.dest_s if i == len(segs) - 1 else rm.geom(ids[0]).length,
                             road in rm.junction_roads, list(seg["lanes"]), entry))
        return legs

    def length_of(self) -> float:
        """The route's length [m] along the lane centres."""
        return sum(leg.s_to - leg.s_from for leg in self.legs)

    def junction_path(self) -> tuple[LaneId, shapely.LineString] | None:
        """The ego's approach lane and its path through the junction (intersections)."""
        for prev, leg in itertools.pairwise(self.legs):
            if leg.junction and self.rm.stop_line_of:
                g = self.rm.geom((*leg.road, leg.entry))  # type: ignore[arg-type]
                line = shapely.LineString(g.xy(np.linspace(0.0, g.length, 16))).buffer(self.rm.spec.lane_width / 2)
                return (*prev.road, prev.entry), line  # type: ignore[return-value]
        return None

    def lane_xy(self, lane: LaneId, s: float, d: float = 0.0) -> np.ndarray:
        return np.asarray(self.rm.geom(lane).xy(np.array(s), d), dtype=float)

    def near_lanes(self, xy: np.ndarray, lanes: list[LaneId], margin: float, s_from: float = -math.inf) -> bool:
        """Is ``xy`` within ``margin`` [m] of the band of any of ``lanes`` (the first one only
        from ``s_from`` [m] on)?"""
        for i, lid in enumerate(lanes):
            g = self.rm.geom(lid)
            s, d = g.frenet_point(float(xy[0]), float(xy[1]))
            lo = max(-5.0, s_from - 5.0) if i == 0 else -5.0
            if lo <= s <= g.length + 5.0 and abs(d) <= g.width / 2 + margin:
                return True
        return False

    # -- static objects -----------------------------------------------------------------------
    def statics(self) -> None:
        weights = self.cfg.static_kinds.model_dump()
        for i in range(self.integer(self.cfg.statics)):
            kind = self.pick(weights)
            if kind == "off_route" and not self.off_route_roads():
                kind = "edge"
            for _ in range(self.TRIES):
                spec = getattr(self, f"static_{kind}")()
                if spec is not None and self.static_fits(spec, kind == "blocker"):
                    spec["id"] = f"{kind}_{i}"
                    self.parts.append(spec)
                    break

    def leg_for(self, legs: list[_Leg]) -> _Leg | None:
        return legs[int(self.rng.integers(len(legs)))] if legs else None

    def free_span(self, leg: _Leg, ahead: float) -> tuple[float, float]:
        """``[lo, hi]`` [m] of a leg where objects may stand: ``ahead`` [m] past where the ego
        enters it (the start clearance on the first road), away from the road ends."""
        first = leg is self.legs[0]
        lo = leg.s_from + (max(ahead, self.cfg.start_clearance) if first else ahead)
        return max(lo, 10.0), min(leg.s_to, leg.length - 10.0)

    def static_blocker(self) -> dict[str, Any] | None:
        legs = [lg for lg in self.legs if not lg.junction and lg.lanes >= 2]
        leg = self.leg_for(legs)
        if leg is None:
            return None
        k = int(self.rng.integers(leg.lanes))
        lo, hi = self.free_span(leg, 45.0)
        last = leg is self.legs[-1]
        room = self.cfg.change_room
        if last:  # never in the destination lane; room for the changes to it after the object
            if k == self.plan.dest[2]:
                return None
            hi = min(hi, leg.s_to - 30.0 - room * max(1, abs(self.plan.dest[2] - leg.entry)))
        elif len(leg.keep) < leg.lanes:  # room to reach a lane the route continues from after it
            hi = min(hi, leg.length - 30.0 - room * (1 + min(abs(k - j) for j in leg.keep)))
        if hi <= lo:
            return None
        obstacle = "CONE" if self.rng.random() < 0.25 else "STATIC_VEHICLE"
        return {"type": "static", "obstacle": obstacle, "lane": [*leg.road, k],
                "s": _r(self.rng.uniform(lo, hi)), "d": _r(self.rng.uniform(-0.4, 0.4), 2)}

    def static_edge(self) -> dict[str, Any] | None:
        leg = self.leg_for([lg for lg in self.legs if not lg.junction])
        if leg is None:
            return None
        lo, hi = self.free_span(leg, 20.0)
        if len(leg.keep) < leg.lanes:  # not on the stretch where the ego lines up for the exit
            hi = min(hi, leg.length - 45.0)
        if hi <= lo:
            return None
        k = int(self.rng.integers(leg.lanes))
        side = 1.0 if self.rng.random() < 0.5 else -1.0
        d = side * (self.rm.spec.lane_width / 2 + self.rng.uniform(-0.2, 0.1))
        return {"type": "static", "obstacle": "CONE", "lane": [*leg.road, k],
                "s": _r(self.rng.uniform(lo, hi)), "d": _r(d, 2)}

    def shoulder(self, road: tuple[str, str], lanes: int, lo: float, hi: float) -> dict[str, Any] | None:
        """A cone or parked vehicle just beyond the right edge of the outer lane (or the left
        edge of lane 0 where no oncoming lane lies there: highway, U-turn)."""
        if hi <= lo:
            return None
        left_ok = self.rm.spec.type != "intersection"
        right = not left_ok or self.rng.random() < 0.6
        obstacle = "CONE" if self.rng.random() < 0.5 else "STATIC_VEHICLE"
        half = SIZES[obstacle][1] / 2
        d = self.rm.spec.lane_width / 2 + self.rng.uniform(0.3, 1.0) + half
        return {"type": "static", "obstacle": obstacle, "lane": [*road, lanes - 1 if right else 0],
                "s": _r(self.rng.uniform(lo, hi)), "d": _r(d if right else -d, 2)}

    def static_shoulder(self) -> dict[str, Any] | None:
        leg = self.leg_for([lg for lg in self.legs if not lg.junction])
        if leg is None:
            return None
        return self.shoulder(leg.road, leg.lanes, *self.free_span(leg, 20.0))

    def off_route_roads(self) -> list[tuple[str, str]]:
        on = {lg.road for lg in self.legs}
        roads = sorted({lid[:2] for lid in self.rm.lane_ids})
        return [r for r in roads if r not in on and r not in self.rm.junction_roads]  # type: ignore[misc]

    def static_off_route(self) -> dict[str, Any] | None:
        roads = self.off_route_roads()
        road = roads[int(self.rng.integers(len(roads)))]
        ids = self.rm.road_lanes(road)
        length = self.rm.geom(ids[0]).length
        if self.rng.random() < 0.4:
            return self.shoulder(road, len(ids), 12.0, length - 12.0)
        if length < 30.0:
            return None
        obstacle = "CONE" if self.rng.random() < 0.3 else "STATIC_VEHICLE"
        return {"type": "static", "obstacle": obstacle, "lane": [*road, int(self.rng.integers(len(ids)))],
                "s": _r(self.rng.uniform(12.0, length - 12.0)), "d": _r(self.rng.uniform(-0.4, 0.4), 2)}

    def static_fits(self, spec: dict[str, Any], blocker: bool) -> bool:
        """Clear of the ego's start and destination, of other objects, and of the lanes the
        ego must drive through (junctions, single-lane roads)."""
        xy = self.lane_xy(tuple(spec["lane"]), spec["s"], spec["d"])  # type: ignore[arg-type]
        length, width = SIZES[spec["obstacle"]]
        half = math.hypot(length, width) / 2
        if np.linalg.norm(xy - self.start_xy) < self.cfg.start_clearance or np.linalg.norm(xy - self.dest_xy) < 12.0:
            return False
        for other, other_blocker, _ in self.static_xy:
            gap = 45.0 if blocker and other_blocker else 20.0
            if np.linalg.norm(xy - other) < gap:
                return False
        must = [(*lg.road, lg.entry) for lg in self.legs if lg.junction or lg.lanes == 1]
        if self.near_lanes(xy, must, 1.5 + half - self.rm.spec.lane_width / 2):  # type: ignore[arg-type]
            return False
        self.static_xy.append((xy, blocker, half))
        return True

    # -- traffic ------------------------------------------------------------------------------
    def chain(self, lane: LaneId) -> list[LaneId] | None:
        """The lanes a traffic vehicle starting on ``lane`` drives: up to three successors, a
        random one at each fork, then on as highway-env continues a finished route (the lane
        nearest to the lane end on any road from its end node), while that is a connected lane.
        The destination is the last successor drawn. None when highway-env would take the
        vehicle onto a road that is not connected (it swerves there) at a node of the ego's
        route (a lane-1 vehicle would U-turn through the bay)."""
        rm = self.rm
        out = [lane]
        while len(out) < 4 and rm.successors[out[-1]]:
            succ = [b for b in rm.successors[out[-1]] if not self.cuts_across(out[-1], b)]
            if not succ:
                return None
            out.append(succ[int(self.rng.integers(len(succ)))])
        dest = out[-1]
        for _ in range(2):
            g = rm.geom(out[-1])
            nxt = tuple(rm.network.next_lane(out[-1], position=g.xy(np.array(g.length))))
            if nxt == out[-1] or nxt in out:
                break
            if nxt not in rm.successors[out[-1]]:
                if out[-1][1] in self.route_nodes:
                    return None
                break
            out.append(nxt)  # type: ignore[arg-type]
        self.chain_dest = dest
        return out

    def cuts_across(self, lane: LaneId, junction_lane: LaneId) -> bool:
        """Would a vehicle from ``lane`` into ``junction_lane`` cross the ego's path through the
        junction on the same green? Traffic vehicles never yield inside a junction, so only the
        ego's own duty to yield (its left turn across oncoming traffic) is left in."""
        rm, ego = self.rm, self.ego_junction
        if ego is None or junction_lane[:2] not in rm.junction_roads or self.plan.family.endswith("left"):
            return False
        mine, theirs = rm.stop_line_of.get(ego[0]), rm.stop_line_of.get(lane)
        if mine is None or theirs is None or rm.light_groups[mine.light_id] != rm.light_groups[theirs.light_id]:
            return False
        g = rm.geom(junction_lane)
        return bool(shapely.LineString(g.xy(np.linspace(0.0, g.length, 16))).intersects(ego[1]))

    def follows_ego(self, chain: list[LaneId], s: float) -> bool:
        """Would a vehicle starting at ``s`` [m] on ``chain[0]`` follow the ego into a junction
        of its route? It would not see the ego there before entering it itself (highway-env
        looks for leaders on the vehicle's own lane) and runs into it when the ego slows."""
        junctions = {lg.road for lg in self.legs if lg.junction}
        first = self.legs[0]
        return any(lid[:2] in junctions for lid in chain) and chain[0][:2] == first.road and s < first.s_from

    def traffic_slot(self) -> tuple[LaneId, float] | None:
        """A lane and s [m] for a vehicle: any road outside junctions, the route's roads thrice
        as likely."""
        on = {lg.road for lg in self.legs}
        roads = sorted({lid[:2] for lid in self.rm.lane_ids if lid[:2] not in self.rm.junction_roads})
        w = np.array([3.0 if r in on else 1.0 for r in roads])
        road = roads[int(self.rng.choice(len(roads), p=w / w.sum()))]
        ids = self.rm.road_lanes(road)  # type: ignore[arg-type]
        lane = ids[int(self.rng.integers(len(ids)))]
        length = self.rm.geom(lane).length
        end = length - (25.0 if self.rm.stop_line_of.get(lane) else 15.0)
        if end <= 5.0:
            return None
        return lane, float(self.rng.uniform(5.0, end))

    def npc_fits(self, xy: np.ndarray, chain: list[LaneId], s: float, all_lanes: bool) -> bool:
        """Clear of the ego's start, of other vehicles, and no static object on its way (a
        traffic vehicle stops behind anything within a lane width of its lane)."""
        if np.linalg.norm(xy - self.start_xy) < self.cfg.start_clearance:
            return False
        if any(np.linalg.norm(xy - o) < 15.0 for o in self.npc_xy):
            return False
        lanes = chain
        if all_lanes:  # it may change lanes: keep every lane of its roads clear
            lanes = [lid for lane in chain for lid in self.rm.road_lanes(lane[:2])]
        for sxy, _, _ in self.static_xy:
            if np.linalg.norm(sxy - xy) < 10.0:
                return False
            first = [lid for lid in lanes if lid[:2] == chain[0][:2]]
            rest = [lid for lid in lanes if lid[:2] != chain[0][:2]]
            # highway-env's on-lane test: a centre within half a lane + 1 m (0.3 m to spare)
            if any(self.near_lanes(sxy, [lid], 1.3, s) for lid in first) or self.near_lanes(sxy, rest, 1.3):
                return False
        return True

    def traffic(self) -> None:
        cfg = self.cfg
        for i in range(self.integer(cfg.traffic)):
            for _ in range(self.TRIES):
                slot = self.traffic_slot()
                if slot is None:
                    continue
                lane, s = slot
                chain = self.chain(lane)
                if chain is None or self.follows_ego(chain, s):
                    continue
                lane_change = bool(self.rng.random() < cfg.traffic_lane_change)
                limit = float(self.rm.lanes[lane].speed_limit)
                speed, target = self.uniform(cfg.traffic_speed) * limit, self.uniform(cfg.traffic_speed) * limit
                xy = self.lane_xy(lane, s)
                if self.npc_fits(xy, chain, s, lane_change):
                    self.npc_xy.append(xy)
                    self.npc_chains.append((chain, s))
                    self.parts.append({"id": f"npc_{i}", "type": "reactive", "lane": list(lane), "s": _r(s),
                                       "speed": _r(speed), "target_speed": _r(max(target, 1.0)),
                                       "destination": {"lane": list(self.chain_dest)}, "lane_change": lane_change})
                    break

    def scripted(self) -> None:
        """One vehicle driving away from the ego's route at or above the speed limit, then on
        beyond the end of the map (it never meets the ego): ahead of the ego in another lane
        (highway), out of the junction on the ego's own side or exit road (intersection), or
        along the return road (U-turn)."""
        rm, plan, rng = self.rm, self.plan, self.rng
        t = rm.spec.type
        if t == "highway":
            k = int(rng.integers(rm.spec.lanes - 1))
            k = k + 1 if k >= plan.start[2] else k
            lanes = [("a", "b", k), ("b", "c", k)]
            s = plan.s0 + float(rng.uniform(30.0, 60.0))
        elif t == "merge":  # along the road after the end, ahead of the ego
            lanes = [("c", "d", int(rng.integers(rm.spec.lanes - 1)))]
            s = float(rng.uniform(0.0, 20.0))
        elif t == "intersection":
            road = (f"il{plan.start[0][1:]}", plan.start[0]) if rng.random() < 0.5 else plan.dest[:2]
            lanes = [(*road, int(rng.integers(rm.spec.lanes)))]  # type: ignore[list-item]
            s = float(rng.uniform(0.0, 10.0))
        else:
            lanes = [("c", "d", int(rng.integers(rm.spec.lanes)))]
            s = float(rng.uniform(0.0, 20.0))
        if s >= rm.geom(lanes[0]).length - 5.0:
            return
        v = float(rm.lanes[lanes[0]].speed_limit) * float(rng.uniform(1.0, 1.15))
        xy = self.lane_xy(lanes[0], s)
        if np.linalg.norm(xy - self.start_xy) < self.cfg.start_clearance:
            return
        if any(self.near_lanes(sxy, lanes, 0.5 + half, s) for sxy, _, half in self.static_xy):
            return
        for chain, s_npc in self.npc_chains:  # no reactive vehicle ahead on its lanes
            if chain[0] in lanes and (chain[0] != lanes[0] or s_npc > s - 10.0):
                return
        end = lanes[-1]
        g = rm.geom(end)
        dist = sum(rm.geom(lid).length for lid in lanes) - s
        h = float(g.heading(np.array(g.length)))
        beyond = self.lane_xy(end, g.length) + 150.0 * np.array([math.cos(h), math.sin(h)])
        t1 = dist / v
        self.parts.append({"id": "scripted_0", "type": "scripted", "waypoints": [
            {"lane": list(lanes[0]), "s": _r(s), "t": 0.0},
            {"lane": list(end), "s": _r(g.length - 0.1), "t": _r(t1, 2)},
            {"x": _r(beyond[0]), "y": _r(beyond[1]), "t": _r(t1 + 150.0 / v, 2)}]})
