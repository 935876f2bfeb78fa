"""Generality, tested: a second planner of another design (tests/support/lane_keeper.py: route following
with an IDM speed profile, the map read from the map message, its own state, trajectory shape
and decision vocabulary) goes through simulation -> extraction -> generated tests -> contract
checker."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from deft_gym.bus.ads import load_ads_config
from deft_gym.experiments.record import ads_overrides
from deft_gym.planner.base import Frame, validate_output
from deft_gym.sim.simulation import Simulation
from extract import extract_episode
from extract.contract import check_path
from extract.minimize import frame_getter, seeded_start
from extract.runtime import load_frames
from tests.support.extract_support import ROOT, run_pytest, short_scenario
from tests.support.lane_keeper import LaneKeeperPlanner

LANE_KEEPER = "tests.support.lane_keeper:LaneKeeperPlanner"


@pytest.fixture(scope="module")
def second(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("second_planner")
    ads = load_ads_config(None, ads_overrides(planner_class=LANE_KEEPER))
    res = Simulation(short_scenario("left_turn", 20.0), ads, jitter_seed=5, out_dir=root / "log").run()
    return res, extract_episode(res.log_path, root / "deft")


def test_it_drives_the_simulation_through_its_frames(second) -> None:
    res, _ = second
    assert res.outcome.outcome == "completed" and len(res.planning) > 100
    modes = {p["decision"]["mode"] for p in res.planning}
    assert {"CRUISE", "ARRIVE"} <= modes  # its own vocabulary
    for p in res.planning:
        assert len(p["trajectory"]["t"]) == LaneKeeperPlanner.N  # its own shape
        assert validate_output(p, p["header"]["stamp"]) == []


def test_extraction_reproduces_its_whole_output(second) -> None:
    _, ext = second
    s = ext.summary
    assert s["frames"] > 100 and s["reproduced_at_theta"] == s["frames"]
    assert s["reproduced_all_fields"]["0"] == s["frames"]
    assert {"t", "v", "heading", "a", "decision.mode", "decision.gap", "decision.leader"} <= set(s["fields"])
    assert all(f["reproduced"] == f["frames"] for f in s["fields"].values())
    header, frames = load_frames(ext.frames_path)
    assert header["roles"] == list(LaneKeeperPlanner.inputs) and "map" in frames[0]["inputs"]
    assert header["planner"]["provenance"]["root"] == str(ROOT)


def test_its_generated_tests_pass_and_run_from_any_directory(second, tmp_path) -> None:
    """From another directory, with only the project on the path: the test imports the planner
    from the folder recorded at extraction."""
    _, ext = second
    out_dir = Path(ext.test_path).parent
    code, outcomes, log = run_pytest(out_dir)
    assert code == 0 and set(outcomes.values()) == {"passed"} and len(outcomes) == ext.summary["frames"], log[-1500:]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
                           "--rootdir", str(tmp_path), str(out_dir)], capture_output=True, text=True, env=env,
                          cwd=tmp_path)
    assert proc.returncode == 0 and f"{ext.summary['frames']} passed" in proc.stdout, proc.stdout[-1500:]
    # a changed planner fails once, at the first frame that differs
    code, outcomes, log = run_pytest(out_dir, env={"DEFT_PLANNER_PARAMS": json.dumps({"smooth": 0.6})})
    assert code == 1 and list(outcomes.values()).count("failed") == 1, log[-1500:]


def test_it_meets_the_planner_contract(second) -> None:
    _, ext = second
    report = check_path(ext.frames_path, max_frames=80)
    assert report.ok, report.text()


def test_it_can_be_seeded(second) -> None:
    """Its state is plain values: a fresh planner loaded with the state before a frame gives that
    frame's recorded output exactly (what a failure test does)."""
    _, ext = second
    header, frames = load_frames(ext.frames_path)
    get = frame_getter([f["time"] for f in frames], lambda j: frames[j]["inputs"])
    spec = header["planner"]
    seed = seeded_start(lambda: LaneKeeperPlanner(spec["map"], **spec["params"]), get, 90,
                        lambda j: {k: frames[j]["expected"][k] for k in ("trajectory", "decision")})
    assert seed.state is not None and seed.note is None
    assert isinstance(get(0), Frame)
