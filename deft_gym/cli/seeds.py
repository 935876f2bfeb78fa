"""Run every seed scenario a few times on the jittered ADS and report how the reruns differ.

    python -m deft_gym.cli.seeds --out runs/demo/seeds [--reruns 3]

An overview of the seed scenarios: one row per seed scenario with its outcomes over the reruns,
collisions, how far the reruns' planning outputs are from the first rerun's, and the sim speed.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from rich import box
from rich.table import Table

from deft_gym.cli import common
from deft_gym.cli.run import divergence_stats
from deft_gym.files import write_atomic
from deft_gym.scenarios.scenario import list_scenarios, load_scenario
from deft_gym.sim.simulation import run_episode


def main(argv: list[str] | None = None) -> int:
    ap = common.parser("seeds", "deft_gym.cli.seeds", __doc__)
    common.add_out(ap, common.RUNS / "demo" / "seeds", help="output folder (logs per scenario and rerun)")
    ap.add_argument("--reruns", type=common.int_range(1, 10_000), default=3, help="reruns per seed scenario")
    common.add_jitter_seed(ap, "jitter seed of rerun 0 of every scenario; rerun i uses S+i")
    common.add_output_flags(ap)
    args = ap.parse_args(argv)
    console = common.console(args, width=110)
    out = Path(args.out)
    with common.locked_out(out):
        return _run(args, console, out)


def _run(args: Any, console: Any, out: Path) -> int:
    seeds = [p for p in list_scenarios() if not p.name.startswith("bench")]
    rows: list[dict[str, Any]] = []
    with common.bar(args, len(seeds) * args.reruns, "seed scenarios") as progress:
        for path in seeds:
            sc = load_scenario(path)
            results = []
            for i in range(args.reruns):
                seed = common.fresh_seed() if args.jitter_seed is None else args.jitter_seed + i
                results.append(run_episode(sc, jitter_seed=seed, out_dir=out / sc.name / str(i)))
                progress.update()
            # reruns without planning outputs to pair have no divergence (median None)
            div = [d for r in results[1:] if (d := divergence_stats(results[0].planning, r.planning))["paired"]]
            rows.append({"scenario": sc.name,
                         "outcomes": [r.outcome.outcome for r in results],
                         "collisions": sum(r.outcome.collision is not None for r in results),
                         "sim_speed": sum(r.sim_time for r in results) / sum(r.wall_time for r in results),
                         "lsed_median": float(np.median([d["median"] for d in div])) if div else None,
                         "jitter_seeds": [r.jitter_seed for r in results]})
    t = Table(title=f"seed scenarios, {args.reruns} reruns each (fresh jitter seeds)", title_justify="left",
              box=box.SIMPLE_HEAD)
    for c in ("scenario", "outcomes", "collisions", "LSED vs rerun 0 [m]", "x real time"):
        t.add_column(c, justify="left" if c in ("scenario", "outcomes") else "right")
    for r in rows:
        t.add_row(r["scenario"], ", ".join(r["outcomes"]), str(r["collisions"]),
                  "-" if r["lsed_median"] is None else f"{r['lsed_median']:.2f}", f"{r['sim_speed']:.0f}")
    common.print_table(console, t)
    write_atomic(out / "summary.json", json.dumps(rows, indent=2))
    console.print(f"logs and summary in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
