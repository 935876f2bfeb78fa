"""Every published byte of every seed scenario at two fixed jitter seeds, against recorded digests.

A change to the simulation, the modules or the planner that alters what a run publishes fails
here; if the change is meant to alter behaviour, re-record deliberately with
``python -m deft_gym.cli.digest --out tests/support/data/digests-numpy<major>.json`` under each numpy
major version (the export extra's ASAM checker pins numpy 1.26, so `make venv` has numpy 1; numpy 2
rounds perception's and prediction's vector arithmetic differently in a few runs). Slow (16 runs,
~15 s) and tied to this platform's floating point (numpy's SIMD kernels), so it is kept out of the
default run.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy
import pytest

from deft_gym.cli.digest import DEFAULT_SEEDS, compute, differences
from deft_gym.scenarios.scenario import list_scenarios

RECORDED = Path(__file__).resolve().parents[1] / "support" / "data" / f"digests-numpy{numpy.__version__.split('.')[0]}.json"


@pytest.mark.slow
def test_logs_match_the_recorded_digests() -> None:
    recorded = json.loads(RECORDED.read_text())
    now = compute(list_scenarios(), DEFAULT_SEEDS, progress=False)
    assert differences(recorded, now) == []


def test_differences_name_run_and_topic() -> None:
    old = {"a/7": {"/t": "1", "outcome": "completed"}, "b/7": {"/t": "2"}}
    new = {"a/7": {"/t": "9", "outcome": "completed"}, "c/7": {"/t": "2"}}
    assert differences(old, new) == ["a/7: /t differs (1 -> 9)", "b/7: only in the recorded digests",
                                     "c/7: only in the new digests"]
