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

    from deft_gym.geometry import box_gap

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
