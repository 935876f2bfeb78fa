"""Decictor's oracles on synthetic and real traces: consistency (IoU), feedback, validity."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from deft_gym.search.context import seed_context
from deft_gym.search.nods import (
    CLEARANCE,
    EGO_LENGTH,
    LaneCells,
    clearances,
    collision_fault,
    iou,
    mean_kernel,
    mmd_linear,
    mmd_rbf,
    world_cells,
)
from deft_gym.search.trace import Actor, Trace
from deft_gym.world.geometry import box_gap, box_polygon


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


def test_mmd_rbf_with_the_kept_reference_kernel_is_the_same_float(ctx):
    """The oracle keeps each reference lane's kernel with itself; f_b is the float it was without."""
    rng = np.random.default_rng(2)
    x, y = rng.normal(size=(350, 4)), rng.normal(0.3, size=(120, 4))
    thin = x[np.round(np.linspace(0, len(x) - 1, 200)).astype(np.int64)]
    assert mmd_rbf(x, y, 1.7, mean_kernel(thin, thin, 1.7)) == mmd_rbf(x, y, 1.7)
    o = ctx.oracle
    ego = ctx.ref.ego.copy()
    ego[:, 3] *= 0.7  # slower all the way
    kept, o._ref_kxx = o._ref_kxx, {j: None for j in o._ref_kxx}  # None: computed again
    try:
        again = o.f_b(ego)
    finally:
        o._ref_kxx = kept
    assert o.f_b(ego) == again > 0.0


def test_validity_replays_the_reference_ego(ctx):
    ref = ctx.ref
    mid = len(ref.ticks) // 2
    on_path = np.array([[ref.ticks[0], 0, ref.xy[mid, 0], ref.xy[mid, 1], 0.0]])  # a cone from the start
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


# -- the loopholes the validity check closes ----------------------------------------------------------
CAR = ("car", "scripted", "VEHICLE", 4.8, 2.0)


def _with_car(ref: Trace, rows: list[tuple[float, float, float, float]], ego: np.ndarray | None = None) -> Trace:
    """``ref`` (as a mutated run, its ego replaced by ``ego``) with one added car on ``rows``
    ``(tick, x, y, heading)``."""
    parts = np.array([(t, 0, x, y, h) for t, x, y, h in rows], dtype=float)
    return dataclasses.replace(ref, actors=[Actor(*CAR, added=True)], parts=parts,
                               ego=ref.ego if ego is None else ego, outcome="completed")


def test_a_car_standing_where_the_reference_passed_2_s_before_is_invasive(ctx):
    """A mutated ego 2 s late meets it there; 4 s after the reference passed it is out of the
    3 s window (a parked vehicle, being static, never is)."""
    ref = ctx.ref
    k = len(ref.ticks) // 2
    x, y, h = ref.ego[k, :3]
    for lag, invasive in ((2.0, True), (4.0, False)):
        t0 = int(ref.ticks[k] + round(lag / ref.world_dt))
        rows = [(ref.ticks[0] + i, x - 60.0 + 0.5 * i, y + 3.5, h) for i in range(20)]  # away from the path first
        rows += [(t, x, y, h) for t in range(t0, t0 + 40)]  # then standing on it for 2 s
        v = ctx.oracle.judge(_with_car(ref, rows))
        assert (v.invasive_why == {"car": "path"}) is invasive, (lag, v.invasive_why)


def test_a_car_on_the_optimal_path_after_the_reference_ended_is_invasive(ctx):
    """The check used to drop every row after the reference's last tick: a car could drive onto
    any part of the path then, where a mutated ego that lags still drives."""
    ref = ctx.ref
    end = int(ref.ticks[-1])
    k = len(ref.ticks) // 3
    x, y, h = ref.ego[k, :3]
    rows = [(end + 20 + i, x, y, h) for i in range(20)]
    assert ctx.oracle.judge(_with_car(ref, rows)).invasive_why == {"car": "path"}


def test_a_car_standing_at_the_destination_after_the_reference_ended_is_invasive(ctx):
    """The reference ends within 3 m of the destination, and its path used to end there too: a car
    standing just past where it ended, on the destination, kept 0.5 m from its last box, while a
    mutated ego that lags still has to drive there. The ego's box on to the destination is
    reserved (in validity and in placement)."""
    ref, oracle = ctx.ref, ctx.oracle
    end = int(ref.ticks[-1])
    x, y, h = ref.ego[-1, :3]
    dest = oracle.reserved.ego[-1, :2]
    assert np.hypot(*(dest - ref.ego[-1, :2])) > 1.0  # the reference stopped short of it
    along = np.array([np.cos(h), np.sin(h)])
    front = 0.5 * (EGO_LENGTH + CAR[3]) + 0.6  # the car's rear 0.6 m past the reference's last front
    car = np.array([x, y]) + front * along
    assert np.hypot(*(car - dest)) < 3.0  # within reach of the destination
    rows = [(ref.ticks[0], car[0] - 60.0, car[1] + 50.0, h)]  # there from the start, far away
    rows += [(end + 20 + i, car[0], car[1], h) for i in range(40)]  # then standing there
    assert clearances(ref, _with_car(ref, rows))[0] > CLEARANCE  # the loophole, the path alone
    assert oracle.judge(_with_car(ref, rows)).invasive_why == {"car": "path"}
    box = box_polygon(car[0], car[1], h, CAR[3], CAR[4])
    assert ctx.areas.forbidden[-1].intersects(box)  # and no method may place it there


def test_a_car_appearing_beside_the_live_ego_is_invasive(ctx):
    """Spawn distance against the ego of the run itself (not the reference's): the mutated ego
    lags 30 m behind the reference, and a car appears 6 m beside it - 30 m from where the
    reference ego was."""
    ref = ctx.ref
    ego = ref.ego.copy()
    ego[:, 0] -= 30.0
    k = len(ref.ticks) // 2
    ex, ey, h = ego[k, :3]
    rows = [(int(ref.ticks[k]) + i, ex + 0.5 * i, ey - 6.0, h) for i in range(40)]
    v = ctx.oracle.judge(_with_car(ref, rows, ego))
    assert v.invasive_why == {"car": "spawn"}
    # one placed exactly 15 m behind the live ego, faster than it, is first recorded a step later
    # and 0.5 m closer (the adversary env's placements): not refused
    gap = [(int(ref.ticks[k]) + 1 + i, ex - 15.0 + 0.5 * (i + 1), ey, h) for i in range(40)]
    ego_k = ego.copy()
    ego_k[:, 3] = 0.0  # a standing ego: all of the closing is the car's
    assert ctx.oracle.judge(_with_car(ref, gap, ego_k)).invasive_why == {}


def _fault(ego_rows: list[tuple[float, float, float, float]], car_rows: list[tuple[float, float, float]],
           first_tick: int = 0) -> tuple[bool, str]:
    """:func:`collision_fault` of a 2 s encounter at 20 Hz: ego rows (x, y, heading, speed) and
    the car's (x, y, heading) per tick, the car present from ``first_tick``, contact at the end."""
    n = len(ego_rows)
    ego = np.array([(x, y, h, v, 0.0) for x, y, h, v in ego_rows])
    parts = np.array([(t, 0, *car_rows[t]) for t in range(first_tick, n)], dtype=float)
    tr = Trace(0.05, np.arange(n), ego, [Actor(*CAR, added=True)], parts, "collision", n * 0.05)
    return collision_fault(tr, {"participant": "car", "time": (n - 1) * 0.05, "ego_moving": True},
                           lambda x, y, h: 0.0)  # a straight road along x


def test_the_ego_is_at_fault_only_when_it_closed_the_gap():
    t = np.arange(41) * 0.05
    ego = [(10.0 * ti, 0.0, 0.0, 10.0) for ti in t]
    # the ego runs into a slower car ahead in its lane
    assert _fault(ego, [(20.0 + 4.0 * ti, 0.0, 0.0) for ti in t]) == (True, "rear_end")
    # a car beside it cuts into the ego's lane
    assert _fault(ego, [(10.0 * ti + 1.0, 3.5 - 1.5 * ti, -0.15) for ti in t]) == (False, "cut_in")
    # the ego changes lanes into a car beside it
    ego_lc = [(10.0 * ti, 1.5 * ti, 0.15, 10.0) for ti in t]
    assert _fault(ego_lc, [(10.0 * ti + 1.0, 3.5, 0.0) for ti in t]) == (True, "lateral")
    # a car that appeared 1 s before the contact, right in front of the ego
    assert _fault(ego, [(20.0 - 5.0 * ti, 0.0, 0.0) for ti in t], first_tick=20) == (False, "appeared")
    # plain bools: the verdict goes into JSON records (a numpy bool ended a training run)
    assert type(_fault(ego, [(20.0 + 4.0 * ti, 0.0, 0.0) for ti in t])[0]) is bool
    assert type(_fault(ego, [(10.0 * ti + 1.0, 3.5 - 1.5 * ti, -0.15) for ti in t])[0]) is bool


# -- the reference path ------------------------------------------------------------------------------
def test_the_reference_is_the_most_typical_of_several_jittered_runs(monkeypatch):
    """One jittered run with a half lane change it gave up is not the optimal path: of five runs the
    medoid is chosen, and runs that do not complete are left out."""
    from deft_gym.scenarios.scenario import load_scenario
    from deft_gym.search import trace as trace_mod

    x = np.linspace(0.0, 100.0, 101)

    def fake(sc, ads=None, jitter_seed=0):
        y = np.full_like(x, 0.05 * jitter_seed)
        if jitter_seed == 0:  # the seed the reference used to be: a half lane change, given up
            y = 1.6 * np.exp(-(((x - 50.0) / 10.0) ** 2))
        ego = np.column_stack([x, y, np.zeros_like(x), np.full_like(x, 10.0), np.zeros_like(x)])
        outcome = "timeout" if jitter_seed == 4 else "completed"
        return Trace(0.1, np.arange(len(x)), ego, [], np.zeros((0, 5)), outcome, 10.0, {"jitter_seed": jitter_seed})

    monkeypatch.setattr(trace_mod, "record_run", fake)
    monkeypatch.setattr(trace_mod, "_MEMO", {})
    ref = trace_mod.reference_run(load_scenario("lane_follow_static"), cache_dir=None)
    assert ref.meta["jitter_seed"] in (1, 2) and ref.meta["reference_of"] == [0, 1, 2, 3]
    assert ref.meta["not_completed"] == [4]


def test_a_reference_none_of_whose_runs_completes_is_cached_as_such(monkeypatch, tmp_path):
    """A scenario whose reference runs all fail (a planner that cannot do it) is named once: the
    error is cached beside the references, and the next call raises it without simulating (an
    evaluation against a slow planner re-checked such a scenario at every start, ~5 CPU-min)."""
    from deft_gym.scenarios.scenario import load_scenario
    from deft_gym.search import trace as trace_mod

    calls: list[int] = []

    def fake(sc, ads=None, jitter_seed=0):
        calls.append(jitter_seed)
        ego = np.zeros((3, 5))
        return Trace(0.1, np.arange(3), ego, [], np.zeros((0, 5)), "timeout", 45.0, {"jitter_seed": jitter_seed})

    monkeypatch.setattr(trace_mod, "record_run", fake)
    monkeypatch.setattr(trace_mod, "_MEMO", {})
    sc = load_scenario("lane_follow_static")
    for _ in range(2):
        with pytest.raises(ValueError, match=r"ended 'timeout' at 45\.0 s"):
            trace_mod.reference_run(sc, cache_dir=tmp_path)
    assert len(calls) == trace_mod.REFERENCE_RUNS  # simulated once, not twice
    (cached,) = tmp_path.glob("*.failed.json")
    cached.write_text("{damaged")  # a damaged verdict is simulated again, not trusted
    with pytest.raises(ValueError, match="ended 'timeout'"):
        trace_mod.reference_run(sc, cache_dir=tmp_path)
    assert len(calls) == 2 * trace_mod.REFERENCE_RUNS


def test_cached_verdicts_outlive_edits_to_the_cache_plumbing_only():
    """The robust verdicts' key hashes what judges (the give-ups, the trace, the consistency
    oracle), not how references are found and cached: an edit to ``reference_run`` or a comment
    keeps the ~300 cached verdicts (CommonRoad's take ~25 CPU-min to rebuild); one to
    ``aborted_changes`` makes them stale."""
    import inspect

    from deft_gym.search import nods, trace
    from deft_gym.search.context import judge_hash

    src, oracle = inspect.getsource(trace), inspect.getsource(nods)
    key = judge_hash([src, oracle])
    plumbing = src.replace("    tr = _MEMO.get(key)\n", "    tr = _MEMO.get(key)  # memoised\n    tr = tr or None\n", 1)
    assert plumbing != src and judge_hash([plumbing, oracle]) == key
    judging = src.replace("GIVE_UP_S = 0.5", "GIVE_UP_S = 0.6", 1)
    assert judging != src and judge_hash([judging, oracle]) != key
    give_ups = src.replace('if e["t"] - back >= hold - 1e-9:', 'if e["t"] - back > hold - 1e-9:', 1)
    assert give_ups != src and judge_hash([give_ups, oracle]) != key
    assert judge_hash([src, oracle.replace("def ", "def _", 1)]) != key


def test_a_reference_that_gives_up_a_lane_change_is_not_robust(ctx):
    from deft_gym.search.context import robust
    from deft_gym.search.trace import aborted_changes

    a, b = ["a", "b", 0], ["a", "b", 1]
    entry = {"home": a, "blocked": [], "tight": [], "refused": {}, "causes": {}}
    gave_up = [{"t": 1.0, "reason": "keep", "lane": a, "target": a, **entry},
               {"t": 2.0, "reason": "borrow", "lane": a, "target": b, **entry},
               {"t": 3.0, "reason": "keep", "lane": a, "target": a, **entry}]
    done = [*gave_up[:2], {"t": 4.0, "reason": "away", "lane": b, "target": b, **entry}]
    assert aborted_changes(dataclasses.replace(ctx.ref, meta={"timeline": gave_up})) == [
        {"t": 2.0, "lane": a, "target": b}]
    assert aborted_changes(dataclasses.replace(ctx.ref, meta={"timeline": done})) == []
    # an emergency stop (no plan, no lane decision) and a one-cycle flicker back are no give-up;
    # wanting the own lane back for 0.5 s is
    stop = {"reason": "estop", "lane": a, "target": a, **entry}
    flicker = [*gave_up[:2], {"t": 2.1, **stop}, {"t": 2.2, "reason": "borrow", "lane": a, "target": b, **entry},
               {"t": 2.3, "reason": "keep", "lane": a, "target": a, **entry},
               {"t": 2.4, "reason": "borrow", "lane": a, "target": b, **entry}, done[-1]]
    assert aborted_changes(dataclasses.replace(ctx.ref, meta={"timeline": flicker})) == []
    held = [*flicker[:4], *({"t": 2.3 + 0.1 * k, "reason": "keep", "lane": a, "target": a, **entry} for k in range(6))]
    assert aborted_changes(dataclasses.replace(ctx.ref, meta={"timeline": held})) == [
        {"t": 2.0, "lane": a, "target": b}]
    # a run that ends wanting its own lane back counts only when it had wanted it for 0.5 s
    end = float(ctx.ref.t[-1])
    late = [{**e, "t": end - 3.0 + e["t"] - 1.0} for e in gave_up[:2]]
    assert aborted_changes(dataclasses.replace(ctx.ref, meta={"timeline": [*late, {**gave_up[2], "t": end - 0.3}]})) == []
    assert aborted_changes(dataclasses.replace(ctx.ref, meta={"timeline": [*late, {**gave_up[2], "t": end - 0.6}]})) == [
        {"t": end - 2.0, "lane": a, "target": b}]
    assert aborted_changes(ctx.ref) == []  # the seed itself is clean
    bad = dataclasses.replace(ctx, ref=dataclasses.replace(ctx.ref, meta={"timeline": gave_up}))
    assert robust(bad, cache_dir=None) is False


def test_a_cached_robust_verdict_is_keyed_by_the_source_that_judged_it(tmp_path, monkeypatch) -> None:
    """The robustness verdict is cached on disk under a key that hashes the judging source
    (search/trace.py, search/nods.py), which the simulation's fingerprint leaves out: a cached
    verdict is reused while that source is the same and judged again once it changes."""
    from deft_gym.search import context
    from deft_gym.search.context import robust, seed_context

    ctx = seed_context("lane_follow_static")
    assert robust(ctx, runs=1, cache_dir=tmp_path)
    (cached,) = tmp_path.glob("*.json")
    assert context._judge_key() in cached.name
    cached.write_text('{"robust": false, "runs": 1}')  # as if other judging code had said no
    assert not robust(ctx, runs=1, cache_dir=tmp_path)
    monkeypatch.setattr(context, "_judge_key", lambda: "edited00")
    assert robust(ctx, runs=1, cache_dir=tmp_path)


def test_a_reference_that_arrives_from_beside_its_destinations_lane_is_no_seed(ctx):
    """CommonRoad's reference on ``dense_cut_ins`` arrives 2.75 m beside its destination's lane,
    inside the 3 m radius by 7 cm: a mutated run a little wider misses it. A seed's reference must
    arrive at least 0.5 m inside the radius sideways."""
    from deft_gym.search.context import arrival_problem

    assert arrival_problem(ctx) is None
    for beside, refused in ((2.4, False), (2.75, True)):
        ego = ctx.ref.ego.copy()
        ego[-1, 1] += beside  # the lane runs along x
        why = arrival_problem(dataclasses.replace(ctx, ref=dataclasses.replace(ctx.ref, ego=ego)))
        assert (why is not None) is refused, why
        assert not refused or f"arrives {beside:.2f} m beside its destination's lane" in why


def test_a_timeout_the_scenarios_own_duration_ended_early_is_no_task_failure(ctx):
    """Mutated runs end at the time rule (1.5 x the reference's time + 10 s) or the scenario's own
    duration, whichever comes first. Where the scenario's comes first, before the ego needed 1.5 x
    the reference's time (slow_truck on CommonRoad's planner: 70 s for a 67 s reference), a
    timeout says only that the ego was slower than the scenario allowed: no task failure, no
    signature, while a timeout at the time rule stays one."""
    slow = dataclasses.replace(ctx.ref, outcome="timeout")
    assert ctx.oracle.timeouts_count and ctx.scenario.duration >= 1.5 * ctx.ref.sim_time
    at_rule = ctx.oracle.judge(slow)
    assert at_rule.task_failure == "timeout" and at_rule.signature.startswith("timeout:") and not at_rule.cut_short
    early = copy.copy(ctx.oracle)
    early.timeouts_count = False
    cut = early.judge(slow)
    assert cut.cut_short and cut.task_failure is None and cut.signature == "" and cut.as_dict()["cut_short"]
    assert early.judge(dataclasses.replace(ctx.ref, outcome="stuck")).task_failure == "stuck"
    # the context decides it from the scenario's duration against the reference's time
    short = ctx.scenario.model_copy(update={"duration": round(1.4 * ctx.ref.sim_time, 1)})
    assert not seed_context(short).oracle.timeouts_count
