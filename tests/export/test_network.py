"""The export's road network and replay waypoints, without the export extra: the network's roads
match the map's lanes, the light phases are the plan's colours, and a scripted vehicle on the
replay waypoints has the recorded position, heading and speed at every world step."""

from __future__ import annotations

import math

import numpy as np
import pytest

from deft_gym.export.network import build_network, lane_polyline
from deft_gym.export.openscenario import light_phases, speeds
from deft_gym.export.roundtrip import replay_waypoints
from deft_gym.world.roadmap import RoadMap
from deft_gym.world.traffic_lights import LightPlan, TrafficLights

MAPS = [{"type": "intersection"}, {"type": "intersection", "lanes": 3, "turn_lanes": 2, "right_turn_lanes": 2},
        {"type": "highway", "lanes": 3}, {"type": "uturn", "turn_lanes": 2}, {"type": "highway", "lanes": 1}]


@pytest.mark.parametrize("spec", MAPS, ids=lambda s: "-".join(f"{v}" for v in s.values()))
def test_every_lane_is_a_lane_of_its_road_in_the_export_frame(spec: dict) -> None:
    rm = RoadMap(spec)
    net = build_network(rm)
    assert sorted(net.lane_of) == sorted(tuple(lid) for lid in rm.lane_ids)
    for lid, (rid, lane) in net.lane_of.items():
        road = net.road(rid)
        g = rm.geom(lid)
        k = -lane - 1
        ratio = road.ref.length / rm.geom(road.lanes[0]).length
        for s in np.linspace(0.0, g.length, 7):
            # lane k's centre is (k + 1/2) widths right of the reference line; y and heading mirrored
            s_ref = s * ratio if g.kind == "straight" else s * road.ref.length / g.length
            x, y, h = road.ref.point(s_ref, -(k + 0.5) * road.width)
            wx, wy = g.xy(np.array(s))
            assert math.hypot(x - wx, y + wy) < 1e-6, (lid, s)
            assert abs(math.remainder(h + float(g.heading(np.array(s))), math.tau)) < 1e-9
    for r in net.roads:  # a road's lanes link where the map's lanes do
        for lane, targets in r.lane_succ.items():
            lid = r.lanes[-lane - 1]
            assert sorted(targets) == sorted(net.lane_of[tuple(s)] for s in rm.successors[lid])
    if rm.stop_lines:
        assert {s.light_id for s in net.signals} == set(rm.light_groups)
    assert lane_polyline(rm, rm.lane_ids[0]).shape[1] == 2


def test_junctions_are_the_map_junctions_and_its_forks() -> None:
    net = build_network(RoadMap({"type": "intersection"}))
    assert len(net.junctions) == 1 and len(next(iter(net.junctions.values()))) == 12
    hw = build_network(RoadMap({"type": "highway"}))
    (members,) = hw.junctions.values()
    assert sorted(hw.road(r).key for r in members) == [("b", "c"), ("b", "x")]  # the exit forks at b


@pytest.mark.parametrize("plan", [{}, {"green": 10.0, "yellow": 3.0, "all_red": 1.0, "offset": 11.0},
                                  {"green": 9.0, "yellow": 0.0, "all_red": 2.5, "offset": 40.3}])
def test_light_phases_are_the_plans_colours(plan: dict) -> None:
    groups = {"tl0": 0, "tl1": 1, "tl2": 0, "tl3": 1}
    phases = light_phases(plan, groups)
    lights = TrafficLights(groups, LightPlan.model_validate(plan))
    assert abs(sum(d for d, _ in phases) - lights.cycle) < 1e-9
    assert all(d > 0 for d, _ in phases)
    starts = np.cumsum([0.0] + [d for d, _ in phases])
    for t in np.linspace(0.0, 3 * lights.cycle, 997):
        i = int(np.searchsorted(starts, t % lights.cycle, side="right")) - 1
        assert phases[i][1] == {lid: lights.color(lid, t) for lid in sorted(groups)}, t


def test_replay_waypoints_give_the_recorded_pose_and_speed_at_every_step() -> None:
    from highway_env.road.road import Road

    from deft_gym.world.participants import ScriptedVehicle

    dt = 0.05
    t = np.arange(1, 120) * dt  # a bicycle's path: heading off its motion, speed changing, a stop
    h = 0.3 * np.sin(t) + 2.0
    v = np.clip(8.0 - 3.0 * t, 0.0, None)
    x = 10.0 + np.cumsum(v * np.cos(h + 0.05) * dt)
    y = -5.0 + np.cumsum(v * np.sin(h + 0.05) * dt)
    rows = np.column_stack([t, x, y, h, v])
    wp = replay_waypoints(rows, dt)
    veh = ScriptedVehicle(Road(RoadMap({"type": "highway"}).network), np.array([[w["t"], w["x"], w["y"]] for w in wp]), wp[0]["heading"])
    assert veh.heading == h[0]
    for tk, xk, yk, hk, vk in rows:
        veh.place(float(tk))
        assert math.hypot(veh.position[0] - xk, veh.position[1] - yk) < 1e-9
        assert abs(math.remainder(veh.heading - hk, math.tau)) < 1e-6
        assert abs(veh.speed - max(vk, 1e-4)) < 1e-6


def test_speeds_of_a_polyline_are_the_step_distances() -> None:
    rows = np.array([[0.0, 0.0, 0.0, 0.0], [0.05, 0.5, 0.0, 0.0], [0.10, 0.9, 0.0, 0.0], [0.15, 0.85, 0.0, 0.0]])
    assert np.allclose(speeds(rows), [10.0, 8.0, -1.0, -1.0])
