"""The execution layer on local processes (no Ray needed): ordered results, the same records
for one and two workers, resume from the record, progress, bad input."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from deft_gym.execution import (
    Backend,
    BackendError,
    Executor,
    Record,
    backend_from_args,
    importable,
    without_timings,
)

ROOT = Path(__file__).resolve().parent.parent


def _runs(items: list[tuple], workers: int) -> list[dict]:
    from deft_gym.cli.calibrate import _job

    ticks: list[int] = []
    with Executor(Backend("local", workers)) as ex:
        out = list(ex.map(_job, items, progress=ticks.append))
    assert sum(ticks) == len(items)
    return out


def test_local_results_in_item_order_and_the_same_for_one_and_two_workers() -> None:
    from deft_gym.scenarios.scenario import load_scenario, scenario_to_dict

    data = scenario_to_dict(load_scenario(ROOT / "configs" / "scenarios" / "lane_follow_static.yaml"))
    items = [(data, seed, None, "k") for seed in (5, 3, 9, 1)]
    one, two = _runs(items, 1), _runs(items, 2)
    assert [r["seed"] for r in two] == [5, 3, 9, 1]
    assert without_timings(one) == without_timings(two)


def test_record_resume_skips_what_it_holds(tmp_path: Path) -> None:
    rec = Record(tmp_path / "r.jsonl")
    rec.add({"key": "a", "seed": 1})
    (tmp_path / "r.jsonl").open("a").write('{"key": "b", "se')  # a line cut by a kill
    again = Record(tmp_path / "r.jsonl")
    assert again.rows == [{"key": "a", "seed": 1}]
    items = [("a", 1), ("a", 2), ("b", 1)]
    assert again.todo(items, lambda i: i, "key", "seed") == [("a", 2), ("b", 1)]


def test_without_timings_drops_durations_at_any_depth() -> None:
    rows = [{"index": 0, "wall_time": 1.5, "failures": [{"signature": "x", "wall_s": 0.1}]}]
    assert without_timings(rows) == [{"index": 0, "failures": [{"signature": "x"}]}]


def test_backend_flags() -> None:
    args = argparse.Namespace(ray=False, ray_address=None)
    assert backend_from_args(args, 3) == Backend("local", 3)
    with pytest.raises(BackendError, match="--workers"):
        backend_from_args(args, 0)


def test_functions_of_main_are_sent_by_module_name() -> None:
    assert importable(json.dumps) is json.dumps


def test_a_campaign_without_ray_says_how_to_get_it(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """``--ray`` where Ray is not installed: one line naming the flag and the install, exit 2."""
    import builtins

    real = builtins.__import__

    def no_ray(name: str, *a, **k):
        if name == "ray" or name.startswith("ray."):
            raise ImportError("No module named 'ray'")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    from deft_gym.cli import calibrate

    assert calibrate.main(["--scenarios", "configs/scenarios/left_turn.yaml", "--ray",
                           "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --ray: Ray is not installed") and "deft-gym[ray]" in err
    assert len(err.splitlines()) == 1
