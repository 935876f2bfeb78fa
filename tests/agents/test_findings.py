"""``deft-gym findings``: a counted failure of an evaluation's records simulated again with its
jitter seed, checked to fail with the same root cause, drawn, and listed by root cause."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import matplotlib.pyplot as plt
import pytest
import yaml

from agents import findings, recount
from agents.search import record_of
from deft_gym.search.context import seed_context
from deft_gym.search.episode import run_scenario
from deft_gym.search.feasible import PAPER, Layout
from tests.support.nods_helpers import place_static


def test_a_counted_failure_is_simulated_again_drawn_and_listed(tmp_path) -> None:
    ctx = seed_context("lane_follow_static", PAPER)  # an evaluation under Decictor's rule, as before 2026-11-26
    added = [place_static(ctx, Layout(ctx.areas), "STATIC_VEHICLE", 40.0, -0.5, "added_0")]  # a NoDS (seed tests)
    run = run_scenario(ctx, added, 0)
    v = run.verdict
    assert v.failure == "nods" and v.signature == "nods:parked:in_lane:blocked"
    rec = {"method": "decictor", "placement": "closest", "scenario": "lane_follow_static", "repeat": 0,
           **record_of(v, 3, 1.0, 1.0, 2, True, 0, 1, run.result.sim_time), "scenario_equivalent": run.scenario}
    # re-simulated under the rule the evaluation ran under (its eval_config.json)
    (tmp_path / "eval_config.json").write_text(json.dumps({"feasible": PAPER.model_dump()}))
    (tmp_path / "records.jsonl").write_text(json.dumps(rec) + "\n" + json.dumps({**rec, "index": 4, "failure": None})
                                             + "\n")
    assert findings.main([str(tmp_path), "--no-progress"]) == 0
    text = (tmp_path / "findings" / "findings.md").read_text()
    assert "| `nods:parked:in_lane:blocked` | 1 |" in text and "again **the same**" in text
    assert "clearance of the trigger 0.6" in text and "borrow in a-b-0" in text
    img = plt.imread(next((tmp_path / "findings").glob("*.png")))
    assert img.shape[0] > 200 and img[..., :3].std() > 0.05


def test_no_records_is_a_one_line_error(tmp_path, capsys) -> None:
    assert findings.main([str(tmp_path)]) == 2
    assert "records.jsonl: no such file" in capsys.readouterr().err


def test_a_drawn_failure_gets_a_replay_command_and_a_failing_test(tmp_path) -> None:
    """``--tests N``: the re-simulation is recorded with the optimal path it is judged against, its
    planning-module tests are extracted, and the non-optimal decision's test (P_departure: the plan
    that took the ego off the optimal path) fails every run; a planner that keeps its lane passes it."""
    import os
    import subprocess
    import sys

    ctx = seed_context("lane_follow_static", PAPER)
    added = [place_static(ctx, Layout(ctx.areas), "STATIC_VEHICLE", 40.0, -0.5, "added_0")]
    run = run_scenario(ctx, added, 0)
    rec = {"method": "decictor", "placement": "closest", "scenario": "lane_follow_static", "repeat": 0,
           **record_of(run.verdict, 3, 1.0, 1.0, 2, True, 0, 1, run.result.sim_time),
           "scenario_equivalent": run.scenario}
    (tmp_path / "eval_config.json").write_text("{}")  # written before the rule was recorded: Decictor's
    (tmp_path / "records.jsonl").write_text(json.dumps(rec) + "\n")
    assert findings.main([str(tmp_path), "--tests", "2", "--no-progress"]) == 0
    out = tmp_path / "findings"
    text = (out / "findings.md").read_text()
    assert "replay: `deft-gym run " in text and next(out.glob("*.replay.yaml")).exists()
    assert "its non-optimal decision (P_departure) test fails **2 of 2** runs" in text
    assert "the reproduction tests pass" in text
    tests = next(out.glob("*_tests"))
    env = {**os.environ, "DEFT_PLANNER": "tests.support.lane_keeper:LaneKeeperPlanner"}
    kept = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
                           "-k", "keeps_to_the_optimal_path", str(tests)], env=env, capture_output=True, text=True)
    assert kept.returncode == 0, kept.stdout[-2000:]


def test_a_record_judged_under_decictors_rule_is_invasive_under_the_default(tmp_path, capsys) -> None:
    """The same in-lane parked car, with no eval_config.json (the default rule): the re-simulation
    calls the mutation invasive, so the failure is not confirmed."""
    ctx = seed_context("lane_follow_static", PAPER)
    added = [place_static(ctx, Layout(ctx.areas), "STATIC_VEHICLE", 40.0, -0.5, "added_0")]
    _, again = findings.resimulate({"scenario": "lane_follow_static", "jitter_seed": 0,
                                    "scenario_equivalent": run_scenario(ctx, added, 0).scenario})
    assert not again.verdict.valid and again.verdict.invasive_why == {"added_0": "path"}
    assert findings.eval_feasible(tmp_path).static_margin == 0.75
    (tmp_path / "eval_config.json").write_text(json.dumps({"feasible": {"static_margin": -1}}))
    (tmp_path / "records.jsonl").write_text("")
    assert findings.main([str(tmp_path)]) == 2 and "field 'feasible'" in capsys.readouterr().err


def test_a_counted_metric_finding_is_simulated_again_and_drawn(tmp_path) -> None:
    """An evaluation that counted metric oracles (``--count-oracles``): each confirmed finding's
    signature is a root cause of its own, re-simulated and checked for the same signature on its
    oracle, drawn, and listed with what the metric measured."""
    from agents.search import search

    recs = list(search("decictor", seed_context("handwritten/parked_street"), 2, seed=0, count=("ttc", "comfort")))
    found = [r for r in recs if r["confirmed_by_oracle"].get("ttc")]
    assert found  # the near miss at the double-parked van (tests/metrics/test_oracles.py)
    lines = [json.dumps({"method": "decictor", "placement": "closest", "scenario": "handwritten/parked_street",
                         "repeat": 0, **r}) for r in recs]
    (tmp_path / "records.jsonl").write_text("\n".join(lines) + "\n")  # no eval_config.json: the default rule
    assert findings.main([str(tmp_path), "--per-cause", "1", "--no-progress"]) == 0
    text = (tmp_path / "findings" / "findings.md").read_text()
    assert f"| `metric:ttc:seed:parked` | {len(found)} |" in text and "## `metric:ttc:seed:parked`" in text
    assert "again **the same**" in text
    assert re.search(r"min TTC [01]\.\d\d s to van \(seed:parked\), below 1\.5 s for [0-9.]+ s; "
                     r"closest 0\.[0-4]\d m, at [0-9.]+ m/s", text), text


def test_the_sample_of_a_root_cause_spreads_over_its_scenarios() -> None:
    recs = [{"scenario": s, "repeat": rep, "index": i, "method": "rl"}
            for s in ("b", "a", "c") for rep in (1, 0) for i in (3, 1)]
    picked = findings.spread(recs, 4)
    assert [(r["scenario"], r["repeat"], r["index"]) for r in picked] == [("a", 0, 1), ("b", 0, 1), ("c", 0, 1),
                                                                          ("a", 0, 3)]
    assert findings.spread(recs[:1], 3) == recs[:1] and findings.spread([], 2) == []


def test_a_run_that_passed_level_with_its_destination_a_lane_over_is_pointed_out() -> None:
    """An ego that passes level with its destination in the next lane (3.5 m over) without
    stopping there has not arrived (3 m radius). The findings page says so, for the analyst to
    judge the picture (a miss, or a seed only just reached); a run that stops far short does not
    get it."""
    ctx = seed_context("lane_follow_static")
    whole = ctx.oracle.reserved  # the reference run on to the destination
    ego = whole.ego.copy()
    ego[:, 1] += 3.5
    over = dataclasses.replace(whole, ego=ego)
    dist, along, beside = findings.destination_approach(ctx, over)
    assert dist == pytest.approx(3.5, abs=0.05) and abs(along) < 0.3 and abs(beside) == pytest.approx(3.5, abs=0.05)
    assert "passed level with it, a lane over" in findings.destination_line(ctx, over)
    short = dataclasses.replace(whole, ego=whole.ego[: len(whole.ego) // 2])
    line = findings.destination_line(ctx, short)
    assert findings.destination_approach(ctx, short)[1] < -50.0 and "a lane over" not in line


def test_statics_from_start_simulates_a_failure_again_with_its_late_objects_there_at_once(tmp_path) -> None:
    """``--statics-from-start``: a static object that joined mid-run is put in the scenario from the
    start for a second simulation, which says whether the same root cause comes back. Here the parked
    car joining at 1 s makes a local detour only, and there from the start it makes the NoDS."""
    from deft_gym.search.episode import late_statics, replay_record, statics_from_start

    ctx = seed_context("lane_follow_static", PAPER)
    added = [place_static(ctx, Layout(ctx.areas), "STATIC_VEHICLE", 40.0, -0.5, "added_0")]
    run = run_scenario(ctx, added, 0)
    assert run.verdict.failure == "nods"
    assert late_statics(run.scenario["participants"], {"added_0": 1.0}) == ["added_0"]
    assert late_statics(run.scenario["participants"], {"added_0": 0.0}) == []
    assert statics_from_start(run.scenario["participants"], {"added_0": 1.0, "veh_1": 2.0}) == {"veh_1": 2.0}
    assert statics_from_start(run.scenario["participants"], {"added_0": 1.0}) is None
    rec = {"method": "rl", "placement": "closest", "scenario": "lane_follow_static", "repeat": 0,
           **record_of(run.verdict, 3, 1.0, 1.0, 2, True, 0, 1, run.result.sim_time),
           "scenario_equivalent": replay_record(run.scenario, 0, {"added_0": 1.0})}
    (tmp_path / "eval_config.json").write_text(json.dumps({"feasible": PAPER.model_dump()}))
    (tmp_path / "records.jsonl").write_text(json.dumps(rec) + "\n")
    assert findings.main([str(tmp_path), "--no-progress", "--statics-from-start"]) == 0
    text = (tmp_path / "findings" / "findings.md").read_text()
    assert "again **NOT the same: local:parked:in_lane:blocked**" in text
    assert "with its static objects that joined after t = 0 (added_0) there from the start: **found again**" in text
    assert "| `nods:parked:in_lane:blocked` | 1 | 1 |" in text.split("## Static objects there from the start")[1]
    # a record that counted with its late objects there from the start is drawn and replayed that way
    (tmp_path / "records.jsonl").write_text(json.dumps({**rec, "late_statics": "from_start"}) + "\n")
    assert findings.main([str(tmp_path), "--no-progress", "--out", str(tmp_path / "f1")]) == 0
    text = (tmp_path / "f1" / "findings.md").read_text()
    assert "jitter seed 0, its static objects there from the start (how it counted: the confirmation's run): " \
        "again **the same**" in text
    replay = yaml.safe_load(next((tmp_path / "f1").glob("*.replay.yaml")).read_text())
    assert replay["added_at"] == {}
    # ... on the confirmation's jitter seed where the record keeps it
    (tmp_path / "records.jsonl").write_text(json.dumps({**rec, "late_statics": "from_start", "confirm_seed": 5}) + "\n")
    assert findings.main([str(tmp_path), "--no-progress", "--out", str(tmp_path / "f3")]) == 0
    assert "jitter seed 5, its static objects there from the start" in (tmp_path / "f3" / "findings.md").read_text()
    assert yaml.safe_load(next((tmp_path / "f3").glob("*.replay.yaml")).read_text())["jitter_seed"] == 5
    # without a late object there is nothing to move
    rec["scenario_equivalent"] = replay_record(run.scenario, 0, None)
    (tmp_path / "records.jsonl").write_text(json.dumps(rec) + "\n")
    assert findings.main([str(tmp_path), "--no-progress", "--statics-from-start", "--out", str(tmp_path / "f2")]) == 0
    text = (tmp_path / "f2" / "findings.md").read_text()
    assert "- no static object joined after t = 0" in text and "No drawn failure has a static object" in text


def test_a_finding_counted_from_the_start_is_replayed_on_its_confirmations_seed() -> None:
    """What counted of an online method's finding under ``late_statics: from_start`` is the
    confirmation's run (its objects there from the start, another jitter seed): the decision
    oracle's kept seed, the aimed metric oracle's, or a counted oracle's derived from the run's."""
    from agents.search import count_confirm_seed

    base = {"jitter_seed": 11, "oracle": "ttc", "oracle_signature": "ttc:vehicle", "oracle_confirmed": True,
            "oracle_confirm_seed": 22, "confirm_seed": 33, "found_by_oracle": {"comfort": "comfort:lon_jerk"}}
    assert findings.confirmation_seed(base) == 33
    assert findings.confirmation_seed({**base, "_oracle": "ttc"}) == 22
    assert findings.confirmation_seed({**base, "_oracle": "comfort"}) == count_confirm_seed(11) != 11
    assert findings.confirmation_seed({"jitter_seed": 11}) is None  # written before the seeds were kept
    # a kept seed of 0 is a seed (it is falsy)
    rec = {"jitter_seed": 11, "late_statics": "from_start", "confirm_seed": 0,
           "scenario_equivalent": {"scenario": {"name": "x", "participants": []}, "jitter_seed": 11}}
    assert findings.counted_equivalent(rec)["jitter_seed"] == 0


def _scripted(pid: str, points: list[tuple[float, float, float]]) -> dict:
    return {"id": pid, "type": "scripted", "length": 4.8, "width": 2.0,
            "waypoints": [{"t": t, "x": x, "y": y, **({"heading": 0.0} if k == 0 else {})}
                          for k, (t, x, y) in enumerate(points)]}


def test_predicted_cut_ins_are_told_apart_from_the_ones_that_come() -> None:
    """The findings page names vehicles the ADS's prediction put into the ego's lane and says
    whether they came: a car driving 1 m off its lane centre towards the ego is predicted to cut in
    (the testbed's intent rule, ``intent_offset`` 0.6 m) again and again and never does; a car that
    changes into the ego's lane comes."""
    ctx = seed_context("lane_follow_static")  # the ego in lane 0 (y 0), lane 1 at y 3.5
    drifter = _scripted("drifter", [(0.0, 40.0, 2.5), (8.0, 104.0, 2.5), (30.0, 280.0, 2.5)])
    changer = _scripted("changer", [(0.0, 40.0, 3.5), (3.0, 70.0, 3.5), (6.0, 100.0, 0.0), (30.0, 340.0, 0.0)])
    got = {}
    for spec in (drifter, changer):
        watched: list[findings.PredictedLaneChanges] = []
        run = run_scenario(ctx, [spec], 0, watch=lambda sim, into=watched: into.append(findings.PredictedLaneChanges(sim)))
        got[spec["id"]] = findings.cut_ins(ctx, run.trace, watched[0].changes, 5.0)
    n, came = got["drifter"]["drifter"]
    assert n >= 20 and came == 0
    assert "**none came true**" in findings.cut_in_line(got["drifter"])
    n, came = got["changer"]["changer"]
    assert came >= 1 and came == n
    assert "none came true" not in findings.cut_in_line(got["changer"])
    assert findings.cut_in_line({}).endswith(": none")


def test_without_the_intent_rule_the_predictor_predicts_no_cut_in() -> None:
    """The recount's counterfactual (``agents.recount.without_intent``): the same context - scenario,
    reference, oracle - whose predictor has no intent rule predicts no lane change for a car 1 m
    off its lane centre, which the testbed's predictor predicts to cut in again and again."""
    ctx = seed_context("lane_follow_static")
    drifter = _scripted("drifter", [(0.0, 40.0, 2.5), (8.0, 104.0, 2.5), (30.0, 280.0, 2.5)])
    bare = recount.without_intent(ctx)
    assert bare.ref is ctx.ref and bare.oracle is ctx.oracle and bare.scenario is ctx.scenario
    assert ctx.ads.prediction.params["intent_offset"] == 0.6  # the context itself is unchanged
    counts = []
    for c in (ctx, bare):
        watched: list[findings.PredictedLaneChanges] = []
        run_scenario(c, [drifter], 0, watch=lambda sim, into=watched: into.append(findings.PredictedLaneChanges(sim)))
        counts.append(len(watched[0].changes))
    assert counts[0] >= 20 and counts[1] == 0


def _rec(method: str, repeat: int, scenario: str, index: int, signature: str | None = None,
         found: dict | None = None) -> dict:
    return {"method": method, "placement": "uniform", "scenario": scenario, "scenario_kind": "handwritten",
            "repeat": repeat, "index": index, "valid": True, "failure": "collision" if signature else None,
            "confirmed": True if signature else None, "signature": signature,
            "found_by_oracle": found or {}, "confirmed_by_oracle": {o: True for o in (found or {})}}


def test_the_recount_counts_each_distinct_finding_once_as_the_evaluation_did() -> None:
    """``counted_pairs`` takes the evaluation's ``any_distinct`` rule: a (scenario, root cause) pair
    once per method, placement, group and repeat (its first record); a metric oracle's ``collision``
    is the decision oracle's already. ``recount.md`` counts per repeat what remains once findings
    that rest on a false predicted cut-in are left out, repeats that found nothing as 0."""
    raw = [_rec("rl", 0, "h/a", 0, "collision:x", {"collision": "collision:x", "ttc": "metric:ttc:v"}),
           _rec("rl", 0, "h/a", 1, "collision:x"),  # the same pair again: not counted twice
           _rec("rl", 1, "h/a", 0, "collision:x"),  # another repeat: counted
           _rec("rl", 2, "h/b", 0),  # a repeat that found nothing
           _rec("decictor", 0, "h/b", 0, None, {"comfort": "metric:comfort:jerk"}),
           _rec("decictor", 1, "h/b", 0)]
    rows = [{**r, "placement": "uniform"} for r in raw]
    pairs = recount.counted_pairs(rows, raw)
    assert sorted(pairs) == [("decictor", "uniform", "handwritten", 0, "h/b", "metric:comfort:jerk"),
                             ("rl", "uniform", "handwritten", 0, "h/a", "collision:x"),
                             ("rl", "uniform", "handwritten", 0, "h/a", "metric:ttc:v"),
                             ("rl", "uniform", "handwritten", 1, "h/a", "collision:x")]
    assert pairs[("rl", "uniform", "handwritten", 0, "h/a", "metric:ttc:v")]["_oracle"] == "ttc"
    rests = {("rl", "uniform", "handwritten", 0, "h/a", "collision:x")}
    judged = {k: {"reproduced": True, "false_cut_ins": k in rests, "rests_on_false_cut_in": k in rests}
              for k in pairs}
    text = "\n".join(recount.recount_markdown(Path("x"), rows, judged, {"handwritten": ["h/a", "h/b", "h/c"]}))
    assert "| RL | 1.0 ± 1.0 | 0.7 ± 0.6 | 1 of 3 |" in text  # repeats 2, 1, 0 as counted; 1, 1, 0 remain
    assert "| Decictor-GA | 0.5 ± 0.7 | 0.5 ± 0.7 | 1 of 3 |" in text
    assert "| all methods | | | 2 of 3 |" in text
    assert "| h/a | rl: `collision:x`; rl: `metric:ttc:v` | `collision:x` |" in text


def test_an_evaluations_findings_are_counted_again_and_the_recount_resumes(tmp_path, monkeypatch) -> None:
    """``findings --recount`` simulates every counted distinct finding again and writes one line per
    finding (reproduced, predicted cut-ins) and ``recount.md``; run again, it simulates nothing."""
    from agents.search import search

    recs = list(search("decictor", seed_context("handwritten/parked_street"), 2, seed=0, count=("ttc",)))
    assert any(r["confirmed_by_oracle"].get("ttc") for r in recs)
    lines = [json.dumps({"method": "decictor", "placement": "closest", "scenario": "handwritten/parked_street",
                         "repeat": 0, **r}) for r in recs]
    (tmp_path / "records.jsonl").write_text("\n".join(lines) + "\n")
    assert findings.main([str(tmp_path), "--recount", "--no-progress"]) == 0
    got = [json.loads(x) for x in (tmp_path / "findings" / "recount.jsonl").read_text().splitlines()]
    assert got and all(d["reproduced"] for d in got)
    assert all(d["rests_on_false_cut_in"] == (d["without_intent"] == "gone") for d in got)
    md = (tmp_path / "findings" / "recount.md").read_text()
    assert "## handwritten, closest placement" in md and "| Decictor-GA |" in md

    def no_simulation(*args, **kwargs):
        raise AssertionError("a finding already counted again was simulated again")

    monkeypatch.setattr(recount, "judge_one", no_simulation)
    assert findings.main([str(tmp_path), "--recount", "--no-progress"]) == 0
    assert (tmp_path / "findings" / "recount.md").read_text() == md
