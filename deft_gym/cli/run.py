"""Run a system-level scenario test N times and show how the reruns differ.

    deft-gym run left_turn --reruns 10                # -> runs/run/left_turn
    python -m deft_gym.cli.run configs/scenarios/left_turn.yaml --reruns 10 --out runs/left_turn
    deft-gym run handwritten gen:2000001-2000024 --reruns 2 --jitter-seed 11 --ads-config configs/ads/commonroad.yaml
                                                      # a suite -> runs/run/suite/<scenario>/ + suite.json

Each rerun gets its own jitter seed (from the OS, or ``--jitter-seed S`` + rerun index for an
exactly reproducible batch) and writes ``OUT/<rerun>/episode.mcap`` and ``truth.jsonl``; the
table compares every rerun's planning outputs with rerun 0's (lock-step Euclidean distance of
the i-th output against the i-th). ``OUT/summary.json`` holds the rows, each with its driving-quality
``metrics`` (docs/metrics.md), their per-run aggregate ``metrics`` and the sim speed.

Several scenarios (or a group name such as ``handwritten``) make a suite: each runs as above into
``OUT/<scenario>/``, and one table says per scenario how the reruns ended and which metrics every
rerun violated (the planner's own failures, confirmed across jitter seeds), ``OUT/suite.json`` the
same. With ``--jitter-seed`` a scenario whose folder already holds the same reruns - same scenario
content, ADS config, code and planner source (``run_key``) - is not run again (an interrupted suite
resumes; a changed planner runs everything again).
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
    p.add_argument("scenario", nargs="+",
                   help="scenario name (configs/scenarios), YAML path, gen:<seed> spec, <group>/<name>, or a "
                        "failure's replay_scenario.yaml (its jitter seed unless --jitter-seed); several, a group "
                        "name (handwritten) or a range gen:A-B run as a suite")
    p.add_argument("--reruns", type=common.int_range(1, 100_000), default=10, help="number of reruns")
    common.add_out(p, None, help="output folder (default: runs/run/<scenario>, runs/run/suite for several)")
    common.add_jitter_seed(p)
    common.add_render(p)
    p.add_argument("--ads-config", default=None, metavar="YAML",
                   help="ADS config (default: configs/ads/default.yaml)")
    p.add_argument("--headers", action="store_true",
                   help="planner publishes the sequence numbers of its inputs (debug.input_seqs)")
    p.add_argument("--compress", action="store_true", help="zstd-compressed MCAP chunks (slower, smaller)")
    common.add_watchdog(p)
    common.add_workers(p, "parallel processes of a suite, one scenario each (the results are the same for any number)")
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
    from deft_gym.scenarios.scenario import expand_groups, scenario_from_dict
    from deft_gym.search.context import resolve_scenario
    from deft_gym.search.episode import load_replay
    from deft_gym.sim.simulation import build_planner

    runs: list[tuple[Any, dict[str, Any] | None]] = []  # (scenario, a failure's replay record)
    try:
        specs = expand_groups([g for spec in args.scenario for g in _generated_range(spec)])
        suite = len(specs) > 1
        overrides = {"planning": {"publish_input_headers": True}} if args.headers else None
        ads = load_ads_config(args.ads_config, overrides)
        for spec in specs:
            eq = load_replay(spec) if str(spec).endswith((".yaml", ".yml")) else None
            if eq is not None:  # a failure's scenario: participants may join mid-run
                scenario = scenario_from_dict(eq["scenario"], source=str(spec))
                if args.jitter_seed is None and not suite:
                    args.jitter_seed = eq["jitter_seed"]
            else:
                scenario = resolve_scenario(spec)
            build_planner(ads, scenario)  # unknown class or parameters: one line, before any run
            runs.append((scenario, eq))
        frame_roles(planner_class(ads.planning.planner.cls), ads.planning, str(args.ads_config or DEFAULT_ADS_CONFIG))
    except (ConfigError, ValueError) as err:
        console.print(f"[red]error:[/red] {err}", highlight=False, soft_wrap=True)
        return 2
    if not suite:
        scenario, eq = runs[0]
        out = Path(args.out or common.RUNS / "run" / scenario.name)
        with common.locked_out(out):
            return _reruns(args, console, scenario, ads, out, eq)
    out = Path(args.out or common.RUNS / "run" / "suite")
    with common.locked_out(out):
        return _suite(args, console, runs, ads, out)


def _generated_range(spec: str) -> list[str]:
    """``gen:A-B`` (or any seed list ``deft-gym generate --seeds`` takes) as ``gen:A`` ... ``gen:B``;
    any other spec as itself. ValueError for a malformed list."""
    from deft_gym.cli.generate import parse_seeds

    head, sep, seeds = spec.partition(":")
    if head != "gen" or not sep or seeds.isdigit():
        return [spec]
    try:
        return [f"gen:{seed}" for seed in parse_seeds(seeds)]
    except ValueError as err:
        raise ValueError(f"scenario {spec!r}: {err}") from None


def _suite(args: argparse.Namespace, console: Any, runs: list[tuple[Any, dict[str, Any] | None]], ads: Any,
           out: Path) -> int:
    """Every scenario of a suite into ``out/<name>/``, then one row per scenario: outcomes, the
    metrics every rerun violated, the mean score and, for a failing one, the plot of its first
    rerun (unless ``--render none``) (``out/suite.json``)."""
    from deft_gym.execution import Backend, Executor
    from deft_gym.record.recorder import init_pool_worker

    names: dict[str, int] = {}
    folders, todo = [], []
    for scenario, eq in runs:
        n = names[scenario.name] = names.get(scenario.name, 0) + 1
        folder = out / (scenario.name if n == 1 else f"{scenario.name}~{n}")
        folders.append(folder)
        if _done_before(folder / "summary.json", scenario, ads, args) is None:
            todo.append((scenario, eq, folder))
    workers = min(args.workers, max(len(todo), 1))
    # in the workers: no progress bars of their own (the suite's shows whole scenarios)
    item_args = argparse.Namespace(**{**vars(args), "no_progress": workers > 1 or args.no_progress})
    rows = []
    with Executor(Backend("local", workers), initializer=init_pool_worker, initargs=(workers,)) as ex:
        ran = ex.map(_suite_item, [(item_args, ads, *item) for item in todo])
        fresh_folders = {folder for _, _, folder in todo}
        for k, ((scenario, _), folder) in enumerate(zip(runs, folders, strict=True)):
            fresh = folder in fresh_folders
            if fresh:  # run now: the map yields in the order of todo, which is the suite's
                next(ran)
            console.print(f"[{k + 1}/{len(runs)}] {scenario.name}" + ("" if fresh else " (done before with the same code and config: kept)"),
                          highlight=False)
            row = suite_row(json.loads((folder / "summary.json").read_text()), folder)
            if row["failing"] and args.render != "none":
                row["plot"] = _draw_failure(folder / "0" / "episode.mcap")
            rows.append(row)
    doc = {"scenarios": rows, "reruns": args.reruns, "jitter_seed": args.jitter_seed,
           "ads_config": str(args.ads_config or ""), "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
    write_atomic(out / "suite.json", json.dumps(doc, indent=2))
    common.print_table(console, _suite_table(rows, args.reruns))
    failing = sum(r["failing"] for r in rows)
    console.print(f"{failing} of {len(rows)} scenarios failed in every rerun (an outcome other than completed, or a "
                  f"violated metric but comfort); wrote {common.shown(out / 'suite.json')}", soft_wrap=True)
    return 0


def _suite_item(item: tuple[argparse.Namespace, Any, Any, dict[str, Any] | None, Path]) -> str:
    """One scenario of a suite, its reruns into its folder (in a worker process or in this one)."""
    args, ads, scenario, eq, folder = item
    _reruns(args, common.console(args), scenario, ads, folder, eq, verbose=False)
    return str(folder)


def _draw_failure(log: Path) -> str | None:
    """The plot of a failing suite scenario's first rerun (``plot.png`` beside its log; kept when
    it is there), else None when the log cannot be drawn."""
    from deft_gym.viz.episode import render_log

    plot = log.parent / "plot.png"
    if not plot.is_file() and log.is_file():
        try:
            render_log(log, video=False)
        except (OSError, ValueError):
            return None
    return str(plot) if plot.is_file() else None


def run_key(scenario: Any, ads: Any, args: argparse.Namespace) -> str | None:
    """What a scenario's reruns depend on, hashed: the scenario's content, the ADS config (the
    planner and its params), the simulation's code, the planner's source when it is not the default
    (:func:`deft_gym.search.trace.content_key`) and the reruns; None without a fixed jitter seed."""
    if args.jitter_seed is None:
        return None
    from deft_gym.search.trace import content_key

    return f"{content_key(scenario, ads, args.jitter_seed)}-{args.reruns}"


def _done_before(path: Path, scenario: Any, ads: Any, args: argparse.Namespace) -> dict[str, Any] | None:
    """The summary of an earlier run of the same scenario content, ADS config, code, reruns and
    jitter seeds (only with a fixed ``--jitter-seed``: fresh seeds never match), else None: a
    changed planner or scenario runs again."""
    if args.jitter_seed is None or not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc if doc.get("run_key") == run_key(scenario, ads, args) else None  # the key holds name, seed and reruns


def suite_row(summary: dict[str, Any], folder: Path) -> dict[str, Any]:
    """One scenario of a suite from its ``summary.json``: outcomes, the metrics every rerun
    violated (``confirmed``; comfort apart, since it is reported, not a failure by itself) and
    those only some did, the mean score; ``failing``: an outcome other than completed in every
    rerun, or a confirmed metric."""
    reruns = summary.get("reruns", [])
    outcomes = [str(r.get("outcome")) for r in reruns]
    viols = [set((r.get("metrics") or {}).get("violations") or []) for r in reruns]
    every = set.intersection(*viols) if viols else set()
    some = set.union(*viols) - every if viols else set()
    failed_every_rerun = bool(outcomes) and all(o != "completed" for o in outcomes)
    confirmed = sorted(every - {"comfort"})
    return {"scenario": summary.get("scenario"), "folder": str(folder), "outcomes": outcomes,
            "failed_every_rerun": failed_every_rerun, "confirmed": confirmed,
            "failing": failed_every_rerun or bool(confirmed), "comfort_every_rerun": "comfort" in every,
            "some_reruns": sorted(some), "mean_score": (summary.get("metrics") or {}).get("mean_score")}


def _suite_table(rows: list[dict[str, Any]], reruns: int) -> Any:
    t = common.table(title=f"{len(rows)} scenarios, {reruns} rerun{'s' if reruns != 1 else ''} each",
                     caption="violated in every rerun: the planner's own failures, confirmed across jitter seeds "
                             "(docs/metrics.md); comfort is shown apart")
    for col, just in [("scenario", "left"), ("outcomes", "left"), ("violated in every rerun", "left"),
                      ("in some", "left"), ("comfort", "left"), ("mean score", "right")]:
        t.add_column(col, justify=just)
    for r in rows:
        counts = {o: r["outcomes"].count(o) for o in dict.fromkeys(r["outcomes"])}
        score = r["mean_score"]
        t.add_row(str(r["scenario"]), ", ".join(f"{o} {c}" for o, c in counts.items()), ", ".join(r["confirmed"]),
                  ", ".join(r["some_reruns"]), "every" if r["comfort_every_rerun"] else "",
                  "-" if score is None else f"{score:.3f}")
    return t


def _reruns(args: argparse.Namespace, console: Any, scenario: Any, ads: Any, out: Path,
            eq: dict[str, Any] | None = None, verbose: bool = True) -> int:
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
    sim_speed = sim_total / wall_total if wall_total > 0 else None
    collided = sum(r["collision"] for r in rows)
    agg = aggregate([r["metrics"] for r in rows])
    if verbose:
        _report(console, scenario.name, rows, agg, collided, sim_speed)
    summary_doc = {
        "scenario": scenario.name,
        "scenario_file": scenario.source,
        "reruns": [{k: r[k] for k in ("rerun", "outcome", "collision", "collision_detail", "task_completed",
                                      "sim_time", "wall_time", "jitter_seed", "min_distance",
                                      "planning_outputs", "divergence", "metrics", "log", "truth", "plot", "video")
                     if k in r}
                   for r in rows],
        "sim_speed": sim_speed,
        "metrics": agg,
        "run_key": run_key(scenario, ads, args),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    write_atomic(out / "summary.json", json.dumps(summary_doc, indent=2))
    if not verbose:
        return 0
    if args.quiet:
        print(f"{collided}/{len(rows)} reruns collided; {out / 'summary.json'}")
    console.print(f"wrote {common.shown(out / 'summary.json')}; next: {common.tool('deft-gym')} extract "
                  f"{common.shown(out)} --out {common.shown(out)}_tests", soft_wrap=True)
    return 0


def _report(console: Any, name: str, rows: list[dict[str, Any]], agg: dict[str, Any], collided: int,
            sim_speed: float | None) -> None:
    """The reruns' table and the lines under it."""
    common.print_table(console, _table(name, rows))
    console.print(f"driving quality: mean score {agg['mean_score']:.3f} (min {agg['min_score']:.3f}); violations "
                  + (", ".join(f"{k} {v}/{len(rows)}" for k, v in agg["violations"].items()) or "none")
                  + " (docs/metrics.md)", highlight=False)
    console.print(f"{collided}/{len(rows)} reruns collided; outcomes {', '.join(sorted({r['outcome'] for r in rows}))}; "
                  f"sim speed {sim_speed:.0f}x real time")
    for r in rows:
        if r.get("plot"):
            console.print(f"rerun {r['rerun']}: {r['plot']}" + (f", {r['video']}" if r.get("video") else ""),
                          soft_wrap=True)


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
