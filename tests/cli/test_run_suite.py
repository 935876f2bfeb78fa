"""`deft-gym run` with several scenarios: a suite - each scenario into its own folder, one row per
scenario (outcomes, the metrics every rerun violated), ``suite.json``, and a resumed suite that
runs nothing twice. Real simulations of the default planner."""

from __future__ import annotations

import json
from pathlib import Path

from deft_gym.cli.run import main, suite_row


def test_a_suite_runs_each_scenario_once_and_tabulates_them(tmp_path: Path, capsys) -> None:
    out = tmp_path / "suite"
    argv = ["lane_follow_static", "gen:1000001", "--reruns", "1", "--jitter-seed", "3", "--render", "none",
            "--out", str(out), "--no-progress"]
    assert main(argv) == 0
    doc = json.loads((out / "suite.json").read_text())
    assert [r["scenario"] for r in doc["scenarios"]] == ["lane_follow_static", "gen-1000001"]  # gen: specs resolve
    for row in doc["scenarios"]:
        summary = json.loads((Path(row["folder"]) / "summary.json").read_text())
        assert row["outcomes"] == [r["outcome"] for r in summary["reruns"]] == ["completed"]
        assert summary["reruns"][0]["jitter_seed"] == 3
    printed = capsys.readouterr().out
    assert "violated in every rerun" in printed and "gen-1000001" in printed
    from deft_gym.cli.report import write_report

    html = write_report(out, draw=False).read_text()  # the suite's table first, then each scenario's reruns
    assert html.index("Suite: 2 scenarios") < html.index("System-level reruns: lane_follow_static")
    assert "failed in every rerun" in html and "gen-1000001" in html
    stamp = (out / "lane_follow_static" / "summary.json").stat().st_mtime_ns
    assert main(argv) == 0  # the same reruns, jitter seeds, config and code: kept, not run again
    assert "same code and config: kept" in capsys.readouterr().out
    assert (out / "lane_follow_static" / "summary.json").stat().st_mtime_ns == stamp
    key = json.loads((out / "lane_follow_static" / "summary.json").read_text())["run_key"]
    assert main([*argv, "--headers"]) == 0  # another ADS config (the planner's inputs): run again
    assert "kept" not in capsys.readouterr().out
    assert json.loads((out / "lane_follow_static" / "summary.json").read_text())["run_key"] != key


def test_a_failing_scenario_of_a_suite_is_drawn(tmp_path: Path) -> None:
    """A scenario that fails in every rerun (lane_follow_static cut to 3 s: it times out) gets the
    plot of its first rerun in its row; a passing one none."""
    import yaml

    from deft_gym.scenarios.scenario import load_scenario, scenario_to_dict

    data = scenario_to_dict(load_scenario("lane_follow_static"))
    data.update(duration=3.0, name="too_short")
    path = tmp_path / "too_short.yaml"
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "suite"
    assert main([str(path), "lane_follow_static", "--reruns", "1", "--jitter-seed", "5", "--render", "failures",
                 "--out", str(out), "--no-progress"]) == 0
    rows = {r["scenario"]: r for r in json.loads((out / "suite.json").read_text())["scenarios"]}
    assert rows["too_short"]["outcomes"] == ["timeout"] and rows["too_short"]["failed_every_rerun"]
    assert Path(rows["too_short"]["plot"]).is_file() and "plot" not in rows["lane_follow_static"]


def test_a_row_confirms_only_what_every_rerun_violated(tmp_path: Path) -> None:
    summary = {"scenario": "x", "metrics": {"mean_score": 0.4}, "reruns": [
        {"outcome": "stuck", "metrics": {"violations": ["standstill", "comfort", "ttc"]}},
        {"outcome": "stuck", "metrics": {"violations": ["standstill", "comfort"]}}]}
    row = suite_row(summary, tmp_path)
    assert row["confirmed"] == ["standstill"] and row["some_reruns"] == ["ttc"]
    assert row["comfort_every_rerun"] and row["failed_every_rerun"] and row["mean_score"] == 0.4
    summary["reruns"][1]["outcome"] = "completed"
    assert not suite_row(summary, tmp_path)["failed_every_rerun"]


def test_a_suite_gives_the_same_results_on_any_number_of_workers(tmp_path: Path) -> None:
    """``--workers 2`` runs the scenarios in two processes; every row and every rerun's summary
    (outcome, metrics, divergence, jitter seed) is what one process gives, timings aside."""
    from deft_gym.execution import without_timings

    def run(workers: int) -> tuple[list[dict], list[dict]]:
        out = tmp_path / f"w{workers}"
        assert main(["lane_follow_static", "gen:1000001", "--reruns", "2", "--jitter-seed", "3", "--render", "none",
                     "--workers", str(workers), "--out", str(out), "--no-progress"]) == 0
        rows = json.loads((out / "suite.json").read_text())["scenarios"]
        summaries = [json.loads((Path(r["folder"]) / "summary.json").read_text()) for r in rows]
        drop = {"folder", "created", "sim_speed", "log", "truth"}

        def clean(doc: dict) -> dict:
            return {k: [{f: x for f, x in r.items() if f not in drop} for r in v] if k == "reruns" else v
                    for k, v in without_timings(doc).items() if k not in drop}
        return [clean(r) for r in rows], [clean(s) for s in summaries]

    one, two = run(1), run(2)
    assert [r["scenario"] for r in one[0]] == ["lane_follow_static", "gen-1000001"]
    assert one == two
