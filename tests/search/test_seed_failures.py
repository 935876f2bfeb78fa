"""A failure can be found on every seed scenario the evaluation searches under Decictor's rule
(``feasible.PAPER``): for each seed a hand-built *valid* mutation (every added object at least
0.5 m from the optimal path, as the oracle's replay judges it), placed where the search methods may place objects (granted by their
own placer under the ``closest`` rule, inside the seed's feasible areas), yields a NoDS under
the paper's oracle (task completed, 2 m grid IoU <= 0.6) for two jitter seeds.

The three turns were laid out for it (docs/search.md, seeds): their turn may be made from both
lanes (map ``turn_lanes: 2``, ``right_turn_lanes: 2``), so a borrow of the other lane before the
junction persists through the turn (no lane change starts within 20 m of a junction) and along
part of the road after it. Their tests also show that path, and that the seeds stay
optimal-decision seeds under timing noise. Each of these mutations stands a parked car or a cone
inside the ego's lane, which the default rule refuses (static objects 0.75 m from the optimal
path; docs/search.md): under it, these are no findings. (With a right turn from one lane only, no single
parked vehicle or cone beside `right_turn`'s path - either side, every 10 m - gave a failure on
both jitter seeds: most left the ego standing before the junction, a task failure.)
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from deft_gym.search.context import SeedContext, robust, seed_context
from deft_gym.search.feasible import PAPER, Layout
from tests.support.nods_helpers import assert_nods, assert_placeable, place_static

# per seed: the objects asked for, as (obstacle, sigma [m] along the optimal path, lateral [m],
# + to the right); the closest rule puts each at the feasible pose nearest to the request
MUTATIONS: dict[str, list[tuple[str, float, float]]] = {
    # a parked vehicle on the right shoulder 35 m before the stop line: its impact buffer blocks the
    # outer left-turn lane; the ego borrows the inner one and turns from there (pattern 2)
    "left_turn": [("STATIC_VEHICLE", 30.0, 0.5)],
    # the same on the right turn, 40 m before the stop line: the ego borrows the inner lane and
    # turns right from there (pattern 2)
    "right_turn": [("STATIC_VEHICLE", 30.0, 0.5)],
    # a parked vehicle on the median shoulder 30 m before the U-turn bay: the ego borrows the
    # outer lane and turns through the outer bay (pattern 2)
    "u_turn": [("STATIC_VEHICLE", 50.0, -0.5)],
    # a parked vehicle on the right shoulder 50 m before the stop line: the borrow persists through
    # the junction
    "cross_intersection": [("STATIC_VEHICLE", 20.0, 0.5)],
    # a parked vehicle on the left shoulder: the ego borrows the right lane
    "lane_follow_static": [("STATIC_VEHICLE", 40.0, -0.5)],
    # a cone near the start, right of the path: the middle lane counts as blocked, the route's lane
    # changes come late, behind the traffic
    "take_exit": [("CONE", 20.0, 0.5)],
    # a parked vehicle in the right part of the ego's lane 20 m before the stop line: the ego stays
    # in the waiting NPC's lane (where it passed the seed's blocker) through the junction
    "blocked_red_light": [("STATIC_VEHICLE", 70.0, 0.5)],
}

# the lane the ego turns through when the borrow persists: the other turn lane of the junction
OTHER_TURN_LANE = {"left_turn": ("ir0", "il1", 0), "right_turn": ("ir0", "il3", 0), "u_turn": ("b", "c", 1)}


def mutation(ctx: SeedContext, name: str) -> list[dict[str, Any]]:
    layout = Layout(ctx.areas)
    return [place_static(ctx, layout, obstacle, sigma, lateral, f"added_{i}")
            for i, (obstacle, sigma, lateral) in enumerate(MUTATIONS[name])]


@pytest.mark.parametrize("name", sorted(MUTATIONS))
def test_a_placeable_valid_mutation_gives_a_nods(name: str) -> None:
    ctx = seed_context(name, PAPER)
    specs = mutation(ctx, name)
    assert_placeable(ctx, specs)
    assert_nods(ctx, specs)


@pytest.mark.parametrize("name", sorted(OTHER_TURN_LANE))
def test_redesigned_turns_borrow_through_the_junction(name: str) -> None:
    """The unmutated seed is an optimal-decision seed (its reference run completes in sensible
    time; eight jitter seeds complete consistently with it), and under the mutation the ego makes
    its turn from the other lane: the wrong decision lasts through the junction."""
    ctx = seed_context(name, PAPER)
    assert ctx.ref.outcome == "completed" and ctx.ref.sim_time < 30.0
    assert 140.0 < ctx.path.length < 175.0
    assert robust(ctx, cache_dir=None)
    (r, *_) = assert_nods(ctx, mutation(ctx, name))
    assert "borrow" in r.reasons()
    geom = ctx.roadmap.geom(OTHER_TURN_LANE[name])
    half = geom.width / 2  # inside that lane (the ego cuts the tight right turn's corner by ~1.1 m)
    s, d = geom.frenet(r.xy)
    on = (np.abs(d) < half) & (s > 0.0) & (s < geom.length)
    assert on.any() and np.ptp(s[on]) > 0.9 * geom.length, "the ego did not turn from the other lane"
    ref_s, ref_d = geom.frenet(ctx.ref.xy)
    assert not ((np.abs(ref_d) < half) & (ref_s > 0.0) & (ref_s < geom.length)).any()


@pytest.mark.parametrize("name", sorted(MUTATIONS))
def test_every_seed_reference_is_typical_and_gives_up_no_lane_change(name: str) -> None:
    """The optimal path of every seed: the most typical of its five jittered runs, and none that
    begins a lane change and gives it up (the robustness check would refuse such a scenario)."""
    from deft_gym.search.trace import aborted_changes

    ctx = seed_context(name)
    assert ctx.ref.meta["reference_of"] == [0, 1, 2, 3, 4] and ctx.ref.meta["jitter_seed"] in range(5)
    assert aborted_changes(ctx.ref) == []
