"""Record deft_gym episodes whose logs differ from the default - to try the extractor on them.

    deft-gym record left_turn --out runs/extract/renamed --topics configs/mappings/renamed_example.yaml
    python -m deft_gym.experiments.record left_turn --out runs/extract/tuned --planner-params '{"w_speed": 4.0}'
    python -m deft_gym.experiments.record left_turn --out runs/extract/hdr --headers --jitter-seed 7
    python -m deft_gym.experiments.record left_turn --out runs/extract/lk --planner tests.support.lane_keeper:LaneKeeperPlanner

``--topics`` renames the bus topics to those of a mapping file (a log as another stack would
name them), ``--planner-params`` configures the planner differently from the default,
``--headers`` makes planning outputs carry their inputs' sequence numbers, ``--planner`` runs
another planner class. The library function
:func:`record_episode` does the same for tests and the evaluation.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from deft_gym.cli import common
from deft_gym.config import ConfigError, deep_merge
from extract.mapping import MappingError, load_mapping

if TYPE_CHECKING:  # the simulation loads on use: --help stays fast
    from deft_gym.scenarios.scenario import Scenario
    from deft_gym.sim.simulation import EpisodeResult


def ads_overrides(topics: dict[str, str] | None = None, planner_params: dict[str, Any] | None = None,
                  headers: bool = False, planner_class: str | None = None) -> dict[str, Any]:
    """An ADS-config override renaming topics, setting the planner (class, parameters) and/or
    headers."""
    out: dict[str, Any] = {}
    if topics:
        out["topics"] = dict(topics)
    if planner_class:
        out = deep_merge(out, {"planning": {"planner": {"class": planner_class}}})
    if planner_params:
        out = deep_merge(out, {"planning": {"planner": {"params": dict(planner_params)}}})
    if headers:
        out = deep_merge(out, {"planning": {"publish_input_headers": True}})
    return out


def record_episode(scenario: Scenario | str | Path, out_dir: Path | str, *, jitter_seed: int | None = None,
                   topics: dict[str, str] | None = None, planner_params: dict[str, Any] | None = None,
                   headers: bool = False, planner_class: str | None = None) -> EpisodeResult:
    """Run one episode into ``out_dir`` (``episode.mcap`` + ``truth.jsonl``)."""
    from deft_gym.bus.ads import load_ads_config
    from deft_gym.sim.simulation import Simulation

    ads = load_ads_config(None, ads_overrides(topics, planner_params, headers, planner_class) or None)
    return Simulation(scenario, ads, jitter_seed=jitter_seed, out_dir=out_dir).run()


def main(argv: list[str] | None = None) -> int:
    ap = common.parser("record", "deft_gym.experiments.record", __doc__)
    ap.add_argument("scenario", help="scenario YAML or the name of one in configs/scenarios")
    common.add_out(ap, None, help="output folder for episode.mcap and truth.jsonl (default: runs/record/<scenario>)")
    common.add_jitter_seed(ap, "jitter seed")
    ap.add_argument("--topics", metavar="MAPPING", default=None, help="take topic names from this mapping YAML")
    ap.add_argument("--planner-params", metavar="JSON", default=None, help="planner parameters, e.g. '{\"w_speed\": 4}'")
    ap.add_argument("--headers", action="store_true", help="planning outputs carry debug.input_seqs")
    ap.add_argument("--planner", metavar="MODULE:CLASS", default=None, help="planner class (default: the ADS config's)")
    common.add_watchdog(ap)
    common.add_output_flags(ap)
    args = ap.parse_args(argv)
    with common.watchdog_env(args):
        return _record(args)


def _record(args: argparse.Namespace) -> int:
    from deft_gym.scenarios.scenario import load_scenario

    try:
        args.out = args.out or str(common.RUNS / "record" / Path(args.scenario).stem)
        topics = dict(load_mapping(args.topics).topics) if args.topics else None
        params = json.loads(args.planner_params) if args.planner_params else None
        if params is not None and not isinstance(params, dict):
            raise ValueError("--planner-params: expected a JSON object")
        scenario = load_scenario(args.scenario)
        with common.locked_out(args.out):
            res = record_episode(scenario, args.out, jitter_seed=args.jitter_seed, topics=topics,
                                 planner_params=params, headers=args.headers, planner_class=args.planner)
    except (ConfigError, MappingError, ValueError) as err:
        return common.cli_error(str(err))
    s = res.summary()
    print(f"{s['outcome']} after {s['sim_time']:.1f} s (jitter seed {s['jitter_seed']}); wrote {s['log']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
