"""The evaluation's statistics and report (agents/stats.py, agents/eval_report.py) on synthetic
record lists: what counts as a failure, mean/sd over repeats, group totals, Mann-Whitney U and
Vargha-Delaney A12 against hand-computed values, the targets block, distinct failures per
CPU-hour, the written files, and partial data. No simulation."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest

from agents import eval_report, stats
from agents.stats import RecordError

SEEDS = ["s1", "s2"]
HELD = [f"gen:{1_000_000 + i}" for i in range(10)]


def rec(method: str = "rl", scenario: str = "s1", repeat: int = 0, index: int = 0, *, failure: str | None = None,
        confirmed: bool | None = None, valid: bool = True, placement: str = "closest", signature: str = "",
        nods_local: bool = False, task_failure: str | None = None, seconds: float = 2.0,
        cpu_seconds: float | None = 1.0, sims: int = 1, band: str = "far",
        mechanism: str = "blocked") -> dict[str, Any]:
    """One record of the evaluation's schema."""
    r = {"method": method, "placement": placement, "scenario": scenario,
         "scenario_kind": "held_out" if scenario.startswith("gen:") else "seed", "repeat": repeat, "index": index,
         "outcome": "collision" if failure == "collision" else task_failure or "completed", "valid": valid,
         "iou": 0.5 if failure == "nods" else 1.0, "f_p": 0.1, "f_b": 0.1, "off_length": 0.0, "failure": failure,
         "nods_local": nods_local, "task_failure": task_failure, "confirmed": confirmed,
         "signature": signature, "seconds": seconds, "sims": sims, "band": band, "mechanism": mechanism}
    if cpu_seconds is not None:
        r["cpu_seconds"] = cpu_seconds
    return r


def cell(method: str, scenario: str, repeat: int, budget: int, failures: list[tuple[str, str]],
         placement: str = "closest", **kw: Any) -> list[dict[str, Any]]:
    """``budget`` records of one job; the first ones are confirmed valid failures (kind, signature)."""
    out = []
    for i in range(budget):
        if i < len(failures):
            kind, sig = failures[i]
            out.append(rec(method, scenario, repeat, i, failure=kind, confirmed=True, signature=sig,
                           placement=placement, sims=2, **kw))
        else:
            out.append(rec(method, scenario, repeat, i, placement=placement, **kw))
    return out


def full_dataset(ga_nods: int = 1, rd_scenarios: int = 6, rl_on_s2: bool = True) -> list[dict[str, Any]]:
    """5 repeats, 2 seeds + 10 held-out scenarios, budget 4, one placement: RL 3 failures per
    scenario (one more on s1 in odd repeats), Decictor-GA ``ga_nods`` NoDS per scenario,
    Random-delta one NoDS on the first ``rd_scenarios`` scenarios, Random one on each seed."""
    recs = []
    for rep in range(5):
        for k, s in enumerate(SEEDS + HELD):
            rl = [("nods", f"n{s}"), ("collision", f"c{s}"), ("collision", f"c{s}b")]
            if s == "s1" and rep % 2:
                rl.append(("collision", "extra"))
            recs += cell("rl", s, rep, 4, rl if rl_on_s2 or s != "s2" else [])
            recs += cell("decictor", s, rep, 4, [("nods", f"g{j}") for j in range(ga_nods)])
            recs += cell("random_delta", s, rep, 4, [("nods", "d")] if k < rd_scenarios else [])
            recs += cell("random", s, rep, 4, [("nods", "r")] if s in SEEDS else [])
    return recs


def summarize(records: list[dict[str, Any]], **kw: Any) -> dict[str, Any]:
    kw.setdefault("seeds", SEEDS)
    kw.setdefault("held_out", HELD)
    kw.setdefault("placements", ["closest"])
    return stats.summarize(records, **kw)


# -- counting -------------------------------------------------------------------------------------
def test_only_valid_confirmed_failures_count():
    recs = [rec(index=0, failure="nods", confirmed=True, signature="a"),
            rec(index=1, failure="collision", confirmed=True, signature="b"),
            rec(index=2, failure="nods", confirmed=False, signature="c"),  # did not reproduce
            rec(index=3, failure="collision", confirmed=None, signature="d"),  # never re-checked
            rec(index=4, failure="nods", confirmed=True, valid=False, signature="e"),  # invasive mutation
            rec(index=5, nods_local=True),
            rec(index=6, nods_local=True, valid=False),
            rec(index=7, task_failure="timeout", confirmed=True),
            rec(index=8, task_failure="stuck", confirmed=False),
            rec(index=9)]
    assert [stats.counted_failure(r) for r in stats.normalize(recs)[0]] == ["nods", "collision"] + [None] * 8
    c = summarize(recs, held_out=[])["per_scenario"]["rl"]["closest"]["s1"]
    got = {m: c[m]["mean"] for m in ("failures", "nods", "collisions", "unconfirmed", "nods_local", "task_failures",
                                     "validity", "distinct", "simulated")}
    assert got == {"failures": 2, "nods": 1, "collisions": 1, "unconfirmed": 2, "nods_local": 1,
                   "task_failures": 1, "validity": 0.8, "distinct": 2, "simulated": 10}


def test_mean_and_sd_over_repeats():
    recs = [r for rep, n in enumerate((1, 2, 6)) for r in cell("rl", "s1", rep, 6, [("nods", f"x{i}") for i in range(n)])]
    c = summarize(recs)["per_scenario"]["rl"]["closest"]["s1"]
    assert c["repeats"] == [0, 1, 2]
    assert c["failures"]["values"] == [1, 2, 6]
    assert c["failures"]["mean"] == pytest.approx(3.0)
    assert c["failures"]["sd"] == pytest.approx(math.sqrt(7.0))  # ((1-3)^2 + (2-3)^2 + (6-3)^2) / 2
    assert c["seconds_per_scenario"]["mean"] == pytest.approx(2.0)
    assert c["sims"]["values"] == [7, 8, 12]  # a confirmed failure took two simulations


def test_group_totals_sum_scenarios_per_repeat_and_count_distinct_per_scenario():
    g = "gen:1000000"
    recs = (cell("rl", "s1", 0, 4, [("nods", "x")]) + cell("rl", "s2", 0, 4, [("nods", "x"), ("collision", "y")])
            + cell("rl", g, 0, 4, [("nods", "z"), ("nods", "z"), ("collision", "w")])
            + cell("rl", "s1", 1, 4, []) + cell("rl", "s2", 1, 4, [("collision", "y")]) + cell("rl", g, 1, 4, [("nods", "z")]))
    groups = summarize(recs, held_out=[g])["groups"]["rl"]["closest"]
    assert groups["seeds"]["failures"]["values"] == [3, 1]
    assert groups["seeds"]["failures"]["sd"] == pytest.approx(math.sqrt(2.0))
    assert groups["held_out"]["failures"]["values"] == [3, 1]
    assert groups["all"]["failures"]["values"] == [6, 2]
    assert groups["all"]["failures"]["mean"] == pytest.approx(4.0)
    assert groups["all"]["nods"]["values"] == [4, 1] and groups["all"]["collisions"]["values"] == [2, 1]
    # signature x on two scenarios is two distinct failures; z twice on one scenario is one
    assert groups["seeds"]["distinct"]["values"] == [3, 1]
    assert groups["all"]["distinct"]["values"] == [5, 2]
    assert groups["all"]["simulated"]["values"] == [12, 12]
    assert groups["all"]["scenarios"] == ["s1", "s2", g] and groups["all"]["complete"]


def test_distinct_failures_per_cpu_hour():
    recs = cell("rl", "s1", 0, 4, [("nods", "a"), ("nods", "a"), ("collision", "b")], cpu_seconds=450.0)
    c = summarize(recs)["per_scenario"]["rl"]["closest"]["s1"]
    assert c["cpu_seconds"]["mean"] == pytest.approx(1800.0)
    assert c["distinct_per_cpu_hour"]["mean"] == pytest.approx(4.0)  # 2 distinct in half a CPU-hour
    s = summarize(cell("rl", "s1", 0, 4, [("nods", "a")], cpu_seconds=None))
    assert s["per_scenario"]["rl"]["closest"]["s1"]["distinct_per_cpu_hour"]["mean"] is None
    assert s["missing_fields"] == {"cpu_seconds": 4}


# -- statistics -----------------------------------------------------------------------------------
def test_mann_whitney_and_a12_against_hand_computed_values():
    r = stats.mann_whitney([3, 4, 5], [0, 1, 2])
    assert r["u"] == 9 and r["a12"] == 1.0
    assert r["p"] == pytest.approx(2 / 20)  # exact: 2 of the C(6, 3) rank splits are as extreme
    r = stats.mann_whitney([10, 11, 12, 13, 14], [0, 1, 2, 3, 4])
    assert r["a12"] == 1.0 and r["p"] == pytest.approx(2 / 252)
    r = stats.mann_whitney([2, 2, 2], [2, 2, 2])
    assert r["a12"] == 0.5 and r["p"] == pytest.approx(1.0)
    # 1 vs 2,3,4: 0; 2 vs 2: 0.5; 3 vs 2: 1, 3 vs 3: 0.5 -> 2 of 9 pairs
    assert stats.mann_whitney([1, 2, 3], [2, 3, 4])["a12"] == pytest.approx(2 / 9)
    assert stats.mann_whitney([0, 1, 2], [3, 4, 5])["a12"] == 0.0
    assert stats.mann_whitney([5], [1]) == {"u": None, "p": None, "a12": None}


def test_statistics_between_methods_and_ratio_over_zero():
    recs = []
    for rep, (x, y) in enumerate(((3, 0), (4, 1), (5, 2))):
        recs += cell("rl", "s1", rep, 6, [("collision", f"c{i}") for i in range(x)])
        recs += cell("decictor", "s1", rep, 6, [("nods", f"n{i}") for i in range(y)])
        recs += cell("random_delta", "s1", rep, 6, [])
    s = summarize(recs, held_out=[])
    row = stats.find_comparison(s, "rl", "decictor", "closest", "all", "failures")
    assert (row["n_x"], row["n_y"], row["mean_x"], row["mean_y"]) == (3, 3, 4.0, 1.0)
    assert row["ratio"] == 4.0 and row["a12"] == 1.0 and row["p"] == pytest.approx(0.1)
    zero = stats.find_comparison(s, "rl", "random_delta", "closest", "all", "failures")
    assert zero["ratio"] is None and "Random-delta mean is 0" in zero["note"]
    assert "- (denominator 0)" in eval_report.statistics_markdown(s["statistics"]["groups"])
    per = [r for r in s["statistics"]["per_scenario"] if (r["x"], r["y"], r["measure"]) == ("rl", "decictor", "failures")]
    assert len(per) == 1 and per[0]["scenario"] == "s1" and per[0]["a12"] == 1.0
    ordering = stats.find_comparison(s, "decictor", "random_delta", "closest", "all")
    assert ordering["measure"] == "nods" and ordering["mean_x"] == 1.0


# -- targets --------------------------------------------------------------------------------------
def test_targets_met_with_the_numbers():
    t = summarize(full_dataset())["targets"]
    assert t["protocol"] == {"met": True, "repeats_min": 5, "repeats_required": 5, "held_out_scenarios": 10,
                             "held_out_required": 10, "budgets": [4.0], "equal_budget": True}
    steps = t["nods_ordering"]["per_placement"]["closest"]["steps"]
    assert [(s["mean_x"], s["mean_y"], s["a12"], s["met"]) for s in steps] == [(12.0, 6.0, 1.0, True),
                                                                              (6.0, 2.0, 1.0, True)]
    rg = t["rl_vs_ga"]["per_placement"]["closest"]
    assert rg["mean_rl"] == pytest.approx(36.4) and rg["mean_ga"] == 12.0  # 36, 37, 36, 37, 36
    assert rg["ratio"] == pytest.approx(36.4 / 12, abs=1e-4) and rg["p"] < 0.05 and rg["met"]
    assert t["validity"]["met"] and t["validity"]["methods"]["rl"]["closest"] == 1.0
    assert t["validity"]["not_required"] == ["random"]
    assert t["failure_on_every_seed"]["per_seed"]["s2"] == {"any": 30, "rl": 15}  # (3 + 1 + 1 + 1) x 5
    assert t["met_17"] is True
    # issue 31's: every failure here has one mechanism, and random actions never ran
    assert t["mechanisms"] == {"met": False, "required": 5, "found": {"blocked": 282}}
    assert t["dominance"]["per_method"]["rl"]["closest"] == {"mechanism": "blocked", "share": 1.0, "failures": 182,
                                                             "dominates": True}
    assert not t["rl_root_causes"]["met"] and t["met"] is False


def test_root_causes_are_the_headline_and_in_lane_ones_a_column_of_their_own():
    """Distinct root causes per repeat over all scenarios: one designed-in threshold found on every
    scenario is one root cause; a trigger inside the ego's lane counts only in the in-lane column;
    identical scenarios found by several methods count once in the 'all methods' union."""
    mechs = ["tight", "parallel", "intent", "gap:rear", "predicted_static"]
    recs = []
    for rep in range(5):
        for k, s in enumerate(SEEDS + HELD):
            rl = [rec("rl", s, rep, 0, failure="nods", confirmed=True, signature="nods:parked:in_lane:blocked",
                      band="in_lane", mechanism="blocked")]
            rl += [rec("rl", s, rep, 1 + j, failure="nods", confirmed=True, signature=f"nods:cone:far:{m}",
                       mechanism=m) for j, m in enumerate(mechs[: 2 + rep % 2])]
            recs += rl + cell("rl", s, rep, 4, [])[len(rl):]
            ga = [rec("decictor", s, rep, 0, failure="nods", confirmed=True, signature="nods:cone:far:blocked")] \
                if k == 0 else []
            recs += ga + cell("decictor", s, rep, 4, [])[len(ga):]
            recs += cell("random_online", s, rep, 4, [])
    s = summarize(recs)
    g = s["groups"]["rl"]["closest"]["all"]
    assert g["failures"]["values"] == [36.0, 48.0] * 2 + [36.0]  # 3 or 4 per scenario
    assert g["root_causes"]["values"] == [2.0, 3.0, 2.0, 3.0, 2.0]  # tight + parallel (+ intent)
    assert g["root_causes_in_lane"]["values"] == [3.0, 4.0, 3.0, 4.0, 3.0]
    cause = s["findings"]["root_causes"]["rl"]["closest"]["nods:parked:in_lane:blocked"]
    assert (cause["failures"], cause["repeats"], len(cause["scenarios"]), cause["band"]) == (60, 5, 12, "in_lane")
    t = s["targets"]
    rc = t["rl_root_causes"]["per_placement"]["closest"]
    assert rc["decictor"]["mean_other"] == 1.0 and rc["decictor"]["met"]  # 2.4 vs 1, p = 0.008
    # random actions found none: the ratio is undefined, and RL's lead is significant
    assert rc["random_online"]["ratio"] is None and rc["random_online"]["met"] and t["rl_root_causes"]["met"]
    assert t["mechanisms"]["found"] == {"blocked": 65, "tight": 60, "parallel": 60, "intent": 24}
    assert not t["mechanisms"]["met"]
    dom = t["dominance"]["per_method"]
    assert dom["rl"]["closest"]["share"] == pytest.approx(60 / 204, abs=1e-4) and not dom["rl"]["closest"]["dominates"]
    assert dom["decictor"]["closest"]["dominates"]  # all of its five failures are one mechanism


def test_targets_not_met_say_where():
    t = summarize(full_dataset(rd_scenarios=12, rl_on_s2=False))["targets"]
    step1 = t["nods_ordering"]["per_placement"]["closest"]["steps"][0]
    assert (step1["mean_x"], step1["mean_y"], step1["a12"], step1["met"]) == (12.0, 12.0, 0.5, False)
    assert not t["nods_ordering"]["met"]
    assert t["failure_on_every_seed"]["any_method"] == {"met": True, "without": []}
    assert t["failure_on_every_seed"]["rl"] == {"met": False, "without": ["s2"]}
    assert t["met"] is False
    t = summarize(full_dataset(ga_nods=0))["targets"]
    rg = t["rl_vs_ga"]["per_placement"]["closest"]
    assert rg["ratio"] is None and "mean is 0" in rg["note"]
    assert not t["nods_ordering"]["met"]  # GA found no NoDS: the ordering fails
    few = [r for r in full_dataset() if r["repeat"] < 2 and r["scenario"] in SEEDS + HELD[:3]]
    pr = summarize(few, held_out=HELD[:3])["targets"]["protocol"]
    assert (pr["met"], pr["repeats_min"], pr["held_out_scenarios"]) == (False, 2, 3)


# -- partial data, files --------------------------------------------------------------------------
def test_missing_methods_placements_and_one_repeat_give_dashes():
    recs = cell("rl", "s1", 0, 3, [("nods", "a")]) + cell("decictor", "s1", 0, 3, [])
    s = summarize(recs, methods=["rl", "decictor", "random"], placements=["closest", "uniform"], held_out=[])
    c = s["groups"]["rl"]["closest"]["all"]
    assert c["failures"]["mean"] == 1.0 and c["failures"]["sd"] is None
    assert c["missing_scenarios"] == ["s2"] and not c["complete"]
    row = stats.find_comparison(s, "rl", "decictor", "closest", "all")
    assert (row["p"], row["a12"], row["u"]) == (None, None, None) and "fewer than 2 repeats" in row["note"]
    assert "no data for random" in stats.find_comparison(s, "rl", "random", "closest", "all")["note"]
    assert s["targets"]["met"] is False
    head = eval_report.headline_markdown(s).splitlines()
    assert head[0].startswith("Mean ± sd over 1 repeat(s)")
    assert len(head) == 4 + 3 * 2  # caption, blank, header, rule, one row per method x placement
    rl_closest = next(line for line in head if line.startswith("| RL | closest"))
    assert "1.0 ± -*" in rl_closest
    assert next(line for line in head if line.startswith("| Random | uniform")).count("| - ") >= 10
    text = eval_report.table_markdown(s)
    assert "## Held-out scenarios" in text and "- | - |" in text


def test_report_files_are_written(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recs = full_dataset() + [r | {"placement": "uniform"} for r in full_dataset(ga_nods=2)]
    summary = eval_report.build_summary(recs, {"methods": ["rl", "decictor", "random_delta", "random"],
                                               "placements": ["closest", "uniform"], "budget": 4, "repeats": 5},
                                        SEEDS, HELD)
    table = eval_report.write_report(recs, summary, tmp_path)
    assert (tmp_path / "table.md").read_text() == table
    for part in ("## Headline", "## Seed scenarios", "## All scenarios", "## Failures per scenario",
                 "## Statistics", "## Targets", "| RL | uniform | 4 |"):
        assert part in table
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["targets"]["met_17"] is True and saved["groups"]["rl"]["uniform"]["all"]["failures"]["mean"] == 36.4
    for name in ("cumulative_failures.png", "per_scenario.png"):
        img = plt.imread(tmp_path / name)
        assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 400
        assert img[..., :3].std() > 0.05  # not a blank canvas


def test_cumulative_curves_mean_and_band():
    from scipy.stats import t as student

    recs = (cell("rl", "s1", 0, 4, []) + cell("rl", "s1", 1, 4, []))
    for r in recs:  # repeat 0 fails at 0 and 2, repeat 1 at 1
        if (r["repeat"], r["index"]) in ((0, 0), (0, 2), (1, 1)):
            r.update(failure="nods", confirmed=True, signature=f"s{r['index']}")
    s = summarize(recs, held_out=[])
    c = stats.cumulative_curves(recs, s)["closest"]["seeds"]["rl"]
    assert c["x"] == [1, 2, 3, 4] and c["n"] == 2
    assert c["mean"] == pytest.approx([0.5, 1.0, 1.5, 1.5])
    half = student.ppf(0.975, 1) * math.sqrt(0.5) / math.sqrt(2)  # sd of (1, 0) over sqrt(2)
    assert c["hi"][0] == pytest.approx(0.5 + half) and c["lo"][0] == 0.0  # clipped at 0
    assert c["lo"][1] == pytest.approx(1.0) and c["hi"][1] == pytest.approx(1.0)  # both repeats at 1
    one = stats.cumulative_curves(recs[:4], summarize(recs[:4], held_out=[]))["closest"]["seeds"]["rl"]
    assert one["lo"] is None and one["mean"] == [1.0, 1.0, 2.0, 2.0]


def test_rl_training_episodes_as_second_budget(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.json").write_text(json.dumps({"episodes": 1234, "train_seconds": 60.0}))
    recs = cell("rl", "s1", 0, 2, []) + cell("decictor", "s1", 0, 2, [])
    s = eval_report.build_summary(recs, {"methods": ["rl", "decictor"], "placements": ["closest"],
                                         "model": str(run / "model.zip")}, SEEDS, [])
    assert s["training"]["rl"]["episodes"] == 1234 and s["training"]["decictor"] is None
    head = eval_report.headline_markdown(s)
    assert "| RL | closest | 2 | 1,234 |" in head and "| Decictor-GA | closest | 2 | 0 |" in head
    (run / "summary.json").write_text(json.dumps({"timesteps": 5}))
    with pytest.raises(RecordError, match=r"summary\.json: field 'episodes'"):
        eval_report.rl_training(str(run / "model.zip"))
    assert eval_report.rl_training(str(tmp_path / "elsewhere" / "model.zip")) is None


def test_rl_training_adds_the_runs_a_model_was_fine_tuned_from(tmp_path):
    first, second = tmp_path / "first", tmp_path / "second"
    for run, episodes, cpu, init in ((first, 1000, 100.0, None), (second, 200, 50.0, first / "model.zip")):
        run.mkdir()
        (run / "summary.json").write_text(json.dumps({"episodes": episodes, "train_seconds": cpu / 2,
                                                      "cpu_seconds": cpu}))
        (run / "config.yaml").write_text(f"init_model: {init}\n" if init else "timesteps: 5\n")
    t = eval_report.rl_training(str(second / "model.zip"))
    assert (t["episodes"], t["cpu_seconds"], t["train_seconds"]) == (1200, 150.0, 75.0)
    assert [leg["episodes"] for leg in t["legs"]] == [200, 1000] and t["summary"] == str(second / "summary.json")
    (first / "summary.json").write_text(json.dumps({"episodes": 1000}))  # a run without its CPU: no sum
    t = eval_report.rl_training(str(second / "model.zip"))
    assert t["episodes"] == 1200 and t["cpu_seconds"] is None
    (first / "config.yaml").write_text(f"init_model: {second / 'model.zip'}\n")  # a loop ends at a run seen
    assert eval_report.rl_training(str(second / "model.zip"))["episodes"] == 1200
    (second / "config.yaml").write_text("init_model: [1, 2]\n")
    with pytest.raises(RecordError, match=r"config\.yaml: field 'init_model': expected a model path"):
        eval_report.rl_training(str(second / "model.zip"))
    (second / "config.yaml").write_text("init_model: [1, 2\n")
    with pytest.raises(RecordError, match=r"config\.yaml: invalid YAML"):
        eval_report.rl_training(str(second / "model.zip"))


def test_bad_records_name_the_record_and_field():
    good = rec()
    for bad, pattern in (({"valid": None}, r"record 2: field 'valid': expected bool"),
                         ({"failure": "crash"}, r"record 2: field 'failure': expected one of"),
                         ({"repeat": "1"}, r"record 2: field 'repeat': expected int"),
                         ({"seconds": -1.0}, r"record 2: field 'seconds': expected a finite number"),
                         ({"scenario_kind": "train"}, r"record 2: field 'scenario_kind'")):
        with pytest.raises(RecordError, match=pattern):
            stats.normalize([good, good | bad], "out/records.jsonl")
    with pytest.raises(RecordError, match=r"record 2: field 'index' is missing"):
        stats.normalize([good, {k: v for k, v in good.items() if k != "index"}])
    with pytest.raises(RecordError, match=r"scenario 's1': field 'scenario_kind'"):
        stats.summarize([good, good | {"scenario_kind": "held_out"}])


def test_old_records_default_placement_and_kind():
    old = [{k: v for k, v in rec(scenario=s).items() if k not in ("placement", "scenario_kind")}
           for s in ("s1", "left_turn~v1000001", "gen:1000005")]
    rows, missing = stats.normalize(old)
    assert [r["placement"] for r in rows] == ["closest"] * 3
    assert [r["scenario_kind"] for r in rows] == ["seed", "held_out", "held_out"]
    assert missing == {"placement": 3, "scenario_kind": 3}


def test_report_cli_rerenders_and_refuses_bad_records(tmp_path, capsys):
    recs = cell("rl", "s1", 0, 3, [("nods", "a")]) + cell("rl", "s1", 1, 3, [])
    (tmp_path / "records.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    (tmp_path / "eval_config.json").write_text(json.dumps({"methods": ["rl"], "placements": ["closest"],
                                                           "scenarios": ["s1"], "held_out": [], "budget": 3}))
    assert eval_report.main([str(tmp_path)]) == 0
    assert "| RL | closest | 3 | - | 0.5 ± 0.7 |" in capsys.readouterr().out
    assert all((tmp_path / n).stat().st_size > 0 for n in ("summary.json", "table.md", "cumulative_failures.png",
                                                            "per_scenario.png"))
    with (tmp_path / "records.jsonl").open("a") as f:
        f.write(json.dumps(recs[0] | {"valid": "yes"}) + "\n")
    assert eval_report.main([str(tmp_path)]) == 2
    assert "records.jsonl: record 7: field 'valid'" in capsys.readouterr().err


def test_evaluation_config_placements(tmp_path):
    from agents.evaluate import load_eval_config, parse_args
    from deft_gym.config import ConfigError

    base = ["--methods", "random", "--out", str(tmp_path)]
    assert load_eval_config(parse_args(base)).placements == ["closest", "uniform"]
    assert load_eval_config(parse_args([*base, "--placements", "uniform"])).placements == ["uniform"]
    with pytest.raises(ConfigError, match="placements"):
        load_eval_config(parse_args([*base, "--placements", "sideways"]))
    assert load_eval_config(parse_args(base)).temperature == 1.0
    assert load_eval_config(parse_args([*base, "--temperature", "4"])).temperature == 4.0
    for bad in ("0", "-1", "nan", "1e9"):
        with pytest.raises(ConfigError, match="--temperature"):
            load_eval_config(parse_args([*base, "--temperature", bad]))


def test_handwritten_scenarios_form_a_third_group(tmp_path):
    """``handwritten/<name>`` scenarios given with the seeds get a group of their own (totals,
    a table section, a headline column, their kind per scenario) and count in ``all``; a report
    without them shows the three groups as before."""
    hand = ["handwritten/a", "handwritten/b"]
    recs = (cell("rl", "s1", 0, 4, [("nods", "x")]) + cell("rl", "handwritten/a", 0, 4, [("nods", "y")])
            + cell("rl", "handwritten/b", 0, 4, [("collision", "z"), ("nods", "w")]))
    for r in recs:
        if r["scenario"].startswith("handwritten/"):
            r["scenario_kind"] = "handwritten"
    summary = eval_report.build_summary(recs, {"methods": ["rl"], "placements": ["closest"], "budget": 4,
                                               "repeats": 1}, ["s1", *hand], [])
    assert summary["seeds"] == ["s1"] and summary["handwritten"] == hand
    assert {s: summary["scenario_kinds"][s] for s in hand} == {s: "handwritten" for s in hand}
    g = summary["groups"]["rl"]["closest"]
    assert g["seeds"]["failures"]["values"] == [1] and g["handwritten"]["failures"]["values"] == [3]
    assert g["all"]["failures"]["values"] == [4] and g["all"]["scenarios"] == ["s1", *hand]
    table = eval_report.write_report(recs, summary, tmp_path)
    assert "## Hand-written scenarios" in table and "failures hand-written" in table
    assert "| handwritten/b | hand-written |" in table and "1 seed, 0 held-out and 2 hand-written scenario(s)" in table
    assert stats.kind_of_name("handwritten/a") == "handwritten" and stats.kind_of_name("handwritten/a~v3") == "held_out"
    plain = eval_report.build_summary(recs[:4], {"methods": ["rl"], "placements": ["closest"]}, ["s1"], [])
    assert plain["handwritten"] == [] and set(plain["groups"]["rl"]["closest"]) == {"seeds", "all"}
    assert "hand-written" not in eval_report.table_markdown(plain)


def test_one_evaluation_per_planner_gives_a_table_per_planner_and_group(tmp_path):
    """``deft-gym evaluate --ads-config A.yaml B.yaml`` writes OUT/A and OUT/B; planners.md shows
    each planner's groups and the hand-written targets: RL's coverage of the group and RL vs
    Decictor-GA in distinct failures (Mann-Whitney over repeats)."""
    hand = [f"handwritten/h{i}" for i in range(4)]
    for label, rl_hits in (("lane_keeper", 4), ("other", 2)):
        recs = []
        for rep in range(5):
            for k, s in enumerate(["s1", *hand]):
                rl = [("nods", f"r{s}{j}") for j in range(2)] if k < rl_hits + 1 else []
                recs += cell("rl", s, rep, 4, rl) + cell("decictor", s, rep, 4, [("nods", "g")] if k == 1 else [])
        for r in recs:
            if r["scenario"].startswith("handwritten/"):
                r["scenario_kind"] = "handwritten"
        cfg = {"methods": ["rl", "decictor"], "placements": ["closest"], "budget": 4, "repeats": 5,
               "ads": f"configs/ads/{label}.yaml"}
        summary = eval_report.build_summary(recs, cfg, ["s1", *hand], [])
        (tmp_path / label).mkdir()
        eval_report.write_report(recs, summary, tmp_path / label)
    assert eval_report.main([str(tmp_path)]) == 0
    text = (tmp_path / "planners.md").read_text()
    assert "## lane_keeper" in text and "## other" in text and "configs/ads/other.yaml" in text
    assert "| hand-written | 4 | RL | closest | 8.0 ± 0.0 | 8.0 ± 0.0 |" in text
    assert "RL found a confirmed failure on 4 of 4 hand-written scenarios (target >= 75%): **met**" in text
    assert "RL found a confirmed failure on 2 of 4 hand-written scenarios (target >= 75%): **not met**" in text
    targets = json.loads((tmp_path / "planners.json").read_text())
    assert targets["lane_keeper"]["targets"]["closest"]["ratio"] == 8.0
    assert targets["lane_keeper"]["targets"]["closest"]["met"] is True


def test_several_ads_configs_must_have_distinct_names(tmp_path):
    from agents.evaluate import main

    a = tmp_path / "x" / "same.yaml"
    b = tmp_path / "y" / "same.yaml"
    code = main(["--methods", "random", "--ads-config", str(a), str(b), "--out", str(tmp_path / "o"), "--quiet"])
    assert code == 2


def test_a_scenario_the_planner_does_not_complete_is_left_out_by_name(tmp_path, monkeypatch):
    """A scenario whose reference run does not complete on the planner under test is no seed for
    it: the evaluation leaves it out, says why, and evaluates the others (it used to stop)."""
    from agents import evaluate

    def problem(item):
        if item["scenario"] == "left_turn":
            return "scenario 'left_turn': the reference run ended 'timeout' at 45.0 s"
        return None

    monkeypatch.setattr(evaluate, "seed_problem", problem)
    out = tmp_path / "ev"
    code = evaluate.main(["--methods", "random", "--budget", "1", "--scenarios", "lane_follow_static", "left_turn",
                          "--held-out", "0", "--placements", "closest", "--workers", "1", "--render", "none",
                          "--out", str(out), "--quiet"])
    assert code == 0
    cfg = json.loads((out / "eval_config.json").read_text())
    assert list(cfg["unfit"]) == ["left_turn"]
    from deft_gym.files import read_jsonl

    assert {r["scenario"] for r in read_jsonl(out / "records.jsonl")} == {"lane_follow_static"}
    assert "Left out, not seeds for the planner under test" in (out / "table.md").read_text()
    assert eval_report.main([str(out)]) == 0  # re-rendered the same way
    assert "`left_turn`" in (out / "table.md").read_text()


def test_the_validity_rule_is_the_evaluations_and_recorded(tmp_path):
    """``--validity paper`` runs every method under Decictor's rule for static objects (0.5 m, no
    lane test) and eval_config.json records it, for ``deft-gym findings`` to re-simulate under;
    without the flag the rule is the default one (out of the ego's lane)."""
    from agents import evaluate, findings
    from deft_gym.search.feasible import PAPER, FeasibleConfig

    for flag, rule in ((["--validity", "paper"], PAPER), ([], FeasibleConfig())):
        out = tmp_path / (flag[-1] if flag else "default")
        code = evaluate.main(["--methods", "random", "--budget", "1", "--scenarios", "lane_follow_static",
                              "--held-out", "0", "--placements", "closest", "--workers", "1", *flag,
                              "--out", str(out), "--quiet"])
        assert code == 0
        assert findings.eval_feasible(out) == rule


def test_counted_oracles_per_oracle_any_oracle_and_coverage(tmp_path):
    """``count_oracles``: a confirmed finding of a counted metric oracle on a valid mutation counts
    per oracle, distinct by (scenario, signature); ``any_distinct`` adds them to the decision
    oracle's distinct failures (a metric collision once: it is the decision oracle's at-fault
    collision) and the hand-written coverage counts a scenario found by any oracle."""
    hand = ["handwritten/a", "handwritten/b", "handwritten/c"]
    recs = []
    for rep in range(2):
        recs += cell("rl", hand[0], rep, 3, [("collision", "c")])
        recs += cell("rl", hand[1], rep, 3, [])
        recs += cell("rl", hand[2], rep, 3, [])
        recs += cell("decictor", hand[0], rep, 3, [])
        recs += cell("decictor", hand[1], rep, 3, [])
        recs += cell("decictor", hand[2], rep, 3, [])
    for r in recs:
        r["scenario_kind"] = "handwritten"
        r["found_by_oracle"], r["confirmed_by_oracle"] = {}, {}
    first = {(r["method"], r["scenario"], r["repeat"], r["index"]): r for r in recs}
    # a: RL's collision, also the metric collision's finding (counted once in any_distinct)
    first[("rl", hand[0], 0, 0)].update(found_by_oracle={"collision": "metric:collision:rear_end"},
                                        confirmed_by_oracle={"collision": True})
    # b: TTC to a cone twice in repeat 0 (one distinct pair), once to a parked car in repeat 1
    for i in (1, 2):
        first[("rl", hand[1], 0, i)].update(found_by_oracle={"ttc": "metric:ttc:cone"},
                                            confirmed_by_oracle={"ttc": True})
    first[("rl", hand[1], 1, 0)].update(found_by_oracle={"ttc": "metric:ttc:parked", "standstill": "metric:standstill:standstill"},
                                        confirmed_by_oracle={"ttc": True, "standstill": True})
    # c: not reproduced, or an invalid mutation: nothing counts
    first[("rl", hand[2], 0, 0)].update(found_by_oracle={"comfort": "metric:comfort:jerk"},
                                        confirmed_by_oracle={"comfort": False})
    first[("rl", hand[2], 1, 0)].update(valid=False, found_by_oracle={"ttc": "metric:ttc:cone"},
                                        confirmed_by_oracle={"ttc": True})
    # what the seed's unmutated runs do too: kept in the record, counted nowhere, named in the table
    first[("decictor", hand[2], 0, 1)].update(unmutated_by_oracle={"comfort": "metric:comfort:lon_accel"})
    cfg = {"methods": ["rl", "decictor"], "placements": ["closest"], "budget": 3, "repeats": 2,
           "count_oracles": ["collision", "ttc", "comfort", "standstill"]}
    summary = eval_report.build_summary(recs, cfg, hand, [])
    g = summary["groups"]["rl"]["closest"]["handwritten"]
    assert g["distinct"]["values"] == [1, 1]
    assert g["found_ttc"]["values"] == [1, 1] and g["found_standstill"]["values"] == [0, 1]
    assert g["found_collision"]["values"] == [1, 0] and g["found_comfort"]["values"] == [0, 0]
    assert g["any_distinct"]["values"] == [2, 3]
    assert g["safety_distinct"]["values"] == [2, 2]  # the decision oracle's and TTC's; no standstill
    assert eval_report.coverage(summary, "rl") == (1, 3)
    assert eval_report.coverage(summary, "rl", measure="any_distinct") == (2, 3)
    t = eval_report.planner_targets(summary)
    assert t["coverage_any"] == {"found": 2, "scenarios": 3, "share": 2 / 3, "met": False}
    table = eval_report.write_report(recs, summary, tmp_path)
    assert "## Findings per oracle" in table
    assert summary["unmutated"] == {"comfort": 1} and "`comfort` in 1 record(s)" in table
    assert "| RL | closest | 1.0 ± 0.0 | 0.5 ± 0.7 | 1.0 ± 0.0 | 0.0 ± 0.0 | 0.5 ± 0.7 | 2.5 ± 0.7 | 2.0 ± 0.0 | 2 of 3 |" in table
    # per scenario: RL found something on a and b, the GA nowhere; c is where no method found anything
    assert "| handwritten/a | hand-written | 1.0 ± 0.0 | 0.0 ± 0.0 | yes |" in table
    assert "| handwritten/b | hand-written | 1.5 ± 0.7 | 0.0 ± 0.0 | yes |" in table
    assert "| handwritten/c | hand-written | 0.0 ± 0.0 | 0.0 ± 0.0 | **none** |" in table
    assert "No method found anything on 1 of 3 scenarios: `handwritten/c`." in table
    # without counted oracles the sections are absent and the coverage by any oracle is not claimed
    plain = eval_report.build_summary(recs, {**cfg, "count_oracles": []}, hand, [])
    assert "Findings per oracle" not in eval_report.table_markdown(plain)
    assert "any oracle" not in eval_report.table_markdown(plain).split("## Failures per scenario")[1]
    assert "coverage_any" not in eval_report.planner_targets(plain)


def test_count_oracles_config(tmp_path):
    from agents.evaluate import load_eval_config, parse_args
    from deft_gym.config import ConfigError
    from deft_gym.metrics.oracle import COUNTED_ORACLES

    base = ["--methods", "random", "--out", str(tmp_path)]
    assert load_eval_config(parse_args(base)).count_oracles == []
    assert load_eval_config(parse_args([*base, "--count-oracles", "all"])).count_oracles == list(COUNTED_ORACLES)
    assert load_eval_config(parse_args([*base, "--count-oracles", "ttc", "ttc", "comfort"])).count_oracles == \
        ["ttc", "comfort"]
    assert stats.FOUND_ORACLES == COUNTED_ORACLES  # the stats' copy of the list (no import of the metrics)
    # and of every metric an episode can violate (EpisodeMetrics.violations, each forced over its bound)
    from deft_gym.metrics.episode import EpisodeMetrics

    worst = EpisodeMetrics(at_fault_collision=True, ttc_below_s=1.0, off_road_max=9.0, wrong_way_max_1s=9.0,
                           red_lights=[{"light": "l"}], uncomfortable=["lon_accel"], max_overspeed=9.0,
                           standstill_max_s=999.0, headway_below_max_s=999.0)
    assert tuple(worst.violations()) == stats.METRIC_VIOLATIONS
    with pytest.raises(ConfigError, match="--count-oracles: unknown \\['default'\\]"):
        load_eval_config(parse_args([*base, "--count-oracles", "default"]))


def test_rl_records_keep_their_temperature_and_another_is_simulated_again(tmp_path):
    """``--temperature``: RL's records carry it, table.md names it, and resuming the folder at
    another temperature simulates RL's scenarios again (random actions' records are kept)."""
    from agents import evaluate
    from deft_gym.files import read_jsonl

    out = tmp_path / "ev"
    args = ["--methods", "rl", "random_online", "--model", "default", "--budget", "1", "--scenarios",
            "lane_follow_static", "--held-out", "0", "--placements", "closest", "--workers", "1", "--render", "none",
            "--out", str(out), "--quiet"]
    assert evaluate.main(args) == 0
    first = {r["method"]: r for r in read_jsonl(out / "records.jsonl")}
    assert first["rl"]["temperature"] == 1.0 and "temperature" not in first["random_online"]
    assert evaluate.main([*args, "--temperature", "4"]) == 0
    recs = read_jsonl(out / "records.jsonl")
    rl = [r for r in recs if r["method"] == "rl"]
    assert [r["temperature"] for r in rl] == [4.0]  # simulated again, the old record replaced
    assert [r for r in recs if r["method"] == "random_online"] == [first["random_online"]]  # kept
    assert "temperature 4 (logits / 4)" in (out / "table.md").read_text()
