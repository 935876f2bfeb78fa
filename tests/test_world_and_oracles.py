"""World, collision oracle, vectorised geometry and the fast IDM path."""

from __future__ import annotations

import numpy as np
import pytest
from highway_env.road.road import Road
from highway_env.vehicle.behavior import IDMVehicle

from deft_gym.roadmap import shared_roadmap
from deft_gym.scenario import build_world, load_scenario, scenario_from_dict, scenario_to_dict
from deft_gym.simulation import run_episode
from tests.conftest import SCENARIOS


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
