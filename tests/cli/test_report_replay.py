"""Every failure card of the HTML report has a replay command, and that command, run as printed,
reproduces the recorded outcome: a search baseline's failure (the scenario with its added
participants from the start) and an RL env episode (participants added mid-run), both stored in
the one shape of a failure's scenario (``deft_gym.search.episode.replay_record``)."""

from __future__ import annotations

import json
import re
import shlex
from html import unescape
from pathlib import Path

import numpy as np

from deft_gym.files import write_json_atomic


def _replays(report: Path) -> list[list[str]]:
    """The replay commands (``deft-gym run ...``) of the report's cards, as argument lists."""
    text = report.read_text()
    return [shlex.split(unescape(c)) for c in re.findall(r"<pre>(deft-gym run [^<]*)</pre>", text)]


def _run_as_printed(words: list[str], out: Path) -> dict:
    """Run a printed replay command in the working directory the report was written from (its
    paths are relative to it), into ``out``; the summary of its one rerun."""
    from deft_gym.cli.run import main

    assert words[:2] == ["deft-gym", "run"] and "--jitter-seed" in words
    args = words[2:]
    i = args.index("--out")
    args[i + 1] = str(out)
    assert main([*args, "--render", "none", "--quiet"]) == 0
    return json.loads((out / "summary.json").read_text())["reruns"][0]


def _recorded(log: Path) -> dict:
    from mcap.reader import make_reader

    with open(log, "rb") as f:
        meta = {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
    return meta["deft_gym.outcome"]


def _same_outcome(again: dict, log: Path) -> None:
    """The replay's outcome record is the recorded one (outcome, sim time, closest distance,
    collision; not the wall time)."""
    rec, mine = _recorded(log), _recorded(Path(again["log"]))
    assert again["outcome"] == rec["outcome"]
    for key in ("outcome", "sim_time", "min_distance", "collision", "task_completed", "jitter_seed"):
        assert mine.get(key) == rec.get(key), key


def test_a_search_failure_card_replays_its_outcome(tmp_path: Path, monkeypatch) -> None:
    from agents.search import _run_record
    from deft_gym.cli.report import write_report
    from deft_gym.metrics.oracle import run_metrics
    from deft_gym.search.context import seed_context
    from deft_gym.search.episode import REPLAY_FORMAT, run_scenario
    from deft_gym.search.feasible import PAPER, Layout
    from tests.support.nods_helpers import place_static

    monkeypatch.chdir(tmp_path)  # the user's project folder: the report's paths are relative to it
    ctx = seed_context("lane_follow_static", PAPER)  # Decictor's rule lets it stand in the lane
    added = [place_static(ctx, Layout(ctx.areas), "STATIC_VEHICLE", 40.0, -0.5, "added_0")]  # a NoDS
    ev = tmp_path / "eval"
    d = ev / "logs" / "decictor" / "lane_follow_static" / "0"
    run = run_scenario(ctx, added, 7, out_dir=d)
    m = run_metrics(ctx, run.trace, run.verdict.collision_detail)
    rec = _run_record(ctx, run, 0, 0.0, 0.0, np.random.default_rng(0), {"mutation": "add", "specs": added}, m)
    assert rec["failure"] == "nods" and rec["scenario_equivalent"]["format"] == REPLAY_FORMAT
    write_json_atomic(d / "episode.json", {**rec, "scenario": "lane_follow_static"})  # as agents.evaluate keeps it
    (ev / "records.jsonl").write_text(json.dumps(rec) + "\n")
    write_json_atomic(ev / "eval_config.json", {"methods": ["decictor"]})
    report = write_report(ev, draw=False)
    cmds = _replays(report)
    assert len(cmds) == 1 and (d / "replay_scenario.yaml").exists()
    assert not any(Path(w).is_absolute() for w in cmds[0]), cmds  # nothing of this clone's path
    _same_outcome(_run_as_printed(cmds[0], tmp_path / "again"), d / "episode.mcap")


def test_an_rl_episode_card_replays_its_outcome_with_participants_added_mid_run(tmp_path: Path, monkeypatch) -> None:
    from deft_gym.cli.report import write_report
    from deft_gym.envs.adversary import ALONG, AT_LAST, LATERAL, OPS, AdversaryEnv
    from deft_gym.search.feasible import PAPER

    def parked(along: float | str, lateral: float) -> np.ndarray:
        i = ALONG.index(along) if along in ALONG else len(ALONG) + AT_LAST.index(along)
        return np.array([OPS.index("static_vehicle"), i, LATERAL.index(lateral), 1, 0])

    monkeypatch.chdir(tmp_path)
    # two parked cars beside the path, the second placed mid-run ahead of the ego: a NoDS
    plan = {1: parked(-10.0, -3.5), 4: parked("last+8", -2.0)}
    ev = tmp_path / "eval"
    env = AdversaryEnv(scenario="lane_follow_static", log_dir=str(ev / "logs"), keep_passing=0.0, extract=False,
                       feasible=PAPER)  # Decictor's rule: the closest rule puts the second car inside the lane
    env.reset(seed=0)
    done, k, info = False, 0, {}
    while not done:
        _, _, done, _, info = env.step(plan.get(k, np.zeros(5, dtype=np.int64)))
        k += 1
    assert info["failure"] == "nods", info
    eq = env.equivalent_scenario()
    assert eq["added_at"] and max(eq["added_at"].values()) > 0  # added while the episode ran
    (ev / "records.jsonl").write_text("{}\n")
    write_json_atomic(ev / "eval_config.json", {"methods": ["rl"]})
    report = write_report(ev, draw=False)
    cmds = _replays(report)
    assert len(cmds) == 1, report.read_text()[-3000:]
    log = next((ev / "logs").rglob("episode.mcap"))
    _same_outcome(_run_as_printed(cmds[0], tmp_path / "again"), log)
