"""The command line of :mod:`deft_gym.experiments.extract_eval` (``deft-gym extract-eval``), apart from it so
that ``--help`` loads no simulation."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from deft_gym.cli import common
from deft_gym.execution import add_backend_arguments

MODES = ("heuristic", "last", "headers")  # extract.search.MODES (checked by tests/test_cli.py)


def _doc() -> str:
    """deft_gym.experiments.extract_eval's docstring, read without importing it."""
    import ast
    from importlib.util import find_spec

    spec = find_spec("deft_gym.experiments.extract_eval")
    return ast.get_docstring(ast.parse(Path(spec.origin).read_text())) or "" if spec and spec.origin else ""


DOC = _doc()


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = common.parser("extract-eval", "deft_gym.experiments.extract_eval", DOC,
                       epilog="\n\n".join(DOC.split("\n\n")[1:3]))
    common.add_scenarios(ap, help="seed scenarios (default: all in configs/scenarios except bench_*)")
    ap.add_argument("--variants", type=int, default=1, help="perturbed variants per seed")
    ap.add_argument("--cut-ins", type=int, default=8, help="cut-in variants per seed")
    ap.add_argument("--extra-cut-ins", type=int, default=0,
                    help="further cut-ins per seed that join only when their S0 collides (default 0)")
    ap.add_argument("--reruns", type=int, default=10, help="system runs per scenario incl. S0")
    ap.add_argument("--test-runs", type=int, default=10, help="executions of the generated tests")
    ap.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES), help="input-search modes")
    common.add_jitter_seed(ap, "S_k uses jitter seed S+k (a resumed evaluation keeps its seeds)")
    common.add_workers(ap, "parallel processes for S0, extraction, reruns")
    common.add_out(ap, common.RUNS / "extract" / "eval")
    ap.add_argument("--report-only", action="store_true", help="re-render report.md, results.json and plots "
                    "from the records of OUT")
    ap.add_argument("--no-pin-planner", dest="pin_planner", action="store_false",
                    help="use the planner module in place instead of a copy pinned at the start")
    add_backend_arguments(ap)
    common.add_watchdog(ap)
    common.add_output_flags(ap)
    args = ap.parse_args(argv)
    if args.reruns < 2:
        ap.error("--reruns must be at least 2 (S0 and one rerun)")
    if args.jitter_seed is None:  # resuming: the seed recorded there; else a fresh one
        try:
            args.jitter_seed = int(json.loads((Path(args.out) / "options.json").read_text())["jitter_seed"])
        except (OSError, ValueError, KeyError, TypeError):
            args.jitter_seed = common.fresh_seed()
    return args



def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)  # --help and bad input answered here, before the simulation loads
    from deft_gym.experiments.extract_eval import main as run

    with common.watchdog_env(args):
        return run(argv)


if __name__ == "__main__":
    sys.exit(main())
