"""The scalar fast paths give numpy's results bit for bit (so speed-ups never change a log)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from deft_gym.interp import interp1
from deft_gym.modules.control import _nearest


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

    from deft_gym.geometry import box_gap, box_gap_point

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


def _bits(a: object) -> bytes:
    return np.asarray(a, dtype=float).tobytes()


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
                assert _bits(got[k]) == _bits(want[k]), k
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

    from deft_gym.geometry import LaneGeom, ReferenceLine

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
            assert _bits(s_l) == _bits(s) and _bits(d_l) == _bits(d)
            st, off = (pts[:, 0] * 3.0).tolist(), float(rng.normal() * 2)
            x_l, y_l = g.xy_list(st, off)
            xy = g.xy(np.array(st), off).reshape(-1, 2)
            assert _bits(x_l) == _bits(xy[:, 0]) and _bits(y_l) == _bits(xy[:, 1])
        for line in lines:
            s, d = line.frenet(pts)
            s_l, d_l = line.frenet_list(pts.tolist())
            assert _bits(s_l) == _bits(s) and _bits(d_l) == _bits(d)
