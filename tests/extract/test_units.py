"""Unit tests of the extractor's parts that need no simulation: mapping, geometry, ranking."""

from __future__ import annotations

import itertools
import math
import re
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import yaml

from deft_gym.planner.lattice import LatticePlanner
from extract.emit import slug
from extract.mapping import DEFAULT_MAPPING, MappingError, get_field, input_roles, load_mapping
from extract.oracle import (
    Track,
    box_gaps,
    boxes_overlap,
    find_faulty,
    find_near_miss,
    find_red_light,
    find_stall,
    find_yellow,
    first_overlaps,
    light_holds,
    near_gaps,
    overlapping_points,
    red_crossings,
)
from extract.search import InputSearch, SearchConfig
from extract.validator import (
    Tolerances,
    compare,
    distance,
    identical,
    parse_tolerances,
    reproduced_counts,
)

LATTICE = "deft_gym.planner.lattice:LatticePlanner"


def test_default_mapping_loads_and_names_roles() -> None:
    mp = load_mapping(None)
    assert mp.source == str(DEFAULT_MAPPING)
    assert mp.inputs is None  # the planner's Planner.inputs
    assert input_roles(mp, LATTICE) == list(LatticePlanner.inputs)
    assert mp.trigger == "prediction" and mp.frame_time_field == "header.stamp"


def test_mapping_inputs_must_match_the_planner() -> None:
    """Planner.inputs is the single source of the frame's roles: a mapping listing others, or a
    trigger outside them, is a one-line error naming the mapping and the planner."""
    base = yaml.safe_load(DEFAULT_MAPPING.read_text())
    same = load_mapping({**base, "inputs": ["prediction", "routing", "localization", "traffic_light"]})
    assert input_roles(same, LATTICE) == list(LatticePlanner.inputs)  # any order, the planner's order
    for patch, needle in [({"inputs": ["routing", "localization", "prediction"]}, "['traffic_light'] missing"),
                          ({"inputs": [*LatticePlanner.inputs, "chassis"]}, "['chassis'] not read by the planner"),
                          ({"trigger": "chassis"}, "trigger: 'chassis' is not one of the planner's inputs")]:
        with pytest.raises(MappingError, match=re.escape(needle)) as err:
            input_roles(load_mapping({**base, "topics": {**base["topics"], "chassis": "/c"}, **patch}), LATTICE)
        assert "\n" not in str(err.value) and "<dict>" in str(err.value)


@pytest.mark.parametrize(("patch", "needle"), [
    ({"colour": 1}, "colour: unknown key"),
    ({"trigger": "chassis", "inputs": ["routing", "localization"]}, "trigger"),
    ({"inputs": ["routing", "odometry"]}, "odometry"),
    ({"topics": {"routing": "/r"}}, "planning"),
])
def test_bad_mapping_names_file_and_field(tmp_path, patch, needle) -> None:
    data = {**yaml.safe_load(DEFAULT_MAPPING.read_text()), **patch}
    path = tmp_path / "m.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(MappingError) as err:
        load_mapping(path)
    assert str(path) in str(err.value) and needle in str(err.value)
    assert "\n" not in str(err.value)


def test_mapping_file_errors(tmp_path) -> None:
    with pytest.raises(MappingError, match="cannot read"):
        load_mapping(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("topics: [unclosed\n")
    with pytest.raises(MappingError, match="invalid YAML"):
        load_mapping(bad)


def test_get_field_paths() -> None:
    payload = {"header": {"stamp": 1.5}, "trajectory": {"t": [2.0, 2.2]}, "debug": None}
    assert get_field(payload, "header.stamp") == 1.5
    assert get_field(payload, "trajectory.t.0") == 2.0
    assert get_field(payload, "trajectory.t.-1") == 2.2
    assert get_field(payload, "trajectory.t.5") is None
    assert get_field(payload, "debug.input_seqs") is None


def test_boxes_overlap_cases() -> None:
    z = np.zeros(1)
    # same place, touching end to end (4.8 m apart along x), 5 m apart, crossing at right angles
    assert boxes_overlap(z, z, z, 4.8, 2.0, z, z, z, 4.8, 2.0).all()
    assert boxes_overlap(z, z, z, 4.8, 2.0, z + 4.8, z, z, 4.8, 2.0).all()
    assert not boxes_overlap(z, z, z, 4.8, 2.0, z + 5.0, z, z, 4.8, 2.0).any()
    assert boxes_overlap(z, z, z, 4.8, 2.0, z + 3.3, z, z + math.pi / 2, 4.8, 2.0).all()
    assert not boxes_overlap(z, z, z, 4.8, 2.0, z + 3.5, z, z + math.pi / 2, 4.8, 2.0).any()
    # diagonal: corners clear although the bounding circles overlap
    assert not boxes_overlap(z, z, z, 4.8, 2.0, z + 2.5, z + 2.1, z, 4.8, 2.0).any()


def _track(t0: float = 0.0) -> Track:
    t = np.arange(t0, t0 + 2.01, 0.1)
    return Track("npc", 1, t, 10.0 + 5.0 * (t - t0), np.zeros_like(t), np.zeros_like(t), np.full_like(t, 5.0), 4.8, 2.0)


def test_track_interpolates_and_extrapolates_briefly() -> None:
    tr = _track()
    x, _, _, known = tr.at(np.array([0.05, 2.0, 2.2, 2.5, -0.1]))
    assert x[0] == pytest.approx(10.25) and x[1] == pytest.approx(20.0) and x[2] == pytest.approx(21.0)
    assert known.tolist() == [True, True, True, False, False]


def _traj(t0: float, x0: float, v: float, n: int = 11) -> dict[str, list[float]]:
    t = [t0 + 0.2 * k for k in range(n)]
    return {"t": t, "x": [x0 + v * (tt - t0) for tt in t], "y": [0.0] * n, "heading": [0.0] * n}


def test_overlapping_points_and_first_overlaps() -> None:
    tr = _track()
    chase = _traj(0.0, 0.0, 10.0)  # the 10 m gap to the participant (5 m/s) closes to 4.8 m at t=1.04 s
    slow = _traj(0.0, 0.0, 2.0)
    assert overlapping_points(chase, tr, (4.8, 2.0)).tolist()[:1] == [6]
    assert overlapping_points(slow, tr, (4.8, 2.0)).size == 0
    assert first_overlaps([chase, slow, chase], tr, (4.8, 2.0)).tolist() == [6, -1, 6]


def test_find_faulty_prefers_last_reproduced_and_avoidable() -> None:
    tr = _track()
    outs = [(0, 0.0, 0.03, 0, {"trajectory": _traj(0.0, 0.0, 10.0)}),  # overlaps at point 7
            (1, 0.1, 0.13, 1, {"trajectory": _traj(0.1, 1.0, 10.0)}),  # overlaps too, later in the run
            (2, 0.2, 0.23, 2, {"trajectory": _traj(0.2, 0.0, 1.0)}),   # never overlaps
            (3, 0.3, 5.00, 3, {"trajectory": _traj(0.3, 0.0, 10.0)})]  # published after the collision
    f = find_faulty(outs, [0.0, 0.0, 0.0, 0.0], tr, (4.8, 2.0), collision_time=2.0, theta=0.0)
    assert f is not None and f.index == 1 and f.faulty_outputs == 2 and f.point > 0
    g = find_faulty(outs, [0.0, 0.5, 0.0, 0.0], tr, (4.8, 2.0), collision_time=2.0, theta=0.0)
    assert g is not None and g.index == 0  # output 1 was not reproduced: the test could not fail on it
    assert find_faulty(outs[2:3], [0.0], tr, (4.8, 2.0), 2.0, 0.0) is None


def test_validator_identity_and_lsed() -> None:
    a = {"trajectory": {"t": [0.0, 0.2, 0.4], "x": [0.0, 1.0, 2.0], "y": [0.0, 0.0, 0.0]}}
    b = {"trajectory": {"t": [0.0, 0.2, 0.4], "x": [0.0, 1.0, 2.0], "y": [0.3, 0.3, 0.3]}}
    assert identical(a, a) and distance(a, a) == 0.0
    assert distance(a, b) == pytest.approx(0.3 * math.sqrt(3))
    assert distance(a, None) == math.inf
    assert distance(a, b, "hausdorff") == pytest.approx(0.3)
    assert reproduced_counts([0.0, 0.05, 0.5, 3.0, math.inf]) == {"0": 1, "0.1": 2, "1": 3, "7": 4}


def _search_over(pub: dict[str, list[int]], trigger: str = "prediction") -> InputSearch:
    mp = load_mapping(None)
    inputs = {r: SimpleNamespace(publish_ns=np.array(p, dtype=np.int64)) for r, p in pub.items()}
    pif = SimpleNamespace(mapping=mp.model_copy(update={"trigger": trigger}), roles=list(pub), inputs=inputs,
                          frame_bound=lambda r, t: int(np.searchsorted(inputs[r].publish_ns, t, side="right")))
    return InputSearch(pif, planner=None, cfg=SearchConfig())  # type: ignore[arg-type]


def test_ranking_is_best_first_and_follows_the_heuristics() -> None:
    ms = 1_000_000
    s = _search_over({"routing": [0], "localization": [50 * ms, 99 * ms, 100 * ms - 200_000],
                      "traffic_light": [], "prediction": [10 * ms, 99 * ms]})
    t_f = 100 * ms
    combos = list(s._ranked(t_f, None, relaxed=False))
    assert combos[0] == {"routing": 0, "localization": 1, "traffic_light": None, "prediction": 1}
    # H2: nothing published after t_F; every joint combination (None: nothing received yet)
    # appears once
    assert len(combos) == len({tuple(c.values()) for c in combos}) == 2 * 4 * 1 * 3
    logp = []
    for c in combos:
        p = 1.0
        for r, j in c.items():
            p *= dict((jj, pp) for pp, jj in s._role_candidates(r, t_f, None, False))[j]
        logp.append(p)
    assert all(a >= b - 1e-15 for a, b in itertools.pairwise(logp))
    # H3: with a previous choice, nothing older is proposed (unless relaxed)
    prev = {"routing": 0, "localization": 1, "traffic_light": None, "prediction": 1}
    assert {c["localization"] for c in s._ranked(t_f, prev, relaxed=False)} == {1, 2}
    assert 0 in {c["localization"] for c in s._ranked(t_f, prev, relaxed=True)}


def test_slug_makes_identifiers() -> None:
    assert slug("left_turn~cut3") == "left_turn_cut3"
    assert slug("3 lanes / merge") == "s_3_lanes_merge"


def _payload(**over: Any) -> dict[str, Any]:
    tr = {"t": [1.0, 1.2, 1.4], "x": [0.0, 1.0, 2.0], "y": [0.0, 0.0, 0.0], "v": [5.0, 5.0, 5.0],
          "heading": [3.14, 3.1415, -3.1415], "a": [0.0, 0.0, 0.0]}
    dec = {"behavior": "CRUISE", "cost": 1.5, "lane": ["a", "b", 0]}
    for k, v in over.items():
        if k.startswith("d_"):
            dec[k[2:]] = v
        else:
            tr[k] = v
    return {"header": {"seq": 1}, "trajectory": tr, "decision": dec}


def test_whole_output_comparison_names_field_point_and_values() -> None:
    """Positions by theta; every other field (and the decision) bit-exact by default, each
    difference with the point of largest deviation and both values at full precision."""
    rec = _payload()
    assert compare(rec, _payload()).reproduced and compare(rec, None).diffs[0].field == "output"
    c = compare(rec, _payload(v=[5.0, 5.0 + 1e-12, 5.0], d_behavior="FOLLOW"))
    assert not c.reproduced and c.distance == 0.0
    assert {d.field for d in c.diffs} == {"v", "decision.behavior"}
    v = next(d for d in c.diffs if d.field == "v")
    assert v.point == 1 and v.time == 1.2 and v.replayed == 5.0 + 1e-12 and repr(5.0 + 1e-12) in v.text()
    assert "recorded 'CRUISE', replayed 'FOLLOW'" in c.text()
    # tolerances per field, the decision's numbers, headings as wrapped angles, NaN == NaN
    assert compare(rec, _payload(v=[5.0, 5.001, 5.0]), Tolerances(fields={"v": 0.01})).reproduced
    assert compare(rec, _payload(d_cost=1.6), Tolerances(decision=0.2)).reproduced
    assert not compare(rec, _payload(d_cost=1.6), Tolerances(decision=0.05)).reproduced
    assert compare(rec, _payload(heading=[3.14, 3.1415, -3.1415 + 2 * math.pi])).reproduced is False  # bits differ
    assert compare(rec, _payload(heading=[3.14, 3.1415, -3.1415 + 2 * math.pi]), Tolerances(fields={"heading": 1e-9})).reproduced
    assert compare(_payload(a=[0.0, math.nan, 0.0]), _payload(a=[0.0, math.nan, 0.0])).reproduced
    # positions: theta, and the point where they differ most
    c = compare(rec, _payload(x=[0.0, 1.0, 2.5]))
    assert [d.field for d in c.diffs] == ["position"] and c.diffs[0].point == 2 and c.distance == 0.5
    assert compare(rec, _payload(x=[0.0, 1.0, 2.5]), Tolerances(theta=0.5)).reproduced
    # missing, extra and re-shaped fields
    extra = _payload()
    extra["trajectory"]["kappa"] = [0.0, 0.0, 0.0]
    assert [d.field for d in compare(rec, extra).diffs] == ["kappa"]
    assert "2 replayed" in compare(rec, _payload(v=[5.0, 5.0])).text()
    no_dec = _payload()
    del no_dec["decision"]
    assert compare(no_dec, dict(no_dec)).reproduced and not compare(rec, no_dec).reproduced


def test_tolerance_options() -> None:
    tol = parse_tolerances(["v=0.01", "decision=0.5", "default=1e-9"], theta=0.1)
    assert tol.of("v") == 0.01 and tol.of("a") == 1e-9 and tol.decision == 0.5 and tol.theta == 0.1
    assert Tolerances.from_dict(tol.as_dict()) == tol
    for bad in (["v"], ["v=-1"], ["v=abc"], ["x=0.1"]):
        with pytest.raises(ValueError, match="tolerance"):
            parse_tolerances(bad)


def test_p_departure_is_the_first_plan_of_the_run_that_took_the_ego_off_the_path() -> None:
    """A non-optimal decision's oracle: the unbroken run of plans leaving the optimal path (a point
    farther than the limit) that ends where a plan starts off it; its first plan is P_departure.
    An earlier plan that strayed and came back is not it; no plan starting off the path: none."""
    import numpy as np

    from extract.oracle import find_departure, off_path, path_distances

    path = np.array([[0.0, 0.0], [50.0, 0.0], [100.0, 0.0]])
    assert list(path_distances([10.0, 120.0], [3.0, 0.0], path)) == [3.0, 20.0]

    def plan(y0: float, y1: float) -> dict:
        x = list(np.linspace(0.0, 40.0, 11))
        return {"trajectory": {"x": x, "y": list(np.linspace(y0, y1, 11)), "t": list(range(11))}}

    outs = [(0, 0.0, plan(0.0, 0.0)), (1, 0.1, plan(0.0, 2.5)), (2, 0.2, plan(0.0, 0.0)),
            (3, 0.3, plan(0.0, 3.0)), (4, 0.4, plan(0.5, 3.2)), (5, 0.5, plan(2.0, 3.5))]
    dep = find_departure(outs, path, 1.75)
    assert dep is not None and (dep["index"], dep["left_at"], dep["point"]) == (3, 0.5, 6)
    assert dep["distance"] > 1.75 and off_path(plan(0.0, 1.0)["trajectory"], path, 1.75) is None
    assert find_departure(outs[:5], path, 1.75) is None


def test_p_wrong_way_is_the_first_plan_of_the_run_that_took_the_ego_against_the_lanes() -> None:
    """A two-lane road, eastbound at y = 0 and westbound at y = -3.5 (3.5 m wide): a point is wrong-way
    where the lanes holding it all point against its heading (a point on the shared edge is in both:
    not wrong-way). P_wrong_way is the first plan of the unbroken run of plans with >= 2 m of path
    wrong-way that ends where a plan starts wrong-way; a plan that strays and comes back is not it,
    and an ego that never drove wrong-way, or got there with no plan planning it, gives none."""
    import numpy as np

    from extract.oracle import find_wrong_way, map_lanes, wrong_way_flags, wrong_way_length

    lanes = map_lanes({"lanes": [{"x": [0.0, 100.0], "y": [0.0, 0.0], "width": 3.5},
                                 {"x": [100.0, 0.0], "y": [-3.5, -3.5], "width": 3.5},
                                 {"x": [0.0], "y": [0.0], "width": 3.5}]})  # one point: no lane
    assert len(lanes) == 2

    def plan(y0: float, y1: float, heading: float = 0.0) -> dict:
        x = list(np.linspace(10.0, 40.0, 11))
        return {"trajectory": {"x": x, "y": list(np.linspace(y0, y1, 11)), "heading": [heading] * 11,
                               "t": list(range(11))}}

    assert wrong_way_flags(plan(-1.75, -3.5)["trajectory"], lanes).tolist() == [False] + [True] * 10
    assert not wrong_way_flags(plan(-3.5, -3.5, heading=np.pi)["trajectory"], lanes).any()  # westbound: its own
    assert wrong_way_length(plan(0.0, 0.0)["trajectory"], lanes) == (-1, 0.0)
    k, length = wrong_way_length(plan(0.0, -3.5)["trajectory"], lanes)
    assert k == 6 and length == pytest.approx(5 * np.hypot(3.0, 0.35))
    outs = [(0, 0.0, plan(0.0, 0.0)), (1, 0.1, plan(0.0, -3.5)), (2, 0.2, plan(0.0, 0.0)),
            (3, 0.3, plan(0.0, -3.5)), (4, 0.4, plan(-1.0, -3.5)), (5, 0.5, plan(-2.5, -3.5))]
    ww = find_wrong_way(outs, lanes)
    assert ww is not None and (ww["index"], ww["entered_at"], ww["point"]) == (3, 0.5, 6) and ww["length"] >= 2.0
    assert find_wrong_way(outs[:5], lanes) is None  # the ego never started a plan wrong-way
    drifted = [*outs[:3], (3, 0.3, plan(-2.5, 0.0))]  # there, but no plan before took it there
    assert find_wrong_way(drifted, lanes) is None and find_wrong_way(outs, []) is None


def test_p_off_road_is_the_first_plan_of_the_run_that_took_the_ego_off_the_road_where_it_left() -> None:
    """A straight 3.5 m lane along y = 0 and a quarter-circle junction lane (paved inside its curve,
    as the drivable-area metric holds). The ego's poses leave the road at x = 30 (its box more than
    0.3 m over the edge at y = 1.75); P_off_road is the first plan of the unbroken run of plans, up
    to the last one before that, that put the box more than 0.3 m off the road within 5 m of there.
    A plan that ran off the road elsewhere does not count, and an ego whose plans stayed on the
    road (the vehicle left them) or that never left gives none."""
    import numpy as np

    from extract.oracle import find_off_road, map_area, off_road_depths

    arc = np.linspace(0.0, np.pi / 2, 20)
    area = map_area({"lanes": [{"x": [0.0, 100.0], "y": [0.0, 0.0], "width": 3.5},
                               {"x": (200 + 10 * np.sin(arc)).tolist(), "y": (10 - 10 * np.cos(arc)).tolist(),
                                "width": 3.5, "junction": True},
                               {"x": [0.0], "y": [0.0], "width": 3.5}]})  # one point: no lane
    ego = (4.8, 2.0)
    inside_turn = {"x": [205.0], "y": [4.0], "heading": [0.0]}  # within the arc's chord, off its lane's surface
    assert off_road_depths(inside_turn, area, (0.1, 0.1))[0] == 0.0
    lane_only = map_area({"lanes": [{"x": (200 + 10 * np.sin(arc)).tolist(), "y": (10 - 10 * np.cos(arc)).tolist(),
                                     "width": 3.5}]})
    assert off_road_depths(inside_turn, lane_only, (0.1, 0.1))[0] > 0.1
    assert off_road_depths({"x": [50.0], "y": [0.0], "heading": [0.0]}, area, ego)[0] == 0.0
    assert off_road_depths({"x": [50.0], "y": [2.0], "heading": [0.0]}, area, ego)[0] == pytest.approx(1.25)

    def plan(y_end: float, x0: float = 10.0) -> dict:
        x = np.linspace(x0, x0 + 30.0, 11)
        return {"trajectory": {"x": x.tolist(), "y": np.linspace(0.0, y_end, 11).tolist(), "heading": [0.0] * 11,
                               "t": list(range(11))}}

    poses = {"t": [0.0, 0.2, 0.4, 0.55, 0.6], "x": [10.0, 15.0, 20.0, 30.0, 32.0],
             "y": [0.0, 0.0, 0.5, 2.0, 2.5], "heading": [0.0] * 5}
    far_off = plan(0.0, x0=10.0)
    far_off["trajectory"]["y"][-1] = 9.0  # its end, at x = 40, off the road: 10 m from where the ego left
    outs = [(0, 0.0, plan(0.0)), (1, 0.1, far_off), (2, 0.2, plan(0.0)), (3, 0.3, plan(4.0)), (4, 0.4, plan(4.0)),
            (5, 0.5, plan(4.0)), (6, 0.6, plan(4.0))]
    off = find_off_road(outs, poses, area, ego)
    assert off is not None and (off["index"], off["left_at"], off["place"]) == (3, 0.55, [30.0, 2.0])
    assert off["depth"] > 0.3 and off["left_depth"] == pytest.approx(1.25)
    assert find_off_road([*outs[:2], *outs[3:]], poses, area, ego)["index"] == 3  # the far plan is not it
    assert find_off_road(outs[:3], poses, area, ego) is None  # no plan put it there: it left its plans
    on_road = {**poses, "y": [0.0] * 5}
    assert find_off_road(outs, on_road, area, ego) is None and find_off_road(outs, poses, None, ego) is None


def test_p_stall_is_the_first_of_the_standing_plans_that_end_a_stuck_run() -> None:
    """A plan stands when its path is shorter than 0.5 m; P_stall is the first standing plan of the
    stretch that ends the outputs in which every plan stands or was dropped unfollowed (the ego
    stood where it starts until the end): an earlier standstill that moved on is not it, a moving
    plan flickered in between does not end the stretch; none when no plan of the stretch stands."""
    from extract.oracle import find_stall, planned_travel

    def plan(x0: float, length: float) -> dict:
        return {"trajectory": {"x": [x0, x0 + length / 2, x0 + length], "y": [0.0, 0.0, 0.0], "t": [0, 1, 2]}}

    assert planned_travel(plan(0.0, 3.0)["trajectory"]) == 3.0 and planned_travel({}) == 0.0
    # the ego drives 0 -> 5, stands at 5 (0.1 m), moves on to 9, then stands for good at 9.2
    starts_lengths = [(0.0, 5.0), (5.0, 0.1), (5.0, 0.0), (5.0, 4.0), (9.0, 0.4), (9.2, 0.0), (9.2, 0.2)]
    outs = [(k, k / 10, plan(x0, length)) for k, (x0, length) in enumerate(starts_lengths)]
    stall = find_stall(outs)
    assert stall is not None and (stall["index"], stall["standing_plans"], stall["last_time"]) == (4, 3, 0.6)
    assert stall["travel"] == pytest.approx(0.4) and stall["dropped_plans"] == 0
    # cut after the plan that moves on from 5: it is the last, so the ego stood at 5 to the end
    assert (find_stall(outs[:4]) or {}).get("index") == 1 and find_stall(outs[:1]) is None
    # the same with the planner flickering: a 9.6 m plan at 9.2 that the next cycle drops
    flicker = [*outs[:6], (6, 0.6, plan(9.2, 9.6)), (7, 0.7, plan(9.2, 0.0))]
    stall = find_stall(flicker)
    assert stall is not None and (stall["index"], stall["standing_plans"], stall["dropped_plans"]) == (4, 3, 1)


def test_box_gaps_are_the_distances_between_oriented_boxes() -> None:
    """Side by side 1 m apart, overlapping (0), and a box turned 90 deg: exact distances [m]."""
    gaps = box_gaps(np.zeros(3), np.zeros(3), np.zeros(3), (4.0, 2.0),
                    np.array([0.0, 1.0, 3.5]), np.array([3.0, 0.5, 0.0]), np.array([0.0, 0.0, math.pi / 2]), (4.0, 2.0))
    assert gaps == pytest.approx([1.0, 0.0, 0.5])  # the turned box spans x 2.5..4.5, the ego's front is at 2
    corner = box_gaps(np.zeros(1), np.zeros(1), np.zeros(1), (4.0, 2.0), np.array([5.0]), np.array([5.0]),
                      np.zeros(1), (4.0, 2.0))
    assert corner == pytest.approx([math.hypot(1.0, 3.0)])  # corner to corner: (2, 1) to (3, 4)


def _static(x: float, y: float, size: float = 0.6) -> Track:
    return Track("1 (CONE)", 1, np.array([0.0, 10.0]), np.array([x, x]), np.array([y, y]), np.zeros(2),
                 np.zeros(2), size, size)


def test_near_gaps_count_a_fast_pass_not_a_slow_one_and_see_between_points() -> None:
    """A plan along y = 0 at 8 m/s passes a cone whose box edge is 1.3 m off the line: 0.3 m from
    the ego's 2 m wide box; the same plan at 1 m/s is no near miss (the relative speed); a car
    crossing between two 0.5 s points is seen by the sub-steps alone."""
    t = np.arange(0.0, 4.01, 0.5)
    plan = {"t": t.tolist(), "x": (8.0 * t).tolist(), "y": [0.0] * len(t), "heading": [0.0] * len(t),
            "v": [8.0] * len(t)}
    gaps = near_gaps(plan, _static(16.0, 1.6), (4.8, 2.0))
    assert gaps.min() == pytest.approx(0.3)
    slow = {**plan, "x": t.tolist(), "v": [1.0] * len(t)}
    assert np.isinf(near_gaps(slow, _static(2.0, 1.6), (4.8, 2.0))).all()
    crossing = Track("2 (VEHICLE)", 2, np.array([0.0, 2.0]), np.array([9.0, 9.0]), np.array([-20.0, 20.0]),
                     np.full(2, math.pi / 2), np.full(2, 20.0), 4.8, 2.0)  # at x = 9 m, y = 0 at t = 1.0 s
    stand = {"t": [0.75, 1.25], "x": [5.0, 5.0], "y": [0.0, 0.0], "heading": [0.0, 0.0], "v": [0.0, 0.0]}
    assert near_gaps(stand, crossing, (4.8, 2.0), substeps=1)[0] > 0.5
    assert near_gaps(stand, crossing, (4.8, 2.0))[0] == pytest.approx(0.6)  # the ego's front at 7.4, the car's side at 8


def test_p_near_miss_is_the_first_of_the_plans_that_led_to_the_close_pass() -> None:
    """Plans from 1 s on hold the line of a cone 0.3 m off the ego's box, the one before swerved
    round it; the ego passes it at 0.3 m at t = 2 s: P_near_miss is the plan at 1 s. A run that
    never came close has none."""
    cone = _static(16.0, 1.6)

    def plan(t0: float, y: float) -> dict[str, Any]:
        t = t0 + np.arange(0.0, 4.01, 0.5)
        return {"trajectory": {"t": t.tolist(), "x": (8.0 * t).tolist(), "y": [y] * len(t),
                               "heading": [0.0] * len(t), "v": [8.0] * len(t)}}

    outputs = [(0, 0.0, plan(0.0, 0.0)), (1, 0.5, plan(0.5, -1.0))] + [(k, 0.5 * k, plan(0.5 * k, 0.0)) for k in (2, 3, 4)]
    tp = np.arange(0.0, 3.0, 0.05)
    poses = {"t": tp.tolist(), "x": (8.0 * tp).tolist(), "y": [0.0] * len(tp), "heading": [0.0] * len(tp),
             "v": [8.0] * len(tp)}
    found = find_near_miss(outputs, poses, [cone], (4.8, 2.0))
    assert found is not None and found["index"] == 2 and found["gap"] == pytest.approx(0.3)
    assert 1.4 < found["close_at"] < 2.0 and found["participant"] == "1 (CONE)"
    assert find_near_miss(outputs, {**poses, "y": [-1.0] * len(tp)}, [cone], (4.8, 2.0)) is None


def test_p_red_light_is_the_first_plan_after_the_light_turned_that_runs_it() -> None:
    """A stop line across y = 0 at x = 40 m, its light yellow from 1 s and red from 3 s; the ego
    (front 2.4 m ahead of its centre) drives on at 10 m/s and crosses at 4 s. Plans made at green
    are no plan to run the light even where they cross at red; P_red_light is the first plan made
    at yellow of the run that crosses at red. Crossing before red, or backwards, is none."""
    line = {"light": "tl", "x": 40.0, "y": 0.0, "heading": 0.0, "half_width": 1.75}
    timeline = {"t": [0.0, 1.0, 3.0], "color": ["GREEN", "YELLOW", "RED"]}

    def plan(t0: float) -> dict[str, Any]:
        t = t0 + np.arange(0.0, 4.01, 0.25)
        return {"trajectory": {"t": t.tolist(), "x": (10.0 * t - 2.4).tolist(), "y": [0.0] * len(t),
                               "heading": [0.0] * len(t), "v": [10.0] * len(t)}}

    outputs = [(k, 0.5 * k, plan(0.5 * k)) for k in range(8)]
    tp = np.arange(0.0, 5.0, 0.05)
    poses = {"t": tp.tolist(), "x": (10.0 * tp - 2.4).tolist(), "y": [0.0] * len(tp), "heading": [0.0] * len(tp)}
    assert list(red_crossings(poses, line, timeline, 4.8)) == [80]  # the front at x = 40 at t = 4 s
    found = find_red_light(outputs, poses, [line], {"tl": timeline}, 4.8)
    assert found is not None and found["index"] == 2 and found["colour"] == "YELLOW"  # made at 1.0 s
    assert found["point_time"] == pytest.approx(4.0) and found["crossed_at"] == pytest.approx(4.0)
    early = {"t": [0.0, 1.0, 5.0], "color": ["GREEN", "YELLOW", "RED"]}
    assert find_red_light(outputs, poses, [line], {"tl": early}, 4.8) is None  # over the line before red
    back = {**poses, "x": poses["x"][::-1], "heading": [math.pi] * len(tp)}
    assert not len(red_crossings(back, line, timeline, 4.8))
    # P_yellow: at 1 s the front is 30 m before the line at 10 m/s (a stop needs 1.7 m/s^2) and the plan
    # drives on over it; the plan at 0.5 s was made at green. Plans that brake to stop are none.
    yellow = find_yellow(outputs, poses, [line], {"tl": timeline}, 4.8)
    assert yellow is not None and yellow["index"] == 2 and yellow["ahead"] == pytest.approx(30.0)
    braking = [(k, t, {"trajectory": {**p["trajectory"], "v": [10.0] + [0.0] * (len(p["trajectory"]["t"]) - 1),
                                      "x": [p["trajectory"]["x"][0]] * len(p["trajectory"]["t"])}})
               for k, t, p in outputs]
    assert find_yellow(braking, poses, [line], {"tl": timeline}, 4.8) is None


def test_a_timed_out_ego_standing_at_a_green_light_stalls_there() -> None:
    """The ego stands 1 m before a stop line from 2 s to the end (10 s); its light is red to 5 s and
    green after: P_stall (for a run that timed out) is the first standing plan made when the light
    had been green a second, at 6 s. Red to the end: a light holds it, no P_stall."""
    line = {"light": "tl", "x": 40.0, "y": 0.0, "heading": 0.0, "half_width": 1.75}

    def plan(t0: float) -> dict[str, Any]:
        x = 40.0 - 1.0 - 2.4 - (max(2.0 - t0, 0.0) * 5.0)  # the front 1 m before the line from 2 s on
        stop = t0 >= 2.0
        return {"trajectory": {"t": [t0, t0 + 1.0], "x": [x, x if stop else x + 5.0], "y": [0.0, 0.0],
                               "heading": [0.0, 0.0]}}

    outputs = [(k, 0.5 * k, plan(0.5 * k)) for k in range(21)]
    green = {"tl": {"t": [0.0, 5.0], "color": ["RED", "GREEN"]}}
    held = light_holds(outputs, [line], green, 4.8)
    assert held == [k * 0.5 < 6.0 for k in range(21)]
    found = find_stall(outputs, free=[not h for h in held])
    assert found is not None and found["index"] == 12 and found["timed_out"] and found["standing_plans"] == 9
    red = {"tl": {"t": [0.0], "color": ["RED"]}}
    assert find_stall(outputs, free=[not h for h in light_holds(outputs, [line], red, 4.8)]) is None
