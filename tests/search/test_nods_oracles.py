"""Decictor's oracles on synthetic and real traces: consistency (IoU), feedback, validity."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from deft_gym.search.context import seed_context
from deft_gym.search.nods import LaneCells, iou, mmd_linear, world_cells
from deft_gym.search.trace import Actor, Trace
from deft_gym.world.geometry import box_gap


@pytest.fixture(scope="module")
def ctx():
    return seed_context("lane_follow_static")


def _shifted(ref: Trace, dy: float) -> Trace:
    ego = ref.ego.copy()
    ego[:, 1] += dy
    return dataclasses.replace(ref, ego=ego)


def test_identical_path_is_consistent(ctx):
    v = ctx.oracle.judge(ctx.ref)
    assert v.iou == 1.0 and v.f_p == pytest.approx(0.0, abs=1e-9) and v.f_b == pytest.approx(0.0, abs=1e-12)
    assert v.valid and not v.nods and not v.collision and v.failure is None


def test_lane_grid_ignores_drift_inside_the_lane(ctx):
    drift = _shifted(ctx.ref, 0.4)  # a nudge: same lane cells
    assert ctx.oracle.iou(drift.xy) == 1.0
    # the square world grid is sensitive to where cell borders fall
    assert iou(world_cells(ctx.ref.xy), world_cells(drift.xy)) < 1.0


def test_a_path_in_the_next_lane_is_a_non_optimal_decision(ctx):
    other = _shifted(ctx.ref, ctx.roadmap.spec.lane_width)
    other = dataclasses.replace(other, outcome="completed")
    v = ctx.oracle.judge(other)
    assert v.iou <= 0.6 and v.nods and v.failure == "nods"
    assert v.f_p == pytest.approx(ctx.roadmap.spec.lane_width, rel=0.05)
    # the same path that ends in a collision or a timeout is no NoDS
    assert not ctx.oracle.judge(dataclasses.replace(other, outcome="timeout")).nods


def test_mmd_linear_is_the_squared_mean_distance():
    rng = np.random.default_rng(1)
    x, y = rng.normal(size=(50, 4)), rng.normal(1.0, size=(70, 4))
    k_xx, k_yy, k_xy = x @ x.T, y @ y.T, x @ y.T
    assert mmd_linear(x, y) == pytest.approx(k_xx.mean() + k_yy.mean() - 2 * k_xy.mean())


def test_validity_replays_the_reference_ego(ctx):
    ref = ctx.ref
    mid = len(ref.ticks) // 2
    on_path = np.array([[ref.ticks[mid], 0, ref.xy[mid, 0], ref.xy[mid, 1], 0.0]])
    beside = on_path.copy()
    beside[0, 3] += 4.0
    actors = [Actor("cone", "static", "CONE", 0.6, 0.6, added=True)]
    bad = dataclasses.replace(ref, actors=actors, parts=on_path)
    good = dataclasses.replace(ref, actors=actors, parts=beside)
    assert ctx.oracle.judge(bad).invasive == ["cone"]
    assert ctx.oracle.judge(good).valid


def test_box_gap_is_a_separating_axis_bound():
    g = box_gap(np.array(0.0), np.array(0.0), np.array(0.0), 4.8, 2.0, np.array([10.0, 3.0]), np.array([0.0, 0.0]),
                np.array([0.0, 0.0]), np.array([4.8, 4.8]), np.array([2.0, 2.0]))
    assert g[0] == pytest.approx(5.2) and g[1] < 0


def test_lane_cells_cover_every_lane_point(ctx):
    cells = LaneCells(ctx.roadmap)
    pi, _li, s = cells.membership(ctx.ref.xy)
    assert set(pi.tolist()) == set(range(len(ctx.ref.xy)))  # every reference point lies on a lane
    assert (s >= 0).all()
