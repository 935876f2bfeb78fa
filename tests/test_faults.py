"""Fault injection: resume without loss, outputs that never collide, crashing and hanging modules,
bad inputs that must be one-line errors. Every test drives the real code (real logs, real
simulations, real SB3 checkpoints); the long ones are marked slow."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from deft_gym.envs.sink import EpisodeSink
from deft_gym.files import append_jsonl, read_jsonl

ROOT = Path(__file__).resolve().parent.parent


# -- data loss ---------------------------------------------------------------------------------
def test_sink_on_an_existing_run_continues_numbering_and_deletes_nothing_it_did_not_make(tmp_path):
    old = tmp_path / "episodes" / "w0-000001-take_exit"
    old.mkdir(parents=True)
    (old / "episode.mcap").write_bytes(b"kept failure")
    user = tmp_path / "episodes" / "w0-000002-mine"
    user.mkdir()
    (user / "notes.txt").write_text("a user's file")
    append_jsonl(tmp_path / "episodes-0.jsonl", {"scenario": "take_exit", "failure": "collision", "kept": True})

    sink = EpisodeSink(tmp_path, worker=0, keep_passing=0.0, extract=False)
    d = sink.episode_dir("take_exit")
    assert d.name == "w0-000003-take_exit"  # after the highest number on disk, never a reused one
    assert (old / "episode.mcap").read_bytes() == b"kept failure" and (user / "notes.txt").exists()
    sink.finish(d, {"scenario": "take_exit", "failure": None}, {})  # passing, not kept: its own folder goes
    assert not d.exists()
    sink.finish(user, {"scenario": "take_exit", "failure": None}, {}, keep=False)  # not its folder: stays
    assert (user / "notes.txt").read_text() == "a user's file"
    lines = read_jsonl(tmp_path / "episodes-0.jsonl")
    assert len(lines) == 3 and lines[0]["kept"] and all("env_steps" in x for x in lines[1:])


def test_resume_rolls_back_the_episodes_after_its_checkpoint_once(tmp_path):
    """A resumed run's journals keep every line (append-only); the summary counts the episodes
    journalled after the checkpoint's step once - the ones redone after the resume - not twice."""
    from agents.train import mark_resume, summarize_run

    for steps, fail in [(10, "collision"), (20, None), (30, "nods"), (40, None)]:
        append_jsonl(tmp_path / "episodes-0.jsonl", {"scenario": "s", "valid": True, "failure": fail,
                                                     "env_steps": steps})
    mark_resume(tmp_path, 1, 25, tmp_path / "checkpoints" / "ppo_25_steps.zip")  # 30 and 40 rolled back
    for steps, fail in [(30, None), (40, "collision")]:
        append_jsonl(tmp_path / "episodes-0.jsonl", {"scenario": "s", "valid": True, "failure": fail,
                                                     "env_steps": steps})
    s = summarize_run(tmp_path)
    assert (s["episodes"], s["collisions"], s["nods"], s["rolled_back_episodes"]) == (4, 2, 0, 2)
    assert len(read_jsonl(tmp_path / "episodes-0.jsonl")) == 7  # nothing deleted


def test_train_resume_from_a_missing_or_truncated_checkpoint_is_one_line(tmp_path, capsys):
    from agents import train

    missing = tmp_path / "ckpt" / "ppo_64_steps.zip"
    assert train.main(["--config", "configs/train/demo.yaml", "--out", str(tmp_path / "run"),
                       "--resume", str(missing)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "ppo_64_steps.zip:" in err and ".zip.zip" not in err
    missing.parent.mkdir()
    missing.write_bytes(b"PK\x03\x04 truncated")
    assert train.main(["--config", "configs/train/demo.yaml", "--out", str(tmp_path / "run"),
                       "--resume", str(missing)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a readable SB3 checkpoint" in err
    assert not (tmp_path / "run").exists()  # refused before any work


@pytest.mark.slow
def test_train_resume_appends_monitor_and_journal_and_keeps_kept_logs(tmp_path):
    """Train, then resume from the last checkpoint: the Monitor CSV and the journal only grow,
    every kept episode folder of the first session is still there, numbering continues."""
    from agents import train

    cfg = tmp_path / "tiny.yaml"
    cfg.write_text("name: tiny\nalgo: ppo\ntimesteps: 48\nseed: 0\nn_envs: 1\nvec_env: dummy\n"
                   "checkpoint_every: 24\nalgo_kwargs: {n_steps: 24, batch_size: 24, n_epochs: 1}\n"
                   "log_episodes: true\nenv: {scenarios: [lane_follow_static], record: failures, "
                   "keep_passing: 1.0, extract: false}\n")
    out = tmp_path / "run"
    assert train.main(["--config", str(cfg), "--out", str(out), "--no-progress"]) == 0
    monitor = out / "monitor" / "env0.monitor.csv"
    rows0 = monitor.read_text().splitlines()
    kept0 = {p.name: p.stat().st_mtime_ns for p in (out / "episodes").iterdir()}
    journal0 = read_jsonl(out / "episodes-0.jsonl")
    assert kept0 and journal0
    ckpt = sorted((out / "checkpoints").glob("ppo_*_steps.zip"))[0]
    assert not list((out / "checkpoints").glob("*.tmp*"))
    assert train.main(["--config", str(cfg), "--out", str(out), "--resume", str(ckpt), "--timesteps", "72",
                       "--no-progress"]) == 0
    rows1 = monitor.read_text().splitlines()
    assert rows1[:len(rows0)] == rows0 and len(rows1) > len(rows0)  # appended, one header
    assert sum(1 for r in rows1 if r.startswith("r,l,t")) == 1
    kept1 = {p.name: p.stat().st_mtime_ns for p in (out / "episodes").iterdir()}
    assert all(kept1.get(k) == v for k, v in kept0.items())  # nothing of the first session touched
    journal1 = read_jsonl(out / "episodes-0.jsonl")
    assert journal1[:len(journal0)] == journal0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["episodes"] + summary["rolled_back_episodes"] == len(journal1) - 1  # one resume marker


def test_extract_folder_gives_colliding_logs_distinct_outputs(tmp_path, lane_follow_log):
    from extract.batch import extract_directory

    root = tmp_path / "logs"
    (root / "lfs").mkdir(parents=True)
    shutil.copy(lane_follow_log.log_path, root / "lfs" / "episode.mcap")
    shutil.copy(lane_follow_log.log_path, root / "lfs.mcap")
    results = extract_directory(root, tmp_path / "out", emit_tests=False)
    dirs = {Path(r.summary["frames_path"]).parent for r in results}
    assert len(results) == 2 and len(dirs) == 2, dirs
    assert {d.name for d in dirs} == {"lfs", "lfs.mcap"}
    for d in dirs:
        assert json.loads((d / "summary.json").read_text())["frames"] == results[0].summary["frames"]


def test_demo_never_deletes_folders_it_did_not_write(tmp_path, capsys):
    from agents import demo

    (tmp_path / "train").mkdir()
    (tmp_path / "train" / "precious.txt").write_text("not the demo's")
    assert demo.main(["--out", str(tmp_path), "--timesteps", "8"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "did not write" in err
    assert (tmp_path / "train" / "precious.txt").exists()


# -- failures never hidden: crashing, hanging, NaN-emitting and silent modules ----------------------
FAULTY = "fault_planners:FaultyPlanner"
LANE_FOLLOW = ROOT / "configs" / "scenarios" / "lane_follow_static.yaml"


def faulty_ads(fault: str, after: int = 20, **params):
    from agents.record import ads_overrides
    from deft_gym.bus.ads import load_ads_config

    return load_ads_config(None, ads_overrides(planner_class=FAULTY,
                                               planner_params={"fault": fault, "after": after, **params}))


def log_outcome(log: str | Path) -> dict:
    from extract.logs import read_log

    return read_log(Path(log), []).metadata["deft_gym.outcome"]


@pytest.fixture(scope="module")
def crash_run(tmp_path_factory):
    from deft_gym.sim.simulation import Simulation

    out = tmp_path_factory.mktemp("crash")
    return Simulation(LANE_FOLLOW, faulty_ads("raise"), jitter_seed=7, out_dir=out).run()


def test_a_module_that_raises_ends_the_episode_as_a_crash_in_result_and_log(crash_run):
    s = crash_run.summary()
    assert s["outcome"] == "crash" and not s["task_completed"]
    f = s["failure"]
    assert (f["kind"], f["module"], f["exception"]) == ("crash", "planning", "ZeroDivisionError: planted fault")
    assert 0 < f["time"] < 5 and crash_run.sim_time < 5  # it ended there, not at the timeout
    rec = log_outcome(crash_run.log_path)
    assert rec["outcome"] == "crash" and rec["failure"]["module"] == "planning"


def test_the_extractor_reports_the_crash_of_the_run_it_extracts(crash_run, tmp_path):
    from extract import extract_episode

    s = extract_episode(crash_run.log_path, tmp_path, emit_tests=False).summary
    assert s["outcome"] == "crash" and s["findings"]["run_failure"]["module"] == "planning"
    assert any("crash of module planning" in w for w in s["warnings"])


def test_a_module_that_blocks_is_a_hang_after_the_wall_clock_watchdog(tmp_path):
    import time

    from deft_gym.sim.simulation import Simulation

    t0 = time.perf_counter()
    r = Simulation(LANE_FOLLOW, faulty_ads("sleep", sleep_s=30.0), jitter_seed=7, out_dir=tmp_path,
                   watchdog_s=0.5).run()
    assert time.perf_counter() - t0 < 10  # not 30 s per planning cycle
    assert r.outcome.outcome == "hang" and r.outcome.failure["module"] == "planning"
    assert log_outcome(r.log_path)["outcome"] == "hang"


def test_watchdog_setting_is_checked(monkeypatch):
    from deft_gym.sim.simulation import DEFAULT_WATCHDOG_S, watchdog_seconds

    assert watchdog_seconds() == DEFAULT_WATCHDOG_S
    from deft_gym.robustness.monitors import wall_budget

    assert wall_budget(1.0) == 3.0  # the stress campaign's own budget, unless the watchdog is set
    monkeypatch.setenv("DEFT_GYM_WATCHDOG_S", "2.5")
    assert watchdog_seconds() == 2.5 and wall_budget(1.0) == 2.5
    monkeypatch.setenv("DEFT_GYM_WATCHDOG_S", "soon")
    with pytest.raises(ValueError, match="DEFT_GYM_WATCHDOG_S"):
        watchdog_seconds()
    with pytest.raises(ValueError, match="watchdog_s"):
        watchdog_seconds(float("nan"))


def test_watchdog_flag_overrides_the_environment_and_is_restored(tmp_path, monkeypatch, capsys):
    """--watchdog-s 0.5 wins over DEFT_GYM_WATCHDOG_S=600: a planner that sleeps is a hang of
    planning within seconds; after the program the variable is what it was."""
    import os
    import time

    from deft_gym.cli import run

    ads = tmp_path / "ads.yaml"
    ads.write_text(f"planning:\n  planner:\n    class: {FAULTY}\n    params: {{fault: sleep, after: 20, sleep_s: 60}}\n")
    monkeypatch.setenv("DEFT_GYM_WATCHDOG_S", "600")
    t0 = time.perf_counter()
    assert run.main([str(LANE_FOLLOW), "--ads-config", str(ads), "--reruns", "1", "--jitter-seed", "7",
                     "--watchdog-s", "0.5", "--out", str(tmp_path / "out"), "--quiet", "--render", "none"]) == 0
    assert time.perf_counter() - t0 < 30
    row = json.loads((tmp_path / "out" / "summary.json").read_text())["reruns"][0]
    assert row["outcome"] == "hang"
    assert log_outcome(row["log"])["failure"]["exception"].endswith("within the 0.5 s wall-clock watchdog")
    assert os.environ["DEFT_GYM_WATCHDOG_S"] == "600"


@pytest.mark.parametrize("value", ["soon", "-1", "nan"])
def test_a_bad_watchdog_variable_is_one_line_exit_2_before_any_work(value, tmp_path, monkeypatch, capsys):
    from deft_gym.cli import run

    monkeypatch.setenv("DEFT_GYM_WATCHDOG_S", value)
    with pytest.raises(SystemExit) as exc:
        run.main([str(LANE_FOLLOW), "--reruns", "1", "--out", str(tmp_path / "out")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "DEFT_GYM_WATCHDOG_S" in err and "--watchdog-s" in err
    assert not (tmp_path / "out").exists()


def _watchdog_of_worker(_: int) -> float:
    from deft_gym.execution.watchdog import watchdog_seconds

    return watchdog_seconds()


def test_worker_processes_follow_the_watchdog_setting_of_the_program(monkeypatch):
    """The forkserver outlives one setting (it may start before --watchdog-s is read, or serve
    later programs of the same process): the pool hands every worker the setting it starts with."""
    from deft_gym.cli import common
    from deft_gym.execution import Backend, Executor

    monkeypatch.delenv("DEFT_GYM_WATCHDOG_S", raising=False)
    with common.watchdog_env(common.argparse.Namespace(watchdog_s=2.5)), Executor(Backend("local", 2)) as ex:
        assert list(ex.map(_watchdog_of_worker, range(4))) == [2.5] * 4
    with Executor(Backend("local", 2)) as ex:
        assert list(ex.map(_watchdog_of_worker, range(2))) == [10.0] * 2


def test_an_ego_that_never_received_a_plan_is_not_completed(tmp_path):
    import yaml

    from deft_gym.sim.simulation import Simulation

    data = yaml.safe_load(LANE_FOLLOW.read_text())
    data["ego"]["destination"] = {"lane": [*data["ego"]["lane"]], "s": data["ego"]["s"] + 1.0}
    path = tmp_path / "at_goal.yaml"
    path.write_text(yaml.safe_dump(data))
    r = Simulation(path, faulty_ads("silent", after=10**6), jitter_seed=7).run()
    assert r.outcome.outcome == "no_plan" and not r.outcome.task_completed


@pytest.fixture(scope="module")
def nan_run(tmp_path_factory):
    from deft_gym.sim.simulation import Simulation

    return Simulation(LANE_FOLLOW, faulty_ads("nan"), jitter_seed=7, out_dir=tmp_path_factory.mktemp("nan")).run()


def test_a_plan_with_nan_ends_the_episode_as_a_crash_of_planning(nan_run):
    """A NaN plan used to be tracked as full throttle and full lock until the run timed out
    (outcome timeout, 40 s): it is a crash of planning, reason non-finite output, at the time it
    was published, in the result and the log, and the log holds the offending plan."""
    from extract.logs import read_log

    s = nan_run.summary()
    assert s["outcome"] == "crash" and not s["task_completed"] and nan_run.sim_time < 5
    f = s["failure"]
    assert (f["kind"], f["module"], f["reason"]) == ("crash", "planning", "non-finite output")
    assert f["exception"] == "NonFiniteOutput: trajectory.x.0 is not finite on /apollo/planning" and 0 < f["time"] < 5
    rec = log_outcome(nan_run.log_path)
    assert rec["outcome"] == "crash" and rec["failure"] == f
    plans = read_log(Path(nan_run.log_path), ["/apollo/planning"]).topics["/apollo/planning"]
    assert plans.payload(len(plans) - 1)["trajectory"]["x"][0] != plans.payload(len(plans) - 1)["trajectory"]["x"][0]


def test_non_finite_fields_are_found_wherever_they_are():
    from deft_gym.bus.messages import non_finite_field

    nan, inf = float("nan"), float("inf")
    assert non_finite_field({"header": {"seq": 1, "stamp": 0.5, "module": "m"}, "a": [1.0, 2], "b": [],
                             "c": ["x", 3], "d": {}, "e": None, "f": True, "g": 10**400}) is None
    assert non_finite_field({"trajectory": {"t": [0.0, 0.1], "x": [1.0, nan]}}) == "trajectory.x.1"
    assert non_finite_field({"obstacles": [{"id": "a", "v": 1.0}, {"id": "b", "v": -inf}]}) == "obstacles.1.v"
    assert non_finite_field({"xs": [1e308, 1e308]}) is None  # a sum that overflows is not a NaN
    assert non_finite_field({"xs": [1.0, "x", inf]}) == "xs.2" and non_finite_field(nan) == ""


def test_nan_outputs_are_reproduced_and_reported_as_findings(nan_run, tmp_path):
    from extract import extract_episode

    s = extract_episode(nan_run.log_path, tmp_path / "x", emit_tests=False).summary
    assert s["findings"]["nan_outputs"] == 1 and s["findings"]["run_failure"]["reason"] == "non-finite output"
    assert s["reproduced"]["0"] == s["frames"]  # NaN == NaN: the replay gives the recorded NaN
    assert any("NaN or inf" in w for w in s["warnings"])


def test_planner_exceptions_during_extraction_are_counted_and_shown(lane_follow_log, tmp_path):
    from extract import extract_episode
    from extract.logs import read_log
    from extract.mapping import load_mapping

    meta = read_log(Path(lane_follow_log.log_path), []).episode_meta()
    mapping = load_mapping(ROOT / "configs" / "mappings" / "deft_gym.yaml").model_dump(by_alias=True)
    mapping["planner"] = {"class": FAULTY, "params": {"fault": "raise", "after": 0}, "map": meta["map"]}
    s = extract_episode(lane_follow_log.log_path, tmp_path, mapping=mapping, emit_tests=False,
                        minimize_failure=False).summary
    f = s["findings"]
    assert f["planner_exceptions"] > 0 and f["outputs_without_replay"] == s["frames"]
    assert s["reproduced"]["7"] == 0 and any("the planner raised in" in w for w in s["warnings"])


@pytest.mark.parametrize("after", [0, 40])
def test_a_planner_that_blocks_during_extraction_is_a_hang_finding(after, lane_follow_log, tmp_path):
    """plan() sleeping a minute per call used to hang extract (no watchdog on the replays): now
    the first call past the wall-clock watchdog is the finding planner_hang (message, frame time,
    output), no plan() is called after it, and the extraction finishes with its summary."""
    import time

    from extract import extract_episode
    from extract.logs import read_log
    from extract.mapping import load_mapping

    meta = read_log(Path(lane_follow_log.log_path), []).episode_meta()
    mapping = load_mapping(ROOT / "configs" / "mappings" / "deft_gym.yaml").model_dump(by_alias=True)
    mapping["planner"] = {"class": FAULTY, "params": {"fault": "sleep", "after": after, "sleep_s": 60.0},
                          "map": meta["map"]}
    t0 = time.perf_counter()
    s = extract_episode(lane_follow_log.log_path, tmp_path, mapping=mapping, emit_tests=False,
                        watchdog_s=0.5).summary
    assert time.perf_counter() - t0 < 30
    hang = s["findings"]["planner_hang"]
    assert hang["kind"] == "hang" and hang["module"] == "planning" and "0.5 s wall-clock watchdog" in hang["exception"]
    assert hang["time"] >= 0 and hang["output"] >= 0
    assert s["findings"]["outputs_without_replay"] > 0 and s["frames"] > 0
    assert any("the planner hung" in w for w in s["warnings"])
    assert json.loads((tmp_path / "summary.json").read_text())["findings"]["planner_hang"] == hang


def test_extraction_of_a_valid_log_has_no_hang_finding(lane_follow_log, tmp_path):
    from extract import extract_episode

    s = extract_episode(lane_follow_log.log_path, tmp_path, emit_tests=False, watchdog_s=5.0).summary
    assert s["findings"]["planner_hang"] is None and s["reproduced"]["0"] == s["frames"]


def test_a_mapping_field_missing_from_the_log_is_one_line_up_front(lane_follow_log, tmp_path):
    from extract import extract_episode
    from extract.mapping import MappingError, load_mapping

    mapping = load_mapping(ROOT / "configs" / "mappings" / "deft_gym.yaml").model_dump(by_alias=True)
    mapping["frame_time_field"] = "header.stamp_typo"
    with pytest.raises(MappingError, match=r"frame_time_field: 'header.stamp_typo' is in none") as err:
        extract_episode(lane_follow_log.log_path, tmp_path, mapping=mapping)
    assert "\n" not in str(err.value) and not (tmp_path / "summary.json").exists()


def test_the_robustness_watchdog_reports_a_blocking_module_by_wall_clock(tmp_path):
    """A planner that sleeps burns no CPU: the CPU-time watchdog alone never fires (the campaign
    hung); the wall-clock one reports it as a hang of planning."""
    import time

    from deft_gym.robustness.monitors import GuardedSupervisor
    from deft_gym.sim.simulation import Simulation

    sim = Simulation(LANE_FOLLOW, faulty_ads("sleep", sleep_s=60.0), jitter_seed=7)
    sup = GuardedSupervisor(sim.bus, deadline_s=0.2, wall_s=1.0)
    sim.bus.supervisor = sup
    t0 = time.perf_counter()
    with sup:
        sim.advance(10.0)
    assert time.perf_counter() - t0 < 20
    assert [(f.kind, f.node, f.reason) for f in sup.failures] == [("hang", "planning", "wall_deadline")]


# -- bad input: one line naming the file and the field, before any work ------------------------------
NAN = float("nan")
SCENARIO_FAULTS = {
    "nan participant position": (lambda d: d["participants"][0].__setitem__("s", NAN), "participants.0.static.s"),
    "inf participant position": (lambda d: d["participants"][0].__setitem__("s", float("inf")),
                                 "participants.0.static.s"),
    "absurd ego d": (lambda d: d["ego"].__setitem__("d", 1e6), "ego.d"),
    "participant on the ego": (lambda d: d["participants"].append(
        {"id": "x", "type": "static", "lane": list(d["ego"]["lane"]), "s": d["ego"]["s"]}), "participants.3"),
    "seed 1e23": (lambda d: d.__setitem__("seed", 1e23), "seed"),
    "nan heading": (lambda d: (d["ego"].pop("lane"), d["ego"].pop("s"),
                               d["ego"].update({"x": 10.0, "y": 0.0, "heading": NAN})), "ego.heading"),
    "nan waypoint": (lambda d: d["participants"].append(
        {"id": "v", "type": "scripted", "waypoints": [{"lane": ["a", "b", 1], "s": 30.0, "t": 0.0},
                                                      {"lane": ["a", "b", 1], "s": NAN, "t": 5.0}]}),
                     "participants.3.scripted.waypoints.1.s"),
    "duplicate ids": (lambda d: d["participants"].append(dict(d["participants"][0])), "participant ids must be unique"),
}


@pytest.mark.parametrize("fault", sorted(SCENARIO_FAULTS))
def test_bad_scenarios_are_one_line_errors_naming_file_and_field(fault, tmp_path):
    import yaml

    from deft_gym.config import ConfigError
    from deft_gym.scenarios.scenario import load_scenario

    mutate, field = SCENARIO_FAULTS[fault]
    data = yaml.safe_load(LANE_FOLLOW.read_text())
    mutate(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as err:
        load_scenario(path)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(f"{path}: ") and field in msg, msg


def _scenario_with(tmp_path, participants: list, pad: int = 0) -> Path:
    import yaml

    data = yaml.safe_load(LANE_FOLLOW.read_text())
    data["participants"] = participants
    path = tmp_path / "many.yaml"
    path.write_text(yaml.safe_dump(data) + "#" * pad)
    return path


def _cones(n: int, s0: float = 30.0) -> list:
    return [{"id": f"c{i}", "type": "static", "obstacle": "CONE", "lane": ["a", "b", 1], "s": s0 + (i % 1000) * 0.1,
             "d": 1.0 + (i // 1000) * 0.01} for i in range(n)]


def test_oversized_scenarios_are_one_line_before_parsing(tmp_path, capsys):
    """A 10 MB scenario of 120k participants took about a minute to parse and validate and its
    run could not finish (5000 participants run at a third of real time): a file over
    MAX_SCENARIO_BYTES is refused before it is parsed, more than MAX_PARTICIPANTS participants
    before each is validated, one line, exit 2."""
    import time

    from deft_gym.cli import run
    from deft_gym.scenarios.scenario import MAX_PARTICIPANTS, MAX_SCENARIO_BYTES

    big = _scenario_with(tmp_path, _cones(3), pad=MAX_SCENARIO_BYTES)
    t0 = time.perf_counter()
    assert run.main([str(big), "--reruns", "1", "--out", str(tmp_path / "out")]) == 2
    msg = " ".join(capsys.readouterr().out.split())
    assert msg.startswith(f"error: {big}: 2.0 MB; expected a scenario file of at most 2 MB"), msg
    many = _scenario_with(tmp_path, _cones(MAX_PARTICIPANTS + 1))
    assert run.main([str(many), "--reruns", "1", "--out", str(tmp_path / "out")]) == 2
    msg = " ".join(capsys.readouterr().out.split())
    assert msg.startswith(f"error: {many}: participants: ") and f"{MAX_PARTICIPANTS + 1} participants; expected at most" in msg
    assert time.perf_counter() - t0 < 30 and not (tmp_path / "out").exists()


def test_a_scenario_with_thousands_of_problems_lists_ten_and_counts_the_rest(tmp_path):
    from deft_gym.config import ConfigError
    from deft_gym.scenarios.scenario import MAX_PROBLEMS, load_scenario

    path = _scenario_with(tmp_path, _cones(600, s0=200.0))  # lane a-b-1 is 156 m long
    with pytest.raises(ConfigError) as err:
        load_scenario(path)
    lines = str(err.value).splitlines()
    assert len(lines) == MAX_PROBLEMS + 1 and lines[-1] == f"{path}: ... and {600 - MAX_PROBLEMS} more problem(s)"


ADS_FAULTS = {
    "world_hz 1e9": ("world_hz: 1.0e9\n", "world_hz"),
    "control rate 1e7": ("control:\n  rate_hz: 1.0e7\n", "control.rate_hz"),
    "inf processing time": ("perception:\n  processing: {mean_ms: .inf}\n", "perception.processing.mean_ms"),
    "unknown trigger role": ("planning:\n  trigger: nosuchrole\n", "planning.trigger"),
    "unknown planner class": ("planning:\n  planner:\n    class: nosuch.module:Planner\n", "planning.planner"),
    "unknown planner params": ("planning:\n  planner:\n    params: {bogus_param: 3}\n", "bogus_param"),
    "two roles on one topic": ("topics:\n  prediction: /apollo/planning\n",
                               "topics.prediction and topics.planning are both '/apollo/planning'"),
    "control on the chassis topic": ("topics:\n  control: /apollo/canbus/chassis\n",
                                     "topics.chassis and topics.control are both"),
    "empty topic name": ("topics:\n  planning: ''\n", "topics.planning: '' is not a topic name"),
    "viewer topic": ("topics:\n  planning: /deft_gym/scene\n", "topics.planning: '/deft_gym/scene' is reserved"),
}


@pytest.mark.parametrize("fault", sorted(ADS_FAULTS))
def test_bad_ads_configs_are_one_line_errors_and_exit_2_before_any_run(fault, tmp_path, capsys):
    from deft_gym.cli import run

    text, field = ADS_FAULTS[fault]
    path = tmp_path / "ads.yaml"
    path.write_text(text)
    out = tmp_path / "out"
    assert run.main([str(LANE_FOLLOW), "--ads-config", str(path), "--reruns", "1", "--out", str(out)]) == 2
    msg = " ".join(capsys.readouterr().out.split())  # the console may wrap
    assert msg.startswith(f"error: {path}: ") and field in msg and "Traceback" not in msg, msg
    assert not out.exists()


def test_a_topic_clash_in_an_ads_overlay_or_a_calibration_config_is_one_line(tmp_path, capsys):
    """Two roles on one topic used to be a KeyError traceback (run), a traceback from a worker
    with exit 1 (calibrate), or a run that 'completed' with control on the chassis topic; now one
    line naming the file (the overlay, for stress) and the field, exit 2, nothing written."""
    from agents import stress
    from deft_gym.cli import calibrate

    clash = tmp_path / "clash.yaml"
    clash.write_text("topics:\n  prediction: /apollo/planning\n")
    assert stress.main(["--ads-overlay", str(clash), "--budget", "1", "--out", str(tmp_path / "s"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {clash} (--ads-overlay): topics: ")
    assert "topics.prediction and topics.planning" in err
    assert calibrate.main(["--scenarios", "lane_follow_static", "--ads-config", str(clash), "--reruns", "1",
                           "--variants", "1", "--out", str(tmp_path / "c"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {clash}: topics: ")
    assert not (tmp_path / "s").exists() and not (tmp_path / "c").exists()


def test_stress_campaign_with_a_missing_invariants_file_is_a_setup_error(tmp_path, capsys):
    """A campaign set-up error exits 2 with one line before any run (it used to exit 0 with every
    test errored)."""
    from agents import stress

    code = stress.main(["--invariants", str(tmp_path / "missing.yaml"), "--budget", "1",
                        "--out", str(tmp_path / "campaign"), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "missing.yaml" in err
    assert not (tmp_path / "campaign").exists()


# -- kill -9 and resume ------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("program", ["evaluate", "calibrate"])
def test_kill_9_then_resume_loses_nothing_and_duplicates_nothing(program, tmp_path):
    """A campaign killed with SIGKILL (its whole process group, workers included) mid-run and run
    again with the same command ends with the records of an uninterrupted run: no finished work
    lost, nothing counted twice."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from deft_gym.execution import without_timings
    from deft_gym.files import read_jsonl

    if program == "evaluate":
        args = ["agents.evaluate", "--methods", "random,random_delta", "--budget", "4", "--scenarios",
                "lane_follow_static,take_exit", "--held-out", "0", "--placements", "closest", "--seed", "3",
                "--workers", "2", "--no-progress"]
        record, key = "records.jsonl", None
    else:
        args = ["deft_gym.cli.calibrate", "--scenarios", "take_exit", "lane_follow_static", "--variants", "2",
                "--cut-ins", "1", "--brakes", "0", "--reruns", "3", "--jitter-seed", "1000", "--workers", "2",
                "--no-progress"]
        record, key = "runs.jsonl", (lambda r: (r["key"], r["seed"]))
    root = Path(__file__).resolve().parent.parent
    full, cut = tmp_path / "full", tmp_path / "cut"
    assert subprocess.run([sys.executable, "-m", *args, "--out", str(full)], cwd=root, capture_output=True,
                          timeout=600).returncode == 0
    expected = read_jsonl(full / record)
    proc = subprocess.Popen([sys.executable, "-m", *args, "--out", str(cut)], cwd=root, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if (cut / record).exists() and len((cut / record).read_text().splitlines()) >= len(expected) // 3:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be killed; give it more work"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=60)
    killed_at = len(read_jsonl(cut / record))
    assert 0 < killed_at < len(expected)
    assert subprocess.run([sys.executable, "-m", *args, "--out", str(cut)], cwd=root, capture_output=True,
                          timeout=600).returncode == 0
    resumed = read_jsonl(cut / record)
    if key is None:  # evaluation records: in job order, identical to the uninterrupted run
        assert without_timings(resumed) == without_timings(expected)
    else:  # calibration runs: one per (variant, seed), the same outcomes
        assert sorted(map(key, resumed)) == sorted(map(key, expected))  # none lost, none twice
        strip = lambda rows: sorted((key(r), r["outcome"], r["collision"]) for r in rows)  # noqa: E731
        assert strip(resumed) == strip(expected)


@pytest.mark.parametrize("body, field", [
    ("algo_kwargs: {learning_rate: -1}", "algo_kwargs.learning_rate"),
    ("algo_kwargs: {n_steps: 0}", "algo_kwargs.n_steps"),
    ("algo_kwargs: {learnin_rate: 0.001}", "algo_kwargs.learnin_rate"),
    ("algo_kwargs: {gamma: .nan}", "algo_kwargs.gamma"),
    ("env: {scenarios: [no_such_scenario]}", "env.scenarios.0"),
])
def test_bad_training_settings_are_one_line_before_any_env_starts(body, field, tmp_path, capsys):
    """Hyper-parameters SB3 would reject (or silently accept) and scenario names that do not
    resolve: one line naming the file and the field, exit 2, no run folder (they used to be an
    AssertionError or a dead env worker's traceback)."""
    from agents import train

    cfg = tmp_path / "train.yaml"
    cfg.write_text(f"name: bad\ntimesteps: 8\n{body}\n")
    assert train.main(["--config", str(cfg), "--out", str(tmp_path / "run"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(cfg) in err and field in err, err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("body, field", [
    ("generation:\n  start_s: {min: 6.0, max: 2.0}\n", "generation.start_s"),
    ("generation:\n  window_s: {min: 0.1, max: .inf}\n", "generation.window_s"),
    ("generation:\n  roles: [no_such_role]\n", "generation.roles"),
])
def test_stress_policies_out_of_order_or_unknown_are_one_line(body, field, tmp_path, capsys):
    """Policy ranges with min > max or infinite bounds, and roles the spec does not know, are
    set-up errors (they used to be accepted and drawn from silently)."""
    from agents import stress

    cfg = tmp_path / "stress.yaml"
    cfg.write_text(body)
    assert stress.main(["--config", str(cfg), "--budget", "1", "--out", str(tmp_path / "c"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and field in err and str(cfg) in err, err
    assert not (tmp_path / "c").exists()


def test_training_settings_check_accepts_every_scenario_spec(tmp_path):
    """The up-front check resolves scenarios as the env does: names, gen:<seed> and <name>~v<seed>."""
    from agents.config import check_train_settings, load_train_config

    cfg = tmp_path / "train.yaml"
    cfg.write_text("name: ok\nenv: {scenarios: [left_turn, gen:3, lane_follow_static~v1000000, left_turn]}\n")
    check_train_settings(load_train_config(cfg), cfg)  # no ConfigError
