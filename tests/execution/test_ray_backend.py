"""The Ray backend on a real local Ray instance (2 CPUs): the adversary evaluation and a robustness
campaign give the same records as local processes, a Ray worker killed mid-campaign loses
nothing and repeats nothing, artifacts come back to the run folder, and training runs with its
envs on Ray actors."""

from __future__ import annotations

import json
import os
import signal
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("ray", reason="Ray is not installed: pip install '.[ray]' (make test installs it)")

from deft_gym.execution import Backend, Executor, without_timings
from deft_gym.files import append_jsonl, read_jsonl

pytestmark = pytest.mark.ray
ROOT = Path(__file__).resolve().parents[2]
RAY = Backend("ray", 2)


@pytest.fixture(scope="module", autouse=True)
def ray_instance() -> Iterator[None]:
    """One local Ray instance of 2 CPUs for the module (every Executor here reuses it)."""
    import ray

    from deft_gym.execution.ray_backend import connect

    connect(RAY)
    yield
    ray.shutdown()


def _records(path: Path) -> list[dict]:
    return without_timings(read_jsonl(path))


def test_evaluation_records_identical_on_ray_and_local_processes(tmp_path: Path) -> None:
    """agents.evaluate with --ray: the records (timings aside) of local processes, in the same
    order (tests/execution/test_local.py: one and two local workers, and a resume, give them too)."""
    from agents import evaluate
    from tests.execution.test_local import EVAL_ARGS

    runs = {}
    for name, extra in (("local2", ["--workers", "2"]), ("ray2", ["--workers", "2", "--ray"])):
        assert evaluate.main([*EVAL_ARGS, *extra, "--out", str(tmp_path / name)]) == 0
        runs[name] = _records(tmp_path / name / "records.jsonl")
    assert len(runs["local2"]) == 16
    assert runs["local2"] == runs["ray2"]


def _campaign(tmp_path: Path):
    from deft_gym.robustness.campaign import Campaign, load_campaign_config

    cfg = tmp_path / "stress.yaml"
    cfg.write_text(json.dumps({"scenarios": ["configs/scenarios/lane_follow_static.yaml"], "seeds_per_scenario": 2,
                               "generation": {"start_s": {"min": 2.0, "max": 6.0}}}))
    return Campaign(load_campaign_config(cfg), seed=7)


def _ray_task_pids() -> list[int]:
    """Ray worker processes running a task now (their title is ``ray::_task``)."""
    pids = []
    for p in os.listdir("/proc"):
        if p.isdigit():
            try:
                title = Path(f"/proc/{p}/cmdline").read_bytes().split(b"\0")[0]
            except OSError:
                continue
            if title.startswith(b"ray::_task"):
                pids.append(int(p))
    return pids


def test_robustness_campaign_identical_and_a_killed_worker_loses_nothing(tmp_path: Path) -> None:
    from deft_gym.robustness.campaign import run_campaign

    budget = 8
    local = run_campaign(_campaign(tmp_path), tmp_path / "local", budget, workers=1, minimise_findings="none")
    killed: list[int] = []

    def kill_a_busy_worker(stage: str, done: int, total: int, counts: dict) -> None:
        if stage != "tests" or killed:
            return
        for _ in range(100):  # the other CPU is on a test: kill its worker process mid-test
            pids = _ray_task_pids()
            if pids:
                os.kill(pids[0], signal.SIGKILL)
                killed.append(pids[0])
                return
            time.sleep(0.02)

    on_ray = run_campaign(_campaign(tmp_path), tmp_path / "ray", budget, minimise_findings="none",
                          progress=kill_a_busy_worker, backend=RAY)
    assert killed, "no Ray worker was running a test when the first result came back"
    rows = read_jsonl(tmp_path / "ray" / "runs.jsonl")
    assert [r["index"] for r in rows] == list(range(budget))  # every test once, in test order
    assert _records(tmp_path / "ray" / "runs.jsonl") == _records(tmp_path / "local" / "runs.jsonl")
    assert _records(tmp_path / "ray" / "baseline.jsonl") == _records(tmp_path / "local" / "baseline.jsonl")
    assert on_ray["runs"] == local["runs"] == budget and on_ray["findings"].keys() == local["findings"].keys()


def episode_item(job: tuple[str, int, str]) -> dict:
    """A work item that notes when it starts and ends (to see what ran twice), around a real episode."""
    from deft_gym.sim.simulation import run_episode

    marks, index, out = job
    append_jsonl(marks, {"index": index, "pid": os.getpid(), "event": "start"})
    res = run_episode(ROOT / "configs" / "scenarios" / "lane_follow_static.yaml", jitter_seed=index,
                      out_dir=out, keep_planning=False)
    append_jsonl(marks, {"index": index, "pid": os.getpid(), "event": "end"})
    return {"index": index, "outcome": res.summary()["outcome"], "sim_time": res.sim_time}


def test_finished_items_are_not_repeated_and_artifacts_come_back(tmp_path: Path) -> None:
    """A worker killed mid-item: only that item runs again (Ray's task retry); the logs that
    items write come back to the run folder as archives (artifacts forced to travel)."""
    marks = tmp_path / "marks.jsonl"
    items = [(str(marks), i, str(tmp_path / "logs" / f"{i}")) for i in range(6)]
    killed: list[int] = []
    results = []
    with Executor(RAY, run_dir=tmp_path, artifacts_mode="return") as ex:
        for res in ex.map(episode_item, items, artifacts=lambda j: [j[2]]):
            results.append(res)
            if not killed:
                for _ in range(200):
                    rows = read_jsonl(marks)
                    ended = {r["index"] for r in rows if r["event"] == "end"}
                    busy = [r for r in rows if r["event"] == "start" and r["index"] not in ended]
                    if busy:
                        os.kill(busy[0]["pid"], signal.SIGKILL)
                        killed.append(busy[0]["pid"])
                        break
                    time.sleep(0.01)
    assert killed
    assert [r["index"] for r in results] == list(range(6))
    starts = [r for r in read_jsonl(marks) if r["event"] == "start"]
    counts = Counter(r["index"] for r in starts)
    in_killed = [r["index"] for r in starts if r["pid"] == killed[0]]
    assert sorted(counts) == list(range(6))
    assert [i for i, n in counts.items() if n > 1] == in_killed[-1:]  # the killed worker's item ran again, no other
    for i in range(6):
        assert (tmp_path / "logs" / f"{i}" / "episode.mcap").stat().st_size > 0
    serial = [episode_item((str(tmp_path / "m1.jsonl"), i, str(tmp_path / "serial" / f"{i}"))) for i in range(2)]
    assert serial == results[:2]


def test_training_with_envs_on_ray_actors_matches_subprocess_envs(tmp_path: Path) -> None:
    """``agents.train --ray``: PPO unchanged, the envs in Ray actors; the episodes are those of
    SubprocVecEnv's processes (pids and timings aside)."""
    from agents import train

    for name, extra in (("ray", ["--ray"]), ("subproc", [])):
        assert train.main(["--config", "configs/train/demo.yaml", "--timesteps", "64", "--out", str(tmp_path / name),
                           "--no-progress", *extra]) == 0
    out = tmp_path / "ray"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["timesteps"] >= 64 and (out / "model.zip").exists()
    assert sorted(p.name for p in out.glob("episodes-*.jsonl")) == ["episodes-0.jsonl", "episodes-1.jsonl"]
    assert not list(out.glob(".execution-token-*"))
    for rank in (0, 1):
        ray_eps, sub_eps = (without_timings([{k: v for k, v in r.items() if k != "pid"}
                                             for r in read_jsonl(tmp_path / n / f"episodes-{rank}.jsonl")])
                            for n in ("ray", "subproc"))
        assert ray_eps and ray_eps == sub_eps


def test_batch_extraction_on_ray_with_logs_and_tests_travelling(tmp_path: Path) -> None:
    """Batch extraction as Ray tasks, its inputs (logs) and artifacts (frames, tests) forced to
    travel: the same extraction as in this process."""
    from deft_gym.sim.simulation import run_episode
    from extract.batch import extract_directory

    for i, name in enumerate(("take_exit", "left_turn")):
        run_episode(ROOT / "configs" / "scenarios" / f"{name}.yaml", jitter_seed=i, out_dir=tmp_path / "runs" / name,
                    keep_planning=False)
    here = extract_directory(tmp_path / "runs", tmp_path / "here")
    with Executor(RAY, run_dir=tmp_path / "far", artifacts_mode="return") as ex:
        far = extract_directory(tmp_path / "runs", tmp_path / "far", executor=ex)
    assert [r.ok for r in far] == [True, True]
    def same(s: dict) -> dict:  # what does not name the output folder, a time or a duration
        return {k: v for k, v in s.items() if not any(w in k for w in ("ms", "path", "created", "_s"))}

    for a, b in zip(here, far):
        assert same(a.summary) == same(b.summary)
        assert b.test_path is not None and b.test_path.read_text()
