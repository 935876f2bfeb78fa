"""Non-invasive feasible areas: what they admit never touches the ego's reference motion."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from deft_gym.search.context import seed_context
from deft_gym.search.feasible import FeasibleConfig, Layout, Placed, reachable_area
from deft_gym.search.nods import EGO_LENGTH, EGO_WIDTH
from deft_gym.search.vehicles import LENGTH, WIDTH, Controls, LaneDriver, VState, complete
from deft_gym.world.geometry import box_corners, box_gap


@pytest.fixture(scope="module")
def ctx():
    return seed_context("lane_follow_static")


def test_reference_run_is_an_optimal_seed(ctx):
    ref = ctx.ref
    assert ref.outcome == "completed"
    assert len(ref.ticks) == len(ref.ego) and ref.ticks[0] == 0
    assert ctx.areas.n_windows == int(np.ceil(ctx.scenario.duration / ctx.feasible.dt))
    # every window's ego area contains the reference ego positions of that window
    for k in range(0, ctx.areas.n_windows, 3):
        t = ref.t
        sel = (t >= k * 2.0) & (t <= (k + 1) * 2.0)
        if sel.any():
            assert shapely.contains_xy(ctx.areas.ego[k], ref.xy[sel, 0], ref.xy[sel, 1]).all()


def test_static_placements_never_touch_the_inflated_reference_ego(ctx):
    rng = np.random.default_rng(0)
    lay = Layout(ctx.areas)
    x0, y0, x1, y1 = ctx.areas.roi.bounds
    x, y = rng.uniform(x0, x1, 3000), rng.uniform(y0, y1, 3000)
    h = rng.uniform(-np.pi, np.pi, 3000)
    ok = lay.static_ok(x, y, h, 0.6, 0.6)
    assert 0 < ok.sum() < len(ok)  # some admitted, some refused
    e = ctx.ref.ego
    m = ctx.feasible.margin
    gap = box_gap(e[None, :, 0], e[None, :, 1], e[None, :, 2], EGO_LENGTH + 2 * m - 1e-6, EGO_WIDTH + 2 * m - 1e-6,
                  x[ok, None], y[ok, None], h[ok, None], 0.6, 0.6)
    assert (gap > 0).all()
    # an obstacle right on the reference path is refused
    mid = ctx.ref.xy[len(ctx.ref.xy) // 2]
    assert not lay.static_ok(mid[:1], mid[1:], np.zeros(1), 0.6, 0.6)[0]


def test_added_participants_are_respected(ctx):
    lay = Layout(ctx.areas)
    x, y = np.array([60.0]), np.array([4.0])
    assert lay.static_ok(x, y, np.zeros(1), 0.6, 0.6)[0]
    lay.add(Placed("c1", "static", {}, area=lay.static_footprint(60.0, 4.0, 0.0, 0.6, 0.6)))
    assert not lay.static_ok(x, y, np.zeros(1), 0.6, 0.6)[0]
    assert lay.remove("c1") is not None
    assert lay.static_ok(x, y, np.zeros(1), 0.6, 0.6)[0]


def test_completed_vehicle_trajectories_stay_clear_of_the_reference_ego(ctx):
    lay = Layout(ctx.areas)
    drv = LaneDriver(ctx.roadmap)
    found = 0
    for s0, v in ((5.0, 6.0), (40.0, 3.0), (80.0, 10.0)):
        st = VState(("a", "b", 1), s0, 0.0, v)
        first = drv.window(st, 0.0, Controls(v))
        if lay.first_conflict(first.t, first.x, first.y, first.h, LENGTH, WIDTH, k_to=1) >= 0:
            continue
        traj = complete(drv, lay, first, ctx.scenario.duration, ctx.path.xy)
        if traj is None:
            continue
        found += 1
        assert np.all(np.diff(traj.t) > 0) and traj.t[-1] >= ctx.scenario.duration - 1e-9
        # time-synchronous check against the reference ego (windows are stricter still)
        t = ctx.ref.t
        vx, vy = np.interp(t, traj.t, traj.x), np.interp(t, traj.t, traj.y)
        vh = np.interp(t, traj.t, np.unwrap(traj.h))
        pres = t >= traj.t[0]
        e = ctx.ref.ego
        gap = box_gap(e[pres, 0], e[pres, 1], e[pres, 2], EGO_LENGTH, EGO_WIDTH, vx[pres], vy[pres], vh[pres],
                      LENGTH, WIDTH)
        assert (gap > 0).all()
        assert lay.first_conflict(traj.t, traj.x, traj.y, traj.h, LENGTH, WIDTH) == -1
    assert found >= 1


def test_lane_driver_changes_lanes_and_follows_successors(ctx):
    drv = LaneDriver(ctx.roadmap)
    w = drv.window(VState(("a", "b", 0), 10.0, 0.0, 8.0), 0.0, Controls(8.0, shift=1))
    assert w.states[-1].lane == ("a", "b", 1) and abs(w.states[-1].d) < 1e-9
    assert abs(w.y[-1] - ctx.roadmap.spec.lane_width) < 1e-6  # lane 1 centre
    assert drv.window(VState(("a", "b", 0), 10.0, 0.0, 8.0), 0.0, Controls(8.0, shift=-1)) is None  # no lane left
    g = ctx.roadmap.geom(("a", "b", 0))
    w2 = drv.window(VState(("a", "b", 0), g.length - 3.0, 0.0, 10.0), 0.0, Controls(10.0))
    assert w2.states[-1].lane[:2] == ("b", "c")


def test_lane_driver_does_not_cross_a_solid_line(ctx):
    """Adversary vehicles change lanes only where the map allows it (a striped line)."""
    from highway_env.road.lane import LineType

    from deft_gym.world.roadmap import RoadMap

    rm = RoadMap(ctx.roadmap.spec)  # a private copy: the shared map stays as it is
    lane = rm.lanes[("a", "b", 1)]
    assert LaneDriver(rm).neighbour(("a", "b", 0), 1) == ("a", "b", 1)
    lane.line_types = (LineType.CONTINUOUS, lane.line_types[1])
    drv = LaneDriver(rm)
    assert drv.neighbour(("a", "b", 0), 1) is None and drv.neighbour(("a", "b", 1), -1) is None
    assert drv.window(VState(("a", "b", 0), 10.0, 0.0, 8.0), 0.0, Controls(8.0, shift=1)) is None


def test_reachable_area_covers_the_next_waypoint(ctx):
    st = VState(("a", "b", 1), 30.0, 0.0, 8.0)
    area = reachable_area(ctx.roadmap, st.lane, st.s, st.v, 2.0, v_max=12.0)
    w = LaneDriver(ctx.roadmap).window(st, 0.0, Controls(8.0))
    assert area.contains(shapely.Point(w.x[-1], w.y[-1]))


def test_config_errors_name_the_field():
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="margin"):
        FeasibleConfig(margin=-1.0)


def _plain_static_ok(lay: Layout, x, y, h, length, width):
    """The box test on every box on the ground (what static_ok answered before its centre test)."""
    ok = shapely.contains_xy(lay.areas.ground, x, y)
    idx = np.flatnonzero(ok)
    polys = shapely.polygons(box_corners(x[idx], y[idx], h[idx], length, width))
    free = ~shapely.intersects(polys, lay.areas.static_forbidden)
    other = lay._added_any()
    if other is not None:
        free &= ~shapely.intersects(polys, other)
    ok[idx] = free
    return ok


@pytest.mark.parametrize("size", [(0.6, 0.6), (4.5, 2.0), (1.0, 0.25)])
def test_static_ok_centre_test_gives_the_box_tests_answer(ctx, size):
    """Centres inside the forbidden area or beyond the box's reach of it are decided without the
    box: every answer is the plain box test's (boxes hugging the area's edge included)."""
    rng = np.random.default_rng(1)
    lay = Layout(ctx.areas)
    lay.add(Placed("c1", "static", {}, area=lay.static_footprint(60.0, 4.0, 0.0, 0.6, 0.6)))
    x0, y0, x1, y1 = ctx.areas.roi.bounds
    x, y = rng.uniform(x0, x1, 20000), rng.uniform(y0, y1, 20000)
    # and centres just inside and outside the reach of the forbidden area's boundary
    edge = shapely.get_coordinates(shapely.boundary(ctx.areas.static_forbidden))[::7]
    reach = 0.5 * np.hypot(*size)
    for r in (reach - 1e-6, reach + 1e-6, 1.02 * reach + 1e-3):
        ang = rng.uniform(-np.pi, np.pi, len(edge))
        x, y = np.r_[x, edge[:, 0] + r * np.cos(ang)], np.r_[y, edge[:, 1] + r * np.sin(ang)]
    h = rng.uniform(-np.pi, np.pi, len(x))
    ok = lay.static_ok(x, y, h, *size)
    np.testing.assert_array_equal(ok, _plain_static_ok(lay, x, y, h, *size))
    assert 0 < ok.sum() < len(ok)
