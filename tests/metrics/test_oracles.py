"""Metric oracles wired into the search baselines and the adversary env (docs/metrics.md): the
records carry the metrics, a finding counts only on a valid mutation, re-checked on a second
jitter seed with the same signature."""

from __future__ import annotations

import numpy as np
import pytest

from deft_gym.metrics.oracle import ORACLES


@pytest.mark.parametrize("oracle", ["default", "ttc"])
def test_search_records_carry_the_metrics_and_the_oracle(oracle: str) -> None:
    from agents.search import search
    from deft_gym.search.context import seed_context

    ctx = seed_context("blocked_red_light")
    recs = list(search("random_delta", ctx, 3, seed=0, oracle=oracle))
    assert len(recs) == 3
    for r in recs:
        assert 0.0 <= r["metric_score"] <= 1.0
        assert set(r["metric_violations"]) <= set(ORACLES)
        if oracle == "default":
            assert "oracle" not in r
            continue
        assert r["oracle"] == "ttc"
        # the seed's own TTC finding (its reference run closes on the parked blocker) never counts
        assert r["oracle_signature"] != "metric:ttc:seed:parked"
        sig = r["oracle_signature"]
        if sig is None:  # no finding: nothing re-checked
            assert r["oracle_confirmed"] is None
        else:  # a finding: a valid mutation that violated the oracle, re-checked once more
            assert r["valid"] and "ttc" in r["metric_violations"] and sig.startswith("metric:ttc:")
            assert isinstance(r["oracle_confirmed"], bool) and r["sims"] >= 2


def test_the_ga_finds_a_confirmed_ttc_finding() -> None:
    """Decictor-GA aimed at TTC on handwritten/parked_street (seed 0): its first mutation delays the
    ego's change round the double-parked van, so that it closes on the van and squeezes past it
    within 0.5 m - a near miss the reference run does not have, on two jitter seeds: a counted
    finding."""
    from agents.search import search
    from deft_gym.search.context import seed_context

    recs = list(search("decictor", seed_context("handwritten/parked_street"), 1, seed=0, oracle="ttc"))
    found = [r for r in recs if r["oracle_signature"]]
    assert found, [(r["metric_violations"], r["metric_min_ttc"]) for r in recs]
    for r in found:
        assert r["valid"] and r["metric_ttc_below_s"] > 0.0 and r["metric_min_ttc"] < 1.5
        assert r["oracle_signature"] == "metric:ttc:seed:parked" and r["oracle_confirmed"] is True
        assert "scenario_equivalent" in r  # kept for the findings, as a failure's is


def test_a_finding_the_reference_run_has_is_none() -> None:
    from deft_gym.metrics.episode import EpisodeMetrics
    from deft_gym.metrics.oracle import oracle_finding

    m = EpisodeMetrics(duration=10.0, min_ttc=0.8, ttc_below_s=0.5, ttc_trigger="cone")
    assert oracle_finding(True, m, "ttc") == "metric:ttc:cone"
    assert oracle_finding(False, m, "ttc") is None  # an invalid mutation
    assert oracle_finding(True, m, "ttc", reference="metric:ttc:cone") is None  # the seed does it anyway
    assert oracle_finding(True, m, "ttc", reference="metric:ttc:seed:parked") == "metric:ttc:cone"
    assert oracle_finding(True, m, "default") is None


def test_the_env_aims_at_its_metric_oracle() -> None:
    """blocked_red_light's reference run closes on the parked blocker at a TTC below 1.5 s (0.63 s:
    it brakes beside it, mid-lane-change). With ``oracle: ttc`` and no-op actions the episode
    violates TTC the same way - no finding, no failure bonus (10), only the severity shaping
    (2 x exp(-TTC / 1.5 s))."""
    import math

    from deft_gym.envs.adversary import AdversaryEnv

    env = AdversaryEnv("blocked_red_light", oracle="ttc")
    env.reset(seed=0, options={"jitter_seed": 0})
    done, total, info = False, 0.0, {}
    while not done:
        _, r, done, _, info = env.step(np.zeros(5, dtype=np.int64))  # no-op
        total += r
    env.close()
    m = info["metrics"]
    assert info["valid"] and "ttc" in m["violations"] and m["ttc_trigger"] == "seed:parked"
    assert info["oracle_signature"] is None
    assert env.last_metrics.min_ttc == pytest.approx(m["min_ttc"], abs=1e-4)
    # the end reward is the severity shaping; the per-window shaping (objective: both) adds the rest
    assert total < env.cfg.reward.failure_bonus / 2
    assert total >= env.cfg.reward.iou_shaping * math.exp(-env.last_metrics.min_ttc / 1.5) - 1e-6


def test_the_sink_keeps_a_metric_finding_once(tmp_path) -> None:
    """A metric oracle's finding is kept (and extracted) as a failure is; a second one with the
    same (scenario, signature) is a duplicate; a passing episode is not kept (keep_passing 0)."""
    from deft_gym.envs.sink import EpisodeSink

    sink = EpisodeSink(tmp_path, 0, keep_passing=0.0, extract=False, distinct=True)
    rec = {"scenario": "left_turn", "failure": None, "signature": "", "oracle_signature": "metric:ttc:cone"}
    assert sink.keeps(rec)
    d = sink.episode_dir("left_turn")
    done = sink.finish(d, rec, {})
    assert done["kept"] and (d / "episode.json").exists()
    assert not sink.keeps(rec)  # distinct: the same finding again
    assert not sink.keeps({**rec, "oracle_signature": None})
    # oracle any: every counted metric oracle's finding is kept, once per (scenario, signatures)
    union = {"scenario": "left_turn", "failure": None, "signature": "", "oracle": "any", "oracle_signature": None,
             "found_by_oracle": {"comfort": "metric:comfort:lon_accel", "ttc": "metric:ttc:cone"}}
    assert sink.keeps(union)
    sink.finish(sink.episode_dir("left_turn"), union, {})
    assert not sink.keeps(union)
    assert sink.keeps({**union, "found_by_oracle": {"ttc": "metric:ttc:parked"}})
    assert not sink.keeps({**union, "oracle": "default"})  # counted, not aimed at: not kept


def test_a_comfort_finding_needs_a_reference_that_is_comfortable() -> None:
    """Comfort's signature names the first signal out of bounds, no participant: where the seed's
    reference run is uncomfortable already, a mutation that only changes which signal breaks
    first is no finding."""
    from deft_gym.metrics.episode import EpisodeMetrics
    from deft_gym.metrics.oracle import oracle_finding

    m = EpisodeMetrics(comfort={"lon_jerk": 9.0}, uncomfortable=["lon_jerk"])
    assert oracle_finding(True, m, "comfort") == "metric:comfort:lon_jerk"
    assert oracle_finding(True, m, "comfort", reference="metric:comfort:lon_accel") is None


def test_counted_oracles_leave_the_search_as_it_was() -> None:
    """``count`` adds each counted oracle's finding and its re-check to a record, on a jitter seed
    derived from the run's: the search's own draws - mutations, jitter seeds, the decision
    oracle's re-check - are what they are without counting."""
    from agents.search import search
    from deft_gym.metrics.oracle import COUNTED_ORACLES
    from deft_gym.search.context import seed_context

    ctx = seed_context("handwritten/parked_street")
    plain = list(search("decictor", ctx, 3, seed=0))
    counted = list(search("decictor", ctx, 3, seed=0, count=COUNTED_ORACLES))
    volatile = {"seconds", "cpu_seconds", "metric_cpu_s", "sims", "scenario_equivalent"}
    for a, b in zip(plain, counted, strict=True):
        assert b["counted_oracles"] == list(COUNTED_ORACLES)
        extra = {"counted_oracles", "found_by_oracle", "confirmed_by_oracle"}
        assert {k: v for k, v in a.items() if k not in volatile} == \
            {k: v for k, v in b.items() if k not in volatile | extra}
        assert set(b["confirmed_by_oracle"]) == set(b["found_by_oracle"])
        assert b["sims"] == a["sims"] + int(bool(b["found_by_oracle"]))
    # the near miss of test_the_ga_finds_a_confirmed_ttc_finding, counted here without aiming at it
    assert counted[0]["found_by_oracle"]["ttc"] == "metric:ttc:seed:parked" and counted[0]["confirmed_by_oracle"]["ttc"]


def test_what_the_unmutated_runs_do_counts_nothing(tmp_path, monkeypatch) -> None:
    """The seed's unmutated runs on the fit check's jitter seeds are simulated once and their
    signatures cached; a counted finding that one of them has (here the near miss of
    test_counted_oracles_leave_the_search_as_it_was, as if an unmutated run had it) moves from
    ``found_by_oracle`` to ``unmutated_by_oracle`` and costs no re-check; on comfort, which names
    no participant, any unmutated violation rules its findings out."""
    from agents.search import search
    from deft_gym.metrics import oracle as mo
    from deft_gym.search.context import FIT_RUNS, seed_context

    ctx = seed_context("handwritten/parked_street")
    monkeypatch.setattr(mo, "_UNMUTATED", {})
    sigs = mo.unmutated_signatures(ctx, cache_dir=tmp_path)
    assert [p.name.split("-")[-2] for p in tmp_path.glob("*.json")] == [f"unmutated{FIT_RUNS}"]
    assert all(o in mo.COUNTED_ORACLES and s for o, s in sigs.items())
    mo._UNMUTATED.clear()
    monkeypatch.setattr(mo, "record_run", lambda *a, **k: pytest.fail("simulated again, not read from the cache"))
    assert mo.unmutated_signatures(ctx, cache_dir=tmp_path) == sigs
    mo._UNMUTATED[id(ctx)] = (ctx, {"ttc": ["metric:ttc:seed:parked"], "comfort": ["metric:comfort:lat_accel"]})
    rec = next(iter(search("decictor", ctx, 1, seed=0, count=mo.COUNTED_ORACLES)))
    assert "ttc" not in rec["found_by_oracle"] and "ttc" not in rec["confirmed_by_oracle"]
    assert rec["unmutated_by_oracle"]["ttc"] == "metric:ttc:seed:parked"
    assert mo.unmutated_finding(ctx, "comfort", "metric:comfort:lon_jerk")  # any comfort violation
    assert not mo.unmutated_finding(ctx, "ttc", "metric:ttc:cone")  # another root cause still counts


def test_the_union_oracle_rewards_each_finding_with_its_own_novelty() -> None:
    """``oracle: any``: the end bonus is the decision oracle's failure bonus plus one for each counted
    metric oracle's finding, each divided by sqrt(1 + n) for the n times this env was rewarded for
    that signature before; a run with none is rewarded as under ``default``."""
    import math
    from types import SimpleNamespace

    from deft_gym.envs.adversary import AdversaryEnv
    from deft_gym.metrics.episode import EpisodeMetrics
    from deft_gym.metrics.oracle import COUNTED_ORACLES, findings_by_oracle

    env = AdversaryEnv("handwritten/parked_street", oracle="any")
    env.reset(seed=0, options={"jitter_seed": 0})
    bonus = env.cfg.reward.failure_bonus
    passed = SimpleNamespace(valid=True, failure=None, nods=False, collision=False, ego_at_fault=False,
                             iou=0.75, finding=None, signature="")
    near_miss = EpisodeMetrics(duration=20.0, min_ttc=0.8, ttc_below_s=0.5, ttc_trigger="cone", progress_ratio=0.5)
    found = findings_by_oracle(env.ctx, True, near_miss, COUNTED_ORACLES)
    assert found == {"ttc": "metric:ttc:cone", "progress": "metric:progress:progress"}
    assert env._union_bonus(passed, found, "timeout") == pytest.approx(2 * bonus)
    assert env._union_bonus(passed, found, "timeout") == pytest.approx(2 * bonus / math.sqrt(2))
    nods = SimpleNamespace(**{**vars(passed), "nods": True, "signature": "nods:cone:edge"})
    assert env._union_bonus(nods, {}, "completed") == pytest.approx(bonus)
    crash = SimpleNamespace(**{**vars(passed), "failure": "collision", "signature": "collision:cone"})
    assert env._union_bonus(crash, {"collision": "metric:collision:rear_end"}, "collision") == pytest.approx(bonus)
    assert env._union_bonus(passed, {}, "completed") == pytest.approx(env.cfg.reward.iou_shaping * 0.25)
    assert env._union_bonus(passed, {}, "stuck") == env.cfg.reward.task_failure
    env.close()


def test_the_ga_aims_at_every_oracle_with_any() -> None:
    """Decictor-GA with ``oracle: any`` keeps the decision oracle's columns, selects by its feedback
    plus the largest growth of a metric's severity over the seed's reference run, and counts the
    metric findings (here the near miss of test_the_ga_finds_a_confirmed_ttc_finding)."""
    from agents.search import feedback, fitness, search
    from deft_gym.metrics.oracle import (
        COUNTED_ORACLES,
        reference_metrics,
        run_metrics,
        severity,
        severity_growth,
    )
    from deft_gym.search.context import seed_context
    from deft_gym.search.episode import run_scenario

    ctx = seed_context("handwritten/parked_street")
    recs = list(search("decictor", ctx, 1, seed=0, oracle="any", count=COUNTED_ORACLES))
    assert recs[0]["oracle"] == "any" and "oracle_signature" not in recs[0]
    assert recs[0]["found_by_oracle"]["ttc"] == "metric:ttc:seed:parked"
    ref = reference_metrics(ctx)
    assert severity_growth(ctx, ref) == 0.0  # the seed itself: nothing grew
    eq = recs[0]["scenario_equivalent"]
    run = run_scenario(ctx, eq["scenario"]["participants"][len(ctx.scenario.participants):], eq["jitter_seed"])
    m = run_metrics(ctx, run.trace, run.verdict.collision_detail)
    assert severity(m, "ttc") > severity(ref, "ttc")
    assert fitness(ctx, run.verdict, m, "any") == pytest.approx(feedback(run.verdict) + severity_growth(ctx, m))
    assert severity_growth(ctx, m) > 0.0


def test_late_statics_from_start_pays_only_what_comes_back_with_the_objects_there_at_t0() -> None:
    """``late_statics: from_start``: an episode with a finding and a static object placed mid-run is
    simulated once more with the object standing from t = 0, and the end bonus pays only the
    findings that come back. A parked car appearing 10 m ahead of the ego at 2 s makes it brake
    hard (comfort); standing there from the start it does not, so that finding earns nothing."""
    import numpy as np

    from deft_gym.envs.adversary import AdversaryEnv

    def episode(rule: str) -> tuple[float, dict]:
        env = AdversaryEnv("lane_follow_static", late_statics=rule, oracle="any",
                           feasible={"static_margin": 0.5, "static_lane_depth": None})
        env.reset(seed=0, options={"jitter_seed": 0})
        total, done, step, info = 0.0, False, 0, {}
        while not done:  # a parked car 10 m ahead, as close to the path as allowed, at the second step
            _, r, done, _, info = env.step(np.array([2, 3, 4, 0, 0]) if step == 1 else np.zeros(5, dtype=int))
            total, step = total + r, step + 1
        env.close()
        return total, info

    placed, placed_info = episode("as_placed")
    start, start_info = episode("from_start")
    assert placed_info["from_start"] is None and placed_info["added"] == 1
    assert "comfort" in start_info["found_by_oracle"] and "comfort" not in start_info["from_start"]["found"]
    assert set(start_info["from_start"]["found"]) < set(start_info["found_by_oracle"])
    assert start < placed  # the same episode, less paid
