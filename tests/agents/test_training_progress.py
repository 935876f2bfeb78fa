"""The training curves cover the whole run: ``progress.jsonl`` gets a last line when training
ends (not only every 50th episode), and the report draws the curves from step 0 to it."""

from __future__ import annotations

import json
from pathlib import Path


def test_progress_reaches_the_end_of_training_and_the_report_draws_it(tmp_path: Path) -> None:
    from agents import train
    from deft_gym.cli.report import write_report
    from deft_gym.files import read_jsonl

    out = tmp_path / "tr"
    assert train.main(["--config", "configs/train/demo.yaml", "--out", str(out), "--timesteps", "64",
                       "--render", "none", "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    progress = read_jsonl(out / "progress.jsonl")
    assert 0 < summary["episodes"] < 50  # fewer than the 50 episodes between regular lines
    assert progress and progress[-1]["episodes"] == summary["episodes"]
    assert progress[-1]["timesteps"] == summary["timesteps"] >= 64
    # how busy the cores were: CPU over wall x cores, a share (the envs' CPU comes from their reports)
    assert summary["cores"] >= 1 and 0 < summary["cores_busy"] <= 1.5
    assert abs(summary["cores_busy"] - train.cores_busy(summary["cpu_seconds"], summary["train_seconds"],
                                                        summary["cores"])) < 0.05
    page = write_report(out, draw=False).read_text()
    assert 'alt="training curves"' in page and "too few progress records" not in page
