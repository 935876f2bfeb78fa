"""Fault injection: resume without loss, outputs that never collide, crashing and hanging modules,
bad inputs that must be one-line errors. Every test drives the real code (real logs, real
simulations, real SB3 checkpoints); the long ones are marked slow."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from deft_gym.envs.sink import EpisodeSink
from deft_gym.files import append_jsonl, first_line, read_jsonl

ROOT = Path(__file__).resolve().parent.parent


# -- data loss ---------------------------------------------------------------------------------
def test_one_line_errors_take_the_first_line_that_says_something():
    """Every one-line error names the exception's first non-blank line; an exception without a
    message (str() empty or blank) gives its type's name (or the caller's default), never an
    IndexError from inside the handler."""
    assert first_line(ValueError("bad field 'x'\n  more detail")) == "bad field 'x'"
    assert first_line(ValueError("\n\n   \n  the reason\nmore")) == "the reason"
    assert first_line(AssertionError()) == "AssertionError"
    assert first_line(RuntimeError("  \n "), default="") == ""


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


def test_an_append_after_a_line_cut_by_a_crash_keeps_its_record(tmp_path):
    """A record appended to a journal whose last line a crash cut (no newline) is not glued onto
    that fragment (it was, and the record - a resume marker, a finished test - was lost)."""
    path = tmp_path / "runs.jsonl"
    path.write_text('{"index": 0}\n{"index": 1, "outc')
    append_jsonl(path, {"index": 1})
    append_jsonl(path, {"index": 2})
    assert read_jsonl(path) == [{"index": 0}, {"index": 1}, {"index": 2}]


class Killed(BaseException):
    """A kill at a chosen point of a command run in-process (nothing after it runs)."""


def test_a_stress_campaign_killed_after_a_row_keeps_its_case_file(tmp_path, monkeypatch):
    """Killed right after a test's row reached runs.jsonl, a campaign resumed does not run that
    test again - so its case file must already be on disk (it was written after the row, and
    lost)."""
    from deft_gym.execution import Record
    from deft_gym.robustness.campaign import Campaign, load_campaign_config, run_campaign

    cfg = tmp_path / "stress.yaml"
    cfg.write_text(json.dumps({"scenarios": ["configs/scenarios/lane_follow_static.yaml"], "seeds_per_scenario": 1,
                               "generation": {"start_s": {"min": 2.0, "max": 6.0}}}))
    campaign, out = Campaign(load_campaign_config(cfg), seed=7), tmp_path / "c"
    add = Record.add

    def add_then_die(self, row):
        add(self, row)
        if row.get("findings"):
            raise Killed

    monkeypatch.setattr(Record, "add", add_then_die)
    with pytest.raises(Killed):
        run_campaign(campaign, out, budget=3, minimise_findings="none")
    monkeypatch.undo()
    s = run_campaign(campaign, out, budget=3, minimise_findings="none")
    rows = read_jsonl(out / "runs.jsonl")
    assert sorted(r["index"] for r in rows) == [0, 1, 2] and s["runs_with_findings"] > 0
    assert {p.name for p in (out / "cases").iterdir()} == {f"run_{r['index']:05d}.json" for r in rows if r["findings"]}


def test_resume_sets_aside_what_came_after_its_checkpoint_and_deletes_nothing(tmp_path):
    """The rollback of a resume (agents.train.roll_back), on the files a killed run leaves: the
    Monitor rows, kept logs, unfinished logs and progress lines after the checkpoint go to
    rolled_back/, the rest stays as it was; a second rollback (a resume killed and resumed
    again) duplicates nothing; a Monitor CSV without env_steps (an older run) is cut by lengths."""
    from agents.train import monitor_totals, roll_back, summarize_run

    head = '#{"t_start": 1.0, "env_id": "None"}\nr,l,t,failure,scenario,valid,iou,outcome,env_steps\n'
    rows = ["1.0,10,1.0,,s,True,1.0,completed,10\n", "2.0,12,2.0,collision,s,True,1.0,collision,22\n",
            "3.0,8,3.0,,s,False,1.0,stuck,30\n", "4.0,5,4.0,nods,s,True,0.1,completed,35\n"]
    (tmp_path / "monitor").mkdir()
    monitor = tmp_path / "monitor" / "env0.monitor.csv"
    monitor.write_text(head + "".join(rows) + "5.0,3,5.0,,s")  # the last row cut by the kill
    old = tmp_path / "monitor" / "env1.monitor.csv"  # an older run's columns: the sums of l say where
    old.write_text('#{}\nr,l,t,failure,scenario,valid,iou\n1.0,10,1.0,,s,True,1.0\n2.0,20,2.0,,s,True,1.0\n')
    for i, (steps, fail) in enumerate([(10, None), (22, "collision"), (30, None), (35, "nods")], 1):
        d = tmp_path / "episodes" / f"w0-{i:06d}-s"
        d.mkdir(parents=True)
        (d / "episode.mcap").write_bytes(b"log")
        append_jsonl(tmp_path / "episodes-0.jsonl", {"scenario": "s", "valid": True, "failure": fail,
                                                     "env_steps": steps, "kept": True, "dir": str(d)})
    (tmp_path / "episodes" / "w0-000005-s").mkdir()  # the episode the kill cut: no journal line
    (tmp_path / "episodes" / "w1-000001-s").mkdir()  # another env's, before the checkpoint
    append_jsonl(tmp_path / "episodes-1.jsonl", {"scenario": "s", "valid": True, "failure": None, "env_steps": 20,
                                                 "kept": True, "dir": str(tmp_path / "episodes" / "w1-000001-s")})
    progress = tmp_path / "progress.jsonl"
    for t in (20, 40, 60, 80):
        append_jsonl(progress, {"timesteps": t, "episodes": t // 10})
    before = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "episodes").iterdir()}

    for _ in range(2):
        roll_back(tmp_path, 1, 24, 48, tmp_path / "checkpoints" / "ppo_48_steps.zip")
        roll_back(tmp_path, 2, 24, 48, tmp_path / "checkpoints" / "ppo_48_steps.zip")  # env1 too
    aside = tmp_path / "rolled_back"
    assert monitor.read_text() == head + "".join(rows[:2])
    assert (aside / "monitor" / "env0.monitor.csv").read_text() == head + "".join(rows[2:]) + "5.0,3,5.0,,s\n"
    assert old.read_text().splitlines()[2:] == ["1.0,10,1.0,,s,True,1.0"]
    assert (aside / "monitor" / "env1.monitor.csv").read_text().splitlines()[2:] == ["2.0,20,2.0,,s,True,1.0"]
    assert sorted(p.name for p in (tmp_path / "episodes").iterdir()) == ["w0-000001-s", "w0-000002-s",
                                                                        "w1-000001-s"]
    assert sorted(p.name for p in (aside / "episodes").iterdir()) == ["w0-000003-s", "w0-000004-s", "w0-000005-s"]
    assert all(p.stat().st_mtime_ns == before[p.name] for p in (tmp_path / "episodes").iterdir())
    assert (aside / "episodes" / "w0-000004-s" / "episode.mcap").read_bytes() == b"log"
    assert [r["timesteps"] for r in read_jsonl(progress)] == [20, 40]
    assert [r["timesteps"] for r in read_jsonl(aside / "progress.jsonl")] == [60, 80]
    s = summarize_run(tmp_path)
    assert (s["episodes"], s["collisions"], s["nods"], s["rolled_back_episodes"]) == (3, 1, 0, 2)
    assert monitor_totals(tmp_path) == {"episodes": 3, "valid": 3, "collision": 1, "outcome_completed": 1,
                                        "outcome_collision": 1}
    (aside / "episodes" / "w0-000020-s").mkdir()
    sink = EpisodeSink(tmp_path, worker=0, extract=False)
    assert sink.episode_dir("s").name == "w0-000021-s"  # a number set aside is not used again


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
    """Train, then go on from the final model: the Monitor CSV and the journal only grow, every
    kept episode folder of the first session is still there, numbering continues."""
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
    assert not list((out / "checkpoints").glob("*.tmp*"))
    assert train.main(["--config", str(cfg), "--out", str(out), "--resume", str(out / "model.zip"), "--timesteps",
                       "72", "--no-progress"]) == 0
    rows1 = monitor.read_text().splitlines()
    assert rows1[:len(rows0)] == rows0 and len(rows1) > len(rows0)  # appended, one header
    assert sum(1 for r in rows1 if r.startswith("r,l,t")) == 1
    kept1 = {p.name: p.stat().st_mtime_ns for p in (out / "episodes").iterdir()}
    assert all(kept1.get(k) == v for k, v in kept0.items())  # nothing of the first session touched
    journal1 = read_jsonl(out / "episodes-0.jsonl")
    assert journal1[:len(journal0)] == journal0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["episodes"] == len(journal1) - 1 == len(rows1) - 2  # one resume marker; two header lines
    assert summary["rolled_back_episodes"] == 0 and not (out / "rolled_back").exists()  # it went on from the end


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


@pytest.mark.slow
def test_pictures_cut_by_a_kill_are_drawn_again(tmp_path, lane_follow_log, monkeypatch):
    """A kill while a failure's video is written leaves no picture under its final name, so the
    next render draws both (the plot came first and said "done": the video stayed broken)."""
    import imageio.v2 as imageio

    from deft_gym.viz.episode import render_failures

    d = tmp_path / "episodes" / "w0-000001-lane_follow_static"
    d.mkdir(parents=True)
    shutil.copy(lane_follow_log.log_path, d / "episode.mcap")
    (d / "episode.json").write_text('{"failure": "nods"}')

    def half_then_die(path, *args, **kwargs):
        Path(path).write_bytes(b"\x00\x00\x00\x18ftypmp42")  # the start of a video
        raise Killed

    monkeypatch.setattr(imageio, "mimsave", half_then_die)
    with pytest.raises(Killed):
        render_failures(tmp_path / "episodes")
    monkeypatch.undo()
    assert sorted(p.name for p in d.iterdir()) == ["episode.json", "episode.mcap"]
    assert len(render_failures(tmp_path / "episodes")) == 1
    assert imageio.get_reader(d / "video.mp4").count_frames() > 10 and (d / "plot.png").stat().st_size > 0


def test_demo_never_deletes_folders_it_did_not_write(tmp_path, capsys):
    from deft_gym.cli import demo

    (tmp_path / "train").mkdir()
    (tmp_path / "train" / "precious.txt").write_text("not the demo's")
    assert demo.main(["--out", str(tmp_path), "--timesteps", "8"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "did not write" in err
    assert (tmp_path / "train" / "precious.txt").exists()


# -- failures never hidden: crashing, hanging, NaN-emitting and silent modules ----------------------
FAULTY = "tests.support.fault_planners:FaultyPlanner"
LANE_FOLLOW = ROOT / "configs" / "scenarios" / "lane_follow_static.yaml"


def faulty_ads(fault: str, after: int = 20, **params):
    from deft_gym.bus.ads import load_ads_config
    from deft_gym.experiments.record import ads_overrides

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
    import numpy

    from deft_gym.bus.messages import non_finite_field

    nan, inf = float("nan"), float("inf")
    assert non_finite_field({"header": {"seq": 1, "stamp": 0.5, "module": "m"}, "a": [1.0, 2], "b": [],
                             "c": ["x", 3], "d": {}, "e": None, "f": True, "g": 10**400}) is None
    assert non_finite_field({"trajectory": {"t": [0.0, 0.1], "x": [1.0, nan]}}) == "trajectory.x.1"
    assert non_finite_field({"obstacles": [{"id": "a", "v": 1.0}, {"id": "b", "v": -inf}]}) == "obstacles.1.v"
    assert non_finite_field({"xs": [1e308, 1e308]}) is None  # a sum that overflows is not a NaN
    assert non_finite_field({"xs": [1.0, "x", inf]}) == "xs.2" and non_finite_field(nan) == ""
    # lists that are not numbers at both ends, bools, a tuple, a numpy float, an int beyond floats
    assert non_finite_field({"xs": ["x", nan]}) == "xs.1" and non_finite_field({"xs": [nan, "x"]}) == "xs.0"
    assert non_finite_field({"xs": [True, nan, 1]}) == "xs.1" and non_finite_field((1, 2, inf)) == "2"
    assert non_finite_field({"xs": [1.0, numpy.float64("nan")]}) == "xs.1"
    assert non_finite_field({"xs": [10**400, 1.0, nan]}) == "xs.2"
    # numpy makes an array of a numpy float plus a ragged list, and raised out of the check
    assert non_finite_field([1.0, numpy.float64(1.0), [1.0, [nan]], 2.0]) == "2.1.0"


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


def test_the_robustness_deadline_leaves_out_the_garbage_collectors_pauses():
    """A full collection of a large heap inside a module computation is the process's pause, not
    the module's CPU (its length depends on everything the process holds: a test worker's heap
    once made a hang of a planning call). It is no hang; a computation that burns its CPU past the
    deadline still is one."""
    import gc
    import time
    from types import SimpleNamespace

    from deft_gym.robustness.monitors import GuardedSupervisor

    heap = [[i] for i in range(2_000_000)]  # tracked objects: a full collection walks them all
    t0 = time.process_time()
    gc.collect()
    pause = time.process_time() - t0
    deadline = pause / 4
    sup = GuardedSupervisor(SimpleNamespace(now=0.0), deadline_s=deadline, wall_s=30.0)

    def spin(seconds: float) -> None:
        end = time.process_time() + seconds
        while time.process_time() < end:
            pass

    collecting, spinning = SimpleNamespace(name="planning", alive=True, busy=False), \
        SimpleNamespace(name="control", alive=True, busy=False)
    with sup:
        sup.run(collecting, lambda: (gc.collect(), gc.collect(), spin(deadline / 4)))
        assert sup.failures == []
        sup.run(spinning, spin, 4 * deadline)
    assert [(f.kind, f.node, f.reason) for f in sup.failures] == [("hang", "control", "deadline")]
    assert collecting.alive and not spinning.alive and len(heap) == 2_000_000


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
    from deft_gym.cli import calibrate
    from deft_gym.robustness import stress

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
    from deft_gym.robustness import stress

    code = stress.main(["--invariants", str(tmp_path / "missing.yaml"), "--budget", "1",
                        "--out", str(tmp_path / "campaign"), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "missing.yaml" in err
    assert not (tmp_path / "campaign").exists()


# -- kill -9 and resume ------------------------------------------------------------------------------
def run_module(args: list[str], out: Path) -> None:
    """``python -m ARGS --out OUT`` to its end; it must succeed."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", *args, "--out", str(out)], cwd=ROOT, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]


def kill_9_when(args: list[str], out: Path, ready, timeout: float = 300) -> None:
    """Start ``python -m ARGS --out OUT`` in its own process group, wait until ``ready()`` says
    enough finished work is on disk, then SIGKILL the whole group (workers included)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    proc = subprocess.Popen([sys.executable, "-m", *args, "--out", str(out)], cwd=ROOT, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + timeout
        while time.time() < deadline and proc.poll() is None and not ready():
            time.sleep(0.05)
        assert proc.poll() is None, "the run ended before it could be killed; give it more work"
        assert ready(), f"no finished work to kill after within {timeout} s"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=60)


def lines_at_least(path: Path, n: int):
    """A ``ready`` for :func:`kill_9_when`: ``path`` holds at least ``n`` complete records."""
    return lambda: len(read_jsonl(path)) >= n


@pytest.mark.slow
@pytest.mark.parametrize("program", ["evaluate", "calibrate"])
def test_kill_9_then_resume_loses_nothing_and_duplicates_nothing(program, tmp_path):
    """A campaign killed with SIGKILL (its whole process group, workers included) mid-run and run
    again with the same command ends with the records of an uninterrupted run: no finished work
    lost, nothing counted twice."""
    from deft_gym.execution import without_timings

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
    full, cut = tmp_path / "full", tmp_path / "cut"
    run_module(args, full)
    expected = read_jsonl(full / record)
    kill_9_when(args, cut, lines_at_least(cut / record, max(len(expected) // 3, 1)))
    killed_at = len(read_jsonl(cut / record))
    assert 0 < killed_at < len(expected)
    run_module(args, cut)
    resumed = read_jsonl(cut / record)
    if key is None:  # evaluation records: in job order, identical to the uninterrupted run
        assert without_timings(resumed) == without_timings(expected)
    else:  # calibration runs: one per (variant, seed), the same outcomes
        assert sorted(map(key, resumed)) == sorted(map(key, expected))  # none lost, none twice
        strip = lambda rows: sorted((key(r), r["outcome"], r["collision"]) for r in rows)  # noqa: E731
        assert strip(resumed) == strip(expected)


@pytest.mark.slow
def test_kill_9_of_a_stress_campaign_in_its_tests_then_in_its_minimisation(tmp_path):
    """A robustness campaign killed while it runs its tests, resumed, killed again while it
    minimises its findings and resumed again ends with the rows, case files, minimised cases and
    summary of an uninterrupted campaign; no test row twice, no finished minimisation redone."""
    from deft_gym.execution import without_timings

    cfg = tmp_path / "stress.yaml"
    cfg.write_text(json.dumps({"scenarios": ["configs/scenarios/lane_follow_static.yaml"], "seeds_per_scenario": 1,
                               "generation": {"start_s": {"min": 2.0, "max": 6.0}},
                               "minimise": {"max_signatures": 7, "max_replays": 6}}))
    args = ["deft_gym.robustness.stress", "--config", str(cfg), "--budget", "16", "--seed", "7", "--workers", "2",
            "--render", "none", "--quiet"]
    full, cut = tmp_path / "full", tmp_path / "cut"
    run_module(args, full)
    expected = read_jsonl(full / "runs.jsonl")
    kill_9_when(args, cut, lines_at_least(cut / "runs.jsonl", 6))
    assert 6 <= len(read_jsonl(cut / "runs.jsonl")) < len(expected)
    infos = lambda out: sorted((out / "minimised").glob("*.info.json"))  # noqa: E731
    kill_9_when(args, cut, lambda: len(infos(cut)) >= 1)
    assert 1 <= len(infos(cut)) < len(infos(full))
    first = {p.name: p.stat().st_mtime_ns for p in infos(cut)}
    run_module(args, cut)
    rows = read_jsonl(cut / "runs.jsonl")
    assert sorted(r["index"] for r in rows) == list(range(16))  # none lost, none twice
    by_index = lambda rs: without_timings(sorted(rs, key=lambda r: r["index"]))  # noqa: E731
    assert by_index(rows) == by_index(expected)
    assert without_timings(read_jsonl(cut / "baseline.jsonl")) == without_timings(read_jsonl(full / "baseline.jsonl"))
    files = lambda out, d: {p.name: p.read_text() for p in sorted((out / d).glob("*.json"))}  # noqa: E731
    assert files(cut, "cases") == files(full, "cases")
    assert {p.name for p in infos(cut)} == {p.name for p in infos(full)}
    assert all((cut / "minimised" / n).stat().st_mtime_ns == t for n, t in first.items())  # not redone
    summary = lambda out: without_timings({k: v for k, v in json.loads((out / "summary.json").read_text()).items()  # noqa: E731
                                           if k not in ("wall_time_s", "test_wall_time_s")})
    assert summary(cut) == summary(full)


@pytest.mark.slow
def test_kill_9_of_a_folder_extraction_then_resume_redoes_nothing_finished(tmp_path, lane_follow_log):
    """``deft-gym extract DIR`` killed after some episodes are extracted and run again: the
    finished episodes are skipped (their files untouched), the others extracted, the batch summary
    lists every log once, as an uninterrupted extraction does."""
    logs = tmp_path / "logs"
    for i in range(12):
        (logs / f"run{i:02d}").mkdir(parents=True)
        shutil.copy(lane_follow_log.log_path, logs / f"run{i:02d}" / "episode.mcap")
    args = ["deft_gym.cli.extract", str(logs), "--workers", "2", "--no-progress", "--render", "none", "--quiet"]
    full, cut = tmp_path / "full", tmp_path / "cut"
    run_module(args, full)
    done = lambda: sorted(cut.glob("run*/summary.json"))  # noqa: E731
    kill_9_when(args, cut, lambda: len(done()) >= 4)
    finished = {p.parent.name: {f.name: f.stat().st_mtime_ns for f in p.parent.iterdir()} for p in done()}
    assert 4 <= len(finished) < 12 and not (cut / "summary.json").exists()
    run_module(args, cut)
    for name, files in finished.items():  # not redone
        assert {f.name: f.stat().st_mtime_ns for f in (cut / name).iterdir()} == files
    keys = ("log", "scenario", "frames", "reproduced", "faulty_trajectory", "error")
    batch = lambda out: json.loads((out / "summary.json").read_text())  # noqa: E731
    listed = lambda out: [{k: e[k] for k in keys} for e in batch(out)["episodes_list"]]  # noqa: E731
    assert listed(cut) == listed(full) and len(listed(cut)) == 12  # every log once, the same results
    assert sorted(e["log"] for e in batch(cut)["episodes_list"] if e.get("skipped")) == \
        sorted(str(logs / n / "episode.mcap") for n in finished)
    for k in ("episodes", "failed", "frames", "reproduced", "collisions"):
        assert batch(cut)[k] == batch(full)[k]


TINY_TRAIN = ("name: tiny\nalgo: ppo\ntimesteps: 128\nseed: 0\nn_envs: 2\nvec_env: dummy\ncheckpoint_every: 32\n"
              "algo_kwargs: {n_steps: 8, batch_size: 16, n_epochs: 1}\nlog_episodes: true\n"
              "env: {scenarios: [lane_follow_static], record: all, keep_passing: 1.0, extract: false}\n")


def monitor_rows(path: Path) -> list[tuple[str, dict[str, str]]]:
    """The rows of a Monitor CSV: (line, fields)."""
    import csv

    if not path.exists():
        return []
    lines = path.read_text().splitlines()
    cols = next(csv.reader([lines[1]]))
    return [(line, dict(zip(cols, next(csv.reader([line]))))) for line in lines[2:]]


@pytest.mark.slow
def test_kill_9_of_training_then_resume_from_the_last_checkpoint(tmp_path):
    """Training killed with SIGKILL after a checkpoint, some episodes later, and resumed from that
    checkpoint: the Monitor CSVs, journals, summary and ``episodes/`` hold exactly the episodes of
    the final model's history - everything before the checkpoint untouched, the episodes after it
    (and the logs of those cut by the kill) set aside under ``rolled_back/``, nothing deleted."""
    from stable_baselines3.common.save_util import load_from_zip_file

    from agents.train import journal_records

    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(TINY_TRAIN)
    out = tmp_path / "run"
    args = ["agents.train", "--config", str(cfg), "--no-progress"]

    def checkpoint() -> tuple[int, Path | None]:
        found = [(int(p.name.split("_")[1]), p) for p in (out / "checkpoints").glob("ppo_*_steps.zip")]
        return max(found, default=(0, None))

    def ready() -> bool:  # a checkpoint, and an episode ended after it
        steps, _ = checkpoint()
        return steps > 0 and any(int(f.get("env_steps") or 0) > steps // 2 for rank in (0, 1)
                                 for _, f in monitor_rows(out / "monitor" / f"env{rank}.monitor.csv"))

    kill_9_when(args, out, ready)
    steps, ckpt = checkpoint()
    step0 = steps // 2
    data, _, _ = load_from_zip_file(ckpt, device="cpu")
    assert data["num_timesteps"] == steps and data["_n_updates"] == steps // 16  # learned from every step before it
    at_kill = {rank: monitor_rows(out / "monitor" / f"env{rank}.monitor.csv") for rank in (0, 1)}
    journal_at_kill = {rank: read_jsonl(out / f"episodes-{rank}.jsonl") for rank in (0, 1)}
    folders_at_kill = {p.name: p.stat().st_mtime_ns for p in (out / "episodes").iterdir()}
    assert not (out / "model.zip").exists()

    run_module([*args, "--resume", str(ckpt)], out)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["timesteps"] == 128
    counted, rolled, kept_logs = 0, 0, set()
    for rank in (0, 1):
        rows = monitor_rows(out / "monitor" / f"env{rank}.monitor.csv")
        aside = monitor_rows(out / "rolled_back" / "monitor" / f"env{rank}.monitor.csv")
        before = [r for r in at_kill[rank] if int(r[1]["env_steps"]) <= step0]
        assert rows[:len(before)] == before  # nothing of the model's history lost, nothing moved
        assert aside == [r for r in at_kill[rank] if int(r[1]["env_steps"]) > step0]  # the rest kept aside
        ends = [int(f["env_steps"]) for _, f in rows]
        starts = [e - int(f["l"]) for e, (_, f) in zip(ends, rows)]
        assert all(s >= e for s, e in zip(starts[1:], ends)) and ends[-1] <= 64  # one history, no overlap
        assert all(s >= step0 for s, e in zip(starts, ends) if e > step0)  # nothing straddles the rollback
        recs, gone = journal_records(out / f"episodes-{rank}.jsonl")
        assert [(r["env_steps"], r["scenario"]) for r in recs] == [(e, f["scenario"]) for e, (_, f) in zip(ends, rows)]
        journal = read_jsonl(out / f"episodes-{rank}.jsonl")
        assert journal[:len(journal_at_kill[rank])] == journal_at_kill[rank]  # append-only
        seeds = lambda rs: {r["jitter_seed"] for r in rs if "jitter_seed" in r}  # noqa: E731
        assert not seeds(journal_at_kill[rank]) & seeds(journal[len(journal_at_kill[rank]):])  # not the start again
        assert len(aside) <= len(gone) <= len(aside) + 1  # + an episode killed between journal and Monitor
        counted += len(rows)
        rolled += len(gone)
        kept_logs |= {Path(r["dir"]).name for r in recs}
    assert (summary["episodes"], summary["rolled_back_episodes"]) == (counted, rolled) and rolled > 0
    assert summary["episodes_this_session"] == counted - sum(
        1 for rank in (0, 1) for r in journal_at_kill[rank] if r.get("env_steps", 0) <= step0)
    folders = {p.name: p.stat().st_mtime_ns for p in (out / "episodes").iterdir()}
    aside_logs = {p.name for p in (out / "rolled_back" / "episodes").iterdir()}
    assert set(folders) == kept_logs and not set(folders) & aside_logs  # every counted episode's log, no other
    assert set(folders_at_kill) == (set(folders_at_kill) & set(folders)) | aside_logs  # none lost
    assert all(folders[n] == t for n, t in folders_at_kill.items() if n in folders)  # untouched


@pytest.mark.parametrize("body, field", [
    ("algo_kwargs: {learning_rate: -1}", "algo_kwargs.learning_rate"),
    ("algo_kwargs: {n_steps: 0}", "algo_kwargs.n_steps"),
    ("algo_kwargs: {learnin_rate: 0.001}", "algo_kwargs.learnin_rate"),
    ("algo_kwargs: {gamma: .nan}", "algo_kwargs.gamma"),
    ("env: {scenarios: [no_such_scenario]}", "env.scenarios.0"),
    ("init_model: no/such/model.zip", "init_model"),
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
    from deft_gym.robustness import stress

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


def test_a_training_config_builds_on_its_base(tmp_path):
    """``base: other.yaml`` in a training config: that file with this one's keys deep-merged on top
    (as for ADS configs); a base that leads back to the file is one line naming it."""
    from agents.config import load_train_config
    from deft_gym.config import ConfigError

    (tmp_path / "a.yaml").write_text("name: a\nseed: 1\nalgo_kwargs: {n_steps: 256, batch_size: 64}\n"
                                     "env: {scenarios: [left_turn, u_turn]}\n")
    (tmp_path / "b.yaml").write_text("base: a.yaml\nname: b\nalgo_kwargs: {n_steps: 512}\n")
    a, b = load_train_config(tmp_path / "a.yaml"), load_train_config(tmp_path / "b.yaml")
    assert (b.name, b.seed, b.algo_kwargs, b.env.scenarios) == ("b", 1, {"n_steps": 512, "batch_size": 64},
                                                                 ["left_turn", "u_turn"])
    assert a.model_dump(exclude={"name", "algo_kwargs"}) == b.model_dump(exclude={"name", "algo_kwargs"})
    (tmp_path / "c.yaml").write_text("base: c.yaml\n")
    with pytest.raises(ConfigError, match=r"c\.yaml: base: 'c\.yaml' leads back to itself"):
        load_train_config(tmp_path / "c.yaml")


def test_sink_keeps_one_log_per_distinct_failure_and_names_it_in_the_duplicates_lines(tmp_path):
    """With ``distinct``, a failure whose (scenario, signature) the worker already kept - in this
    session or in the journal of a run it resumes, while that log is in place - is journalled with
    ``duplicate_of`` and gets no log; a new signature or scenario is kept."""
    earlier = tmp_path / "episodes" / "w0-000001-s"
    earlier.mkdir(parents=True)
    append_jsonl(tmp_path / "episodes-0.jsonl", {"scenario": "s", "failure": "nods", "signature": "old",
                                                 "kept": True, "dir": str(earlier)})
    sink = EpisodeSink(tmp_path, worker=0, keep_passing=0.0, extract=False, distinct=True)
    first = {"scenario": "s", "failure": "nods", "signature": "nods@30m:left"}
    assert sink.keeps(first)
    d = sink.episode_dir("s")
    assert sink.finish(d, first, {}, keep=True)["kept"] and (d / "episode.json").exists()
    again = sink.finish(None, dict(first), {}, keep=sink.keeps(first))
    assert not again["kept"] and again["duplicate_of"] == str(d)
    assert sink.finish(None, {**first, "signature": "old"}, {}, keep=False)["duplicate_of"] == str(earlier)
    assert sink.keeps({**first, "signature": "collision@10m"}) and sink.keeps({**first, "scenario": "t"})
    lines = read_jsonl(tmp_path / "episodes-0.jsonl")
    assert [x.get("duplicate_of") for x in lines[1:]] == [None, str(d), str(earlier)]
    assert EpisodeSink(tmp_path, worker=0, extract=False).keeps(first)  # keep_duplicates: every failure


def test_shared_sinks_skip_a_failure_another_worker_kept_at_an_earlier_env_step_only(tmp_path):
    """With ``shared``, worker 1 does not keep a failure worker 0 kept at an earlier env step, and
    names worker 0's log; one kept at the same step (which worker 1 could not be sure to see, the
    workers running concurrently) or later is kept again, and so is everything without ``shared``."""
    w0 = EpisodeSink(tmp_path, worker=0, keep_passing=0.0, extract=False, distinct=True, shared=True)
    w1 = EpisodeSink(tmp_path, worker=1, keep_passing=0.0, extract=False, distinct=True, shared=True)
    fail = {"scenario": "s", "failure": "nods", "signature": "nods@30m:left"}
    w0.steps = 5
    d0 = w0.episode_dir("s")
    assert w0.finish(d0, fail, {}, keep=w0.keeps(fail))["kept"]
    w1.steps = 5  # the same vec-env step: not visible to worker 1 whatever the timing
    assert w1.keeps(fail)
    with open(tmp_path / "episodes-0.jsonl", "ab") as fh:  # worker 0 in the middle of its next line
        fh.write(b'{"env_steps": 6, "failure": "nods", "kept": tru')
    w1.steps = 6
    assert not w1.keeps(fail)
    assert w1.finish(None, dict(fail), {}, keep=False)["duplicate_of"] == str(d0)
    assert w1.keeps({**fail, "signature": "collision@10m"})
    alone = EpisodeSink(tmp_path, worker=2, keep_passing=0.0, extract=False, distinct=True)
    alone.steps = 9
    assert alone.keeps(fail)  # not shared: only its own failures count


# == issue 34: a planner cannot take the tool down, no output folder is shared, nothing silently wrong ==
PY = __import__("sys").executable


def one_line(err: str) -> str:
    """The single line a refused command printed (it must be one)."""
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err.strip()


# -- 1. one writer per output folder ------------------------------------------------------------------
def hold(folder: Path):
    """Another process holding ``folder`` (deft_gym.files.folder_lock) until it is killed."""
    import subprocess

    proc = subprocess.Popen([PY, "-c", "import sys, time\nfrom deft_gym.files import folder_lock\n"
                             f"with folder_lock({str(folder)!r}, 'the holder'):\n    print('held', flush=True)\n"
                             "    time.sleep(600)\n"], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


WRITERS = {
    "run": ("deft_gym.cli.run", [str(LANE_FOLLOW), "--reruns", "1", "--render", "none"]),
    "calibrate": ("deft_gym.cli.calibrate", ["--scenarios", "lane_follow_static", "--variants", "1", "--cut-ins", "0",
                                              "--brakes", "0", "--reruns", "1", "--workers", "1", "--no-progress"]),
    "stress": ("deft_gym.robustness.stress", ["--scenarios", "lane_follow_static", "--budget", "1", "--workers", "1",
                                              "--quiet"]),
    "evaluate": ("agents.evaluate", ["--methods", "random", "--budget", "1", "--held-out", "0", "--scenarios",
                                     "lane_follow_static", "--workers", "1", "--no-progress"]),
    "generate": ("deft_gym.cli.generate", ["--seeds", "0"]),
    "record": ("deft_gym.experiments.record", [str(LANE_FOLLOW)]),
    "train": ("agents.train", ["--config", "configs/train/demo.yaml", "--timesteps", "8", "--no-progress"]),
}


@pytest.mark.parametrize("program", sorted(WRITERS))
def test_a_second_writer_of_an_output_folder_is_one_line_naming_the_holder(program, tmp_path, capsys):
    """Two programs into one --out both ran (equal seeds: a traceback; campaigns did all the work
    twice and doubled their records): a second writer is now refused at once, one line naming the
    folder and the process that holds it, exit 2, and writes nothing."""
    import importlib

    module, argv = WRITERS[program]
    out = tmp_path / "out"
    holder = hold(out)
    try:
        with pytest.raises(SystemExit) as exc:
            importlib.import_module(module).main([*argv, "--out", str(out)])
        assert exc.value.code == 2
        err = one_line(capsys.readouterr().err)
        assert err.startswith(f"error: {out} is being written by another process (pid {holder.pid}") and \
            "the holder" in err
        assert [p.name for p in out.iterdir()] == [".deft-gym.lock"]
    finally:
        holder.kill()
        holder.wait()


def test_the_extraction_into_a_busy_folder_is_refused_too(lane_follow_log, tmp_path, capsys):
    from deft_gym.cli import extract

    holder = hold(tmp_path / "x")
    try:
        with pytest.raises(SystemExit) as exc:
            extract.main([lane_follow_log.log_path, "--out", str(tmp_path / "x"), "--render", "none"])
        assert exc.value.code == 2 and f"pid {holder.pid}" in one_line(capsys.readouterr().err)
    finally:
        holder.kill()
        holder.wait()


def test_a_lock_left_by_a_killed_writer_never_blocks(tmp_path):
    """The lock is flock on OUT/.deft-gym.lock: the kernel drops it with its process, kill -9
    included, so the next run goes ahead (and the file names the last holder)."""
    from deft_gym.cli import run

    out = tmp_path / "out"
    holder = hold(out)
    holder.kill()  # SIGKILL
    holder.wait()
    assert (out / ".deft-gym.lock").exists()
    assert run.main([str(LANE_FOLLOW), "--reruns", "1", "--jitter-seed", "7", "--render", "none", "--quiet",
                     "--out", str(out)]) == 0
    assert json.loads((out / "summary.json").read_text())["reruns"][0]["outcome"] == "completed"


def test_two_runs_started_together_into_one_folder_one_runs_the_other_is_refused(tmp_path):
    """Two `deft-gym run` started at the same moment into one --out (both used to exit 0, and only
    the second's logs remained): exactly one runs and keeps all its logs, the other exits 2
    naming the first."""
    import subprocess

    out = tmp_path / "out"
    # 8 reruns hold the folder for seconds: two runs of 2 could miss each other when one process's
    # start-up is slow (a loaded machine, a fresh venv compiling its bytecode) and both exit 0
    cmd = [PY, "-m", "deft_gym.cli.run", str(LANE_FOLLOW), "--reruns", "8", "--jitter-seed", "7", "--render", "none",
           "--quiet", "--out", str(out)]
    procs = [subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    assert sorted(code for code, _ in results) == [0, 2], results
    (err,) = [e for code, e in results if code == 2]
    assert "is being written by another process" in one_line(err)
    rows = json.loads((out / "summary.json").read_text())["reruns"]
    assert [r["rerun"] for r in rows] == list(range(8)) and all(Path(r["log"]).exists() for r in rows)


def test_a_folder_a_refused_run_created_is_not_left_behind(tmp_path, capsys):
    from deft_gym.files import folder_lock

    with folder_lock(tmp_path / "a" / "b"):
        pass
    assert not (tmp_path / "a").exists()
    with folder_lock(tmp_path / "c") as d:
        (d / "kept.txt").write_text("work")
    assert (tmp_path / "c" / "kept.txt").exists()


def test_a_full_or_read_only_disk_under_out_is_one_line(tmp_path, monkeypatch, capsys):
    """ENOSPC while a run writes, or an --out that cannot be created: one line naming the file,
    never a traceback."""
    import errno

    from deft_gym.cli import run

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "out" / "0" / "episode.mcap.tmp"))

    monkeypatch.setattr(run, "_reruns", full)
    with pytest.raises(SystemExit) as exc:
        run.main([str(LANE_FOLLOW), "--reruns", "1", "--out", str(tmp_path / "out")])
    assert exc.value.code == 1
    assert "No space left on device" in one_line(capsys.readouterr().err)
    monkeypatch.undo()
    with pytest.raises(SystemExit) as exc:
        run.main([str(LANE_FOLLOW), "--reruns", "1", "--out", "/proc/deft_gym_not_writable/out"])
    assert exc.value.code == 2 and "cannot write the output folder" in one_line(capsys.readouterr().err)


# -- 2. a planner that tries to end the program is an outcome ------------------------------------------
ENDINGS = [("exit", "inline", "SystemExit: 4"), ("interrupt", "inline", "KeyboardInterrupt"),
           ("base", "inline", "PlantedBaseException: planted"), ("exit", "process", "SystemExit: 4"),
           ("interrupt", "auto", "KeyboardInterrupt"), ("os_exit", "auto", "exited with status 3"),
           ("segfault", "auto", "killed by SIGSEGV"), ("sigterm", "auto", "killed by SIGTERM"),
           ("sigkill", "auto", "killed by SIGKILL")]


@pytest.mark.parametrize("fault, isolation, said", ENDINGS)
def test_a_planner_that_ends_its_process_or_raises_anything_is_a_crash_of_planning(fault, isolation, said,
                                                                                    tmp_path, monkeypatch):
    """SystemExit or KeyboardInterrupt raised by a planner used to end `run` with no message (or
    130) and leave a finished log saying timeout; os._exit or a segfault ended run, extract and
    stress. Now every one is the outcome crash of planning, at the time it happened, in the result
    and in the log - in the simulation's process (any BaseException) or, for a planner in a
    process of its own (os._exit, a signal, a segfault), from its exit status."""
    import signal

    from deft_gym.sim.simulation import Simulation

    monkeypatch.setenv("DEFT_GYM_PLANNER_ISOLATION", isolation)
    # Ctrl-C is told from a planner's KeyboardInterrupt only under Python's own SIGINT handler (a
    # test runner's worker, or a test before this one, may have installed another)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        r = Simulation(LANE_FOLLOW, faulty_ads(fault), jitter_seed=7, out_dir=tmp_path).run()
    finally:
        signal.signal(signal.SIGINT, previous)
    f = r.outcome.failure
    assert r.outcome.outcome == "crash" and f["module"] == "planning" and said in f["exception"], f
    assert 0 < f["time"] < 5 and "\n" not in f["exception"]
    assert log_outcome(r.log_path)["outcome"] == "crash"


def test_a_planner_that_dies_during_extraction_is_the_finding_planner_crash(lane_follow_log, tmp_path):
    from extract import extract_episode
    from extract.logs import read_log
    from extract.mapping import load_mapping

    meta = read_log(Path(lane_follow_log.log_path), []).episode_meta()
    mapping = load_mapping(ROOT / "configs" / "mappings" / "deft_gym.yaml").model_dump(by_alias=True)
    mapping["planner"] = {"class": FAULTY, "params": {"fault": "os_exit", "after": 40}, "map": meta["map"]}
    s = extract_episode(lane_follow_log.log_path, tmp_path, mapping=mapping, emit_tests=False).summary
    crash = s["findings"]["planner_crash"]
    assert crash["kind"] == "crash" and "exited with status 3" in crash["exception"]
    assert s["findings"]["outputs_without_replay"] > 0 and s["frames"] > 0
    assert any("the planner failed" in w for w in s["warnings"])


@pytest.mark.parametrize("fault", ["os_exit", "segfault"])
def test_a_stress_test_whose_planner_dies_is_a_crash_finding_not_a_harness_error(fault):
    from deft_gym.robustness.runner import run_case
    from deft_gym.robustness.testcase import TestCase

    case = TestCase(id="x", scenario=str(LANE_FOLLOW), jitter_seed=7, ads_overrides={
        "planning": {"planner": {"class": FAULTY, "params": {"fault": fault, "after": 20}}}})
    r = run_case(case)
    assert r.signatures == ["crash:planning:HostDied@tests/support/fault_planners.py:plan"] and not r.harness_errors


def test_the_users_ctrl_c_ends_a_run_in_one_line_and_the_log_says_interrupted(tmp_path):
    """Ctrl-C still stops the program (exit 130, one line, no traceback) - only a KeyboardInterrupt
    the planner raises is a crash - and the log it leaves says interrupted, never timeout."""
    import signal
    import subprocess
    import time

    ads = tmp_path / "ads.yaml"
    ads.write_text(f"planning:\n  planner:\n    class: {FAULTY}\n    params: {{fault: sleep, after: 0, sleep_s: 0.3}}\n")
    out = tmp_path / "out"
    proc = subprocess.Popen([PY, "-m", "deft_gym.cli.main", "run", str(LANE_FOLLOW), "--ads-config", str(ads),
                             "--reruns", "1", "--jitter-seed", "7", "--render", "none", "--quiet", "--out", str(out)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**__import__("os").environ, "PYTHONPATH": str(ROOT)},
                            # as from a shell: a test runner's worker (xdist) ignores SIGINT, and an
                            # ignored signal stays ignored in its children
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 120
    while time.time() < deadline and not (out / "0" / "episode.mcap.tmp").exists():
        time.sleep(0.1)
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=60) == 130
    assert "interrupted" in one_line(proc.stderr.read())
    rec = log_outcome(out / "0" / "episode.mcap")
    assert rec["outcome"] == "interrupted" and rec["failure"]["kind"] == "interrupted"


def test_a_planner_too_slow_for_the_per_call_watchdog_meets_the_whole_run_cap(tmp_path):
    """A planner sleeping 5 s per 0.1 s cycle never tripped the 10 s per-call watchdog and nothing
    capped the run (~30 min): the run's calls together now have a wall-clock cap
    (DEFT_GYM_RUN_WALL_S, default 600 s) and the call that passes it ends the run as a hang."""
    import time

    from deft_gym.sim.simulation import Simulation

    t0 = time.perf_counter()
    r = Simulation(LANE_FOLLOW, faulty_ads("sleep", after=0, sleep_s=0.3), jitter_seed=7, out_dir=tmp_path,
                   watchdog_s=5.0, run_wall_s=2.0).run()
    assert time.perf_counter() - t0 < 15
    f = r.outcome.failure
    assert r.outcome.outcome == "hang" and f["reason"] == "run wall-clock cap" and "whole-run cap" in f["exception"]
    assert log_outcome(r.log_path)["outcome"] == "hang"


def test_the_run_cap_setting_is_checked(monkeypatch):
    from deft_gym.execution.watchdog import DEFAULT_RUN_WALL_S, run_wall_seconds

    monkeypatch.delenv("DEFT_GYM_RUN_WALL_S", raising=False)
    assert run_wall_seconds() == DEFAULT_RUN_WALL_S
    monkeypatch.setenv("DEFT_GYM_RUN_WALL_S", "soon")
    with pytest.raises(ValueError, match="DEFT_GYM_RUN_WALL_S"):
        run_wall_seconds()


# -- 3. every setup error exits non-zero ---------------------------------------------------------------
STRESS_SETUP = {
    "missing scenario": (["--scenarios", "configs/scenarios/nosuch.yaml"], None, "no such file"),
    "unimportable overlay node": ([], "control:\n  node: nosuch.module:Node\n", "cannot import 'nosuch.module:Node'"),
    "planner class as a node": ([], "control:\n  node: deft_gym.planner.lattice:LatticePlanner\n",
                                "is not a deft_gym.bus.bus.Node subclass"),
    "infinite horizon": (["--config", "CFG"], "horizon_s: .inf\n", "horizon_s"),
    "0 policies": (["--config", "CFG"], "generation: {policies: {min: 0, max: 0}}\n", "generation.policies"),
    "a 0 s window": (["--config", "CFG"], "generation: {window_s: {min: 0.0, max: 0.0}}\n", "generation.window_s"),
    "duplicate key": (["--config", "CFG"], "seeds_per_scenario: 1\nseeds_per_scenario: 2\n", "duplicate key"),
}


@pytest.mark.parametrize("fault", sorted(STRESS_SETUP))
def test_stress_setup_errors_are_one_line_exit_2_before_any_test(fault, tmp_path, capsys):
    """Stress with a missing scenario, an unimportable overlay node or an infinite horizon used to
    report 'harness errors' and exit 0 (0 policies or a 0 s window: a traceback)."""
    from deft_gym.robustness import stress

    argv, text, needle = STRESS_SETUP[fault]
    path = tmp_path / "given.yaml"
    if text is not None:
        path.write_text(text)
    extra = [] if argv and argv[0] == "--config" else (["--ads-overlay", str(path)] if text is not None else [])
    argv = [str(path) if a == "CFG" else a for a in argv]
    code = stress.main([*argv, *extra, "--budget", "1", "--out", str(tmp_path / "c"), "--quiet"])
    assert code == 2
    assert needle in one_line(capsys.readouterr().err)
    assert not (tmp_path / "c").exists()


def test_a_stress_campaign_with_harness_errors_exits_1(tmp_path, monkeypatch, capsys):
    """An error of the tool in a test is not a finding and not a success."""
    from deft_gym.robustness import campaign, stress

    def broken(case, *a, **k):
        raise RuntimeError("a harness bug")

    monkeypatch.setattr(campaign, "run_case", broken)
    cfg = tmp_path / "stress.yaml"
    cfg.write_text("scenarios: [configs/scenarios/lane_follow_static.yaml]\nseeds_per_scenario: 1\n")
    code = stress.main(["--config", str(cfg), "--budget", "1", "--workers", "1", "--out", str(tmp_path / "c"),
                        "--quiet", "--render", "none", "--minimise", "none"])
    assert code == 1 and "harness error" in capsys.readouterr().err


# -- 4. bounded work -------------------------------------------------------------------------------------
BOMB = ("planning:\n  planner:\n    params:\n      a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n"
        + "".join(f"      {c}: &{c} [{', '.join([f'*{p}'] * 9)}]\n" for p, c in zip("abcdefgh", "bcdefghi")))


def test_a_yaml_bomb_is_refused_at_once_without_printing_its_expansion(tmp_path, capsys):
    import time

    from deft_gym.cli import run

    ads = tmp_path / "bomb.yaml"
    ads.write_text(BOMB)
    t0 = time.perf_counter()
    assert run.main([str(LANE_FOLLOW), "--ads-config", str(ads), "--reruns", "1", "--out", str(tmp_path / "o")]) == 2
    out = capsys.readouterr().out
    assert time.perf_counter() - t0 < 10 and len(out) < 400 and out.count("lol") == 0
    assert "YAML bomb" in " ".join(out.split()) and not (tmp_path / "o").exists()


@pytest.mark.parametrize("argv, needle", [
    (["--variants", str(10**12)], "--variants"),
    (["--variants", "10000", "--reruns", "1000"], "at most 1,000,000"),
    (["--strength", "nan"], "--strength"),
])
def test_calibration_counts_are_bounded_before_any_work(argv, needle, tmp_path, capsys):
    """--variants 1e12 grew memory without bound (the variant list was built first)."""
    from deft_gym.cli import calibrate

    try:
        code = calibrate.main([*argv, "--out", str(tmp_path / "c"), "--no-progress"])
    except SystemExit as exc:  # argparse
        code = exc.code
    assert code == 2 and needle in capsys.readouterr().err and not (tmp_path / "c").exists()


def test_a_fifo_as_a_scenario_is_refused_before_it_blocks(tmp_path):
    import os
    import subprocess

    fifo = tmp_path / "scenario.yaml"
    os.mkfifo(fifo)
    proc = subprocess.run([PY, "-m", "deft_gym.cli.run", str(fifo), "--reruns", "1", "--out", str(tmp_path / "o")],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "not a regular file" in proc.stdout + proc.stderr


def test_huge_budgets_are_one_line(tmp_path, capsys):
    from agents import evaluate
    from deft_gym.robustness import stress

    with pytest.raises(SystemExit):
        stress.main(["--budget", str(10**9), "--out", str(tmp_path / "s")])
    assert "--budget" in capsys.readouterr().err
    assert evaluate.main(["--methods", "random", "--budget", "100000", "--repeats", "1000", "--held-out", "0",
                          "--scenarios", "lane_follow_static", "--out", str(tmp_path / "e")]) == 2
    assert "simulated scenarios" in one_line(capsys.readouterr().err)


# -- 5. no tracebacks ------------------------------------------------------------------------------------
def test_the_rerun_comparison_counts_plans_it_cannot_compare():
    from deft_gym.cli.run import divergence_stats

    good = {"trajectory": {"t": [0.0, 1.0], "x": [0.0, 1.0], "y": [0.0, 0.0]}}
    odd = [{}, {"trajectory": {"t": [], "x": [], "y": []}}, {"trajectory": {"t": [0, 1], "x": ["a", 1], "y": [0]}},
           {"trajectory": {"t": [0, 1, 2], "x": [0.0, 1.0], "y": [0.0, 0.0]}}, None, "garbage"]
    s = divergence_stats([good] * 7, [good, *odd])
    assert (s["paired"], s["identical"], s["incomparable"]) == (1, 1, 6)


@pytest.mark.parametrize("body, needle", [
    ("policy_kwargs: {net_arch: [-5]}", "net_arch"),
    ("policy_kwargs: {net_arch: {pi: [64], qf: [3]}}", "net_arch"),
    ("policy_kwargs: {bogus: 1}", "policy_kwargs.bogus"),
    ("name: ../../x", "name"),
])
def test_bad_network_settings_are_one_line(body, needle, tmp_path, capsys):
    from agents import train

    cfg = tmp_path / "train.yaml"
    cfg.write_text(f"timesteps: 8\n{body}\n")
    assert train.main(["--config", str(cfg), "--out", str(tmp_path / "run"), "--no-progress"]) == 2
    assert needle in one_line(capsys.readouterr().err) and not (tmp_path / "run").exists()


@pytest.mark.parametrize("model", [b"", b"not a zip", b"PK\x03\x04 truncated"])
def test_evaluate_with_an_empty_or_corrupt_model_is_one_line(model, tmp_path, capsys):
    from agents import evaluate

    path = tmp_path / "model.zip"
    path.write_bytes(model)
    assert evaluate.main(["--methods", "rl", "--model", str(path), "--budget", "1", "--held-out", "0",
                          "--scenarios", "lane_follow_static", "--out", str(tmp_path / "e")]) == 2
    err = one_line(capsys.readouterr().err)
    assert err.startswith("error: --model: ") and "not a readable SB3 model" in err


def test_evaluate_with_bad_scenarios_is_one_line_naming_the_flag(tmp_path, capsys):
    from agents import evaluate

    assert evaluate.main(["--methods", "random", "--budget", "1", "--held-out", "0", "--scenarios",
                          "lane_follow_static,no_such_scenario", "--out", str(tmp_path / "e")]) == 2
    assert one_line(capsys.readouterr().err).startswith("error: --scenarios: 'no_such_scenario' does not resolve")


def test_render_of_an_infinite_heading_draws_and_of_a_damaged_log_says_so(lane_follow_log, tmp_path, capsys):
    """A stress finding's log with an infinite heading lost its plot and video ("math domain
    error", swallowed) and `render` said "0 of 1 drawn" with exit 0."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    from deft_gym.bus import ros1
    from deft_gym.bus.codec import encode
    from deft_gym.bus.ros1 import ChannelDecoders
    from deft_gym.cli import render

    d = tmp_path / "inf"
    d.mkdir()
    with open(lane_follow_log.log_path, "rb") as f, open(d / "episode.mcap", "wb") as g:
        r, w = make_reader(f), Writer(g)
        w.start()
        summ = r.get_summary()
        sch = {i: w.register_schema(s.name, s.encoding, s.data) for i, s in summ.schemas.items()}
        ch = {i: w.register_channel(c.topic, c.message_encoding, sch.get(c.schema_id, 0), c.metadata)
              for i, c in summ.channels.items()}
        for m in r.iter_metadata():
            w.add_metadata(m.name, m.metadata)
        decoders = ChannelDecoders()
        for s, c, m in r.iter_messages():
            data = m.data
            if c.topic == "/apollo/localization/pose" and m.sequence % 5 == 2:
                p = {**decoders(s, c, data), "heading": float("inf")}  # the log's encoding, either
                data = encode(p) if c.message_encoding == "json" else ros1.encode(
                    ros1.parse_definition(s.data).program, p)
            w.add_message(ch[c.id], m.log_time, data, m.publish_time, m.sequence)
        w.finish()
    assert render.main([str(d / "episode.mcap"), "--quiet"]) == 0
    assert (d / "plot.png").stat().st_size > 0 and (d / "video.mp4").stat().st_size > 0
    capsys.readouterr()
    bad = tmp_path / "bad" / "episode.mcap"
    bad.parent.mkdir()
    raw = bytearray(Path(lane_follow_log.log_path).read_bytes())
    raw[len(raw) // 2: len(raw) // 2 + 64] = b"\xab" * 64
    bad.write_bytes(bytes(raw))
    assert render.main([str(bad), "--no-video", "--quiet"]) == 1
    got = capsys.readouterr()
    assert f"error: {bad}: not drawn" in got.err and "0 of 1 episode(s) drawn; 1 could not be" in got.out


# -- 6. no silent acceptance -------------------------------------------------------------------------------
SCENARIO_REFUSED = {
    "duplicate key": (lambda text, d: text + "duration: 30\nduration: 31\n", "duplicate key 'duration'"),
    "name ../../x": (lambda text, d: text.replace(f"name: {d['name']}", "name: ../../x"), "cannot name a folder"),
    "NUL byte in the name": (lambda text, d: text.replace(f"name: {d['name']}", 'name: "a\\0b"'),
                             "cannot name a folder"),
    "duration 0.01": (lambda text, d: text + "duration: 0.01\n", "duration"),
}


@pytest.mark.parametrize("fault", sorted(SCENARIO_REFUSED))
def test_scenarios_accepted_silently_before_are_one_line_errors(fault, tmp_path, capsys):
    """A scenario named ../../x moved the default output outside runs/; a NUL byte in its name
    was a traceback; duplicate keys kept the last silently; 0.01 s ran an episode of nothing."""
    import yaml

    from deft_gym.cli import run

    text = LANE_FOLLOW.read_text()
    data = yaml.safe_load(text)
    text = "\n".join(line for line in text.splitlines() if not line.startswith("duration:")) + "\n"
    mutate, needle = SCENARIO_REFUSED[fault]
    path = tmp_path / "bad.yaml"
    path.write_text(mutate(text, data))
    assert run.main([str(path), "--reruns", "1"]) == 2
    msg = " ".join(capsys.readouterr().out.split())
    assert msg.startswith(f"error: {path}") and needle in msg, msg


def test_two_vehicles_overlapping_at_the_start_are_refused(tmp_path, capsys):
    import yaml

    from deft_gym.cli import run

    data = yaml.safe_load(LANE_FOLLOW.read_text())
    car = next(p for p in data["participants"] if p.get("obstacle") == "STATIC_VEHICLE")
    data["participants"].append({**car, "id": "twin", "s": car["s"] + 1.0})
    path = tmp_path / "overlap.yaml"
    path.write_text(yaml.safe_dump(data))
    assert run.main([str(path), "--reruns", "1", "--out", str(tmp_path / "o")]) == 2
    assert "'twin' overlaps" in " ".join(capsys.readouterr().out.split())


@pytest.mark.parametrize("text, needle", [("world_hz: 0.001\n", "world_hz"), ("localization: {rate_hz: 0.01}\n",
                                                                               "localization.rate_hz"),
                                          ("world_hz: 20\nworld_hz: 30\n", "duplicate key 'world_hz'")])
def test_ads_settings_accepted_silently_before_are_one_line_errors(text, needle, tmp_path, capsys):
    from deft_gym.cli import run

    ads = tmp_path / "ads.yaml"
    ads.write_text(text)
    assert run.main([str(LANE_FOLLOW), "--ads-config", str(ads), "--reruns", "1", "--out", str(tmp_path / "o")]) == 2
    assert needle in " ".join(capsys.readouterr().out.split())


def test_a_tolerance_of_a_field_no_output_has_is_refused(lane_follow_log, tmp_path, capsys):
    from deft_gym.cli import extract

    assert extract.main([lane_follow_log.log_path, "--tolerance", "nosuchfield=1", "--out", str(tmp_path / "x"),
                         "--render", "none", "--no-progress"]) == 2
    assert "tolerance 'nosuchfield'" in one_line(capsys.readouterr().err)


def test_flag_errors_name_the_flag_not_the_config_file(tmp_path, capsys):
    from agents import evaluate, train

    assert train.main(["--config", "configs/train/demo.yaml", "--timesteps", "0", "--out", str(tmp_path / "t")]) == 2
    assert one_line(capsys.readouterr().err).startswith("error: --timesteps: ")
    cfg = tmp_path / "eval.yaml"
    cfg.write_text("methods: [random]\nheld_out: 0\nscenarios: [lane_follow_static]\n")
    assert evaluate.main(["--config", str(cfg), "--model", str(tmp_path / "none.zip"), "--methods", "rl",
                          "--out", str(tmp_path / "e")]) == 2
    assert one_line(capsys.readouterr().err).startswith("error: --model: ")


# -- 7. extraction and contract results are never wrong without a word -------------------------------------
def test_a_log_without_its_metadata_is_refused_not_extracted_into_0_frames(lane_follow_log, tmp_path, capsys):
    """A log stripped of its deft_gym metadata extracted 0 of 291 frames, said "complete" and
    exited 0: its log times cannot be mapped onto the frame times, and the extraction says so."""
    import yaml
    from mcap.reader import make_reader
    from mcap.writer import Writer

    from deft_gym.cli import extract
    from extract.logs import read_log

    src, dst = Path(lane_follow_log.log_path), tmp_path / "bare.mcap"
    with open(src, "rb") as f, open(dst, "wb") as g:
        r, w = make_reader(f), Writer(g)
        w.start()
        summ = r.get_summary()
        sch = {i: w.register_schema(s.name, s.encoding, s.data) for i, s in summ.schemas.items()}
        ch = {i: w.register_channel(c.topic, c.message_encoding, sch.get(c.schema_id, 0), c.metadata)
              for i, c in summ.channels.items()}
        for _, c, m in r.iter_messages():
            w.add_message(ch[c.id], m.log_time, m.data, m.publish_time, m.sequence)
        w.finish()
    meta = read_log(src, []).episode_meta()
    mapping = yaml.safe_load((ROOT / "configs" / "mappings" / "deft_gym.yaml").read_text())
    mapping["planner"] = {"class": meta["planner"]["class"], "params": meta["planner"]["params"], "map": meta["map"]}
    mp = tmp_path / "mapping.yaml"
    mp.write_text(yaml.safe_dump(mapping))
    assert extract.main([str(dst), "--mapping", str(mp), "--out", str(tmp_path / "x"), "--render", "none",
                         "--no-progress"]) == 2
    err = one_line(capsys.readouterr().err)
    assert "cannot be mapped onto the frames" in err and "deft_gym.episode metadata" in err


def test_frames_after_lost_planning_outputs_are_said_to_follow_them(lane_follow_log, tmp_path):
    """After a lost chunk, the frames that follow (their inputs intact) did not reproduce - the
    replay never planned the lost outputs' frames - and were counted against the planner without
    a word; now a warning and the finding after_lost_outputs say so, and their tests' xfail too."""
    from deft_gym.experiments.log_damage import chunk_table, damage
    from extract import extract_episode

    buf = Path(lane_follow_log.log_path).read_bytes()
    table = chunk_table(buf)
    log = tmp_path / "damaged" / "episode.mcap"
    log.parent.mkdir()
    log.write_bytes(damage(buf, "payload_digit", table[len(table) // 3]))
    res = extract_episode(log, tmp_path / "x")
    s = res.summary
    n = s["findings"]["after_lost_outputs"]
    assert n > 0 and any("lost planning output(s)" in w and "not of the planner" in w for w in s["warnings"])
    assert s["frames"] - s["reproduced"]["0"] >= n
    header = json.loads(Path(res.frames_path).read_text().splitlines()[0])
    assert sum(1 for f in header["frames_index"] if f.get("after_lost")) == n


def test_evaluate_keeps_failure_logs_of_a_scenario_given_by_absolute_path_inside_out(tmp_path):
    """`evaluate --log-failures` built its log folder from the scenario's absolute path, outside
    --out (pathlib drops the prefix before an absolute part), and crashed."""
    from agents.evaluate import _log_root, folder_name

    job = {"out": str(tmp_path / "out"), "method": "random", "placement": "closest", "scenario": str(LANE_FOLLOW),
           "repeat": 0}
    root = _log_root(job)
    assert root.is_relative_to(tmp_path / "out") and root.parent.name.startswith("lane_follow_static-")
    assert folder_name("lane_follow_static") == "lane_follow_static" and folder_name("gen:7") == "gen_7"
    assert "/" not in folder_name("../../etc/x.yaml") and folder_name("a~v3") == "a_v3"


@pytest.mark.parametrize("text, needle", [
    ("a: 1\nb: {c: 1, c: 2}\n", "duplicate key 'c' (first at line 2)"),
    ("a: &x [1, *x]\n", "YAML bomb"),
    ("a: 1\n\x00\n", "NUL byte"),
])
def test_strict_yaml_refuses_what_pyyaml_accepts_or_loops_on(text, needle, tmp_path):
    from deft_gym.config import ConfigError, load_yaml

    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_yaml(path)
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_strict_yaml_keeps_merge_keys_and_refuses_oversized_files(tmp_path):
    from deft_gym.config import ConfigError, load_yaml

    path = tmp_path / "m.yaml"
    path.write_text("base: &b {x: 1, y: 2}\nd:\n  <<: *b\n  x: 3\n")
    assert load_yaml(path)["d"] == {"x": 3, "y": 2}
    path.write_text("#" * 2000)
    with pytest.raises(ConfigError, match=r"at most 0\.001 MB"):
        load_yaml(path, max_bytes=1000)


def test_stress_compare_of_a_folder_without_a_campaign_is_one_line(tmp_path, capsys):
    from deft_gym.robustness import stress

    assert stress.main(["compare", str(tmp_path)]) == 2
    assert "expected a campaign folder" in one_line(capsys.readouterr().err)


def test_the_run_cap_flag_sets_the_variable_for_the_run_and_a_bad_variable_is_one_line(tmp_path, monkeypatch,
                                                                                       capsys):
    import os

    from deft_gym.cli import run

    ads = tmp_path / "ads.yaml"
    ads.write_text(f"planning:\n  planner:\n    class: {FAULTY}\n    params: {{fault: sleep, after: 0, sleep_s: 0.3}}\n")
    monkeypatch.setenv("DEFT_GYM_RUN_WALL_S", "600")
    assert run.main([str(LANE_FOLLOW), "--ads-config", str(ads), "--reruns", "1", "--jitter-seed", "7",
                     "--run-wall-s", "1.5", "--out", str(tmp_path / "out"), "--quiet", "--render", "none"]) == 0
    row = json.loads((tmp_path / "out" / "summary.json").read_text())["reruns"][0]
    assert row["outcome"] == "hang" and log_outcome(row["log"])["failure"]["reason"] == "run wall-clock cap"
    assert os.environ["DEFT_GYM_RUN_WALL_S"] == "600"
    monkeypatch.setenv("DEFT_GYM_RUN_WALL_S", "-3")
    with pytest.raises(SystemExit) as exc:
        run.main([str(LANE_FOLLOW), "--reruns", "1", "--out", str(tmp_path / "o2")])
    assert exc.value.code == 2 and "--run-wall-s" in one_line(capsys.readouterr().err)
