"""bench-scale: the calibration gets fixed jitter seeds (identical records across worker counts)
and Amdahl's efficiency from a serial share."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from deft_gym.cli.bench_scale import amdahl, campaign_command, cpu_growth


def test_calibrate_runs_get_the_same_jitter_seeds() -> None:
    a = argparse.Namespace(scenarios=None, reruns=2, jitter_seed=1000, budget=4, repeats=2)
    one, four = (campaign_command("calibrate", Path("out"), w, "local", a) for w in (1, 4))
    for cmd in (one, four):
        assert cmd[cmd.index("--jitter-seed") + 1] == "1000"
    assert [x for x in one if x not in ("1", "4")] == [x for x in four if x not in ("1", "4")]


def test_amdahl() -> None:
    assert amdahl(0.0, 64) == 1.0
    assert amdahl(1.0, 16) == pytest.approx(1 / 16)
    assert amdahl(0.01, 16) == pytest.approx(1 / (0.16 + 0.99))


def test_cpu_growth_is_an_items_cpu_at_the_most_workers_over_the_fewest() -> None:
    # the 16-core machine of issue 36: 768 items, 214.8 CPU s at one worker, 251.0 at 16
    rows = [{"workers": 1, "items": 768, "item_cpu_s": 214.8}, {"workers": 16, "items": 768, "item_cpu_s": 251.0}]
    top, ratio = cpu_growth(rows)
    assert top == 16 and ratio == pytest.approx(251.0 / 214.8)
    assert cpu_growth(rows[:1]) is None
