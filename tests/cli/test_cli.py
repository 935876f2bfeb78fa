"""The ``deft-gym`` command and the conventions every program shares: help with defaults on every
option, fast help (no simulation imported), --version, the shared flags, one-line errors with
exit status 2, the module entry points, and the Makefile's Python 3.11 check."""

from __future__ import annotations

import contextlib
import importlib
import io
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from deft_gym.cli import common
from deft_gym.cli.main import COMMANDS
from deft_gym.cli.main import main as deft_gym

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("torch", "stable_baselines3", "highway_env", "matplotlib", "deft_gym.sim.simulation", "shapely", "scipy.stats")


def _help(name: str) -> str:
    """``deft-gym NAME --help`` in this process."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), pytest.raises(SystemExit) as exc:
        deft_gym([name, "--help"])
    assert exc.value.code == 0
    common.INVOKED_AS = None
    return buf.getvalue()


def _options(text: str) -> dict[str, str]:
    """Option -> its help text, from argparse's help output."""
    out: dict[str, str] = {}
    current = None
    for line in text.splitlines():
        m = re.match(r"^  (-{1,2}[\w-]+)", line)
        if m:
            current = m.group(1)
            out[current] = line
        elif current and line.startswith("    "):
            out[current] += " " + line.strip()
        elif not line.strip():
            current = None
    return out


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_option_of_every_command_has_help_with_its_default(name: str) -> None:
    text = _help(name)
    assert text.startswith(f"usage: deft-gym {name}")
    opts = _options(text)
    assert "--version" in opts
    for opt, line in opts.items():
        if opt in ("-h", "--help", "--version"):
            continue
        assert "default" in line, f"deft-gym {name} {opt}: no default in its help: {line!r}"


def test_help_imports_no_simulation() -> None:
    code = ("import sys, importlib; from deft_gym.cli.main import COMMANDS\n"
            "for mod, _ in COMMANDS.values(): importlib.import_module(mod)\n"
            f"print(sorted(m for m in {HEAVY!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "[]", f"importing the programs loads {out.stdout.strip()}"
    from deft_gym.robustness.stress import SUBCOMMANDS

    # every command's help (and the stress subcommands'), each in a fresh interpreter: what it
    # imports, not how long it takes (a timed test fails on a loaded machine); the CPU time it
    # costs is 0.3-0.9 s on a 2-core machine, most of it pydantic, mcap and extract for the
    # commands that build their parser from a config
    show = ("import sys; from deft_gym.cli.main import main\n"
            "try:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
            f"print(sorted(m for m in {HEAVY!r} if m in sys.modules))")
    calls = [["--help"], ["--version"]] + [[name, "--help"] for name in sorted(COMMANDS)]
    calls += [["stress", sub, "--help"] for sub in SUBCOMMANDS]
    for argv in calls:
        out = subprocess.run([sys.executable, "-c", show, *argv], capture_output=True, text=True, cwd=ROOT,
                             check=True)
        assert out.stdout.splitlines()[-1] == "[]", f"deft-gym {' '.join(argv)} loads {out.stdout.splitlines()[-1]}"


def test_version_and_top_level_help(capsys) -> None:
    assert deft_gym(["--version"]) == 0
    assert re.match(r"deft-gym \d+\.\d+", capsys.readouterr().out)
    assert deft_gym(["--help"]) == 0
    text = capsys.readouterr().out
    assert all(f"  {name} " in text for name in COMMANDS)
    assert deft_gym(["no-such-command"]) == 2
    assert "unknown command 'no-such-command'" in capsys.readouterr().err


def test_shared_flags_mean_the_same_everywhere() -> None:
    with_out = ["run", "calibrate", "generate", "bench", "extract", "train", "evaluate", "stress", "demo",
                "record", "extract-eval", "planner-edits", "log-damage", "render", "report"]
    for name in with_out:
        opts = _options(_help(name))
        assert "--out" in opts, name
        assert re.search(r"default: (runs/|beside|DIR/)", opts["--out"]), (name, opts["--out"])
        assert "--no-progress" in opts and "--quiet" in opts, name
    for name in ("calibrate", "extract", "stress", "extract-eval"):
        assert f"the CPUs, {common.cpus()} here" in _options(_help(name))["--workers"], name
    for name in ("run", "calibrate", "generate", "extract-eval", "record", "planner-edits"):
        assert "fresh seeds from the OS" in _options(_help(name))["--jitter-seed"], name
    for name in ("calibrate", "evaluate", "stress", "extract-eval", "digest", "planner-edits", "bench-env"):
        assert "--scenarios" in _options(_help(name)), name
    for name in ("train", "evaluate", "stress", "extract", "run"):
        assert "{failures,all,none}" in _options(_help(name))["--render"], name
    for name in ("run", "calibrate", "generate", "extract", "train", "evaluate", "stress", "demo", "record",
                 "extract-eval"):
        help_text = _options(_help(name))["--watchdog-s"]
        assert "hang" in help_text and "DEFT_GYM_WATCHDOG_S" in help_text and "else 10" in help_text, name


def test_scenarios_take_spaces_and_commas() -> None:
    from agents.evaluate import parse_args

    args = parse_args(["--scenarios", "left_turn,take_exit", "u_turn", "--methods", "rl,random", "--out", "x"])
    assert args.scenarios == ["left_turn", "take_exit", "u_turn"] and args.methods == ["rl", "random"]


@pytest.mark.parametrize("argv, flag", [
    (["run", "left_turn", "--reruns", "0"], "--reruns"),
    (["extract", "/no/such/log.mcap", "--out", "x"], "/no/such/log.mcap"),
    (["extract", "x.mcap", "--theta", "-1"], "--theta"),
    (["render", "/no/such/folder"], "LOG|episode.json|DIR"),
    (["report", "/no/such/folder"], "DIR"),
    (["stress", "--budget", "0"], "--budget"),
    (["evaluate", "--methods", "nope", "--out", "/tmp/deft-gym-x"], "methods"),
    (["run", "left_turn", "--watchdog-s", "0"], "--watchdog-s"),
    (["extract", "x.mcap", "--watchdog-s", "nan"], "--watchdog-s"),
    (["stress", "--watchdog-s", "inf"], "--watchdog-s"),
    (["evaluate", "--watchdog-s", "-1"], "--watchdog-s"),
    (["calibrate", "--watchdog-s", "soon"], "--watchdog-s"),
])
def test_bad_input_is_one_line_naming_the_flag_exit_2(argv: list[str], flag: str, capfd) -> None:
    try:
        code = deft_gym(argv)
    except SystemExit as exc:
        code = exc.code
    finally:
        common.INVOKED_AS = None
    err = capfd.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and flag in err, err


@pytest.mark.parametrize("module", ["agents.train", "extract", "deft_gym.cli.run"])
def test_module_entry_points_keep_working(module: str) -> None:
    out = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0 and out.stdout.startswith(f"usage: python -m {module}")


def test_every_program_module_has_a_main() -> None:
    for module, _ in COMMANDS.values():
        assert callable(importlib.import_module(module).main), module
    from deft_gym.experiments.extract_eval import MODES
    from extract.search import MODES as SEARCH_MODES

    assert tuple(SEARCH_MODES) == MODES  # the light parser's copy


def test_make_refuses_another_python(tmp_path: Path) -> None:
    fake = tmp_path / "python3.12"
    fake.write_text("#!/bin/sh\ncase \"$*\" in *platform*) echo 3.12.1;; *) exit 1;; esac\n")
    fake.chmod(0o755)
    env = {k: v for k, v in os.environ.items() if not k.startswith("MAKE")}
    out = subprocess.run(["make", "-s", "check-python", f"PYTHON={fake}"], capture_output=True, text=True, cwd=ROOT,
                         env=env)
    assert out.returncode != 0 and "needs Python 3.11" in out.stderr and "3.12.1" in out.stderr
    out = subprocess.run(["make", "-s", "check-python", "PYTHON=no-such-python3.11"], capture_output=True, text=True,
                         cwd=ROOT, env=env)
    assert out.returncode != 0 and "was not found" in out.stderr


FOLDER_OUT = ["run", "calibrate", "generate", "extract", "train", "evaluate", "stress", "demo", "record",
              "extract-eval", "planner-edits", "log-damage", "render", "bench-scale"]


@pytest.mark.parametrize("name", FOLDER_OUT)
def test_out_that_is_a_file_is_one_line_before_any_work(name: str, tmp_path, capsys) -> None:
    """A program that writes a folder refuses an --out that names an existing file (exit 2, one
    line naming the flag), before it imports the simulation or writes anything."""
    afile = tmp_path / "afile"
    afile.write_text("the user's file")
    positional = {"run": ["left_turn"], "extract": [str(tmp_path / "x.mcap")], "render": [str(tmp_path)]}
    with pytest.raises(SystemExit) as exc:
        deft_gym([name, *positional.get(name, []), "--out", str(afile)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--out" in err and "is a file" in err, err
    assert afile.read_text() == "the user's file"
