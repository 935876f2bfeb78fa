"""The placement rules every adversary shares, and the search baselines' bookkeeping (near-
duplicates, re-checks, records)."""

from __future__ import annotations

import numpy as np
import pytest

from agents.mutation import Mutant, NonInvasiveMutator
from agents.search import POPULATION, search
from deft_gym.search.context import seed_context
from deft_gym.search.feasible import Layout
from deft_gym.search.placement import STEP, Placer


@pytest.fixture(scope="module")
def ctx():
    return seed_context("lane_follow_static")


def test_closest_is_on_the_feasibility_boundary(ctx) -> None:
    lay = Layout(ctx.areas)
    placer = Placer(ctx, "closest", np.random.default_rng(0))
    pose = placer.static(lay, "CONE", 80.0, 0.5)  # requested on the path, right side
    assert pose is not None and pose.lateral > 0.5
    # one grid step closer to the path is infeasible: "as close as allowed"
    xy, h = ctx.path.offset(np.array([pose.sigma]), np.array([pose.lateral - STEP]))
    assert not lay.static_ok(xy[:, 0], xy[:, 1], h, 0.6, 0.6)[0]
    again = Placer(ctx, "closest", np.random.default_rng(99)).static(lay, "CONE", 80.0, 0.5)
    assert (again.x, again.y) == (pose.x, pose.y)  # deterministic, whatever the RNG


def test_uniform_draws_feasible_points_near_the_request(ctx) -> None:
    lay = Layout(ctx.areas)
    poses = [Placer(ctx, "uniform", np.random.default_rng(s)).static(lay, "CONE", 80.0, 3.0) for s in range(8)]
    poses = [p for p in poses if p is not None]
    assert len(poses) >= 6 and len({(p.x, p.y) for p in poses}) == len(poses)
    for p in poses:
        assert abs(p.sigma - 80.0) <= 3.0 and abs(p.lateral - 3.0) <= 3.0
        assert lay.static_ok(np.array([p.x]), np.array([p.y]), np.array([p.heading]), 0.6, 0.6)[0]


def test_no_room_gives_none_and_rules_are_checked(ctx) -> None:
    lay = Layout(ctx.areas)
    far = Placer(ctx, "closest", np.random.default_rng(0)).static(lay, "CONE", 80.0, 60.0)  # off the road
    assert far is None
    with pytest.raises(ValueError, match="placement rule"):
        Placer(ctx, "nearest", np.random.default_rng(0))


def test_vehicle_placements_stay_feasible(ctx) -> None:
    lay = Layout(ctx.areas)
    placer = Placer(ctx, "closest", np.random.default_rng(0))
    traj = placer.vehicle(lay, 2.0, 60.0, 3.5, 0.6, "keep")
    assert traj is not None and traj.t[0] == pytest.approx(2.0) and traj.t[-1] >= ctx.scenario.duration - 1e-6
    from deft_gym.search.vehicles import LENGTH, WIDTH

    assert lay.first_conflict(traj.t, traj.x, traj.y, traj.h, LENGTH, WIDTH) < 0


def test_mutants_key_near_duplicates(ctx) -> None:
    rng = np.random.default_rng(1)
    mut = NonInvasiveMutator(ctx, rng, "closest")
    m = Mutant(Layout(ctx.areas))
    child = mut.mutate(m)
    assert child is not None and child.key() != m.key()
    assert child.copy().key() == child.key()


def test_search_records_carry_the_schema_and_recheck_failures(ctx) -> None:
    recs = list(search("random_delta", ctx, 2 * POPULATION, seed=3, rule="uniform"))
    assert [r["index"] for r in recs] == list(range(2 * POPULATION))
    for r in recs:
        assert {"outcome", "valid", "iou", "f_p", "f_b", "failure", "nods_local", "task_failure", "confirmed",
                "signature", "seconds", "cpu_seconds", "sims"} <= set(r)
        checked = r["failure"] is not None or r["task_failure"] is not None
        assert (r["confirmed"] is not None) == checked and r["sims"] == 1 + checked
        assert ("confirm_seed" in r) == checked  # the confirmation's jitter seed, to replay what counted
        assert r["cpu_seconds"] > 0.0


def test_random_never_starts_a_participant_on_the_ego() -> None:
    """Random ignores the feasible areas, but a participant that starts on the ego is no scenario
    (the scenario check refuses it): Random draws again. On gen:1000008 its 30th-odd draw put a
    cone 0.49 m from the ego's start, and the ConfigError ended the whole evaluation."""
    from agents.mutation import RandomMutator
    from deft_gym.scenarios.scenario import MIN_GAP, pose_xyh

    ctx = seed_context("gen:1000008")
    recs = list(search("random", ctx, 30, 0, 8, lambda i: None, rule="closest"))
    assert len(recs) == 30
    mut = RandomMutator(ctx, np.random.default_rng(0), "closest", max_added=8)
    exy, _ = pose_xyh(ctx.roadmap, ctx.scenario.ego)
    for _ in range(300):
        m = Mutant(Layout(ctx.areas))
        assert mut.add_static(m, "CONE")
        spec = m.layout.placed[0].spec
        assert np.hypot(spec["x"] - exy[0], spec["y"] - exy[1]) >= MIN_GAP


def test_random_never_starts_a_vehicle_on_the_ego(monkeypatch: pytest.MonkeyPatch) -> None:
    """A Random vehicle drawn off the lane starts where it is clamped onto the lane: on
    left_turn one drawn 2.05 m beside the ego's start, off the road, started 1.75 m from it, and
    the ConfigError ended a budget-100 evaluation. Its trajectory's first pose is checked."""
    from agents.mutation import RandomMutator
    from deft_gym.scenarios.scenario import MIN_GAP, pose_xyh, scenario_from_dict, with_participants

    ctx = seed_context("left_turn")
    exy, _ = pose_xyh(ctx.roadmap, ctx.scenario.ego)
    off_road = (float(exy[0]) + 2.05, float(exy[1]))  # beside the ego's start, outside its (edge) lane
    added = 0
    for seed in range(20):
        mut = RandomMutator(ctx, np.random.default_rng(seed), "closest", max_added=8)
        t0 = 2.0 * (seed % 2)  # half of them at the start
        monkeypatch.setattr(mut, "_point_at", lambda t0=t0: (*off_road, t0))
        m = Mutant(Layout(ctx.areas))
        if not mut.add_vehicle(m):
            continue
        added += 1
        w0 = m.layout.placed[0].spec["waypoints"][0]
        assert w0["t"] > 0 or np.hypot(w0["x"] - exy[0], w0["y"] - exy[1]) >= MIN_GAP
        scenario_from_dict(with_participants(ctx.scenario, "left_turn+mut", m.specs), source="left_turn (mutated)")
    assert added  # those appearing later are fine


# -- an honest comparison ---------------------------------------------------------------------------
def test_every_method_asks_from_the_same_request_grid(ctx) -> None:
    """The RL env's actions index the grid the baselines draw their requests from, and the
    baselines' requests (kind, distance ahead of the reference ego, lateral offset, speed,
    manoeuvre) all lie on it - the distribution uniform random actions ask from."""
    from agents.mutation import RandomMutator
    from deft_gym.envs import adversary
    from deft_gym.search import placement

    assert (adversary.ALONG, adversary.LATERAL, adversary.SPEEDS, adversary.MANOEUVRES) == \
        (placement.ALONG, placement.LATERAL, placement.SPEEDS, placement.MANOEUVRES)
    mut = NonInvasiveMutator(ctx, np.random.default_rng(3))
    seen = set()
    for _ in range(400):
        req, t0, sigma = mut._request()
        assert req.along in placement.ALONG and req.lateral in placement.LATERAL
        assert req.speed in placement.SPEEDS and req.manoeuvre in placement.MANOEUVRES
        assert sigma == pytest.approx(ctx.path.sigma_at_time(t0) + req.along)
        seen.add((req.kind, req.lateral))
    assert len(seen) == len(placement.KINDS) * len(placement.LATERAL)  # the whole grid, not a corner of it
    rnd = RandomMutator(ctx, np.random.default_rng(3))
    x, y, _t0 = rnd._point_at()
    _sigma, lat, _ = ctx.path.project(np.array([x, y]))
    assert min(abs(lat - v) for v in placement.LATERAL) < 1e-3  # (the projection is exact to a few um)


def test_the_ga_and_random_delta_do_not_draw_the_same_first_generation(ctx, monkeypatch) -> None:
    """With one seed they used one random stream, so both simulated (and both counted) the same
    first generation."""
    import agents.search as search_mod

    firsts: dict[str, list] = {}
    real = search_mod.run_scenario

    def spy(c, specs, *a, **kw):
        firsts.setdefault(method, []).append(specs)
        return real(c, specs, *a, **kw)

    monkeypatch.setattr(search_mod, "run_scenario", spy)
    for method in ("decictor", "random_delta"):
        list(search(method, ctx, 2, 0, 8, None, rule="closest"))
    assert firsts["decictor"][0] != firsts["random_delta"][0]


def test_a_failure_counts_only_when_the_second_run_has_the_same_root_cause(ctx, monkeypatch) -> None:
    """The re-check used to compare only the kind of failure; now the root cause must match."""
    import dataclasses

    import agents.search as search_mod
    from deft_gym.search.nods import Verdict

    first = Verdict("completed", False, True, 0.3, 1.0, 0.1, True, signature="nods:parked:far:blocked")
    for again_sig, expected in (("nods:parked:far:blocked", True), ("nods:cone:near:tight", False)):
        again = dataclasses.replace(first, signature=again_sig)
        monkeypatch.setattr(search_mod, "run_scenario", lambda *a, v=again, **kw: type("R", (), {"verdict": v})())
        assert search_mod.confirm(ctx, first, [], 1)[0] is expected
