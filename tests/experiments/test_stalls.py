"""`python -m deft_gym.experiments.stalls`: bad input is one clear line and exit status 2, nothing
written (the stall taken apart on a real extraction is checked in tests/extract/test_generated.py)."""

from __future__ import annotations

from pathlib import Path

from deft_gym.experiments.stalls import main


def test_bad_input_is_one_line_and_writes_nothing(tmp_path: Path, capsys) -> None:
    out = tmp_path / "out"
    assert main([str(tmp_path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no frames.jsonl" in err and str(tmp_path) in err
    assert main([str(tmp_path), "--variant", "{not json", "--out", str(out), "--quiet"]) == 2
    assert "--variant: not JSON" in capsys.readouterr().err
    assert main([str(tmp_path), "--variant", "[1, 2]", "--out", str(out), "--quiet"]) == 2
    assert "expected a JSON object" in capsys.readouterr().err
    assert not out.exists()
