"""Run a system-level scenario test N times and show how the reruns differ.

    deft-gym run left_turn --reruns 10                # -> runs/run/left_turn
    python -m deft_gym.cli.run configs/scenarios/left_turn.yaml --reruns 10 --out runs/left_turn

Each rerun gets its own jitter seed (from the OS, or ``--jitter-seed S`` + rerun index for an
exactly reproducible batch) and writes ``OUT/<rerun>/episode.mcap`` and ``truth.jsonl``; the
table compares every rerun's planning outputs with rerun 0's (lock-step Euclidean distance of
the i-th output against the i-th). ``OUT/summary.json`` holds the rows, each with its driving-quality
``metrics`` (docs/metrics.md), their per-run aggregate ``metrics`` and the sim speed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from deft_gym.cli import common
from deft_gym.files import write_atomic


def build_parser() -> common.Parser:
    p = common.parser("run", "deft_gym.cli.run", __doc__)
    p.add_argument("scenario", help="scenario name (configs/scenarios), YAML path or gen:<seed> spec, or a "
                                    "failure's replay_scenario.yaml (its jitter seed unless --jitter-seed)")
    p.add_argument("--reruns", type=common.int_range(1, 100_000), default=10, help="number of reruns")
    common.add_out(p, None, help="output folder (default: runs/run/<scenario>)")
    common.add_jitter_seed(p)
    common.add_render(p)
    p.add_argument("--ads-config", default=None, metavar="YAML",
                   help="ADS config (default: configs/ads/default.yaml)")
    p.add_argument("--headers", action="store_true",
                   help="planner publishes the sequence numbers of its inputs (debug.input_seqs)")
    p.add_argument("--compress", action="store_true", help="zstd-compressed MCAP chunks (slower, smaller)")
    common.add_watchdog(p)
    common.add_output_flags(p)
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    return build_parser().parse_args(argv)


def divergence_stats(ref: list[dict[str, Any]], other: list[dict[str, Any]]) -> dict[str, Any]:
    """How far ``other``'s planning outputs are from ``ref``'s, lock-step. A pair that cannot be
    compared - a plan without a trajectory, an empty one, series of other lengths or not numbers
    (a planner that breaks its output contract) - is counted in ``incomparable``, not compared."""
    import numpy as np

    from deft_gym.planner.trajectory import lsed

    dists, incomparable = [], 0
    with np.errstate(all="ignore"):
        for a, b in zip(ref, other):
            try:
                d = lsed(a, b)
            except (KeyError, IndexError, TypeError, ValueError, AttributeError):
                incomparable += 1
                continue
            if d == d:  # NaN: a non-finite plan
                dists.append(d)
            else:
                incomparable += 1
    d = np.array(dists)
    if d.size == 0:
        return {"paired": 0, "identical": 0, "median": None, "max": None, "incomparable": incomparable}
    return {"paired": int(d.size), "identical": int((d == 0.0).sum()),
            "median": float(np.median(d)), "max": float(d.max()), "incomparable": incomparable}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    with common.watchdog_env(args):
        return _main(args)


def _main(args: argparse.Namespace) -> int:
    console = common.console(args)
    from deft_gym.bus.ads import DEFAULT_ADS_CONFIG, load_ads_config
    from deft_gym.config import ConfigError
    from deft_gym.modules.planning import frame_roles
    from deft_gym.planner.base import planner_class
    from deft_gym.scenarios.scenario import load_scenario, scenario_from_dict
    from deft_gym.search.episode import load_replay
    from deft_gym.sim.simulation import build_planner

    try:
        eq = load_replay(args.scenario) if str(args.scenario).endswith((".yaml", ".yml")) else None
        if eq is not None:  # a failure's scenario: participants may join mid-run
            scenario = scenario_from_dict(eq["scenario"], source=str(args.scenario))
            if args.jitter_seed is None:
                args.jitter_seed = eq["jitter_seed"]
        else:
            scenario = load_scenario(args.scenario)
        overrides = {"planning": {"publish_input_headers": True}} if args.headers else None
        ads = load_ads_config(args.ads_config, overrides)
        build_planner(ads, scenario)  # unknown class or parameters: one line, before any run
        frame_roles(planner_class(ads.planning.planner.cls), ads.planning, str(args.ads_config or DEFAULT_ADS_CONFIG))
    except (ConfigError, ValueError) as err:
        console.print(f"[red]error:[/red] {err}", highlight=False, soft_wrap=True)
        return 2
    out = Path(args.out or common.RUNS / "run" / scenario.name)
    with common.locked_out(out):
        return _reruns(args, console, scenario, ads, out, eq)


def _reruns(args: argparse.Namespace, console: Any, scenario: Any, ads: Any, out: Path,
            eq: dict[str, Any] | None = None) -> int:
    from deft_gym.metrics.episode import aggregate, simulation_metrics
    from deft_gym.search.episode import replay
    from deft_gym.search.trace import TraceRecorder
    from deft_gym.sim.simulation import Simulation

    rows: list[dict[str, Any]] = []
    ref_plans: list[dict[str, Any]] = []
    sim_total = wall_total = 0.0
    held: dict[str, Any] = {}  # this rerun's simulation and its trace recorder

    def attach(sim: Simulation) -> None:  # ground truth per world step for the metrics (passive hooks)
        held["sim"], held["trace"] = sim, TraceRecorder(sim)

    with common.bar(args, args.reruns, scenario.name) as bar:
        for i in range(args.reruns):
            seed = args.jitter_seed + i if args.jitter_seed is not None else common.fresh_seed()
            if eq is None:
                sim = Simulation(scenario, ads, jitter_seed=seed, out_dir=out / str(i), compress=args.compress)
                attach(sim)
                result = sim.run()
            else:
                result = replay(eq, ads, out / str(i), jitter_seed=seed, compress=args.compress, attach=attach)
            summary = result.summary()
            summary["metrics"] = simulation_metrics(held["sim"], held["trace"], result).as_dict()
            if i == 0:
                ref_plans = result.planning
            summary["divergence"] = divergence_stats(ref_plans, result.planning)
            summary["rerun"] = i
            if args.render == "all" or (args.render == "failures" and summary["collision"]):
                from deft_gym.viz.episode import render_log

                pics = render_log(Path(result.log_path))
                summary["plot"], summary["video"] = pics["plot"], pics["video"]
            rows.append(summary)
            sim_total += result.sim_time
            wall_total += result.wall_time
            bar.update()
    common.print_table(console, _table(scenario.name, rows))
    sim_speed = sim_total / wall_total if wall_total > 0 else None
    collided = sum(r["collision"] for r in rows)
    agg = aggregate([r["metrics"] for r in rows])
    console.print(f"driving quality: mean score {agg['mean_score']:.3f} (min {agg['min_score']:.3f}); violations "
                  + (", ".join(f"{k} {v}/{len(rows)}" for k, v in agg["violations"].items()) or "none")
                  + " (docs/metrics.md)", highlight=False)
    console.print(f"{collided}/{len(rows)} reruns collided; outcomes {', '.join(sorted({r['outcome'] for r in rows}))}; "
                  f"sim speed {sim_speed:.0f}x real time")
    for r in rows:
        if r.get("plot"):
            console.print(f"rerun {r['rerun']}: {r['plot']}" + (f", {r['video']}" if r.get("video") else ""),
                          soft_wrap=True)
    summary_doc = {
        "scenario": scenario.name,
        "scenario_file": scenario.source,
        "reruns": [{k: r[k] for k in ("rerun", "outcome", "collision", "collision_detail", "task_completed",
                                      "sim_time", "wall_time", "jitter_seed", "min_distance",
                                      "planning_outputs", "divergence", "metrics", "log", "truth", "plot", "video")
                     if k in r}
                   for r in rows],
        "sim_speed": sim_speed,
        "metrics": aggregate([r["metrics"] for r in rows]),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    write_atomic(out / "summary.json", json.dumps(summary_doc, indent=2))
    if args.quiet:
        print(f"{collided}/{len(rows)} reruns collided; {out / 'summary.json'}")
    console.print(f"wrote {common.shown(out / 'summary.json')}; next: {common.tool('deft-gym')} extract "
                  f"{common.shown(out)} --out {common.shown(out)}_tests", soft_wrap=True)
    return 0


def compared(rerun: dict[str, Any], ref: dict[str, Any]) -> str | None:
    """Why ``rerun``'s plans are not compared with rerun 0's (``ref``), or None when they are: a
    rerun with another outcome drove elsewhere after the two parted, so a lock-step distance
    between its plans and rerun 0's measures nothing (it would read as tens of metres)."""
    if rerun["rerun"] == ref["rerun"]:
        return "(reference)"
    if rerun["outcome"] != ref["outcome"]:
        return "not compared"
    return None


def _table(name: str, rows: list[dict[str, Any]]) -> Any:
    t = common.table(
        title=f"{name}: {len(rows)} reruns of one scenario; only the module timing (jitter) differs",
        caption="plans vs rerun 0: the i-th planning output against rerun 0's i-th (lock-step distance, m), for "
                "reruns with rerun 0's outcome; a rerun with another outcome drove elsewhere and is not compared. "
                "Reruns that differ from rerun 0 are the flakiness DeFT's extracted tests remove")
    for col, just in [("rerun", "right"), ("outcome", "left"), ("hit", "left"), ("closest m", "right"),
                      ("sim s", "right"), ("wall s", "right"), ("jitter seed", "right"),
                      ("same plans as rerun 0", "right"), ("plan dist. med/max m", "right")]:
        t.add_column(col, justify=just)
    for r in rows:
        dv = r["divergence"]
        coll = r["collision_detail"]
        why = compared(r, rows[0])
        ident = why or f"{dv['identical']} of {dv['paired']}"
        dist = "-" if why or dv["median"] is None else f"{dv['median']:.3f} / {dv['max']:.2f}"
        t.add_row(str(r["rerun"]), r["outcome"], coll["participant"] if coll else "",
                  "-" if r["min_distance"] is None else f"{r['min_distance']:.2f}",
                  f"{r['sim_time']:.1f}", f"{r['wall_time']:.2f}", str(r["jitter_seed"]), ident, dist)
    return t


if __name__ == "__main__":
    sys.exit(main())
