"""The reference planner behind a moving leader: it keeps a time gap instead of closing in to its
hard buffer (v38; before, it followed a 6 m/s truck 1.0 m behind for a minute, docs/metrics.md
``headway``). Real simulations of the hand-written ``slow_truck`` and the planner's own cost on
hand-made predictions."""

from __future__ import annotations

import numpy as np
import pytest

from deft_gym.bus.ads import load_ads_config
from deft_gym.planner.lattice import LatticeParams, LatticePlanner
from deft_gym.scenarios.scenario import load_scenario


def _headway(params: dict) -> tuple[float, float, list[str]]:
    """Minimum time headway [s], the longest stretch below 0.8 s [s] and the violations of the
    ego on slow_truck (jitter seed 0) with these planner parameters."""
    from deft_gym.metrics.episode import simulation_metrics
    from deft_gym.search.trace import TraceRecorder
    from deft_gym.sim.simulation import Simulation

    ads = load_ads_config(None, {"planning": {"planner": {"params": params}}})
    sim = Simulation(load_scenario("handwritten/slow_truck"), ads, jitter_seed=0, out_dir=None,
                     keep_planning=False, recorder_process=False)
    recorder = TraceRecorder(sim)
    result = sim.run()
    assert result.outcome.outcome == "completed"
    m = simulation_metrics(sim, recorder, result)
    return m.min_headway, m.headway_below_max_s, m.violations()


def test_the_planner_follows_a_slow_truck_at_a_time_gap_not_at_its_bumper() -> None:
    min_headway, below, violations = _headway({})
    assert min_headway > 0.95 and below == 0.0 and "headway" not in violations
    # the planner before v38 (no closing cost, FOLLOW aimed at the leader's place at the horizon's end)
    min_headway, below, violations = _headway({"w_closing": 0.0, "follow_times": []})
    assert min_headway < 0.3 and below > 50.0 and "headway" in violations


def _obs(rear_now: float, rear_end: float, v: float, d: float = 0.0) -> dict:
    """One predicted obstacle, 4 m long, its rear at ``rear_now`` now and ``rear_end`` at the end of
    the horizon along the reference, ``d`` beside it."""
    return {"n": 1, "fs": [[rear_now + 2.0, rear_end + 2.0]], "fes": [[2.0, 2.0]], "fd": [d], "fed": [1.0],
            "v": [v]}


@pytest.fixture(scope="module")
def planner() -> LatticePlanner:
    return LatticePlanner(load_scenario("lane_follow_static").map.model_dump())


def test_closing_in_costs_keeping_the_gap_or_an_oncoming_car_does_not(planner: LatticePlanner) -> None:
    """The ego at 10 m/s, s = 0; a leader 10 m/s ahead, its rear 2.4 + 15 m ahead (1.5 s). A profile
    at 10 m/s keeps the gap: free; one at 14 m/s closes in below 1.0 s: costs; the same gap with the
    car coming the other way (oncoming) or beside the ego's band costs nothing."""
    tk, half = planner.tk, LatticeParams().ego_length / 2
    sva = np.zeros((3, 2, len(tk)))
    sva[1, 0], sva[1, 1] = 10.0, 14.0
    sva[0, 0], sva[0, 1] = 10.0 * tk, 14.0 * tk
    rear = half + 15.0
    cost = planner._closing_cost(_obs(rear, rear + 10.0 * tk[-1], 10.0), 0.0, 0.0, 10.0, sva)
    assert cost[0] == 0.0 and cost[1] > 0.5
    assert planner._closing_cost(_obs(rear, rear - 10.0 * tk[-1], 10.0), 0.0, 0.0, 10.0, sva) == 0.0  # oncoming
    assert planner._closing_cost(_obs(rear, rear + 10.0 * tk[-1], 10.0, d=3.5), 0.0, 0.0, 10.0, sva) == 0.0
    # a gap already short (a cut-in 5 m ahead): holding it costs nothing, closing in further does
    cost = planner._closing_cost(_obs(half + 5.0, half + 5.0 + 10.0 * tk[-1], 10.0), 0.0, 0.0, 10.0, sva)
    assert cost[0] == 0.0 and cost[1] > 0.0
