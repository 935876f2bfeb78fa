"""Console tables never cut a value: on a 100-column terminal (a real pseudo-terminal) headers
wrap and values stay whole; piped (a CI log) every value is printed in full."""

from __future__ import annotations

import fcntl
import os
import pty
import re
import struct
import subprocess
import sys
import termios
from pathlib import Path

import pytest

from deft_gym.config import CONFIG_DIR

FLAKY = CONFIG_DIR / "scenarios" / "handwritten" / "stopped_bus.yaml"  # the demo's: 1002 collides, 1003 completes
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def in_terminal(argv: list[str], columns: int = 100, cwd: Path | None = None) -> str:
    """The output of ``python argv...`` on a pseudo-terminal ``columns`` wide (ANSI codes removed)."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 50, columns, 0, 0))
    env = {**os.environ, "COLUMNS": str(columns), "TERM": "xterm"}
    proc = subprocess.Popen([sys.executable, *argv], stdout=slave, stderr=slave, stdin=subprocess.DEVNULL,
                            env=env, cwd=cwd)
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 65536)
        except OSError:  # the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    proc.wait(timeout=300)
    os.close(master)
    assert proc.returncode == 0, b"".join(chunks)[-2000:]
    return ANSI.sub("", b"".join(chunks).decode(errors="replace")).replace("\r", "")


def piped(argv: list[str], cwd: Path | None = None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    proc = subprocess.run([sys.executable, *argv], capture_output=True, text=True, env=env, cwd=cwd, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def table_lines(text: str) -> list[str]:
    """The lines of the first table: its (wrapped) header lines, its rule and its rows."""
    lines = text.splitlines()
    rule = next(i for i, ln in enumerate(lines) if "────" in ln)
    start = rule
    while start > 0 and lines[start - 1].strip():
        start -= 1
    end = next((i for i in range(rule + 1, len(lines)) if not lines[i].strip() or lines[i].startswith(("wrote", "1/"))),
               len(lines))
    return lines[start:end]


@pytest.fixture(scope="module")
def reruns(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("tables")


def test_run_table_fits_100_columns_and_prints_every_value(reruns: Path) -> None:
    argv = ["-m", "deft_gym.cli.run", str(FLAKY), "--reruns", "2", "--jitter-seed", "1002", "--render", "none",
            "--no-progress"]
    tty = in_terminal([*argv, "--out", str(reruns / "a")])
    body = table_lines(tty)
    assert "…" not in tty and all(len(ln) <= 100 for ln in body), "\n".join(body)
    assert re.search(r"0 +collision +bus .* 1002 +\(reference\)", tty), tty
    assert "completed" in tty and "timeout" not in tty  # rerun 1 passes the bus, printed whole
    pipe = piped([*argv, "--out", str(reruns / "b")])
    assert "…" not in pipe and "same plans as rerun 0" in pipe and "not compared" in pipe


def test_extract_table_fits_100_columns_and_prints_every_value(reruns: Path, tmp_path: Path) -> None:
    log = reruns / "a" / "0" / "episode.mcap"
    if not log.exists():
        pytest.skip("needs the run of the test before")
    argv = ["-m", "deft_gym.cli.extract", str(log), "--render", "none", "--no-progress"]
    tty = in_terminal([*argv, "--out", str(tmp_path / "a")])
    assert "…" not in tty and "100.0%" in tty and "frame " in tty, tty
    assert all(len(ln) <= 100 for ln in table_lines(tty)), tty
    pipe = piped([*argv, "--out", str(tmp_path / "b")])
    assert "…" not in pipe and "100.0%" in pipe and "ms/frame" in pipe


def test_markdown_tables_and_units_are_printed_whole() -> None:
    """``print_markdown`` (the evaluation's headline) and ``print_table`` with a unit in brackets."""
    from rich.console import Console

    from deft_gym.cli.common import print_markdown, print_table, table

    md = ("A caption.\n\n| method | placement | budget | root causes | failures seeds | failures held-out |\n"
          "|---|---|---|---|---|---|\n| RL (PPO) | closest | 100 | **149.4 ± 12.0** | 458.4 ± 5.7 | 282.6 ± 11.4 |\n")
    for terminal, width in ((True, 40), (True, 100), (False, 80)):
        con = Console(force_terminal=terminal, width=width, record=True, color_system=None)
        print_markdown(con, md)
        t = table(title="stress")
        t.add_column("measure")
        t.add_column("value", justify="right")
        t.add_row("wall time \\[s]", "1234567")
        print_table(con, t)
        out = con.export_text()
        assert "…" not in out and "wall time [s]" in out and "1234567" in out, out
        words = out.split()
        assert all(w in words for w in ["RL", "(PPO)", "149.4", "±", "12.0", "458.4", "5.7", "282.6", "11.4"]), out
        if terminal:  # fitted: within the terminal; a value of several words may wrap at its spaces
            assert max(len(ln.rstrip()) for ln in out.splitlines()) <= width, out
        if width == 40:  # too narrow for the row: turned, a line per column
            assert re.search(r"failures held-out +282\.6 ± 11\.4", out), out
        if width >= 100:  # room enough: every value on one line
            assert "149.4 ± 12.0" in out and "282.6 ± 11.4" in out and "RL (PPO)" in out, out


def test_stress_summary_keeps_its_units(tmp_path: Path, capsys) -> None:
    """``deft-gym stress``'s summary table: ``wall time [s]`` is printed with its unit (rich
    markup would take ``[s]`` for a style)."""
    from deft_gym.robustness.stress import print_summary

    s = {"hardening": False, "runs": 12, "crashes": 1, "hangs": 0, "runs_with_violations": 2,
         "runs_with_findings": 3, "harness_errors": 0, "violations": {"speed_limit": 2}, "wall_time_s": 61.0,
         "findings": {"crash:planning:ValueError": {"runs": 1, "first_run": 4}}, "minimised": [], "planted": {}}
    print_summary(s, tmp_path)
    out = capsys.readouterr()
    text = out.out + out.err
    assert "wall time [s]" in text and "61" in text and "crash:planning:ValueError" in text and "…" not in text
