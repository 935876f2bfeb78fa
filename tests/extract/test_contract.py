"""The planner contract checker (extract.contract) and the input search's answer to planners that
break it: real logs, real planners, planted breaches."""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from deft_gym.bus.ads import load_ads_config
from deft_gym.experiments.record import ads_overrides
from deft_gym.planner.lattice import LatticePlanner
from deft_gym.sim.simulation import Simulation
from extract import extract_episode
from extract.contract import CHECKS, assert_contract, check_contract, check_path, frames_from_log
from extract.mapping import DEFAULT_MAPPING
from tests.support.extract_support import ROOT, HiddenStatePlanner, short_scenario

FRAMES = 60
#: a delivery prior far from the truth: the search tries several candidates per output (restores)
SLOW_PRIOR = {"delivery": {"mean_ms": 60.0, "std_ms": 10.0, "drop_prob": 0.001, "dispatch_ms": 0.3}}


class ClockPlanner(LatticePlanner):
    """Reads the wall clock (a time budget), without it changing the output."""

    def plan(self, frame: Any) -> dict[str, Any] | None:
        deadline = time.perf_counter() + 0.1
        out = super().plan(frame)
        if out is not None and time.perf_counter() > deadline:
            out["decision"]["late"] = True
        return out


class GlobalRandomPlanner(LatticePlanner):
    """Breaks cost ties with the global random generator."""

    def plan(self, frame: Any) -> dict[str, Any] | None:
        out = super().plan(frame)
        if out is not None:
            out["decision"]["cost"] += random.random() * 1e-12
        return out


class NoneChangesStatePlanner(LatticePlanner):
    """Counts the frames it could not plan in its state, and lets that count shift the plan."""

    def plan(self, frame: Any) -> dict[str, Any] | None:
        if frame.get("localization") is None:
            self.state.cycles += 1
            return None
        out = super().plan(frame)
        if out is not None:
            out["trajectory"]["v"] = [v + 1e-9 * self.state.cycles for v in out["trajectory"]["v"]]
        return out


@pytest.fixture(scope="module")
def frames(lane_follow_log) -> tuple[dict[str, Any], list[Any]]:
    return frames_from_log(lane_follow_log.log_path, max_frames=FRAMES)


def _make(cls: type, spec: dict[str, Any]) -> Any:
    return lambda: cls(spec["map"], **spec["params"])


def test_reference_planner_meets_the_contract(frames) -> None:
    spec, fr = frames
    report = assert_contract(_make(LatticePlanner, spec), fr)
    assert report.ok and report.frames == FRAMES and report.checks == dict.fromkeys(CHECKS, "ok")


def test_state_hidden_outside_self_state_is_flagged(frames) -> None:
    """The planted CommonRoad-like flag: a clean replay is deterministic, but snapshot / another
    frame / restore does not return to the same state; the report names the frame and field."""
    spec, fr = frames
    report = check_contract(_make(HiddenStatePlanner, spec), fr)
    assert report.checks["deterministic"] == "ok" and report.checks["output"] == "ok"
    assert report.checks["snapshot_restore"] == "violated"
    (v,) = [v for v in report.violations if v.check == "snapshot_restore"]
    assert v.frame is not None and f"frame {v.frame} (t={fr[v.frame].time!r} s)" in v.text()
    assert "position" in v.message and "outside self.state" in v.message
    with pytest.raises(AssertionError, match="snapshot_restore: violated"):
        assert_contract(_make(HiddenStatePlanner, spec), fr)


def test_clock_and_global_generator_use_are_flagged(frames) -> None:
    spec, fr = frames
    clock = check_contract(_make(ClockPlanner, spec), fr[:10])
    assert clock.checks["no_clock_or_global_rng"] == "violated" and clock.checks["deterministic"] == "ok"
    assert "time.perf_counter" in clock.text()
    rng = check_contract(_make(GlobalRandomPlanner, spec), fr[:10])
    assert rng.checks["no_clock_or_global_rng"] == "violated" and "random.random" in rng.text()
    assert rng.checks["deterministic"] == "violated" and "decision.cost" in rng.text()


def test_a_none_that_changes_the_state_is_flagged(frames) -> None:
    spec, fr = frames
    report = check_contract(_make(NoneChangesStatePlanner, spec), fr[:10])
    assert report.checks["none_keeps_state"] == "violated"
    (v,) = [v for v in report.violations if v.check == "none_keeps_state"]
    assert v.frame == 0 and "v: largest deviation" in v.message


def test_cli_checks_a_log_and_a_planner(lane_follow_log, capsys) -> None:
    from extract.contract import main

    log = str(lane_follow_log.log_path)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    ok = subprocess.run([sys.executable, "-m", "extract.contract", log, "--max-frames", "20"],
                        capture_output=True, text=True, env=env)
    assert ok.returncode == 0, ok.stderr
    assert "holds" in ok.stdout
    assert main([log, "--max-frames", "20", "--planner", "tests.support.extract_support:HiddenStatePlanner", "--json"]) == 1
    rep = json.loads(capsys.readouterr().out)
    assert rep["checks"]["snapshot_restore"] == "violated" and rep["violations"][0]["frame"] is not None
    for args, needle in [(["nope.mcap"], "no such file"), ([log, "--params", "[1]"], "JSON object"),
                         ([log, "--planner", "no.such:Planner"], "cannot import")]:
        assert main(args) == 2
        err = capsys.readouterr().err
        assert needle in err and err.count("\n") == 1, err


def test_checking_frames_of_an_extraction(lane_follow_log, tmp_path) -> None:
    res = extract_episode(lane_follow_log.log_path, tmp_path, emit_tests=False)
    report = check_path(res.frames_path, max_frames=30)
    assert report.ok and report.planner == "deft_gym.planner.lattice:LatticePlanner"


def test_search_is_right_when_restore_is_not_faithful(tmp_path) -> None:
    """A log of the hidden-state planner, extracted with a poor delivery prior so that the search
    tries several candidates: the validation replay catches the unfaithful restore, the frames
    from there are searched again on fresh planners, and every output is reproduced - as the
    generated tests (fresh replays) then confirm."""
    from tests.support.extract_support import run_pytest

    ads = load_ads_config(None, ads_overrides(planner_class="tests.support.extract_support:HiddenStatePlanner"))
    res = Simulation(short_scenario("left_turn", 8.0), ads, jitter_seed=11, out_dir=tmp_path / "log").run()
    mapping = {**yaml.safe_load(DEFAULT_MAPPING.read_text()), **SLOW_PRIOR}
    out = extract_episode(res.log_path, tmp_path / "x", mapping=mapping)
    s = out.summary
    assert s["search"]["restores"] > 0 and s["search"]["restore_faithful"] is False
    assert s["search"]["nondeterministic_at"] is None
    assert s["reproduced_at_theta"] == s["frames"]
    assert any("not faithful" in w for w in s["warnings"])
    code, outcomes, log = run_pytest(Path(out.test_path).parent)
    assert code == 0 and set(outcomes.values()) == {"passed"}, log[-1500:]


class CounterPlanner(LatticePlanner):
    """Keeps a counter outside self.state that changes its plan only after 10,000 calls: no
    frame of a short log exercises it, so the output checks all pass - the attributes do not."""

    def __init__(self, map_spec: dict[str, Any], **params: Any) -> None:
        super().__init__(map_spec, **params)
        self.calls = 0

    def plan(self, frame: Any) -> dict[str, Any] | None:
        self.calls += 1
        out = super().plan(frame)
        if out is not None and self.calls > 10_000:
            out["trajectory"]["x"] = [x + 1.0 for x in out["trajectory"]["x"]]
        return out


def test_hidden_state_the_frames_never_exercise_is_flagged(frames) -> None:
    """check-planner used to pass a planner whose state outside self.state no given frame made
    visible; it now names the attribute plan() changed and the first frame it did so, while the
    reference planner (whose memo caches are declared in `caches`) passes."""
    spec, fr = frames
    report = check_contract(_make(CounterPlanner, spec), fr[:10])
    assert report.checks["snapshot_restore"] == "ok" and report.checks["deterministic"] == "ok"
    assert report.checks["hidden_state"] == "violated"
    (v,) = [v for v in report.violations if v.check == "hidden_state"]
    assert v.frame == 0 and "self.calls" in v.message
    assert check_contract(_make(LatticePlanner, spec), fr[:10]).checks["hidden_state"] == "ok"
    assert check_contract(_make(HiddenStatePlanner, spec), fr[:10]).checks["hidden_state"] == "violated"
