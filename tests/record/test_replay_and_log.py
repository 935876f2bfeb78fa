"""Jitter-seed replay, the MCAP log read back with the plain mcap reader, and the truth file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from mcap.reader import make_reader

from deft_gym.bus.messages import DEFAULT_TOPICS, VIEWER_TOPICS
from deft_gym.sim.simulation import run_episode

SCENARIO = Path(__file__).resolve().parents[2] / "configs" / "scenarios" / "cross_intersection.yaml"


def _messages(path: str) -> list[tuple[str, int, int, bytes]]:
    """The bus messages of a log: topic, sim time [ns] (log_time less the log's epoch start),
    sequence number, payload bytes (the viewer topics, which carry epoch times, left out)."""
    with open(path, "rb") as fh:
        meta = next((m.metadata for m in make_reader(fh).iter_metadata() if m.name == "deft_gym.episode"), {})
    start = int(meta.get("log_start_ns", 0))
    with open(path, "rb") as fh:
        return [(ch.topic, m.log_time - start, m.sequence, m.data) for _, ch, m in make_reader(fh).iter_messages()
                if ch.topic not in VIEWER_TOPICS]


def test_same_jitter_seed_gives_byte_identical_payloads(tmp_path: Path) -> None:
    a = run_episode(SCENARIO, jitter_seed=11, out_dir=tmp_path / "a")
    b = run_episode(SCENARIO, jitter_seed=11, out_dir=tmp_path / "b")
    c = run_episode(SCENARIO, jitter_seed=12, out_dir=tmp_path / "c")
    ma, mb, mc = _messages(a.log_path), _messages(b.log_path), _messages(c.log_path)
    assert len(ma) > 1000
    assert ma == mb  # topics, publish times, sequence numbers and payload bytes
    assert ma != mc  # another seed, other timing


def test_log_holds_every_topic_and_the_metadata(lane_follow_log) -> None:
    with open(lane_follow_log.log_path, "rb") as fh:
        reader = make_reader(fh)
        topics = {ch.topic for _, ch, _ in reader.iter_messages()}
    with open(lane_follow_log.log_path, "rb") as fh:
        meta = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}
    # every bus topic (an empty light detection on a map without lights) and the viewer topics
    assert topics == set(DEFAULT_TOPICS.values()) | set(VIEWER_TOPICS)
    ep = meta["deft_gym.episode"]
    assert json.loads(ep["jitter_seed"]) == 7 and ep["scenario_name"] == "lane_follow_static"
    assert json.loads(ep["planner"])["class"] == "deft_gym.planner.lattice:LatticePlanner"
    assert meta["deft_gym.outcome"]["outcome"] == lane_follow_log.outcome.outcome


def test_truth_file_names_logged_messages(lane_follow_log) -> None:
    truth = [json.loads(line) for line in Path(lane_follow_log.truth_path).read_text().splitlines()]
    with open(lane_follow_log.log_path, "rb") as fh:
        start = int(next(m for m in make_reader(fh).iter_metadata() if m.name == "deft_gym.episode").metadata[
            "log_start_ns"])
    with open(lane_follow_log.log_path, "rb") as fh:  # log_time = the episode's epoch start + sim time
        logged = {(ch.topic, m.sequence): m.log_time - start for _, ch, m in make_reader(fh).iter_messages()}
    assert len(truth) == len(lane_follow_log.planning)
    for rec in truth:
        assert (DEFAULT_TOPICS["planning"], rec["planning_seq"]) in logged
        for topic, seq in rec["inputs"].items():
            if seq is not None:  # consumed messages were published before the frame time
                assert logged[(topic, seq)] <= rec["frame_ns"] <= rec["publish_ns"]


@pytest.mark.parametrize("background", [True, False], ids=["recorder-process", "inline"])
def test_recorder_keeps_publish_order_across_batches(tmp_path: Path, monkeypatch, background: bool) -> None:
    """Messages handed to the writer in batches keep publish order around metadata and a
    channel registered mid-run, and hold the payload as it was when published (in the
    recorder process and in this one)."""
    from deft_gym.bus.messages import Message
    from deft_gym.record.recorder import McapRecorder

    monkeypatch.setattr(McapRecorder, "BATCH", 3)
    rec = McapRecorder(tmp_path / "x.mcap", {"control": DEFAULT_TOPICS["control"]}, {"k": 1}, background=background)
    sent = []
    for i in range(8):
        topic = DEFAULT_TOPICS["control"] if i % 3 else "/extra/topic"
        payload = {"header": {"seq": i}, "v": i + 0.1}
        rec(Message(topic, i, 1000 * i, payload))
        payload["v"] = -1.0  # a later change does not reach the log
        sent.append((topic, 1000 * i, i, json.dumps({"header": {"seq": i}, "v": i + 0.1}, separators=(",", ":")).encode()))
        if i == 4:
            rec.add_metadata("mid", {"at": i})
    rec.close({"done": True})
    assert _messages(str(tmp_path / "x.mcap")) == sent
    with open(tmp_path / "x.mcap", "rb") as fh:
        names = [m.name for m in make_reader(fh).iter_metadata()]
    assert names == ["deft_gym.episode", "mid", "deft_gym.outcome"]
