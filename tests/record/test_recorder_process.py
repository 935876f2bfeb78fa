"""The recorder process: the same bytes as the in-process writer, errors surfaced at the log's
open or close, a fresh process after a fork or a crash, and an unfinished ``.tmp`` when the
simulation's process dies."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from multiprocessing import get_context
from pathlib import Path

import pytest
from mcap.reader import make_reader

from deft_gym.bus.messages import DEFAULT_TOPICS, Message
from deft_gym.record import recorder
from deft_gym.record.recorder import McapRecorder, RecorderError, RecorderProcess
from deft_gym.sim.simulation import Simulation
from tests.support.fixtures import SCENARIOS

SCENARIO = SCENARIOS / "lane_follow_static.yaml"
TOPICS = {"control": DEFAULT_TOPICS["control"], "planning": DEFAULT_TOPICS["planning"]}


def _write(path: Path, background: bool, n: int = 600) -> McapRecorder:
    rec = McapRecorder(path, TOPICS, {"scenario": "unit", "seed": 3}, background=background)
    for i in range(n):
        topic = TOPICS["control"] if i % 4 else TOPICS["planning"]
        rec(Message(topic, i, 10_000_000 * i, {"header": {"seq": i}, "v": i / 7, "nan": float("nan") if i == 5 else 0.0}))
    rec.add_metadata("mid", {"at": 1})
    rec.close({"outcome": "ok"})
    return rec


def test_recorder_process_writes_the_in_process_bytes(tmp_path: Path) -> None:
    a = _write(tmp_path / "a.mcap", background=True)
    b = _write(tmp_path / "b.mcap", background=False)
    assert a.path.read_bytes() == b.path.read_bytes()
    assert a.process_seconds > 0.0  # the recorder process reports the CPU it spent on the log
    assert not (tmp_path / "a.mcap.tmp").exists()


def test_full_run_same_log_in_both_modes(tmp_path: Path) -> None:
    for name, background in (("p", True), ("i", False)):
        Simulation(SCENARIO, jitter_seed=4, out_dir=tmp_path / name, keep_planning=False,
                   recorder_process=background, log_start_ns=1_700_000_000 * 10**9).run()
    p, i = (_records(tmp_path / name / "episode.mcap") for name in ("p", "i"))
    assert len(p[0]) > 1000 and p[0] == i[0]  # every message, byte for byte
    for meta in (p[1], i[1]):
        meta["deft_gym.outcome"].pop("wall_time")  # the one value that differs between two runs
    assert p[1] == i[1]


def _records(path: Path) -> tuple[list, dict]:
    with open(path, "rb") as fh:
        msgs = [(ch.topic, m.log_time, m.sequence, m.data) for _, ch, m in make_reader(fh).iter_messages()]
    with open(path, "rb") as fh:
        meta = {m.name: dict(m.metadata) for m in make_reader(fh).iter_metadata()}
    return msgs, meta


def test_open_error_is_raised_at_once(tmp_path: Path) -> None:
    (tmp_path / "log.mcap.tmp").mkdir()  # the file the log would be written to is a directory
    with pytest.raises(RecorderError, match=r"log\.mcap\.tmp"):
        McapRecorder(tmp_path / "log.mcap", TOPICS, {}, background=True)


def test_write_error_is_raised_at_close(tmp_path: Path) -> None:
    rec = McapRecorder(tmp_path / "log.mcap", TOPICS, {}, background=True)
    rec(Message(TOPICS["control"], 0, 0, {"v": {1.0, 2.0}}))  # a set has no JSON form
    with pytest.raises(RecorderError, match=r"MCAP log .*log\.mcap: .*/apollo/control message 0: .*set"):
        rec.close({"outcome": "ok"})
    assert not (tmp_path / "log.mcap").exists() and (tmp_path / "log.mcap.tmp").exists()
    _write(tmp_path / "next.mcap", background=True)  # the recorder process goes on with other logs
    assert (tmp_path / "next.mcap").exists()


def test_dead_recorder_process_is_reported_and_replaced(tmp_path: Path) -> None:
    rec = McapRecorder(tmp_path / "log.mcap", TOPICS, {}, background=True)
    proc = RecorderProcess.get().proc
    proc.kill()
    proc.wait()
    rec(Message(TOPICS["control"], 0, 0, {"v": 1.0}))
    with pytest.raises(RecorderError, match=r"MCAP log .*log\.mcap: the recorder process"):
        rec.close()
    assert RecorderProcess.get().proc is not proc  # a new one for the next log
    _write(tmp_path / "next.mcap", background=True)


def test_forked_child_uses_its_own_recorder_process(tmp_path: Path) -> None:
    _write(tmp_path / "parent0.mcap", background=True)
    parent_proc = RecorderProcess.get().proc
    pid = os.fork()
    if pid == 0:  # the child: a log of its own, through a recorder process of its own
        code = 1
        try:
            _write(tmp_path / "child.mcap", background=True)
            code = 0 if RecorderProcess.get().proc is not parent_proc else 2
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0
    _write(tmp_path / "parent1.mcap", background=True)  # the parent's pipe is intact
    assert RecorderProcess.get().proc is parent_proc
    assert (tmp_path / "child.mcap").read_bytes() == (tmp_path / "parent1.mcap").read_bytes()


def test_simulation_process_dying_leaves_the_tmp(tmp_path: Path) -> None:
    script = (
        "import os, sys\n"
        "from deft_gym.bus.messages import Message\n"
        "from deft_gym.record.recorder import McapRecorder, RecorderProcess\n"
        f"rec = McapRecorder({str(tmp_path / 'log.mcap')!r}, {TOPICS!r}, {{}}, background=True)\n"
        "for i in range(1000):\n"
        f"    rec(Message({TOPICS['control']!r}, i, i, {{'v': i}}))\n"
        "print(RecorderProcess.get().proc.pid, flush=True)\n"
        "os._exit(3)\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert out.returncode == 3, out.stderr
    worker = int(out.stdout.split()[0])
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and os.path.exists(f"/proc/{worker}") and \
            "Z" not in Path(f"/proc/{worker}/stat").read_text().split()[2]:
        time.sleep(0.05)
    assert not os.path.exists(f"/proc/{worker}") or "Z" in Path(f"/proc/{worker}/stat").read_text().split()[2]
    assert not (tmp_path / "log.mcap").exists()
    assert (tmp_path / "log.mcap.tmp").stat().st_size > 1000  # the messages handed over are in it


def test_recorder_mode_from_environment_and_cpus(monkeypatch) -> None:
    from deft_gym.record import recorder

    monkeypatch.delenv(recorder.RECORDER_ENV, raising=False)
    monkeypatch.setattr(recorder, "available_cpus", lambda: 1)
    assert recorder.recorder_in_process()  # auto, one CPU: the recorder process would compete
    monkeypatch.setattr(recorder, "available_cpus", lambda: 2)
    assert not recorder.recorder_in_process()
    monkeypatch.setenv(recorder.RECORDER_ENV, "inline")
    assert recorder.recorder_in_process()
    monkeypatch.setenv(recorder.RECORDER_ENV, "process")
    monkeypatch.setattr(recorder, "available_cpus", lambda: 1)
    assert not recorder.recorder_in_process()
    monkeypatch.setenv(recorder.RECORDER_ENV, "thread")
    with pytest.raises(ValueError, match="DEFT_GYM_RECORDER='thread': expected auto, process or inline"):
        recorder.recorder_in_process()


def _no_recorder_env(monkeypatch) -> None:
    """DEFT_GYM_RECORDER unset for this test, and as it was after it."""
    monkeypatch.setenv(recorder.RECORDER_ENV, "auto")  # registers the restore
    monkeypatch.delenv(recorder.RECORDER_ENV)


def test_pool_workers_filling_the_cpus_log_inline(monkeypatch) -> None:
    _no_recorder_env(monkeypatch)
    monkeypatch.setattr(recorder, "available_cpus", lambda: 4)
    recorder.init_pool_worker(3)  # a CPU to spare: each worker gets a recorder process
    assert recorder.RECORDER_ENV not in os.environ and not recorder.recorder_in_process()
    recorder.init_pool_worker(4)
    assert os.environ[recorder.RECORDER_ENV] == "inline" and recorder.recorder_in_process()
    monkeypatch.setenv(recorder.RECORDER_ENV, "process")  # the user's choice stands
    recorder.init_pool_worker(8)
    assert os.environ[recorder.RECORDER_ENV] == "process"


def test_pool_initializer_runs_in_the_workers(monkeypatch) -> None:
    _no_recorder_env(monkeypatch)
    n = recorder.available_cpus()
    with get_context("spawn").Pool(1, recorder.init_pool_worker, (n,)) as pool:
        assert pool.apply(recorder.recorder_in_process)
    with get_context("spawn").Pool(1, recorder.init_pool_worker, (1,)) as pool:
        assert pool.apply(recorder.recorder_in_process) == (n < 2)


def test_training_envs_filling_the_cpus_log_inline(monkeypatch) -> None:
    from agents import train
    from agents.config import TrainConfig, complete

    _no_recorder_env(monkeypatch)
    monkeypatch.setattr(recorder, "available_cpus", lambda: 2)
    complete()
    cfg = TrainConfig()
    train.make_env(cfg, 0, None)().close()  # envs in this process: its own choice
    assert recorder.RECORDER_ENV not in os.environ
    train.make_env(cfg, 0, None, workers=2)().close()
    assert os.environ[recorder.RECORDER_ENV] == "inline"
