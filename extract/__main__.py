"""Extract deterministic planning-module tests from episode logs (DeFT).

    python -m extract runs/left_turn/0/episode.mcap --out runs/left_turn/0/deft
    python -m extract runs/left_turn --out runs/left_turn_deft --workers 2
    pytest runs/left_turn_deft

For one log, OUT gets ``frames.jsonl``, ``test_<scenario>.py`` and ``summary.json``; for a folder
of runs, every log gets its own sub-folder and OUT/summary.json totals them. Exit status: 0 on
success, 1 when some log of a folder could not be extracted, 2 on bad input.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from rich import box
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from deft_gym.execution import BackendError, Executor, add_backend_arguments, backend_from_args
from extract.batch import extract_directory, find_logs
from extract.episode import ExtractionResult, extract_episode
from extract.logs import LogError
from extract.mapping import MappingError, load_mapping
from extract.search import MODES
from extract.validator import SUMMARY_THETAS, parse_tolerances, theta_key

MEASURES = ("lsed", "frechet", "hausdorff")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m extract", description=__doc__.split("\n\n")[0],
                                 epilog="Generated tests run with plain `pytest OUT`.")
    ap.add_argument("log", metavar="LOG_OR_DIR", help="an MCAP episode log, or a folder searched for *.mcap")
    ap.add_argument("--out", required=True, metavar="DIR", help="output folder")
    ap.add_argument("--mode", choices=MODES, default="heuristic",
                    help="input search: heuristic (DeFT TISE, default), last (baseline), headers "
                         "(inputs named by the output's debug.input_seqs)")
    ap.add_argument("--theta", type=float, default=0.0, metavar="T",
                    help="reproduction threshold [m] of the generated tests (default 0 = exact)")
    ap.add_argument("--measure", choices=MEASURES, default="lsed", help="trajectory distance (default lsed)")
    ap.add_argument("--tolerance", action="append", default=[], metavar="FIELD=VALUE",
                    help="tolerance of one output field other than positions, in its unit (v=0.01, heading=1e-6, "
                         "decision=0.5 for the decision's numbers, default=... for unlisted fields); repeatable. "
                         "Default 0: every field equal")
    ap.add_argument("--mapping", metavar="FILE", default=None,
                    help="topic-role mapping YAML (default configs/mappings/deft_gym.yaml)")
    ap.add_argument("--workers", type=int, default=1, metavar="N", help="parallel processes for a folder (default 1)")
    add_backend_arguments(ap)
    ap.add_argument("--no-tests", action="store_true", help="write frames and summary only")
    ap.add_argument("--force", action="store_true", help="redo episodes whose extraction is up to date")
    args = ap.parse_args(argv)
    if args.theta < 0:
        ap.error("--theta must be >= 0")
    if args.workers < 1:
        ap.error("--workers must be at least 1")
    try:
        args.tolerances = parse_tolerances(args.tolerance, args.theta).as_dict()
    except ValueError as exc:
        ap.error(str(exc))
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    console = Console(width=None if sys.stdout.isatty() else 130, highlight=False)
    kwargs: dict[str, Any] = {"mode": args.mode, "theta": args.theta, "measure": args.measure,
                              "mapping": args.mapping, "emit_tests": not args.no_tests,
                              "tolerances": args.tolerances}
    cols = [TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()]
    try:
        backend = backend_from_args(args, args.workers)
    except BackendError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    try:
        load_mapping(args.mapping)
        root = Path(args.log)
        logs = find_logs(root)
        if not logs:
            raise LogError(f"{root}: no .mcap logs found")
        with Progress(*cols, console=console, transient=True) as progress:
            if root.is_file():
                task = progress.add_task(root.name, total=None)
                res = extract_episode(root, args.out, **kwargs,
                                      on_frame=lambda done, total: progress.update(task, completed=done, total=total))
                results = [res]
            else:
                task = progress.add_task(f"{len(logs)} logs", total=len(logs))
                with Executor(backend, run_dir=args.out) as ex:
                    results = extract_directory(root, args.out, workers=args.workers, force=args.force,
                                                on_episode=lambda _: progress.advance(task), executor=ex, **kwargs)
    except (LogError, MappingError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    console.print(_table(results, args))
    for r in results:
        for w in r.summary.get("warnings", []):
            console.print(f"[yellow]warning:[/yellow] {w}", soft_wrap=True)
        if not r.ok:
            console.print(f"[red]error:[/red] {r.summary['error']}", soft_wrap=True)
    out = Path(args.out)
    console.print(f"wrote {out / 'summary.json'}" + (f"; run the tests with: pytest {out}" if not args.no_tests else ""))
    return 0 if all(r.ok for r in results) else 1


def _table(results: list[ExtractionResult], args: argparse.Namespace) -> Table:
    t = Table(title=f"DeFT extraction: mode {args.mode}, {args.measure}, theta {args.theta:g} m (positions; "
                    f"'all fields': every field within tolerance at theta)",
              title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False, padding=(0, 1))
    for col in ["scenario", "frames", *(f"<={theta_key(x)} m" for x in SUMMARY_THETAS), "all fields", "ms/frame",
                "planner", "overhead", "truth", "P_faulty"]:
        t.add_column(col, justify="left" if col in ("scenario", "P_faulty") else "right", no_wrap=True)
    for r in results:
        s = r.summary
        if not r.ok:
            t.add_row(Path(s["log"]).parent.name, "error", *[""] * 9)
            continue
        n = s["frames"] or 1
        f = s.get("faulty_trajectory")
        t.add_row(
            str(s["scenario"]) + (" (cached)" if s.get("skipped") else ""), str(s["frames"]),
            *(f"{100 * s['reproduced'][theta_key(x)] / n:.1f}%" for x in SUMMARY_THETAS),
            "-" if s.get("reproduced_at_theta") is None else f"{100 * s['reproduced_at_theta'] / n:.1f}%",
            f"{s['ms_per_frame']:.2f}", f"{s['planner_ms_per_frame']:.2f}", f"{s['overhead_ms_per_frame']:.2f}",
            "-" if s.get("truth_agreement") is None else f"{100 * s['truth_agreement']:.1f}%",
            f"frame {f['index']} t={f['time']:.2f}s" if f else ("-" if not s.get("collision") else "none found"))
    return t


if __name__ == "__main__":
    sys.exit(main())
