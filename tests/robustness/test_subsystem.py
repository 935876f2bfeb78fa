"""Subsystem replay testing on DeFT-extracted frames: findings become failing pytest tests."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from deft_gym.robustness.subsystem import FrameCase, FrameReplay, run_subsystem
from deft_gym.sim.simulation import run_episode

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> Path:
    extract = pytest.importorskip("extract")
    d = tmp_path_factory.mktemp("episode")
    r = run_episode(ROOT / "configs/scenarios/left_turn.yaml", jitter_seed=0, out_dir=d)
    res = extract.extract_episode(r.log_path, d / "deft", emit_tests=False)
    return Path(res.frames_path)


def test_frame_replay_finds_a_planner_crash_and_is_clean_nominally(frames: Path) -> None:
    rp = FrameReplay(frames)
    assert all(not s for s in rp.nominal)  # the unmodified frames violate nothing
    crash = rp.run(FrameCase(40, [{"role": "localization", "path": "y", "value": "float.nan"}]))
    assert crash.signatures and crash.signatures[0].startswith("crash:planner:"), crash
    ok = rp.run(FrameCase(40, [{"role": "localization", "path": "yaw_rate", "value": "float.one"}]))
    assert ok.signatures == []
    again = rp.run(FrameCase(40, [{"role": "localization", "path": "y", "value": "float.nan"}]))
    assert again.signatures == crash.signatures  # deterministic from the frame's snapshot


def test_subsystem_campaign_emits_failing_tests(frames: Path, tmp_path: Path) -> None:
    s = run_subsystem(frames, tmp_path / "sub", budget=40, seed=3)
    assert s["harness_errors"] == 0 and s["minimised"]
    for case in s["minimised"]:
        assert case["atoms"] <= 2
    module = next((tmp_path / "sub").glob("test_robustness_*.py"))
    cases = json.loads((tmp_path / "sub" / "cases.json").read_text())
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(module)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    # every emitted test reproduces its finding: it fails until the planner is fixed
    assert f"{len(cases)} failed" in proc.stdout, proc.stdout[-2000:]
