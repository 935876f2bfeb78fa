"""The planner is a deterministic function of its frames - the premise DeFT stands on."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from deft_gym.bus.codec import decode, encode
from deft_gym.bus.ros1 import ChannelDecoders
from deft_gym.planner.base import Frame, load_planner
from deft_gym.sim.simulation import Simulation

SCENARIOS = Path(__file__).resolve().parents[2] / "configs" / "scenarios"
LATTICE = "deft_gym.planner.lattice:LatticePlanner"


def _record_frames(name: str, seed: int) -> tuple[dict, list[Frame], list[dict]]:
    sim = Simulation(SCENARIOS / f"{name}.yaml", jitter_seed=seed)
    frames: list[Frame] = []
    outs: list[dict] = []
    plan = sim.planner.plan

    def spy(frame: Frame) -> dict | None:
        out = plan(frame)
        if out is not None:
            frames.append(frame)
            outs.append(out)
        return out

    sim.planner.plan = spy  # type: ignore[method-assign]
    sim.run()
    return sim.scenario.map.model_dump(), frames, outs


def test_same_frames_give_bit_identical_trajectories() -> None:
    map_spec, frames, live = _record_frames("blocked_red_light", seed=5)
    assert len(frames) > 100
    for _ in range(2):
        planner = load_planner(LATTICE, map_spec, {})
        replay = [planner.plan(f) for f in frames]
        assert [encode(r) for r in replay] == [encode(r) for r in live]


def test_frames_decoded_from_json_reproduce_exactly() -> None:
    map_spec, frames, live = _record_frames("left_turn", seed=2)
    planner = load_planner(LATTICE, map_spec, {})
    for frame, expected in zip(frames, live):
        decoded = Frame(frame.time, {k: decode(encode(v)) if v is not None else None for k, v in frame.inputs.items()})
        assert encode(planner.plan(decoded)) == encode(expected)


def test_snapshot_and_restore_return_to_the_same_state() -> None:
    map_spec, frames, _ = _record_frames("lane_follow_static", seed=1)
    planner = load_planner(LATTICE, map_spec, {})
    for f in frames[:40]:
        planner.plan(f)
    snap = planner.snapshot()
    first = encode(planner.plan(frames[40]))
    planner.plan(frames[41])  # move on, then go back
    planner.restore(snap)
    assert encode(planner.plan(frames[40])) == first


def test_different_parameters_give_a_different_plan() -> None:
    map_spec, frames, live = _record_frames("lane_follow_static", seed=1)
    planner = load_planner(LATTICE, map_spec, {"w_speed": 2.0})
    diffs = [np.abs(np.array(planner.plan(f)["trajectory"]["x"]) - np.array(o["trajectory"]["x"])).max()
             for f, o in zip(frames, live)]
    assert max(diffs) > 0.01


def test_live_planning_messages_match_the_log(lane_follow_log) -> None:
    """What the recorder wrote is exactly what the planner published."""
    with open(lane_follow_log.log_path, "rb") as fh:
        decode = ChannelDecoders()
        logged = [decode(sc, ch, m.data) for sc, ch, m in make_reader(fh).iter_messages() if ch.topic == "/apollo/planning"]
    assert [encode(p) for p in logged] == [encode(p) for p in lane_follow_log.planning]
