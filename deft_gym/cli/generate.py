"""Generate held-out scenarios, write them as YAML, and optionally check that the reference ADS
completes each one.

    deft-gym generate --seeds 0-9                                 # -> runs/generated
    deft-gym generate --seeds 0-199 --check --jitter-seed 0

Each seed becomes ``OUT/gen-<seed>.yaml`` (loadable with
:func:`deft_gym.scenarios.scenario.load_scenario`; the same scenario as the spec ``gen:<seed>``)
and a row of the table. ``--check`` runs every scenario once, unmutated, with a fixed jitter
seed and reports its outcome (completed / timeout / stuck / collision) and the share completed
per family. ``OUT/summary.json`` holds the rows.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml
from rich import box
from rich.table import Table

from deft_gym.cli import common
from deft_gym.config import load_mapping, validate
from deft_gym.files import write_atomic, write_json_atomic

if TYPE_CHECKING:
    from deft_gym.scenarios.generate import Generated

MAX_SEEDS = 100_000


def parse_seeds(text: str) -> list[int]:
    """Seeds from ``"0-9"``, ``"5"`` or a comma list of both (``"0-4,10,20-22"``), in order,
    without repeats; ``ValueError`` with a one-line reason otherwise."""
    seeds: dict[int, None] = {}
    for part in text.split(","):
        m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        if m is None:
            raise ValueError(f"--seeds {text!r}: expected seeds >= 0 like '0-9', '5' or '0-4,10'")
        lo = int(m.group(1))
        hi = int(m.group(2)) if m.group(2) is not None else lo
        if hi < lo:
            raise ValueError(f"--seeds {text!r}: range {lo}-{hi} runs backwards")
        if hi - lo + 1 + len(seeds) > MAX_SEEDS:
            raise ValueError(f"--seeds {text!r}: more than {MAX_SEEDS} seeds")
        seeds.update(dict.fromkeys(range(lo, hi + 1)))
    return list(seeds)


class _Dumper(yaml.SafeDumper):
    """YAML with short lists of plain values (lane ids) on one line."""


def _represent_list(dumper: yaml.SafeDumper, data: list[Any]) -> yaml.Node:
    flat = all(not isinstance(x, list | dict) for x in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flat)


_Dumper.add_representer(list, _represent_list)


def scenario_yaml(g: Generated) -> str:
    """The YAML text of a generated scenario, headed by a comment naming its spec."""
    from deft_gym.scenarios.generate import SPEC_PREFIX
    from deft_gym.scenarios.scenario import scenario_to_dict

    data = scenario_to_dict(g.scenario)
    data["participants"] = [{"id": p["id"], "type": p["type"], **p} for p in data.get("participants", [])]
    head = f"# {SPEC_PREFIX}{g.seed}: written by deft-gym generate\n"
    return head + yaml.dump(data, Dumper=_Dumper, sort_keys=False, width=100)


def row_of(g: Generated) -> dict[str, Any]:
    return {"seed": g.seed, "name": g.scenario.name, "family": g.family, "lanes": g.lanes,
            "route_length": g.route_length, "lane_changes": g.lane_changes, **g.counts,
            "duration": g.scenario.duration}


def check(gens: list[Generated], rows: list[dict[str, Any]], jitter_seed: int, console: Any,
          progress: bool = True) -> None:
    """Run each scenario once (jitter seed ``jitter_seed``) and add its outcome to its row."""
    from deft_gym.sim.simulation import run_episode

    with common.Bar(len(gens), "check", progress, console) as bar:
        for g, row in zip(gens, rows):
            r = run_episode(g.scenario, jitter_seed=jitter_seed, keep_planning=False)
            row.update(outcome=r.outcome.outcome, sim_time=round(r.sim_time, 2), wall_time=round(r.wall_time, 3))
            if r.outcome.collision is not None:
                row["hit"] = r.outcome.collision.participant
            bar.update()


def shares(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per family (and ``all``): runs, outcome counts and the share completed."""
    by: dict[str, Counter[str]] = defaultdict(Counter)
    for r in rows:
        by[r["family"]][r["outcome"]] += 1
        by["all"][r["outcome"]] += 1
    order = [*sorted(f for f in by if f != "all"), "all"]
    return {f: {"runs": sum(by[f].values()), "outcomes": dict(sorted(by[f].items())),
                "completed": by[f]["completed"] / sum(by[f].values())} for f in order if f in by}


def _table(rows: list[dict[str, Any]], checked: bool) -> Table:
    t = Table(title=f"{len(rows)} generated scenarios (route in m, duration in s)", title_justify="left",
              box=box.SIMPLE_HEAD, pad_edge=False, padding=(0, 1))
    cols = [("seed", "right"), ("family", "left"), ("lanes", "right"), ("route", "right"),
            ("changes", "right"), ("participants", "left"), ("duration", "right")]
    cols += [("outcome", "left"), ("sim s", "right")] if checked else []
    for col, just in cols:
        t.add_column(col, justify=just, no_wrap=True)
    for r in rows:
        parts = f"{r['reactive']} reactive, {r['scripted']} scripted, {r['static']} static"
        cells = [str(r["seed"]), r["family"], str(r["lanes"]), f"{r['route_length']:.0f}",
                 str(r["lane_changes"]), parts, f"{r['duration']:.1f}"]
        if checked:
            style = "green" if r["outcome"] == "completed" else "red"
            cells += [f"[{style}]{r['outcome']}[/{style}]" + (f" ({r['hit']})" if r.get("hit") else ""),
                      f"{r['sim_time']:.1f}"]
        t.add_row(*cells)
    return t


def _share_table(stats: dict[str, dict[str, Any]], jitter_seed: int) -> Table:
    t = Table(title=f"unmutated runs, jitter seed {jitter_seed}: share completed per family",
              title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False, padding=(0, 1))
    for col, just in [("family", "left"), ("runs", "right"), ("completed", "right"), ("outcomes", "left")]:
        t.add_column(col, justify=just, no_wrap=True)
    for fam, s in stats.items():
        outcomes = ", ".join(f"{k} {v}" for k, v in s["outcomes"].items())
        t.add_row(fam, str(s["runs"]), f"{100 * s['completed']:.1f} %", outcomes)
    return t


def build_parser() -> common.Parser:
    ap = common.parser("generate", "deft_gym.cli.generate", __doc__)
    ap.add_argument("--seeds", default="0-9", help="generator seeds: '0-9', '5' or '0-4,10' (default %(default)s)")
    common.add_out(ap, common.RUNS / "generated", help="folder for gen-<seed>.yaml and summary.json")
    ap.add_argument("--check", action="store_true", help="run each scenario once, unmutated, and report its outcome")
    common.add_jitter_seed(ap, "jitter seed of the --check runs (every scenario runs with it)")
    ap.add_argument("--config", type=Path, default=None,
                    help="generator config YAML (GeneratorConfig fields; default: the built-in defaults)")
    common.add_watchdog(ap)
    common.add_output_flags(ap)
    return ap


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    args = build_parser().parse_args(argv)
    args.out = Path(args.out)
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    with common.watchdog_env(args):
        return _main(args)


def _main(args: argparse.Namespace) -> int:
    console = common.console(args, stderr=True)
    out = common.console(args, width=140)
    if args.jitter_seed is None:
        args.jitter_seed = common.fresh_seed()
    try:
        seeds = parse_seeds(args.seeds)
        from deft_gym.scenarios.generate import GeneratorConfig, build

        cfg = validate(GeneratorConfig, load_mapping(args.config), args.config) if args.config else GeneratorConfig()
        gens = [build(s, cfg) for s in seeds]
    except (ValueError, OSError) as err:  # ConfigError is a ValueError
        console.print(f"[red]error:[/red] {err}", highlight=False)
        return 2
    if args.jitter_seed < 0:
        console.print(f"[red]error:[/red] --jitter-seed {args.jitter_seed}: expected an integer >= 0", highlight=False)
        return 2
    with common.locked_out(args.out):
        return _write(args, console, out, gens, cfg)


def _write(args: argparse.Namespace, console: Any, out: Any, gens: list[Any], cfg: Any) -> int:
    from deft_gym.scenarios.generate import NAME_PREFIX

    for g in gens:
        write_atomic(args.out / f"{NAME_PREFIX}{g.seed}.yaml", scenario_yaml(g))
    rows = [row_of(g) for g in gens]
    t0 = time.perf_counter()
    if args.check:
        check(gens, rows, args.jitter_seed, console, common.show_progress(args))
    common.print_table(out, _table(rows, args.check))
    doc: dict[str, Any] = {"seeds": args.seeds, "config": cfg.model_dump(mode="json"), "scenarios": rows,
                           "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
    if args.check:
        stats = shares(rows)
        common.print_table(out, _share_table(stats, args.jitter_seed))
        doc.update(jitter_seed=args.jitter_seed, completed=stats, check_wall_s=round(time.perf_counter() - t0, 1))
        allc = stats["all"]
        out.print(f"{allc['outcomes'].get('completed', 0)}/{allc['runs']} completed "
                  f"({100 * allc['completed']:.1f} %) in {doc['check_wall_s']} s")
    write_json_atomic(args.out / "summary.json", doc)
    out.print(f"wrote {len(gens)} scenarios and summary.json to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
