"""`python -m deft_gym.experiments.off_road`: bad input is one clear line and exit status 2, nothing
written (a violation taken apart on a real log is checked in tests/extract/test_generated.py)."""

from __future__ import annotations

from pathlib import Path

from deft_gym.experiments.off_road import main


def test_bad_input_is_one_line_and_writes_nothing(tmp_path: Path, capsys) -> None:
    out = tmp_path / "out"
    assert main([str(tmp_path / "runs"), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no episode.mcap found" in err
    bad = tmp_path / "suite" / "s" / "0" / "episode.mcap"
    bad.parent.mkdir(parents=True)
    bad.write_text("not a log")
    assert main([str(tmp_path / "suite"), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "not an MCAP file" in err and str(bad) in err
    assert not out.exists()
