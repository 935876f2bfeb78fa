"""`make demo`: the adversary pipeline end to end on a small budget.

1. train the RL adversary briefly on one seed scenario (``configs/train/demo.yaml``);
2. evaluate it against Random-delta at an equal budget of simulated scenarios;
3. extract planning-module tests (DeFT) from the adversary's failing episodes;
4. run the extracted tests with pytest and print a summary: the reproduction tests pass (the
   replayed frames give the recorded plans); the failure oracles of a collision fail - the
   failure reproduces deterministically in the planning module.

    python -m agents.demo --out runs/demo [--timesteps 1536] [--budget 16]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from agents import evaluate, train

MARKER = ".agents-demo"  # in --out: train/ and eval/ there are the demo's and may be replaced


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m agents.demo", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=Path("runs/demo"))
    p.add_argument("--config", type=Path, default=Path("configs/train/demo.yaml"))
    p.add_argument("--timesteps", type=int, default=None, help="training steps (default: the config's)")
    p.add_argument("--budget", type=int, default=16, help="simulated scenarios per method in the evaluation")
    p.add_argument("--scenario", default=None, help="seed scenario (default: the config's first)")
    p.add_argument("--no-progress", action="store_true")
    return p.parse_args(argv)


def _tests(root: Path) -> list[Path]:
    return sorted(root.rglob("extracted/test_*.py"))


def _pytest(tests: list[Path], select: str) -> str:
    """Run the extracted modules' tests matching ``-k select``; pytest's summary line."""
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
                           "--import-mode=importlib", "-k", select, *map(str, tests)], capture_output=True, text=True)
    lines = proc.stdout.strip().splitlines()
    return lines[-1].strip("= ") if lines else proc.stderr.strip()[-200:]


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    out: Path = args.out
    t0 = time.time()
    cfg = train.load_train_config(args.config)
    scenario = args.scenario or cfg.env.scenarios[0]
    if out.exists() and not out.is_dir():
        print(f"error: --out {out}: is a file; expected a folder for the demo's outputs", file=sys.stderr)
        return 2
    marker = out / MARKER
    if not marker.exists() and any((out / part).exists() for part in ("train", "eval")):
        print(f"error: --out {out}: holds train/ or eval/ that agents.demo did not write (no {MARKER}); "
              "choose another --out", file=sys.stderr)
        return 2
    for part in ("train", "eval"):  # the demo's own outputs (the marker says so): a new demo replaces them
        if (out / part).exists():
            shutil.rmtree(out / part)
    out.mkdir(parents=True, exist_ok=True)
    marker.write_text("written by agents.demo; a new demo into this folder replaces train/ and eval/\n")
    print(f"[1/4] training the adversary on {scenario} ...", flush=True)
    targs = ["--config", str(args.config), "--out", str(out / "train")]
    if args.timesteps:
        targs += ["--timesteps", str(args.timesteps)]
    if args.no_progress:
        targs.append("--no-progress")
    if train.main(targs) != 0:
        return 1
    t_train = time.time() - t0
    print(f"[2/4] evaluating RL vs Random-delta, budget {args.budget} each ...", flush=True)
    eargs = ["--methods", "rl,random_delta", "--budget", str(args.budget), "--repeats", "1", "--scenarios", scenario,
             "--model", str(out / "train" / "model.zip"), "--out", str(out / "eval"), "--log-failures"]
    if args.no_progress:
        eargs.append("--no-progress")
    if evaluate.main(eargs) != 0:
        return 1
    summary = json.loads((out / "eval" / "summary.json").read_text())
    print("[3/4] extracted tests of the adversary's failures ...", flush=True)
    tests = _tests(out / "train") + _tests(out / "eval" / "logs" / "rl")
    print(f"      {len(tests)} test module(s)")
    print("[4/4] running them ...", flush=True)
    result: dict[str, Any] = {"modules": len(tests)}
    if tests:
        result["reproduce"] = _pytest(tests, "reproduces")  # replayed frames give the recorded plans
        result["oracle"] = _pytest(tests, "not reproduces")  # fail while the planner still crashes
    t_sum = json.loads((out / "train" / "summary.json").read_text())
    per = summary["per_scenario"]
    print("\n==================== DeFT-Gym adversary demo ====================")
    print(f"training   : {t_sum.get('timesteps')} steps, {t_sum['episodes']} episodes in {t_train:.0f} s; "
          f"{t_sum['collisions']} collisions + {t_sum['nods']} NoDS, validity {100 * t_sum['validity']:.1f} %")
    for m in ("rl", "random_delta"):
        for placement, cells in per.get(m, {}).items():
            c = {k: v["mean"] for k, v in cells[scenario].items() if isinstance(v, dict)} if scenario in cells else None
            if c:
                print(f"eval {m:<12}: {c['failures']:g} failures ({c['collisions']:g} collisions + {c['nods']:g} "
                      f"NoDS) in {c['simulated']:g} scenarios ({placement} placement), validity "
                      f"{100 * c['validity']:.1f} %, {c['distinct']:g} distinct, {c['seconds_per_scenario'] or float('nan'):.2f} "
                      "s/scenario")
    print(f"extracted  : {result['modules']} pytest module(s) from failing adversary episodes")
    if tests:
        print(f"pytest     : reproduction tests: {result['reproduce']}")
        print(f"             failure oracles (fail = the failure reproduced): {result['oracle']}")
    print(f"total time : {time.time() - t0:.0f} s   outputs: {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
