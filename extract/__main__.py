"""Extract deterministic planning-module tests from episode logs (DeFT).

    deft-gym extract runs/run/left_turn/0/episode.mcap --out runs/left_turn_0_tests
    python -m extract runs/run/left_turn --out runs/left_turn_tests --workers 2
    pytest runs/left_turn_tests

For one log, OUT gets ``frames.jsonl``, ``test_<scenario>_<log id>.py`` and ``summary.json``
(``deft-gym extract`` adds ``plot.png`` and ``video.mp4`` of a collision, ``--render``); for a folder
of runs, every log gets its own sub-folder and OUT/summary.json totals them. Exit status: 0 on
success, 1 when some log could not be extracted or is damaged (a chunk fails its CRC, messages are
missing, the file is cut short: it is extracted as far as it is intact, its row is marked and its
summary says what was lost), 2 on bad input.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from rich import box
from rich.table import Table

from deft_gym.cli import common
from deft_gym.execution import BackendError, Executor, add_backend_arguments, backend_from_args
from extract.batch import damaged_log, extract_directory, find_logs
from extract.episode import ExtractionResult, extract_episode
from extract.logs import LogError
from extract.mapping import MappingError, load_mapping
from extract.search import MODES
from extract.validator import SUMMARY_THETAS, parse_tolerances, theta_key

MEASURES = ("lsed", "frechet", "hausdorff")


def build_parser() -> common.Parser:
    ap = common.parser("extract", "extract", __doc__, epilog="Generated tests run with plain `pytest OUT` "
                       "(any set of extraction folders: `pytest A B C`).")
    ap.add_argument("log", metavar="LOG_OR_DIR", help="an MCAP episode log, or a folder searched for *.mcap")
    common.add_out(ap, None, help="output folder (default: runs/extract/<log's folder name>)")
    ap.add_argument("--mode", choices=MODES, default="heuristic",
                    help="input search: heuristic (DeFT TISE), last (baseline), headers "
                         "(inputs named by the output's debug.input_seqs)")
    ap.add_argument("--theta", type=common.finite_float(0.0, 1e6), default=0.0, metavar="T",
                    help="reproduction threshold [m] of the generated tests (0 = exact)")
    ap.add_argument("--measure", choices=MEASURES, default="lsed", help="trajectory distance")
    ap.add_argument("--tolerance", action="append", default=[], metavar="FIELD=VALUE",
                    help="tolerance of one output field other than positions, in its unit (v=0.01, heading=1e-6, "
                         "decision=0.5 for the decision's numbers, default=... for unlisted fields); repeatable. "
                         "Default 0: every field equal")
    ap.add_argument("--mapping", metavar="FILE", default=None,
                    help="topic-role mapping YAML (default: configs/mappings/deft_gym.yaml)")
    common.add_workers(ap, "parallel processes for a folder")
    add_backend_arguments(ap)
    ap.add_argument("--no-tests", action="store_true", help="write frames and summary only")
    ap.add_argument("--force", action="store_true", help="redo episodes whose extraction is up to date")
    ap.add_argument("--xfail-failures", action="store_true",
                    help="emit each failure oracle as a strict xfail (CI stays green while the failure reproduces "
                         "and fails once the planner is fixed)")
    common.add_watchdog(ap)
    common.add_output_flags(ap)
    return ap


def parse_args(argv: list[str] | None = None, ap: argparse.ArgumentParser | None = None) -> argparse.Namespace:
    ap = ap or build_parser()
    args = ap.parse_args(argv)
    if args.theta < 0:
        ap.error("--theta must be >= 0")
    try:
        args.tolerances = parse_tolerances(args.tolerance, args.theta).as_dict()
    except ValueError as exc:
        ap.error(f"--tolerance: {exc}")
    if args.out is None:
        src = Path(args.log)
        name = (src.parent.name if src.suffix == ".mcap" else src.name) or "log"
        args.out = str(common.RUNS / "extract" / name)
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    with common.watchdog_env(args):
        return run(args)[0]


def run(args: argparse.Namespace) -> tuple[int, list[ExtractionResult]]:
    """Extract as ``args`` say, print the table; the exit status and the results."""
    console = common.console(args, width=130)
    kwargs: dict[str, Any] = {"mode": args.mode, "theta": args.theta, "measure": args.measure,
                              "mapping": args.mapping, "emit_tests": not args.no_tests,
                              "tolerances": args.tolerances, "xfail_failures": args.xfail_failures,
                              "watchdog_s": getattr(args, "watchdog_s", None)}
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
        with common.locked_out(args.out):
            if root.is_file():
                with common.bar(args, None, f"frames of {root.parent.name or root.name}") as bar:
                    res = extract_episode(root, args.out, **kwargs,
                                          on_frame=lambda done, total: bar.set(done, total))
                results = [res]
            else:
                with common.bar(args, len(logs), "logs") as bar, Executor(backend, run_dir=args.out) as ex:
                    results = extract_directory(root, args.out, workers=args.workers, force=args.force,
                                                on_episode=lambda _: bar.update(), executor=ex, **kwargs)
    except (LogError, MappingError) as err:
        return common.cli_error(str(err)), []
    common.print_table(console, _table(results, args, root))
    for r in results:
        for w in r.summary.get("warnings", []):
            console.print(f"[yellow]warning:[/yellow] {w}", soft_wrap=True)
        if not r.ok:
            console.print(f"[red]error:[/red] {r.summary['error']}", soft_wrap=True)
    damaged = [r.summary for r in results if r.ok and damaged_log(r.summary)]
    for s in damaged:
        console.print(f"[red]damaged log:[/red] {s['log']}: {s['log_status']}; its tests cover only its intact "
                      "messages", soft_wrap=True)
    out = Path(args.out)
    line = f"wrote {common.shown(out / 'summary.json')}" + (
        f"; run the tests with: {common.tool('pytest')} {common.shown(out)}" if not args.no_tests else "")
    if args.quiet:
        print(line)
    console.print(line, soft_wrap=True)
    return (0 if all(r.ok for r in results) and not damaged else 1), results


def _table(results: list[ExtractionResult], args: argparse.Namespace, root: Path) -> Table:
    t = Table(title=f"DeFT extraction: mode {args.mode}, {args.measure}, theta {args.theta:g} m (positions; "
                    f"'all fields': every field within tolerance at theta)",
              title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False, padding=(0, 1))
    for col in ["log", "scenario", "frames", *(f"<={theta_key(x)} m" for x in SUMMARY_THETAS), "all fields",
                "ms/frame", "planner", "overhead", "truth", "failure tests"]:
        t.add_column(col, justify="left" if col in ("log", "scenario", "failure tests") else "right", no_wrap=True)
    for r in results:
        s = r.summary
        log = Path(s["log"])
        try:  # the log's folder under the input folder: which rerun / episode this row is
            name = str(log.parent.relative_to(root)) if root.is_dir() else log.parent.name
        except ValueError:
            name = log.parent.name
        name = name if name not in ("", ".") else log.stem
        if not r.ok:
            t.add_row(name, "error", *[""] * 10)
            continue
        n = s["frames"] or 1
        failing = "; ".join(f"{k} frame {o['index']} t={o['time']:.2f}s" for k, o in (s.get("failure_oracles") or {}).items())
        t.add_row(
            name, str(s["scenario"]) + (" (cached)" if s.get("skipped") else ""), str(s["frames"]),
            *(f"{100 * s['reproduced'][theta_key(x)] / n:.1f}%" for x in SUMMARY_THETAS),
            "-" if s.get("reproduced_at_theta") is None else f"{100 * s['reproduced_at_theta'] / n:.1f}%",
            f"{s['ms_per_frame']:.2f}", f"{s['planner_ms_per_frame']:.2f}", f"{s['overhead_ms_per_frame']:.2f}",
            "-" if s.get("truth_agreement") is None else f"{100 * s['truth_agreement']:.1f}%",
            failing or ("-" if not s.get("collision") else "no P_faulty found"),
            style="red" if damaged_log(s) else None)  # named below the table ("damaged log: ...")
    return t


if __name__ == "__main__":
    sys.exit(main())
