"""The scalar fast paths give numpy's results bit for bit (so speed-ups never change a log)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from deft_gym.modules.control import _nearest
from deft_gym.world.interp import interp1
from tests.support.fixtures import float_bits


def _same(a: float, b: float) -> bool:
    return a == b or (math.isnan(a) and math.isnan(b))


@pytest.mark.parametrize("seed", range(4))
def test_interp1_matches_np_interp_bitwise(seed: int) -> None:
    rng = np.random.default_rng(seed)
    checked = 0
    for _ in range(500):
        n = int(rng.integers(1, 35))
        xp = np.sort(rng.normal(size=n) * rng.choice([1e-3, 1.0, 1e3]))
        if n > 2 and rng.random() < 0.3:
            xp[n // 2] = xp[n // 2 - 1]  # repeated sample point (a standing trajectory's arc length)
        fp = rng.normal(size=n) * 50.0
        if rng.random() < 0.1:
            fp[int(rng.integers(n))] = rng.choice([np.inf, -np.inf, np.nan])
        queries = [xp[0] - 1.0, xp[-1] + 1.0, math.nan, *xp.tolist(),
                   *rng.uniform(xp[0] - 0.1, xp[-1] + 0.1, 6).tolist()]
        for x in queries:
            want = float(np.interp(x, xp, fp))
            got = interp1(float(x), xp.tolist(), fp.tolist())
            assert _same(want, got), (x, xp, fp, want, got)
            checked += 1
    assert checked > 10_000


def test_nearest_matches_np_argmin() -> None:
    rng = np.random.default_rng(5)
    for _ in range(2000):
        xs, ys = rng.normal(size=8).round(1), rng.normal(size=8).round(1)  # ties happen
        if rng.random() < 0.2:
            xs[int(rng.integers(8))] = np.nan
        x, y = float(rng.normal()), float(rng.normal())
        want = int(np.argmin((xs - x) ** 2 + (ys - y) ** 2))
        assert _nearest(xs.tolist(), ys.tolist(), x, y) == want


def test_box_gap_is_a_lower_bound_of_the_polygon_distance() -> None:
    """The collision check skips the exact polygon distance when this bound already exceeds
    the minimum; it must never exceed the exact distance, and must be positive when apart."""
    from types import SimpleNamespace

    import shapely

    from deft_gym.world.geometry import box_gap, box_gap_point

    rng = np.random.default_rng(3)
    for _ in range(3000):
        boxes = []
        for _ in range(2):
            length, width = [(4.8, 2.0), (0.6, 0.6), (8.0, 2.5)][int(rng.integers(3))]
            o = SimpleNamespace(position=rng.normal(size=2) * 6, heading=float(rng.uniform(-4, 4)),
                                LENGTH=length, WIDTH=width)
            c, s = math.cos(o.heading), math.sin(o.heading)
            corners = np.array([[-1, -1], [-1, 1], [1, 1], [1, -1]]) * [length / 2, width / 2]
            boxes.append((o, shapely.Polygon(corners @ np.array([[c, s], [-s, c]]) + o.position)))
        (a, pa), (b, pb) = boxes
        exact = pa.distance(pb)
        gap = float(box_gap(*a.position, a.heading, a.LENGTH, a.WIDTH, *b.position, b.heading, b.LENGTH, b.WIDTH))
        assert gap <= exact + 1e-9
        assert (gap > 0) == (exact > 0)
        scalar = box_gap_point(*a.position.tolist(), a.heading, a.LENGTH, a.WIDTH, *b.position.tolist(), b.heading,
                               b.LENGTH, b.WIDTH)
        assert scalar == pytest.approx(gap, abs=1e-12)


def test_unwrap_shortcut_matches_np_unwrap_bitwise() -> None:
    from deft_gym.modules.control import _unwrap

    rng = np.random.default_rng(9)
    for _ in range(3000):
        h = np.cumsum(rng.normal(size=int(rng.integers(1, 32))) * rng.choice([0.05, 1.0, 4.0]))
        h = (h + np.pi) % (2 * np.pi) - np.pi
        if rng.random() < 0.2:
            h[0] = -0.0
        if rng.random() < 0.05:
            h[int(rng.integers(len(h)))] = np.nan
        want, got = np.unwrap(h), _unwrap(h)
        assert np.array_equal(want.view(np.int64), got.view(np.int64))  # identical bits, signed zeros too


def test_control_trajectory_lists_match_the_numpy_path_bitwise() -> None:
    """Control converts a plan with plain-float lists itself; it must give numpy's values."""
    from deft_gym.modules.control import _float_lists, _numpy_trajectory, _well_formed

    rng = np.random.default_rng(13)
    taken = 0
    for _ in range(1500):
        n = int(rng.integers(1, 40))
        tr = {k: (rng.normal(size=n) * 20).tolist() for k in ("x", "y", "v", "a")}
        tr["t"] = np.cumsum(rng.uniform(0.0, 0.2, size=n)).tolist()
        h = np.cumsum(rng.normal(size=n) * rng.choice([0.05, 1.0, 4.0]))
        tr["heading"] = ((h + np.pi) % (2 * np.pi) - np.pi).tolist()
        if rng.random() < 0.2:
            tr["heading"][int(rng.integers(n))] = -0.0
        if rng.random() < 0.1:
            tr[str(rng.choice(["x", "heading", "t"]))][int(rng.integers(n))] = float("nan")
        if rng.random() < 0.05 and n > 1:
            tr["t"][-1] = tr["t"][0] - 1.0  # time going backwards
        want, fast = _numpy_trajectory(tr)
        got = _float_lists(tr)
        assert got is not None
        assert _well_formed(got) == fast
        if fast:
            taken += 1
            assert set(got) == set(want)
            for k in want:
                assert float_bits(got[k]) == float_bits(want[k]), k
    assert taken > 1000
    # anything but equal-length lists of plain floats is left to numpy
    assert _float_lists({"t": [0, 1], "x": [0.0, 1.0], "y": [0.0, 1.0], "v": [1.0, 1.0], "a": [0.0, 0.0],
                         "heading": [0.0, 0.0]}) is None
    assert _float_lists({"t": [0.0, 1.0], "x": [0.0], "y": [0.0, 1.0], "v": [1.0, 1.0], "a": [0.0, 0.0],
                         "heading": [0.0, 0.0]}) is None


def test_scalar_frenet_matches_numpy_bitwise() -> None:
    """``frenet_list`` and ``xy_list`` (scalar on straight lanes) give ``frenet``'s and ``xy``'s
    bits, NaN and all, on single lanes and on reference lines mixing straight and circular pieces."""
    from highway_env.road.lane import CircularLane, StraightLane

    from deft_gym.world.geometry import LaneGeom, ReferenceLine

    rng = np.random.default_rng(21)
    a = StraightLane([0.0, 0.0], [37.3, 21.9])  # diagonal: products are not exact
    end = a.position(a.length, 0.0)
    b = CircularLane(end + np.array([-30.0 * math.sin(a.heading), 30.0 * math.cos(a.heading)]), 30.0,
                     a.heading - math.pi / 2, a.heading, clockwise=True)
    c = StraightLane(b.position(b.length, 0.0), b.position(b.length, 0.0) + np.array([3.0, 55.0]))
    geoms = [LaneGeom(lane) for lane in (a, b, c)]
    lines = [ReferenceLine([("a", "b", 0)], geoms[:1]),
             ReferenceLine([("a", "b", 0), ("b", "c", 0), ("c", "d", 0)], geoms)]
    for _ in range(300):
        pts = rng.normal(size=(int(rng.integers(0, 12)), 2)) * 40 + [30.0, 30.0]
        if len(pts) and rng.random() < 0.2:
            pts[int(rng.integers(len(pts))), int(rng.integers(2))] = np.nan
        for g in geoms:
            s, d = g.frenet(pts)
            s_l, d_l = g.frenet_list(pts.tolist())
            assert float_bits(s_l) == float_bits(s) and float_bits(d_l) == float_bits(d)
            st, off = (pts[:, 0] * 3.0).tolist(), float(rng.normal() * 2)
            x_l, y_l = g.xy_list(st, off)
            xy = g.xy(np.array(st), off).reshape(-1, 2)
            assert float_bits(x_l) == float_bits(xy[:, 0]) and float_bits(y_l) == float_bits(xy[:, 1])
        for line in lines:
            s, d = line.frenet(pts)
            s_l, d_l = line.frenet_list(pts.tolist())
            assert float_bits(s_l) == float_bits(s) and float_bits(d_l) == float_bits(d)


def test_footprint_is_highway_envs_polygon_bitwise() -> None:
    """The collision check's footprints are ``RoadObject.polygon()``'s arrays, bit for bit."""
    from deft_gym.scenarios.scenario import build_world, load_scenario
    from deft_gym.world.world import footprint
    from tests.support.fixtures import SCENARIOS

    world = build_world(load_scenario(SCENARIOS / "take_exit.yaml"))
    objs = [world.ego] + [p.obj for p in world.participants]  # ego, reactive, a cone
    rng = np.random.default_rng(8)
    for k in range(3000):
        o = objs[k % len(objs)]
        o.position = rng.normal(size=2) * 10.0 ** float(rng.integers(0, 4))
        o.heading = float(rng.normal() * 4) if k % 7 else float(rng.choice([0.0, math.pi / 2, -math.pi]))
        got, want = footprint(o), o.polygon()
        assert got.shape == want.shape and got.tobytes() == want.tobytes()


def _plain_neighbours(road, vehicle, lane_index):
    """highway-env's neighbour search as DeFT-Gym first wrote it: every member projected,
    the on-lane test, None-started comparisons."""
    from highway_env.road.lane import AbstractLane
    from highway_env.vehicle.objects import Landmark

    members = [v for v in road.vehicles + road.objects if not isinstance(v, Landmark)]
    geom = road.geoms[lane_index]
    s_all, lat = geom.frenet_list([[float(v.position[0]), float(v.position[1])] for v in members])
    L = AbstractLane.VEHICLE_LENGTH
    half, end = geom.width / 2 + 1.0, geom.length + L
    me = next(i for i, m in enumerate(members) if m is vehicle)
    s = s_all[me]
    s_front = s_rear = None
    i_front = i_rear = -1
    for i, s_v in enumerate(s_all):
        if i == me or not (abs(lat[i]) <= half and -L <= s_v < end):
            continue
        if s <= s_v and (s_front is None or s_v <= s_front):
            s_front, i_front = s_v, i
        if s_v < s and (s_rear is None or s_v > s_rear):
            s_rear, i_rear = s_v, i
    return (members[i_front] if i_front >= 0 else None, members[i_rear] if i_rear >= 0 else None,
            s_front - s if i_front >= 0 else None)


@pytest.mark.parametrize("kind", ["highway", "intersection"])
def test_fast_road_neighbours_match_the_plain_search(kind: str) -> None:
    """FastRoad's neighbours (cached projections, on-lane lists, members rebuilt only when the
    road's lists change) are the plain search's, ties included, on straight and circular lanes;
    the front gap is ``lane_distance_to``'s."""
    from highway_env.road.road import Road

    from deft_gym.world.participants import StaticObstacle
    from deft_gym.world.road import FastRoad
    from deft_gym.world.roadmap import shared_roadmap

    rm = shared_roadmap({"type": kind})
    road = FastRoad(network=rm.network, np_random=np.random.RandomState(0), record_history=False, geoms=rm.geoms)
    stock = Road(network=rm.network, np_random=np.random.RandomState(0), record_history=False)
    rng = np.random.default_rng(4)
    lanes = list(rm.geoms)
    checked = 0
    where: dict[int, tuple] = {}  # object -> (lane, s, d)
    for step in range(60):
        if step % 6 == 0:  # the road's lists change: a new object (sometimes on another's spot)
            if where and rng.random() < 0.5:
                lane_index, s, d = where[int(rng.integers(len(where)))]
            else:
                lane_index = lanes[int(rng.integers(len(lanes)))]
                s, d = float(rng.uniform(-8, rm.geoms[lane_index].length)), float(rng.normal())
            road.objects.append(StaticObstacle(road, np.zeros(2), 0.0, "CONE"))
            where[len(road.objects) - 1] = (lane_index, s, d)
        for k, o in enumerate(road.objects):  # everybody moves a little along its lane
            lane_index, s, d = where[k]
            g = rm.geoms[lane_index]
            if step % 6:
                s, d = s + float(rng.uniform(0, 2)), d + float(rng.normal() * 0.2)
                where[k] = (lane_index, s, d)
            o.position = g.xy(np.array(s), d)
            o.heading = g.heading_point(s)
            o.lane_index, o.lane = lane_index, rm.lanes[lane_index]
        road.advance()
        stock.objects = road.objects
        for o in road.objects:
            for lane_index in {o.lane_index, lanes[int(rng.integers(len(lanes)))]}:
                front, rear, gap = road.neighbours(o, lane_index)
                want = _plain_neighbours(road, o, lane_index)
                assert (front, rear) == want[:2] == road.neighbour_vehicles(o, lane_index)
                assert (gap if front is not None else None) == want[2]
                if front is not None and lane_index == o.lane_index:
                    assert gap == o.lane_distance_to(front)  # highway-env's, on the object's lane
                if kind == "highway":
                    assert (front, rear) == stock.neighbour_vehicles(o, lane_index)
                checked += 1
        # a vehicle that is no road member: projected on its own, no gap from the projections
        lane_index, s, d = where[int(rng.integers(len(where)))]
        ghost = StaticObstacle(road, rm.geoms[lane_index].xy(np.array(s + 0.5), d), 0.0, "CONE")
        front, rear, gap = road.neighbours(ghost, lane_index)
        assert math.isnan(gap) and road.index_of(ghost) == -1
        if kind == "highway":
            assert (front, rear) == stock.neighbour_vehicles(ghost, lane_index)
    assert checked > 500


def test_polyline_distance_is_shapelys_distance_bitwise() -> None:
    """The segment tree gives shapely's distance to the whole line, float for float: random walks,
    repeated vertices, points on and next to the line, far away, and not finite."""
    import shapely

    from deft_gym.world.geometry import PolylineDistance

    rng = np.random.default_rng(0)
    for k in range(60):
        m = int(rng.integers(2, 1500))
        xy = np.cumsum(rng.normal(0, 1, (m, 2)), axis=0)
        if k % 3 == 0:
            xy[int(rng.integers(1, m))] = xy[int(rng.integers(0, m))]  # a repeated vertex
        if k % 5 == 0:
            xy = np.round(xy, 1)
        pts = np.r_[xy[rng.integers(0, m, 30)], xy.mean(0) + rng.normal(0, 30, (100, 2)),
                    xy[rng.integers(0, m, 20)] + rng.normal(0, 1e-9, (20, 2)), [[np.nan, 0.0], [np.inf, 1.0]]]
        got = PolylineDistance(xy)(pts)
        want = shapely.distance(shapely.points(pts), shapely.LineString(xy))
        np.testing.assert_array_equal(float_bits(got), float_bits(want))
