"""The planner-edit experiment (deft_gym.experiments.planner_edits) on one short episode: an edit that changes
the output is caught by the generated tests, one that changes nothing is not flagged."""

from __future__ import annotations

import json

import pytest

from deft_gym.experiments.planner_edits import EDITS, _apply, main


def test_every_edit_applies_to_the_reference_planner() -> None:
    import importlib.util
    from pathlib import Path

    src = Path(importlib.util.find_spec("deft_gym.planner.lattice").origin).read_text()
    assert len(EDITS) >= 20 and len({e.name for e in EDITS}) == len(EDITS)
    assert [e.name for e in EDITS if _apply(src, e) is None] == []
    assert sum(e.kind == "neutral" for e in EDITS) >= 5


@pytest.mark.slow
def test_a_behavioural_edit_is_caught_and_a_neutral_one_is_not(tmp_path) -> None:
    assert main(["--out", str(tmp_path), "--scenarios", "lane_follow_static", "--duration", "6",
                 "--edits", "w_jerk", "comment"]) == 0
    rows = {r["edit"]: r for r in json.loads((tmp_path / "edits.json").read_text())["rows"]}
    assert rows["w_jerk"]["changes_output"] and rows["w_jerk"]["caught"] and rows["w_jerk"]["tests_failed"] == 1
    assert not rows["comment"]["changes_output"] and not rows["comment"]["caught"]
