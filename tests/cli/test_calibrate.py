"""Flaky-share bookkeeping of ``deft_gym.cli.calibrate`` (both definitions, resumable run log)."""

from __future__ import annotations

from pathlib import Path

from deft_gym.cli.calibrate import summarise
from deft_gym.files import read_jsonl


def _runs(name: str, flags: str) -> list[dict]:
    return [{"key": name, "name": name, "seed": 1000 + i, "outcome": "collision" if f == "X" else "completed",
             "collision": f == "X", "sim_time": 1.0, "wall_time": 0.1} for i, f in enumerate(flags)]


def test_paper_and_any_rerun_definitions() -> None:
    results = (_runs("always", "XXXX") + _runs("s0_only", "X...") + _runs("later", "..X.")
               + _runs("never", "....") + _runs("s0_mostly", "XXX."))
    results.reverse()  # the log is in completion order; S0 is the lowest jitter seed
    doc = summarise(results)
    assert doc["paper"] == {"collision_scenarios": 3, "flaky": 2, "share": 2 / 3}
    assert doc["any_rerun"] == {"collision_scenarios": 4, "flaky": 3, "share": 3 / 4}
    assert doc["reproduced_per_rerun"] == [2, 2, 1]
    assert doc["total_scenarios"] == 5 and doc["outcome_flaky_scenarios"] == 3


def test_run_log_skips_a_torn_last_line(tmp_path: Path) -> None:
    log = tmp_path / "runs.jsonl"
    log.write_text('{"name": "a", "seed": 1}\n{"name": "b", "se')
    assert read_jsonl(log) == [{"name": "a", "seed": 1}]
    assert read_jsonl(tmp_path / "missing.jsonl") == []
