"""`make demo`: what DeFT-Gym is for, end to end, in a few minutes.

1. a system-level test - one scenario on the jittered multi-module ADS - rerun 10 times: only
   the module timing differs, yet some reruns collide and some do not (flaky);
2. DeFT extracts planning-module tests from the log of a colliding rerun;
3. the extracted failure test runs 10 times: it fails every time (deterministic), in a fraction
   of the time of a system rerun;
4. the RL adversary shipped in the package (``deft_gym/models/adversary``, trained by
   ``configs/train/adversary.yaml``) is compared with random actions in its env, Decictor-GA and
   Random-delta at an equal, small budget - the numbers as they come out, root causes first - and
   its failures become tests too (``--train``: train a small one first, ``configs/train/demo.yaml``);
5. one HTML report of all of it (``OUT/report.html``), with a picture of every failure.

    deft-gym demo [--out runs/demo] [--budget 16] [--train [--timesteps 1536]]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shutil
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any

from deft_gym.cli import common

FLAKY = ("scenarios", "handwritten", "stopped_bus.yaml")  # in configs/: overtaking a stopped bus
JITTER_SEED = 1000  # the reruns' jitter seeds: 1000..1009 (a reproducible demo)

MARKER = ".agents-demo"  # in --out: train/ and eval/ there are the demo's and may be replaced


def build_parser() -> common.Parser:
    p = common.parser("demo", "deft_gym.cli.demo", __doc__)
    common.add_out(p, common.RUNS / "demo")
    p.add_argument("--train", action="store_true",
                   help="train a small adversary first instead of using the shipped one (default: off)")
    p.add_argument("--config", type=Path, default=None,
                   help="with --train: adversary training YAML (default: configs/train/demo.yaml)")
    p.add_argument("--timesteps", type=int, default=None, help="with --train: training steps (default: the config's)")
    p.add_argument("--scenario", default="take_exit",
                   help="the scenario of the adversary comparison (default: take_exit)")
    p.add_argument("--budget", type=int, default=16, help="simulated scenarios per method in the evaluation")
    p.add_argument("--reruns", type=common.positive_int, default=10, help="system reruns and test runs")
    p.add_argument("--skip-adversary", action="store_true", help="only the flaky -> deterministic part")
    common.add_watchdog(p)
    common.add_output_flags(p)
    return p


def _quietly(fn: Any, *args: Any) -> Any:
    """Call ``fn`` with its prints (not its progress bars: they go to stderr) held back."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        return fn(*args)


def _pytest(paths: list[Path], select: str | None = None) -> dict[str, Any]:
    """One pytest run of ``paths``: counts of passed / failed / xfailed and the wall time [s]."""
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=", "-W", "ignore",
           "--durations=0", "--durations-min=0", *(["-k", select] if select else []), *map(str, paths)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    last = (proc.stdout.strip().splitlines() or [""])[-1]
    counts: dict[str, Any] = {k: 0 for k in ("passed", "failed", "xfailed", "error", "deselected")}
    took = last.rsplit(" in ", 1)[-1].split("s")[0] if " in " in last else ""
    counts["session_seconds"] = float(took) if took.replace(".", "", 1).isdigit() else seconds
    # the tests' own time: the "call" phases of pytest's --durations report
    calls = [ln.split()[0] for ln in proc.stdout.splitlines() if " call " in ln and ln.split()[0].endswith("s")]
    counts["call_seconds"] = sum(float(c[:-1]) for c in calls if c[:-1].replace(".", "", 1).isdigit())
    for part in last.strip("= ").split(","):
        words = part.split()
        if len(words) >= 2 and words[0].isdigit():
            key = words[1].rstrip("s") if words[1].startswith("error") else words[1]
            counts[key] = counts.get(key, 0) + int(words[0])
    return {**counts, "seconds": seconds, "summary": last.strip("= "), "code": proc.returncode}


def flaky_story(out: Path, reruns: int, con: Any) -> dict[str, Any]:
    """Steps 1-3 (see the module docstring)."""
    from deft_gym.cli import run as run_cli
    from deft_gym.config import CONFIG_DIR

    scenario = CONFIG_DIR.joinpath(*FLAKY)
    runs = out / "reruns"
    con.print(f"[bold][1/5][/bold] a system-level test, rerun {reruns} times: {scenario.stem} (overtaking a "
              f"stopped bus), jitter seeds {JITTER_SEED}-{JITTER_SEED + reruns - 1}", soft_wrap=True)
    _quietly(run_cli.main, [str(scenario), "--reruns", str(reruns), "--jitter-seed", str(JITTER_SEED),
                            "--out", str(runs), "--render", "failures", "--quiet"])
    s = json.loads((runs / "summary.json").read_text())
    rerun_s = sum(r["wall_time"] for r in s["reruns"]) / reruns  # the simulation alone, without pictures
    marks = "".join("X" if r["collision"] else "." for r in s["reruns"])
    hit = [r for r in s["reruns"] if r["collision"]]
    con.print(f"      {marks}   {len(hit)} of {reruns} reruns collide (X) - the same test, only the module "
              f"timing differs: flaky", soft_wrap=True)
    story: dict[str, Any] = {"scenario": str(scenario), "reruns": reruns, "collided": len(hit),
                             "pattern": marks, "rerun_seconds": rerun_s}
    if not hit:
        story["story"] = f"No rerun of {scenario.stem} collided this time (0 of {reruns}); nothing to extract."
        con.print("      [yellow]no collision to extract[/yellow] (the planner or the scenario changed?)")
        return story
    first = hit[0]
    tests_root = out / "reruns_tests"
    ext = tests_root / str(first["rerun"])
    con.print(f"[bold][2/5][/bold] DeFT extracts planning-module tests from the log of rerun {first['rerun']} "
              f"(collided with {first['collision_detail']['participant']} at {first['collision_detail']['time']:.2f} s)",
              soft_wrap=True)
    from deft_gym.cli.extract import main as extract_main

    _quietly(extract_main, [first["log"], "--out", str(ext), "--render", "failures", "--quiet"])
    es = json.loads((ext / "summary.json").read_text())
    f = es.get("faulty_trajectory")
    con.print(f"      {es['reproduced_at_theta']} of {es['frames']} planning outputs reproduced bit-exactly from "
              f"the log; the planner's failing plan (P_faulty) is frame {f['index']} at t={f['time']:.2f} s"
              if f else f"      {es['frames']} frames; no plan into the collision found", soft_wrap=True)
    test = Path(es["test_path"])
    con.print(f"[bold][3/5][/bold] the extracted failure test, run {reruns} times ({test.name})")
    results = [_pytest([test], "does_not_plan_into_collision") for _ in range(reruns)]
    failed = sum(1 for r in results if r["failed"])
    test_s = sum(r["call_seconds"] for r in results) / len(results)
    session_s = sum(r["session_seconds"] for r in results) / len(results)
    repro = _pytest([test], "reproduces")
    con.print(f"      {'F' * failed}{'.' * (reruns - failed)}   fails {failed} of {reruns} runs: deterministic. The test "
              f"takes {test_s:.3f} s (its pytest session {session_s:.1f} s, mostly imports and loading "
              f"{repro['passed']} frames); a system rerun simulates for {rerun_s:.2f} s and collides in "
              f"{len(hit)} of {reruns}", soft_wrap=True)
    con.print(f"      its {repro['passed']} reproduction tests pass: the replayed frames give the recorded plans",
              soft_wrap=True)
    story.update(test=str(test), test_runs=reruns, test_failed=failed, test_seconds=test_s,
                 test_session_seconds=session_s,
                 reproduction=repro["summary"], extraction=str(ext),
                 story=f"{len(hit)} of {reruns} system-level reruns of {scenario.stem} collided ({marks}); the "
                       f"planning-module test DeFT extracted from rerun {first['rerun']} failed {failed} of {reruns} "
                       f"runs.")
    return story


def adversary_story(args: Any, out: Path, con: Any) -> dict[str, Any]:
    """Step 4 (see the module docstring)."""
    from agents import evaluate, train
    from deft_gym.config import CONFIG_DIR
    from deft_gym.models import default_model

    for part in ("train", "eval"):  # the demo's own outputs (its marker says so): a new demo replaces them
        if (out / part).exists():
            shutil.rmtree(out / part)
    model = default_model()
    story: dict[str, Any] = {}
    if args.train or not model.exists():
        config = args.config or CONFIG_DIR / "train" / "demo.yaml"
        steps = args.timesteps or train.load_train_config(config).timesteps
        why = "" if args.train else " (no adversary ships with this copy)"
        con.print(f"[bold][4/5][/bold] a small RL adversary learns where to place obstacles{why} ({steps} env steps) ...")
        t0 = time.perf_counter()
        targs = ["--config", str(config), "--out", str(out / "train"), "--quiet", "--render", "failures"]
        if args.timesteps:
            targs += ["--timesteps", str(args.timesteps)]
        if _quietly(train.main, targs) != 0:
            raise RuntimeError("training failed")
        model = out / "train" / "model.zip"
        ts = json.loads((out / "train" / "summary.json").read_text())
        con.print(f"      {ts['episodes']} episodes in {time.perf_counter() - t0:.0f} s - far too few to learn much: "
                  "the shipped adversary trained on ~10,000", soft_wrap=True)
    else:
        ts = json.loads((model.parent / "summary.json").read_text())
        con.print(f"[bold][4/5][/bold] the shipped RL adversary (trained on {ts['episodes']:,} episodes by "
                  "configs/train/adversary.yaml) ...", soft_wrap=True)
    story["train"] = ts
    story["model"] = str(model)
    scenario, methods = args.scenario, ["rl", "random_online", "decictor", "random_delta"]
    con.print(f"      against random actions, Decictor-GA and Random-delta on {scenario}, {args.budget} simulated "
              "scenarios each ...", soft_wrap=True)
    eargs = ["--methods", *methods, "--budget", str(args.budget), "--repeats", "1", "--scenarios",
             scenario, "--held-out", "0", "--placements", "closest", "--model", str(model),
             "--out", str(out / "eval"), "--log-failures", "--quiet", "--render", "failures"]
    if _quietly(evaluate.main, eargs) != 0:
        raise RuntimeError("evaluation failed")
    summary = json.loads((out / "eval" / "summary.json").read_text())
    labels = {"rl": "RL adversary", "random_online": "random actions", "decictor": "Decictor-GA",
              "random_delta": "Random-delta"}
    lines = []
    for m in methods:
        cell = ((summary.get("per_scenario", {}).get(m, {}).get("closest") or {}).get(scenario)) or {}
        c = {k: (v["mean"] if isinstance(v, dict) else v) for k, v in cell.items()}
        if c:
            lines.append(f"{labels[m]}: {c['root_causes']:g} root cause(s) outside the ego's lane "
                         f"({c['root_causes_in_lane']:g} with them), {c['failures']:g} failures ({c['collisions']:g} "
                         f"collisions + {c['nods']:g} NoDS), {c['task_failures']:g} task failures")
    for line in lines:
        con.print(f"      {line}", soft_wrap=True)
    con.print(f"      (one repeat of {args.budget} scenarios: a glimpse, not a result - docs/search.md has the "
              "evaluation)", soft_wrap=True)
    tests = sorted((out / "train").rglob("extracted/test_*.py")) + sorted((out / "eval").rglob("extracted/test_*.py"))
    if tests:
        r = _pytest(tests)
        con.print(f"      {len(tests)} planning-module test module(s) extracted from the failures: "
                  f"{r['failed']} failure test(s) fail (the failures reproduced: a plan into the collision, a "
                  f"plan off the optimal path), {r['passed']} reproduction tests pass", soft_wrap=True)
        story["tests"] = [str(t) for t in tests]
    else:
        con.print("      no failure this time, so no test extracted from one", soft_wrap=True)
    story.update(scenario=scenario, budget=args.budget,
                 story=f"On {scenario}, {args.budget} simulated scenarios per method (one repeat): " + "; ".join(lines)
                 + ".")
    return story


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    with common.watchdog_env(args):
        return _main(args)


def _main(args: argparse.Namespace) -> int:
    con = common.console(args)
    os.environ.setdefault("PYTHONWARNINGS", "ignore")  # the demo shows results, not library warnings
    warnings.simplefilter("ignore")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        return common.cli_error(f"--out {out}: is a file; expected a folder for the demo's outputs")
    marker = out / MARKER
    if not marker.exists() and any((out / part).exists() for part in ("flaky", "train", "eval")):
        return common.cli_error(f"--out {out}: holds flaky/, train/ or eval/ that deft_gym.cli.demo did not write "
                                f"(no {MARKER}); choose another --out")
    with common.locked_out(out):
        return _demo(args, con, out, marker)


def _demo(args: argparse.Namespace, con: Any, out: Path, marker: Path) -> int:
    out.mkdir(parents=True, exist_ok=True)
    marker.write_text("written by deft_gym.cli.demo; a new demo into this folder replaces flaky/, train/ and eval/\n")
    t0 = time.perf_counter()
    doc: dict[str, Any] = {"created": time.strftime("%Y-%m-%dT%H:%M:%S")}
    doc["flaky"] = flaky_story(out / "flaky", args.reruns, con)
    if not args.skip_adversary:
        doc["adversary"] = adversary_story(args, out, con)
    doc["seconds"] = round(time.perf_counter() - t0, 1)
    from deft_gym.files import write_json_atomic

    write_json_atomic(out / "demo.json", doc)
    con.print("[bold][5/5][/bold] the report ...")
    from deft_gym.cli.report import write_report

    report = write_report(out)
    test = doc["flaky"].get("test")
    shown = common.shown
    con.print(f"\ndone in {doc['seconds']:.0f} s. Next:", soft_wrap=True)
    con.print(f"  open the report       {shown(report)}", soft_wrap=True)
    if test:
        con.print(f"  run the failing test  {common.tool('pytest')} {shown(test)}", soft_wrap=True)
    if not args.skip_adversary and (out / "train" / "tb").exists():
        con.print(f"  training curves       {common.tool('tensorboard')} --logdir {shown(out / 'train' / 'tb')}",
                  soft_wrap=True)
    logs = sorted((out / "flaky" / "reruns").glob("*/episode.mcap"))
    if logs:
        con.print(f"  a log in Foxglove     open {shown(logs[0])} with the layout configs/foxglove/layout.json",
                  soft_wrap=True)
    con.print(f"  any command           {common.tool('deft-gym')} --help", soft_wrap=True)
    if common.tool("deft-gym") != "deft-gym":
        con.print("  (or first: source .venv/bin/activate, then the commands without .venv/bin/)", soft_wrap=True)
    if args.quiet:
        print(f"report: {shown(report)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
