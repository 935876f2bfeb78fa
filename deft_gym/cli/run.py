"""Run a system-level scenario test N times and show how the reruns differ.

    python -m deft_gym.cli.run configs/scenarios/left_turn.yaml --reruns 10 --out runs/left_turn

Each rerun gets its own jitter seed (from the OS, or ``--jitter-seed S`` + rerun index for an
exactly reproducible batch) and writes ``OUT/<rerun>/episode.mcap`` and ``truth.jsonl``; the
table compares every rerun's planning outputs with rerun 0's (lock-step Euclidean distance of
the i-th output against the i-th). ``OUT/summary.json`` holds the rows and the sim speed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from rich import box
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from deft_gym.bus.ads import DEFAULT_ADS_CONFIG, load_ads_config
from deft_gym.bus.jitter import os_seed
from deft_gym.config import ConfigError
from deft_gym.files import write_atomic
from deft_gym.modules.planning import frame_roles
from deft_gym.planner.base import planner_class
from deft_gym.planner.trajectory import lockstep_divergence
from deft_gym.scenarios.scenario import load_scenario
from deft_gym.sim.simulation import Simulation, build_planner


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        prog="python -m deft_gym.cli.run",
        description="Run a scenario N times on the jittered ADS and compare the reruns.")
    ap.add_argument("scenario", help="scenario YAML (or the name of one in configs/scenarios)")
    ap.add_argument("--reruns", type=int, default=10, help="number of reruns (default 10)")
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--jitter-seed", type=int, default=None,
                    help="seed of rerun 0 (rerun i uses S+i); default: fresh seeds from the OS")
    ap.add_argument("--render", action="store_true", help="write plot.png and video.mp4 per rerun")
    ap.add_argument("--ads-config", default=None, help="ADS config YAML (default configs/ads/default.yaml)")
    ap.add_argument("--headers", action="store_true",
                    help="planner publishes the sequence numbers of its inputs (debug.input_seqs)")
    ap.add_argument("--compress", action="store_true", help="zstd-compressed MCAP chunks (slower, smaller)")
    args = ap.parse_args(argv)
    if args.reruns < 1:
        ap.error("--reruns must be at least 1")
    return args


def divergence_stats(ref: list[dict[str, Any]], other: list[dict[str, Any]]) -> dict[str, Any]:
    """How far ``other``'s planning outputs are from ``ref``'s, lock-step."""
    d = np.array(lockstep_divergence(ref, other)) if ref and other else np.zeros(0)
    if d.size == 0:
        return {"paired": 0, "identical": 0, "median": None, "max": None}
    return {"paired": int(d.size), "identical": int((d == 0.0).sum()),
            "median": float(np.median(d)), "max": float(d.max())}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    console = Console(width=None if sys.stdout.isatty() else 120)
    try:
        scenario = load_scenario(args.scenario)
        overrides = {"planning": {"publish_input_headers": True}} if args.headers else None
        ads = load_ads_config(args.ads_config, overrides)
        build_planner(ads, scenario)  # unknown class or parameters: one line, before any run
        frame_roles(planner_class(ads.planning.planner.cls), ads.planning, str(args.ads_config or DEFAULT_ADS_CONFIG))
    except (ConfigError, ValueError) as err:
        console.print(f"[red]error:[/red] {err}", highlight=False, soft_wrap=True)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    ref_plans: list[dict[str, Any]] = []
    sim_total = wall_total = 0.0
    cols = [TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()]
    with Progress(*cols, console=console, transient=True) as progress:
        task = progress.add_task(scenario.name, total=args.reruns)
        for i in range(args.reruns):
            seed = args.jitter_seed + i if args.jitter_seed is not None else os_seed()
            sim = Simulation(scenario, ads, jitter_seed=seed, out_dir=out / str(i),
                             compress=args.compress)
            trace = None
            if args.render:
                from deft_gym.viz.plot import EpisodeTrace

                trace = EpisodeTrace(sim, video=True)
            result = sim.run()
            summary = result.summary()
            if i == 0:
                ref_plans = result.planning
            summary["divergence"] = divergence_stats(ref_plans, result.planning)
            summary["rerun"] = i
            if trace is not None:
                title = f"{scenario.name} rerun {i}: {summary['outcome']} (jitter seed {seed})"
                trace.save_plot(out / str(i) / "plot.png", title=title, collision=summary["collision_detail"])
                video = trace.save_video(out / str(i) / "video.mp4")
                summary["plot"] = str(out / str(i) / "plot.png")
                summary["video"] = str(video) if video else None
            rows.append(summary)
            sim_total += result.sim_time
            wall_total += result.wall_time
            progress.advance(task)
    console.print(_table(scenario.name, rows))
    sim_speed = sim_total / wall_total if wall_total > 0 else None
    collided = sum(r["collision"] for r in rows)
    console.print(f"{collided}/{len(rows)} reruns collided; outcomes "
                  f"{sorted({r['outcome'] for r in rows})}; sim speed {sim_speed:.1f}x real time")
    summary_doc = {
        "scenario": scenario.name,
        "scenario_file": scenario.source,
        "reruns": [{k: r[k] for k in ("rerun", "outcome", "collision", "collision_detail", "task_completed",
                                      "sim_time", "wall_time", "jitter_seed", "min_distance",
                                      "planning_outputs", "divergence", "log", "truth")}
                   for r in rows],
        "sim_speed": sim_speed,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    write_atomic(out / "summary.json", json.dumps(summary_doc, indent=2))
    console.print(f"wrote {out / 'summary.json'}")
    return 0


def _table(name: str, rows: list[dict[str, Any]]) -> Table:
    t = Table(title=f"{name}: {len(rows)} reruns (distances in m; LSED vs rerun 0, lock-step)",
              title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False, padding=(0, 1))
    for col, just in [("#", "right"), ("outcome", "left"), ("hit", "left"), ("min d", "right"),
                      ("sim s", "right"), ("wall s", "right"), ("seed", "right"),
                      ("LSED med", "right"), ("LSED max", "right"), ("same", "right")]:
        t.add_column(col, justify=just, no_wrap=True)
    for r in rows:
        dv = r["divergence"]
        coll = r["collision_detail"]
        t.add_row(str(r["rerun"]), r["outcome"], coll["participant"] if coll else "",
                  "-" if r["min_distance"] is None else f"{r['min_distance']:.2f}",
                  f"{r['sim_time']:.1f}", f"{r['wall_time']:.2f}", str(r["jitter_seed"]),
                  "-" if dv["median"] is None else f"{dv['median']:.3f}",
                  "-" if dv["max"] is None else f"{dv['max']:.2f}",
                  f"{dv['identical']}/{dv['paired']}")
    return t


if __name__ == "__main__":
    sys.exit(main())
