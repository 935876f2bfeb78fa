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

ROOT = Path(__file__).resolve().parents[2]


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


# the evaluation of issue 17 on a tiny budget: a search method and a baseline, a seed and a
# held-out generated scenario, both placement rules (8 jobs of 2 simulated scenarios)
EVAL_ARGS = ["--methods", "decictor,random", "--budget", "2", "--scenarios", "lane_follow_static",
             "--held-out", "1", "--placements", "closest,uniform", "--seed", "3", "--no-progress"]


def test_evaluation_the_same_records_for_one_and_two_workers_and_after_a_resume(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """agents.evaluate on the execution layer: the records (timings aside) do not depend on the
    number of workers, and a run cut mid-job resumes into the same file (finished jobs kept,
    the cut job simulated again)."""
    from agents import evaluate
    from deft_gym.files import read_jsonl

    assert evaluate.main([*EVAL_ARGS, "--workers", "1", "--out", str(tmp_path / "one")]) == 0
    one = read_jsonl(tmp_path / "one" / "records.jsonl")
    assert len(one) == 16 and {r["scenario_kind"] for r in one} == {"seed", "held_out"}
    assert [(r["method"], r["placement"]) for r in one[:8:2]] == [
        ("decictor", "closest"), ("decictor", "uniform"), ("random", "closest"), ("random", "uniform")]
    # Random has no placement rule: it runs once, its records are copied to the other rule
    assert [{**r, "placement": "uniform"} for r in one[4:6]] == one[6:8]
    cut = tmp_path / "two" / "records.jsonl"
    cut.parent.mkdir()
    lines = (tmp_path / "one" / "records.jsonl").read_text().splitlines(keepends=True)
    cut.write_text("".join(lines[:5]) + lines[5][:40])  # two jobs done, one half done, a line cut by a kill
    capsys.readouterr()
    assert evaluate.main([*EVAL_ARGS, "--workers", "2", "--out", str(tmp_path / "two")]) == 0
    # the cut Random job and the second scenario's three jobs (Random's uniform rows are copies)
    assert "4 jobs, 8 simulated scenarios, 2 local worker processes" in capsys.readouterr().out
    two = read_jsonl(cut)
    assert two[:4] == one[:4]  # the finished jobs were kept as they were
    assert without_timings(two) == without_timings(one)
    assert (tmp_path / "two" / "table.md").exists() and (tmp_path / "two" / "summary.json").exists()


def test_the_execution_layer_is_not_simulation_code() -> None:
    """Changing deft_gym.execution leaves the code fingerprint (so reference-run caches and
    evaluation records made before it stay valid)."""
    from deft_gym.search.trace import code_fingerprint

    pkg = ROOT / "deft_gym"
    changed = code_fingerprint(pkg, read=lambda f: b"# changed\n" + f.read_bytes() if "execution" in f.parts
                               else f.read_bytes())
    assert changed == code_fingerprint(pkg)


def test_evaluation_resume_simulates_again_what_an_edited_scenario_file_made(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Records carry their scenario's content key: after the scenario file changes, a resumed
    evaluation does not reuse the records of the old version."""
    from agents import evaluate
    from deft_gym.files import read_jsonl

    scn = tmp_path / "lfs.yaml"
    scn.write_text((ROOT / "configs" / "scenarios" / "lane_follow_static.yaml").read_text())
    args = ["--methods", "random", "--budget", "1", "--scenarios", str(scn), "--placements", "closest",
            "--held-out", "0", "--repeats", "1",
            "--no-progress", "--workers", "1", "--out", str(tmp_path / "ev")]
    assert evaluate.main(args) == 0
    before = read_jsonl(tmp_path / "ev" / "records.jsonl")
    assert evaluate.main(args) == 0  # unchanged: nothing simulated again
    assert "0 jobs" in capsys.readouterr().out
    scn.write_text(scn.read_text().replace("duration: 40.0", "duration: 39.0"))
    assert evaluate.main(args) == 0
    out = capsys.readouterr().out
    assert "1 earlier record(s) ran other simulation code or another version of their scenario" in out
    after = read_jsonl(tmp_path / "ev" / "records.jsonl")
    assert len(after) == 1 and after[0]["scenario_key"] != before[0]["scenario_key"]
    assert read_jsonl(tmp_path / "ev" / "records.set_aside.jsonl") == before  # set aside, not deleted


def test_evaluation_resume_judges_again_what_other_oracle_code_judged(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """Records carry the oracles' code (``judge``; the metrics and the decision oracle are outside
    the simulation's fingerprint): a record judged by other oracle code is simulated again, not
    counted with today's rules."""
    from agents import evaluate
    from deft_gym.files import read_jsonl, write_atomic
    from deft_gym.metrics.oracle import oracle_code

    args = ["--methods", "random", "--budget", "1", "--scenarios", "lane_follow_static", "--placements", "closest",
            "--held-out", "0", "--repeats", "1", "--no-progress", "--workers", "1", "--out", str(tmp_path / "ev")]
    assert evaluate.main(args) == 0
    rec = read_jsonl(tmp_path / "ev" / "records.jsonl")
    assert [r["judge"] for r in rec] == [oracle_code()]
    write_atomic(tmp_path / "ev" / "records.jsonl", json.dumps({**rec[0], "judge": "0ld0rac1"}) + "\n")
    capsys.readouterr()
    assert evaluate.main(args) == 0
    assert "1 earlier record(s) ran other simulation code" in capsys.readouterr().out
    assert [r["judge"] for r in read_jsonl(tmp_path / "ev" / "records.jsonl")] == [oracle_code()]


def test_rl_evaluation_records_do_not_depend_on_what_the_worker_ran_before(tmp_path: Path) -> None:
    """The policy samples its actions with torch's RNG: each episode seeds it, so an RL job gives
    the same records whichever jobs its worker process ran before (it did not: the evaluation's RL
    rows depended on the worker's history)."""
    import torch
    from stable_baselines3 import PPO

    from agents import evaluate
    from deft_gym.envs.adversary import AdversaryEnv

    model = tmp_path / "model.zip"
    PPO("MlpPolicy", AdversaryEnv(config={"scenarios": ["lane_follow_static"]}), n_steps=64, seed=0).save(model)
    job = {"method": "rl", "placement": "closest", "scenario": "lane_follow_static", "scenario_kind": "seed",
           "repeat": 0, "budget": 2, "seed": 5, "env": {"max_added": 8}, "model": str(model),
           "deterministic": False, "out": str(tmp_path / "ev"), "log_failures": False, "max_added": 8}
    first = evaluate.run_job(job)
    torch.rand(1000)  # another job's sampling in between
    again = evaluate.run_job(job)
    assert without_timings(first) == without_timings(again)
    assert any(r["added"] for r in first)  # the policy acted


def test_workers_end_when_the_campaign_process_is_killed(tmp_path: Path) -> None:
    """``kill -9`` of the process that runs the pool: its workers end too (they used to go on
    simulating, and writing into the run folder, beside the run that resumes it)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "campaign.py"
    script.write_text(
        "import os, sys, time\n"
        "from deft_gym.execution import Backend, Executor\n"
        "def work(item):\n"
        "    print(os.getpid(), flush=True)\n"
        "    time.sleep(60)\n"
        "if __name__ == '__main__':\n"
        "    sys.path.insert(0, os.path.dirname(__file__))\n"
        "    import campaign\n"
        "    with Executor(Backend(workers=2)) as ex:\n"
        "        list(ex.map(campaign.work, [1, 2]))\n")
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": f"{tmp_path}:{os.environ.get('PYTHONPATH', '')}"})
    workers = [int(proc.stdout.readline()) for _ in range(2)]
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    deadline = time.time() + 20
    alive = workers
    while alive and time.time() < deadline:
        time.sleep(0.2)
        alive = [p for p in alive if _alive(p)]
    assert not alive, f"workers {alive} outlived the killed campaign"


def _alive(pid: int) -> bool:
    import os

    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (exited, not yet reaped by its parent) is gone too
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def test_online_methods_records_name_their_late_statics_rule_and_resume_only_under_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Random actions place while the scenario runs: their records say under which rule a failure
    was confirmed (late static objects there from the start, by default), and a resumed evaluation
    under the other rule simulates them again instead of counting them."""
    from agents import evaluate
    from deft_gym.files import read_jsonl

    args = ["--methods", "random_online", "--budget", "2", "--scenarios", "lane_follow_static",
            "--placements", "closest", "--held-out", "0", "--no-progress", "--workers", "1",
            "--out", str(tmp_path / "ev")]
    assert evaluate.main(args) == 0
    first = read_jsonl(tmp_path / "ev" / "records.jsonl")
    assert len(first) == 2 and {r["late_statics"] for r in first} == {"from_start"}
    assert json.loads((tmp_path / "ev" / "eval_config.json").read_text())["late_statics"] == "from_start"
    capsys.readouterr()
    assert evaluate.main([*args, "--late-statics", "as_placed"]) == 0
    assert "1 jobs, 2 simulated scenarios" in capsys.readouterr().out
    assert {r["late_statics"] for r in read_jsonl(tmp_path / "ev" / "records.jsonl")} == {"as_placed"}
