"""World, collision oracle, vectorised geometry and the fast IDM path."""

from __future__ import annotations

import numpy as np
import pytest
from highway_env.road.road import Road
from highway_env.vehicle.behavior import IDMVehicle

from deft_gym.scenarios.scenario import (
    build_world,
    load_scenario,
    scenario_from_dict,
    scenario_to_dict,
)
from deft_gym.sim.simulation import run_episode
from deft_gym.world.roadmap import MapSpec, shared_roadmap
from tests.support.fixtures import SCENARIOS


@pytest.mark.parametrize("name", ["left_turn", "right_turn", "lane_follow_static", "u_turn",
                                  "cross_intersection", "take_exit", "blocked_red_light"])
def test_every_seed_scenario_completes(name: str) -> None:
    r = run_episode(SCENARIOS / f"{name}.yaml", jitter_seed=3, keep_planning=False)
    assert r.outcome.outcome == "completed", r.summary()
    assert r.outcome.collision is None and r.outcome.min_distance > 0.0


def _with_rammer(hit: bool) -> dict:
    data = scenario_to_dict(load_scenario(SCENARIOS / "lane_follow_static.yaml"))
    data["participants"] = []
    # a scripted vehicle drives head-on along the ego's lane (y = 0), or one lane over
    y = 0.0 if hit else 7.0
    data["participants"].append({"id": "rammer", "type": "scripted",
                                 "waypoints": [{"t": 0.0, "x": 120.0, "y": y}, {"t": 6.0, "x": 0.0, "y": y}]})
    return data


def test_collision_oracle_names_participant_time_and_motion() -> None:
    r = run_episode(scenario_from_dict(_with_rammer(hit=True), source="rammer"), jitter_seed=1, keep_planning=False)
    c = r.outcome.collision
    assert r.outcome.outcome == "collision" and c is not None
    assert c.participant == "rammer" and c.kind == "scripted" and c.participant_num == 1
    assert 0.0 < c.time < 6.0 and c.time == pytest.approx(r.outcome.sim_time)
    assert isinstance(c.ego_moving, bool) and r.outcome.min_distance == 0.0


def test_no_collision_when_passing_a_lane_away() -> None:
    r = run_episode(scenario_from_dict(_with_rammer(hit=False), source="pass"), jitter_seed=1, keep_planning=False)
    assert r.outcome.collision is None
    assert 1.0 < r.outcome.min_distance < 6.0  # 7 m between centres, 2 m wide cars


@pytest.mark.parametrize("kind", ["intersection", "highway", "uturn"])
def test_vectorised_lane_geometry_matches_highway_env(kind: str) -> None:
    rm = shared_roadmap({"type": kind})
    rng = np.random.default_rng(0)
    for lane_id, g in rm.geoms.items():
        lane = rm.lanes[lane_id]
        s = rng.uniform(0, g.length, 20)
        d = rng.uniform(-2, 2, 20)
        ours = g.xy(s, d)
        ref = np.array([lane.position(a, b) for a, b in zip(s, d)])
        assert np.allclose(ours, ref, atol=1e-9)
        back_s, back_d = g.frenet(ours)
        ref_sd = np.array([lane.local_coordinates(p) for p in ref])
        assert np.allclose(np.c_[back_s, back_d], ref_sd, atol=1e-9)
        assert np.allclose(g.heading(s), [lane.heading_at(a) for a in s], atol=1e-12)


@pytest.mark.parametrize("kind", ["intersection", "uturn"])
def test_turn_lanes_add_turns_from_the_next_lanes_only(kind: str) -> None:
    """``turn_lanes: 2``: the left turn (intersection) or the U-turn also leaves from lane 1, into
    lane 1 of the road turned onto; every other lane is the default map's, exactly."""
    approach, turn, after = ((("o0", "ir0"), ("ir0", "il1"), ("il1", "o1")) if kind == "intersection"
                             else (("a", "b"), ("b", "c"), ("c", "d")))
    one, two = shared_roadmap({"type": kind}), shared_roadmap({"type": kind, "turn_lanes": 2})
    assert len(one.road_lanes(turn)) == 1 and len(two.road_lanes(turn)) == 2
    assert not any(s[:2] == turn for s in one.successors[(*approach, 1)])
    for k in (0, 1):
        assert (*turn, k) in two.successors[(*approach, k)] and (*after, k) in two.successors[(*turn, k)]
    extra = set(two.lane_ids) - set(one.lane_ids)
    assert (*turn, 1) in extra and set(one.lane_ids) <= set(two.lane_ids)
    assert len(extra) == (4 if kind == "intersection" else 1)  # one per approach
    s = np.linspace(0.0, 30.0, 7)
    for lane_id in one.lane_ids:
        assert np.array_equal(one.geoms[lane_id].xy(s, 0.5), two.geoms[lane_id].xy(s, 0.5))
    with pytest.raises(ValueError, match="turn_lanes"):
        MapSpec(type=kind, lanes=2, turn_lanes=3)


@pytest.mark.parametrize("ramp", [True, False])
def test_merge_map_ends_its_rightmost_lane(ramp: bool) -> None:
    """``merge``: the rightmost lane of b->c has no successor and only a lane change out of it,
    c->d has one lane less; with ``ramp`` the on-ramp j->k->b feeds it, tangent at b; without,
    it is a lane of a->b (a lane drop). Routes from it reach the lane beside it on c->d."""
    rm = shared_roadmap({"type": "merge", "lanes": 3, "length": 400.0, "ramp": ramp})
    assert len(rm.road_lanes(("b", "c"))) == 3 and len(rm.road_lanes(("c", "d"))) == 2
    assert len(rm.road_lanes(("a", "b"))) == (2 if ramp else 3)
    assert rm.successors[("b", "c", 2)] == [] and rm.changeable_neighbours(("b", "c", 2)) == [("b", "c", 1)]
    start = ("j", "k", 0) if ramp else ("a", "b", 2)
    route = rm.lane_route(start, ("c", "d", 1))
    assert route is not None and route[-2:] == [("b", "c", 1), ("c", "d", 1)]
    if ramp:
        assert rm.successors[("k", "b", 0)] == [("b", "c", 2)]
        g, e = rm.geom(("k", "b", 0)), rm.geom(("b", "c", 2))
        assert np.allclose(g.xy(np.array(g.length)), e.xy(np.array(0.0)), atol=1e-9)
        assert abs(float(g.heading(np.array(g.length)))) < 1e-9
    with pytest.raises(ValueError, match="at least 2 lanes"):
        MapSpec(type="merge", lanes=1)
    with pytest.raises(ValueError, match="merge_length"):
        MapSpec(type="merge", length=100.0, merge_at=0.5, merge_length=60.0)


def test_merge_options_leave_other_maps_as_they_were() -> None:
    """The merge options are dumped only when set: the other maps dump (and key caches) as before."""
    for kind in ("highway", "intersection", "uturn"):
        assert not {"ramp", "merge_at", "merge_length"} & set(MapSpec(type=kind).model_dump())
    assert MapSpec(type="merge", length=300.0, ramp=False).model_dump()["ramp"] is False


def test_right_turn_lanes_add_right_turns_from_the_next_outer_lanes_only() -> None:
    """``right_turn_lanes: 2`` on a 3-lane intersection: the right turn also leaves from lane 1,
    into lane 1 of the road turned onto (the turn road's lanes ordered left to right, as
    highway-env's); every other lane is the default map's, exactly."""
    base = {"type": "intersection", "lanes": 3}
    one, two = shared_roadmap(base), shared_roadmap({**base, "right_turn_lanes": 2})
    approach, turn, after = ("o0", "ir0"), ("ir0", "il3"), ("il3", "o3")
    assert len(one.road_lanes(turn)) == 1 and len(two.road_lanes(turn)) == 2
    assert (*turn, 0) in one.successors[(*approach, 2)] and (*after, 2) in one.successors[(*turn, 0)]
    for k, j in ((1, 0), (2, 1)):  # approach lane k, turn lane j
        assert (*turn, j) in two.successors[(*approach, k)] and (*after, k) in two.successors[(*turn, j)]
    assert not any(s[:2] == turn for s in two.successors[(*approach, 0)])
    s = np.linspace(0.0, 30.0, 7)
    right_turns = {(f"ir{c}", f"il{(c - 1) % 4}") for c in range(4)}
    for lane_id in one.lane_ids:
        if lane_id[:2] not in right_turns:
            assert np.array_equal(one.geoms[lane_id].xy(s, 0.5), two.geoms[lane_id].xy(s, 0.5))
    assert np.array_equal(one.geoms[(*turn, 0)].xy(s, 0.5), two.geoms[(*turn, 1)].xy(s, 0.5))
    assert "right_turn_lanes" not in MapSpec(**base).model_dump()
    with pytest.raises(ValueError, match="right_turn_lanes"):
        MapSpec(type="intersection", lanes=2, right_turn_lanes=3)


def test_fast_idm_follows_highway_envs_idm() -> None:
    """Our reactive vehicles compute highway-env's IDM/MOBIL with faster code: the same
    trajectories as stock IDMVehicle on the same road."""
    sc = load_scenario(SCENARIOS / "bench_highway.yaml")
    world = build_world(sc)
    stock_road = Road(network=world.roadmap.network, np_random=np.random.RandomState(0))
    stock = []
    for p in world.participants:
        o = p.obj
        v = IDMVehicle(stock_road, o.position.copy(), o.heading, o.speed, target_lane_index=o.lane_index,
                       target_speed=o.target_speed, enable_lane_change=o.enable_lane_change, timer=o.timer)
        v.DELTA = o.DELTA
        stock_road.vehicles.append(v)
        stock.append(v)
    ego = world.ego
    ego_twin = IDMVehicle(stock_road, ego.position.copy(), ego.heading, ego.speed)
    ego_twin.act = lambda action=None: None  # a vehicle that just keeps going, like our ego below
    stock_road.vehicles.insert(0, ego_twin)
    for _ in range(200):  # 10 s
        for v in stock:
            v.act()
        for v in stock_road.vehicles:
            v.step(0.05)
        world.step(0.05, 0.0, 0.0)
    for p, v in zip(world.participants, stock):
        assert np.allclose(p.obj.position, v.position, atol=1e-6), p.id
        assert p.obj.speed == pytest.approx(v.speed, abs=1e-6)


def _plain_act(self, action=None) -> None:
    """ReactiveVehicle.act as first written: highway-env's IDMVehicle.act step by step
    (change_lane_policy called every step, the generic IDM acceleration), then the lights."""
    if self.crashed:
        return
    self.follow_road()
    if self.enable_lane_change:
        self.change_lane_policy()
    steering = self.steering_control(self.target_lane_index)
    front, rear = self.road.neighbour_vehicles(self, self.lane_index)
    acc = self.acceleration(self, front, rear)
    if self.lane_index != self.target_lane_index:
        front, rear = self.road.neighbour_vehicles(self, self.target_lane_index)
        acc = min(acc, self.acceleration(self, front, rear))
    acc = max(-self.ACC_MAX, min(self.ACC_MAX, acc))
    acc_light = self._light_acceleration()
    if acc_light is not None and acc_light < acc:
        acc = max(acc_light, -self.ACC_MAX)
    self.action = {"steering": max(-self.MAX_STEERING_ANGLE, min(self.MAX_STEERING_ANGLE, steering)),
                   "acceleration": acc}


@pytest.mark.parametrize("name", ["bench_highway", "left_turn"])
def test_fast_act_is_the_plain_act_bit_for_bit(name: str) -> None:
    """ReactiveVehicle.act's shortcuts (change_lane_policy's timer test made before the call,
    the IDM gap taken from the neighbour search, comparisons for the clamps) change no bit: two
    worlds, one with the plain act, stay identical through lane changes, MOBIL decisions and
    lights, with more vehicles than the scenario has."""
    import types

    data = scenario_to_dict(load_scenario(SCENARIOS / f"{name}.yaml"))
    if name == "bench_highway":  # denser traffic: slow leaders, lane changes, one of them aborted
        rng = np.random.default_rng(0)
        for i in range(10):
            data["participants"].append({"id": f"extra_{i}", "type": "reactive", "lane": ["a", "b", i % 3],
                                         "s": 150.0 + 25.0 * i, "speed": float(rng.uniform(3, 18)),
                                         "target_speed": float(rng.uniform(5, 20))})
    sc = scenario_from_dict(data, source=name)
    fast, plain = build_world(sc), build_world(sc)
    for p in plain.participants:
        if p.kind == "reactive":
            p.obj.act = types.MethodType(_plain_act, p.obj)
    changes = 0
    for k in range(600):
        steer, acc = 0.02 * np.sin(k * 0.02), 0.8 * np.cos(k * 0.013)
        fast.step(0.05, steer, acc)
        plain.step(0.05, steer, acc)
        for a, b in zip(fast.participants, plain.participants, strict=True):
            o, q = a.obj, b.obj
            assert o.position.tobytes() == q.position.tobytes(), (k, a.id)
            assert (o.heading, o.speed) == (q.heading, q.speed), (k, a.id)
            if a.kind == "reactive":
                assert (o.action, o.lane_index, o.target_lane_index, o.timer) == \
                    (q.action, q.lane_index, q.target_lane_index, q.timer), (k, a.id)
                changes += o.lane_index != o.target_lane_index
        assert fast.min_distance == plain.min_distance
    assert changes > 0  # lane changes happened


def _plain_check_collisions(self, t: float) -> None:
    """The collision check as first written: every present participant's exact polygon distance."""
    import shapely

    from deft_gym.world.world import Collision

    ego = self.ego
    ego_poly = shapely.Polygon(ego.polygon())
    for p in self.present_participants():
        dist = ego_poly.distance(shapely.Polygon(p.obj.polygon()))
        self.min_distance = min(self.min_distance, dist)
        if dist <= 0.0 and self.collision is None:
            self.collision = Collision(p.id, p.num, p.kind, p.obstacle_type, t, float(ego.speed),
                                       bool(ego.speed > 0.1), float(ego.position[0]), float(ego.position[1]))


@pytest.mark.parametrize("hit", [True, False])
def test_collision_check_is_the_plain_check_bit_for_bit(hit: bool) -> None:
    """The bounds that skip exact distances, the sorting of only the pairs that can lower the
    minimum and the footprints built without np.tile give the plain check's minimum distance
    (every bit) and collision, with static, scripted (appearing late) and reactive participants."""
    import types

    data = scenario_to_dict(load_scenario(SCENARIOS / "take_exit.yaml"))
    data["participants"].append({"id": "late", "type": "scripted",
                                 "waypoints": [{"t": 1.5, "x": 120.0, "y": 0.0 if hit else 4.0},
                                               {"t": 8.0, "x": 0.0, "y": 0.0 if hit else 4.0}]})
    sc = scenario_from_dict(data, source="collision check")
    fast, plain = build_world(sc), build_world(sc)
    plain._check_collisions = types.MethodType(_plain_check_collisions, plain)
    for k in range(300):
        steer, acc = 0.002 * np.sin(k * 0.05), 0.0
        fast.step(0.05, steer, acc)
        plain.step(0.05, steer, acc)
        assert repr(fast.min_distance) == repr(plain.min_distance), k
        assert fast.collision == plain.collision, k
    assert (fast.collision is not None) == hit


def _red_wait(offset: float, blocked: bool = False) -> dict:
    """cross_intersection with a 3 s stuck time and the light plan shifted by ``offset`` [s];
    ``blocked``: a parked vehicle across the ego's lane before the junction, a wait no light ends."""
    data = scenario_to_dict(load_scenario(SCENARIOS / "cross_intersection.yaml"))
    data["stuck_time"] = 3.0
    data["lights"] = {**data["lights"], "offset": offset}
    data["participants"] = [p for p in data["participants"] if p["id"] != "lead"]
    if blocked:
        data["participants"] += [{"id": f"wall{k}", "type": "static", "obstacle": "STATIC_VEHICLE",
                                  "lane": ["o0", "ir0", k], "s": 70.0} for k in (0, 1)]
    return data


def test_a_wait_at_a_red_light_is_not_stuck_however_long() -> None:
    # offset 8 s: the ego reaches its stop line on red and stands there for about 9 s (> 3 s)
    r = run_episode(scenario_from_dict(_red_wait(8.0), source="red"), jitter_seed=1, keep_planning=False)
    assert r.outcome.outcome == "completed", r.summary()
    standing = r.outcome.sim_time - 10.0  # it needs about 10 s without the wait
    assert standing > 6.0, r.summary()
    # the same standstill with no light to wait for is stuck after the 3 s
    r = run_episode(scenario_from_dict(_red_wait(0.0, blocked=True), source="wall"), jitter_seed=1,
                    keep_planning=False)
    assert r.outcome.outcome == "stuck", r.summary()


def test_standing_counts_what_a_shorter_stuck_time_would_end() -> None:
    from deft_gym.cli.standing import shorter_rule

    rows = [{"outcome": "completed", "failure": "nods", "sim_time": 30.0, "stretches": [(5.0, 6.5)]},
            {"outcome": "stuck", "failure": None, "sim_time": 40.0, "stretches": [(15.0, 40.0)]},
            {"outcome": "timeout", "failure": None, "sim_time": 50.0, "stretches": [(10.0, 22.0), (30.0, 50.0)]}]
    c = shorter_rule(rows, 10.0)  # ends the stuck run at 25 s and the timeout at 20 s; the NoDS stands
    assert (c["ended"], c["failures"], c["completed"]) == (2, 0, 0)
    assert c["saved"] == pytest.approx((15.0 + 30.0) / 120.0)
    assert shorter_rule(rows, 1.0)["failures"] == 1 and shorter_rule(rows, 30.0)["ended"] == 0


def test_a_reactive_vehicle_too_close_to_a_standing_leader_does_not_reverse() -> None:
    """IDM's acceleration is negative at a standstill when the gap is below its standstill gap;
    highway-env then lets the speed go negative (a car rolled back at -1.7 m/s into the ego on
    gen:2000003). Ours stands."""
    data = scenario_to_dict(load_scenario(SCENARIOS / "handwritten" / "stalled_car.yaml"))
    data["participants"] = [
        {"id": "parked", "type": "static", "obstacle": "STATIC_VEHICLE", "lane": ["a", "b", 2], "s": 100.0},
        {"id": "close", "type": "reactive", "lane": ["a", "b", 2], "s": 94.0, "speed": 0.0,
         "target_speed": 10.0, "lane_change": False}]
    world = build_world(scenario_from_dict(data, source="close"))
    car = next(p.obj for p in world.participants if p.id == "close")
    start = car.position.copy()
    speeds = []
    for _ in range(60):  # 3 s
        world.step(0.05, 0.0, 0.0)
        speeds.append(car.speed)
    assert min(speeds) == 0.0  # IDM braked it (into reverse, before the fix)
    assert car.position[0] >= start[0] - 1e-9


@pytest.mark.parametrize(("beside", "speed", "done"), [(0.0, 5.0, True), (3.5, 0.0, True), (3.5, 5.0, False),
                                                       (7.0, 0.0, False)])
def test_an_ego_standing_level_with_its_destination_a_lane_over_has_arrived(beside: float, speed: float,
                                                                           done: bool) -> None:
    """Within 3 m of the destination point the ego has arrived; 3.5 m beside it, in the next lane,
    only once it stands there (it stopped at its destination, one lane over), never while it
    drives past, and never two lanes over."""
    from deft_gym.scenarios.scenario import destination_xy
    from deft_gym.sim.oracles import EpisodeOracle

    sc = load_scenario(SCENARIOS / "lane_follow_static.yaml")
    world = build_world(sc)
    lane = world.roadmap.geom(tuple(sc.ego.destination.lane))
    xy, s = destination_xy(world.roadmap, sc.ego.destination)
    oracle = EpisodeOracle(world, xy, sc.duration, destination_lane=lane, destination_s=s)
    world.ego.position = lane.xy(np.array(s - 1.0), beside).astype(float)  # 1 m short of it
    world.ego.speed = speed
    assert (oracle.check() == "completed") is done
    assert oracle.arrival == (None if not done else "radius" if beside == 0.0 else "a lane over")
    if done:
        assert ("arrival" in oracle.outcome().as_dict()) is (beside > 0.0)


def test_a_run_that_arrives_a_lane_over_says_so_in_its_summary() -> None:
    """A car parked on the destination of the hand-written parked street: the ego, in the other
    lane, stops beside it, level with its destination one lane over - it has arrived (before
    2026-11-27 this run timed out, standing there), and its summary says how."""
    from deft_gym.scenarios.scenario import destination_xy
    from deft_gym.search.context import resolve_scenario

    sc = resolve_scenario("handwritten/parked_street")
    xy, _ = destination_xy(shared_roadmap(sc.map), sc.ego.destination)
    data = scenario_to_dict(sc)
    data["participants"].append({"id": "on_destination", "type": "static", "obstacle": "STATIC_VEHICLE",
                                 "x": float(xy[0]), "y": float(xy[1]), "heading": 0.0})
    s = run_episode(scenario_from_dict(data, source="parked on the destination"), jitter_seed=1,
                    keep_planning=False).summary()
    assert (s["outcome"], s.get("arrival")) == ("completed", "a lane over"), s


def test_a_scripted_vehicle_moving_from_the_start_is_perceived_moving_in_the_first_frame() -> None:
    """Perception's first frame comes before the first step places the scripted vehicles: one that
    drives from t = 0 starts with its first segment's speed (it was 0, so slow_truck's truck at
    6 m/s was predicted parked for prediction's static_hold, and both planners pulled out round it);
    one that waits at its first waypoint starts standing."""
    from deft_gym.world.participants import ScriptedVehicle

    road = Road(shared_roadmap(MapSpec(type="highway")).network)
    moving = ScriptedVehicle(road, np.array([[0.0, 0.0, 0.0], [10.0, 60.0, 0.0]]), 0.0)
    assert moving.speed == pytest.approx(6.0)
    moving.place(5.0)
    assert moving.speed == pytest.approx(6.0) and moving.position[0] == pytest.approx(30.0)
    waiting = ScriptedVehicle(road, np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [10.0, 30.0, 0.0]]), 0.0)
    assert waiting.speed == 0.0
    world = build_world(load_scenario("handwritten/slow_truck"))  # the world perception's first frame reads
    truck = next(p.obj for p in world.participants if p.id == "truck")
    assert truck.speed == pytest.approx(6.0)
