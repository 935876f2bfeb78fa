"""The generated pytest modules, run for real in subprocesses, and the CLI.

A collision episode is recorded and extracted once; its generated tests must pass on the
unchanged planner (reproduction tests), give identical results run after run, fail on a changed
planner, and the failure test (oracle transformation) must fail every time until the planner
stops planning into the collision.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from extract import extract_episode
from tests.support.extract_support import colliding_episode, run_pytest

FAILURE = "does_not_plan_into_collision"


@pytest.fixture(scope="module")
def collision(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("collision")
    found = colliding_episode(root / "logs")
    if found is None:
        pytest.skip("none of the candidate cut-in scenarios collides with the current planner")
    log, name = found
    res = extract_episode(log, root / "tests")
    return res, name


def _reproduction(outcomes: dict[str, str]) -> dict[str, str]:
    return {k: v for k, v in outcomes.items() if "_reproduces[" in k}


def test_extraction_finds_the_faulty_plan(collision) -> None:
    res, _ = collision
    s = res.summary
    assert s["outcome"] == "collision" and s["reproduced"]["0"] == s["frames"]
    f = res.faulty
    assert f is not None and f["participant"] == s["collision"]["participant"]
    assert f["publish_time"] <= s["collision"]["time"] and f["distance"] == 0.0
    assert 0 <= f["replay_from"] <= f["index"]
    assert res.test_path is not None and FAILURE in res.test_path.read_text()


def test_generated_tests_pass_fail_as_expected_and_are_deterministic(collision) -> None:
    res, _ = collision
    out_dir = res.test_path.parent
    code1, first, log1 = run_pytest(out_dir)
    code2, second, _ = run_pytest(out_dir)
    assert first == second, "two runs of the generated tests differ"
    repro = _reproduction(first)
    assert len(repro) == res.summary["frames"] and set(repro.values()) == {"passed"}, log1[-2000:]
    failure = {k: v for k, v in first.items() if FAILURE in k}
    assert list(failure.values()) == ["failed"] and code1 == code2 == 1
    # names tell scenario, frame, time (and, for the failure test, the participant and collision time)
    (fname,) = failure
    f = res.faulty
    assert f"frame{f['index']:04d}-t{f['time']:.3f}s" in fname and f["participant"] in fname
    assert res.test_path.stem.removeprefix("test_") in fname
    assert "the planner still plans into the collision" in log1


@pytest.mark.parametrize("runs", [2, pytest.param(10, marks=pytest.mark.slow)])
def test_failure_test_fails_every_time(collision, runs: int) -> None:
    res, _ = collision
    verdicts = [run_pytest(res.test_path.parent, "-k", FAILURE)[1] for _ in range(runs)]
    assert all(list(v.values()) == ["failed"] for v in verdicts)


def test_failure_test_replaying_all_frames_agrees(collision) -> None:
    res, _ = collision
    _, minimal, _ = run_pytest(res.test_path.parent, "-k", FAILURE)
    _, full, _ = run_pytest(res.test_path.parent, "-k", FAILURE, env={"DEFT_FULL_PREFIX": "1"})
    assert minimal == full and list(full.values()) == ["failed"]


def test_changed_planner_fails_once_at_the_first_divergent_frame(collision) -> None:
    """A small deliberate change (a cost weight) fails the first frame whose output differs, with
    the differing fields at full precision; every later frame is reported as its consequence."""
    res, _ = collision
    _, outcomes, log = run_pytest(res.test_path.parent, "-rx",
                                  env={"DEFT_PLANNER_PARAMS": json.dumps({"w_speed": 8.5})})
    repro = _reproduction(outcomes)
    failed = [k for k, v in repro.items() if v == "failed"]
    assert len(failed) == 1, log[-1500:]
    first = sorted(repro).index(failed[0])
    assert all(v == "passed" for k, v in sorted(repro.items())[:first])
    assert all(v == "skipped" for k, v in sorted(repro.items())[first + 1:])  # xfail: a consequence
    assert "the first frame of this episode that does" in log and "consequences:" in log
    assert "a consequence of frame" in log
    assert "recorded " in log and "replayed " in log


def test_failure_test_passes_once_the_planner_stops_planning_into_it(collision) -> None:
    res, _ = collision
    _, outcomes, _ = run_pytest(res.test_path.parent, "-k", FAILURE,
                                env={"DEFT_PLANNER": "tests.support.extract_support:ElsewherePlanner"})
    assert list(outcomes.values()) == ["passed"]


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "extract", *args], capture_output=True, text=True)


def test_cli_extracts_one_log(collision, tmp_path) -> None:
    res, _ = collision
    log = Path(res.summary["log"])
    proc = _cli(str(log), "--out", str(tmp_path / "cli"), "--theta", "0.1", "--measure", "frechet")
    assert proc.returncode == 0, proc.stderr
    s = json.loads((tmp_path / "cli" / "summary.json").read_text())
    assert s["theta"] == 0.1 and s["measure"] == "frechet" and s["reproduced"]["0"] == s["frames"]
    assert "P_faulty" in proc.stdout and "pytest" in proc.stdout


def test_cli_bad_input_is_one_clear_line(tmp_path) -> None:
    for args, needle in [((str(tmp_path / "nope.mcap"),), "no such file"),
                         ((str(tmp_path),), "no .mcap logs"),
                         ((str(tmp_path), "--mapping", str(tmp_path / "m.yaml")), "cannot read mapping")]:
        proc = _cli(*args, "--out", str(tmp_path / "o"))
        assert proc.returncode == 2 and needle in proc.stderr
        assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("error: ")
    assert _cli("--help").returncode == 0
    assert _cli("x.mcap").returncode == 2  # --out is required


def test_a_second_regression_later_in_the_episode_fails_too(collision) -> None:
    """Frames after a divergence are consequences only while they differ one after the other: a
    planner changed in two separate windows of frames fails twice (the first frame of each
    window), xfails the rest of each window, and passes the frames between and after them that
    replay equal - they used to be xfailed as consequences of the first, hiding the second."""
    res, _ = collision
    index = json.loads(Path(res.frames_path).read_text().splitlines()[0])["frames_index"]
    times = [f["time"] for f in index]
    n = len(times)
    assert n > 30
    w1, w2 = (times[5] - 1e-6, times[8] + 1e-6), (times[20] - 1e-6, times[23] + 1e-6)
    _, outcomes, log = run_pytest(res.test_path.parent, "-k", "reproduces", "-rx",
                                  env={"DEFT_PLANNER": "tests.support.extract_support:WindowedPlanner",
                                       "DEFT_WINDOWS": json.dumps([w1, w2])})
    got = [v for _, v in sorted(_reproduction(outcomes).items())]
    want = ["passed"] * 5 + ["failed"] + ["skipped"] * 3 + ["passed"] * 11 + ["failed"] + ["skipped"] * 3 + \
        ["passed"] * (n - 24)
    assert got == want, log[-2000:]
    assert "a divergence of its own" in log and "a consequence of frame 5" in log and "a consequence of frame 20" in log


def _fails_every_time_and_passes_on_the_reference(folder: Path, test: str, message: str) -> None:
    """The failure test ``test`` of an extraction folder fails in each of 3 runs, with ``message``
    in its report, while every reproduction test passes; on the reference planner it passes."""
    for _ in range(3):
        _, outcomes, log_text = run_pytest(folder)
        assert [v for k, v in outcomes.items() if test in k] == ["failed"], log_text[-1500:]
        assert all(v == "passed" for v in _reproduction(outcomes).values())
        assert message in log_text
    _, outcomes, _ = run_pytest(folder, "-k", test, env={"DEFT_PLANNER": "deft_gym.planner.lattice:LatticePlanner"})
    assert list(outcomes.values()) == ["passed"]


def test_a_plan_into_the_oncoming_lane_gets_a_driving_direction_test(tmp_path: Path) -> None:
    """P_wrong_way: a planner that bends its plans one lane to the left (tests.support's
    OncomingPlanner) drives the ego into the oncoming lane of left_turn's approach; the extraction
    finds the first plan of that run, and its generated test fails every time on that planner
    (the reproduction tests pass) and passes on the reference planner, which keeps to its side."""
    from tests.support.extract_support import record, short_scenario

    log = record(tmp_path / "log", short_scenario("left_turn", 8.0), seed=7,
                 planner_class="tests.support.extract_support:OncomingPlanner")
    res = extract_episode(log, tmp_path / "tests")
    header = json.loads(res.frames_path.read_text().splitlines()[0])
    ww = header["oracle"]["wrong_way"]
    assert ww["length"] >= ww["limit"] == 2.0 and ww["time"] >= 3.0  # it bends from 3 s on
    assert "P_wrong_way: frame" in res.test_path.read_text()
    _fails_every_time_and_passes_on_the_reference(res.test_path.parent, "keeps_to_its_side_of_the_road",
                                                  "still plans the ego against the lane direction")


def test_a_plan_off_the_road_gets_a_drivable_area_test(tmp_path: Path) -> None:
    """P_off_road: the same bent planner on lane_follow_static, whose ego drives in the left lane
    of a road with nothing to its left, plans the ego off the road from 3 s on; the extraction
    finds the first plan of the run that put its box off the road where the ego left it, and the
    generated test fails every time on that planner and passes on the reference planner. The
    experiment that takes such runs apart (deft_gym.experiments.off_road) calls it planned."""
    from tests.support.extract_support import record, short_scenario

    log = record(tmp_path / "log", short_scenario("lane_follow_static", 6.0), seed=7,
                 planner_class="tests.support.extract_support:OncomingPlanner")
    res = extract_episode(log, tmp_path / "tests")
    header = json.loads(res.frames_path.read_text().splitlines()[0])
    off = header["oracle"]["off_road"]
    assert 3.0 <= off["time"] < off["left_at"] and off["depth"] > off["limit"] == 0.3
    assert "wrong_way" not in header["oracle"]  # no lane there at all
    assert "P_off_road: frame" in res.test_path.read_text()
    _fails_every_time_and_passes_on_the_reference(res.test_path.parent, "keeps_on_the_road",
                                                  "still plans the ego off the road")
    from deft_gym.experiments.off_road import take_apart

    row = take_apart(log)
    assert row is not None and row["verdict"] == "planned" and row["p_off_road"]["index"] == off["index"]
    assert row["last_plan"]["depth_near"] > 0.3 and row["depth_max"] > 1.0


def test_a_stuck_run_gets_a_test_that_the_planner_plans_progress(tmp_path: Path) -> None:
    """P_stall: a planner that plans standstills from 2 s on (tests.support's StallingPlanner)
    leaves the ego stuck on lane_follow_static's free road (the episode oracle: stuck after 4 s);
    the extraction finds the first plan of the standing run that ends the log, and its generated
    test fails every time on that planner and passes on the reference planner, which drives on."""
    from deft_gym.scenarios.scenario import load_scenario, scenario_from_dict, scenario_to_dict
    from tests.support.extract_support import record

    data = scenario_to_dict(load_scenario("lane_follow_static"))
    data.update(duration=12.0, stuck_time=4.0, name="lane_follow_static_stall")
    log = record(tmp_path / "log", scenario_from_dict(data, source="test"), seed=7,
                 planner_class="tests.support.extract_support:StallingPlanner")
    res = extract_episode(log, tmp_path / "tests")
    header = json.loads(res.frames_path.read_text().splitlines()[0])
    assert header["outcome"] == "stuck"
    stall = header["oracle"]["stall"]
    assert 2.0 <= stall["time"] < 2.3 and stall["travel"] < stall["limit"] == 0.5 and stall["standing_plans"] >= 30
    _fails_every_time_and_passes_on_the_reference(res.test_path.parent, "plans_progress",
                                                  "still leaves the ego standing")
    # taken apart at its first frame (deft_gym.experiments.stalls): on the road, replayed as recorded
    from deft_gym.experiments.stalls import take_apart

    row = take_apart(res.frames_path.parent, [])
    assert row is not None and row["frame"] == stall["index"] and row["speed"] > 0.0
    assert row["outside_lanes_m2"] == 0.0
    assert row["variants"][0]["decision"] == row["recorded"] != "no output"


def test_a_pass_too_close_gets_a_near_miss_test(tmp_path: Path) -> None:
    """P_near_miss: a planner that goes straight on along its lane's centre (tests.support's
    StraightPlanner) passes a cone standing 1.75 m off that centre (its box 0.45 m from the ego's)
    at 8 m/s; the extraction finds the first plan of the run that planned the pass that close, and
    the generated test fails every time on that planner and passes on the reference planner, which
    keeps 0.9 m away."""
    from deft_gym.scenarios.scenario import load_scenario, scenario_from_dict, scenario_to_dict
    from tests.support.extract_support import record

    data = scenario_to_dict(load_scenario("lane_follow_static"))
    data.update(duration=8.0, name="lane_follow_cone")
    data["participants"] = [dict(data["participants"][0], d=-1.75)]
    log = record(tmp_path / "log", scenario_from_dict(data, source="test"), seed=7,
                 planner_class="tests.support.extract_support:StraightPlanner")
    res = extract_episode(log, tmp_path / "tests")
    header = json.loads(res.frames_path.read_text().splitlines()[0])
    near = header["oracle"]["near_miss"]
    assert near["participant"] == "1 (CONE)" and near["gap"] < near["clearance"] == 0.5
    assert near["time"] < near["point_time"] and near["close_gap"] < 0.5 and 4.0 < near["close_at"] < 5.0
    assert res.summary["failure_oracles"] == {"P_near_miss": {"index": near["index"], "time": near["time"]}}
    assert "P_near_miss: frame" in res.test_path.read_text()
    _fails_every_time_and_passes_on_the_reference(res.test_path.parent, "keeps_its_distance",
                                                  "still plans the ego past 1 (CONE) too close")


@pytest.mark.slow  # 17 s idle, 70 s loaded: 160 frames replayed four times (test_units.py has its rule)
def test_a_red_light_run_gets_a_red_light_test(tmp_path: Path) -> None:
    """P_red_light: a planner told every light is green (tests.support's GreenLightPlanner) drives
    over blocked_red_light's stop line (its obstacles left out) at red; the extraction finds the
    first plan, made after the light turned, that planned the crossing at red, and the generated
    test fails every time on that planner and passes on the reference planner, which stops."""
    from deft_gym.scenarios.scenario import load_scenario, scenario_from_dict, scenario_to_dict
    from tests.support.extract_support import record

    data = scenario_to_dict(load_scenario("blocked_red_light"))
    data.update(duration=16.0, name="red_light_run", participants=[])
    log = record(tmp_path / "log", scenario_from_dict(data, source="test"), seed=7,
                 planner_class="tests.support.extract_support:GreenLightPlanner")
    res = extract_episode(log, tmp_path / "tests")
    header = json.loads(res.frames_path.read_text().splitlines()[0])
    red = header["oracle"]["red_light"]
    assert red["light"] == "tl0" and red["colour"] == "RED" and red["time"] < red["point_time"]
    assert red["crossed_at"] > red["time"] >= 2.0  # the light turned red at 2 s; the ego crossed later
    assert "P_red_light: frame" in res.test_path.read_text()
    _fails_every_time_and_passes_on_the_reference(res.test_path.parent, "stops_at_red",
                                                  "still plans to run the red light tl0")
