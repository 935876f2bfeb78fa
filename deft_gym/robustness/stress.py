"""ASTAA-style robustness testing of the ADS on DeFT-Gym's bus.

    deft-gym stress --scenarios left_turn --budget 200 --out runs/stress/left_turn
    python -m deft_gym.robustness.stress replay runs/stress/left_turn/minimised/<finding>.json
    python -m deft_gym.robustness.stress check runs/stress/left_turn/minimised/<finding>/episode.mcap
    python -m deft_gym.robustness.stress spec
    python -m deft_gym.robustness.stress compare runs/stress/off runs/stress/on
    python -m deft_gym.robustness.stress subsystem FRAMES.jsonl --out runs/stress/subsystem

The campaign (default command) generates interception policies from the message schemas and
the exceptional-values dictionary, runs them live on the jittered bus, classifies every run
(crash, hang, invariant violation by name), attributes findings to planted faults, minimises
each distinct finding by delta debugging and writes OUT/summary.json. See
deft_gym/robustness/__init__.py for the parts.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path
from typing import Any

from rich import box
from rich.markup import escape
from rich.table import Table

from deft_gym.cli import common
from deft_gym.config import CONFIG_DIR, ConfigError, deep_merge, load_mapping
from deft_gym.execution import add_backend_arguments, backend_from_args

SUBCOMMANDS = ("replay", "check", "spec", "compare", "subsystem")
MAX_BUDGET = 1_000_000  # tests of one campaign (checked before any work)
console = common.console(stderr=True, width=160)


def _scenario_path(name: str) -> str:
    p = Path(name)
    if p.suffix in (".yaml", ".yml"):
        return name
    cand = CONFIG_DIR / "scenarios" / f"{name}.yaml"
    if not cand.exists():
        raise ConfigError(f"--scenario: no scenario {name!r} (looked for {cand})")
    return str(cand.relative_to(CONFIG_DIR.parent))


def campaign_parser() -> argparse.ArgumentParser:
    ap = common.parser(
        "stress", "deft_gym.robustness.stress",
        "ASTAA robustness campaign: intercept live bus messages with exceptional values, "
        "monitor crashes, hangs and safety invariants, minimise findings.",
        epilog="other commands: replay CASE.json|DIR, check LOG.mcap, spec, compare DIR DIR, "
               "subsystem FRAMES.jsonl (each with --help)")
    common.add_scenarios(ap, flags=("--scenarios", "--scenario"),
                         help="scenario YAMLs or names in configs/scenarios (default: the campaign config's list)")
    ap.add_argument("--budget", type=common.int_range(1, MAX_BUDGET), default=100, help="number of tests")
    common.add_out(ap, common.RUNS / "stress" / "campaign", help="campaign folder (resumed if it exists)")
    ap.add_argument("--config", default=None, help="campaign config YAML (default: configs/stress/default.yaml)")
    common.add_seed(ap, 0, "campaign seed: the tests and their jitter seeds")
    ap.add_argument("--ads-config", default=None, help="ADS config YAML (default: configs/ads/default.yaml)")
    ap.add_argument("--ads-overlay", action="append", default=[],
                    help="YAML merged over the ADS config, e.g. configs/ads/faults/nan_speed.yaml (repeatable)")
    ap.add_argument("--hardening", choices=("off", "on"), default="off",
                    help="wrap prediction/planning/control in sanitisation + consistency checks")
    ap.add_argument("--brittle", action="store_true", help="also inject into brittle fields (stamps, seq numbers)")
    ap.add_argument("--order", choices=("random", "covering"), default=None,
                    help="how tests pick fields and values: covering (test i sets entry i mod the number of fields (and one "
                         "stale duplicate per role) to its next exceptional value, so every field is hit early), or "
                         "random (ASTAA's random draws); default: the config's generation.order (covering)")
    ap.add_argument("--invariants", default=None, help="invariants YAML (default configs/invariants/default.yaml)")
    common.add_workers(ap)
    add_backend_arguments(ap)
    ap.add_argument("--minimise", choices=("all", "planted", "none"), default="all",
                    help="minimise every distinct finding (default), only planted-fault findings, or none")
    ap.add_argument("--until-found", action="store_true",
                    help="with planted faults: stop the tests once every planted fault was found")
    ap.add_argument("--max-replays", type=common.int_range(1, 100_000), default=None,
                    help="replays per minimisation (default: the campaign config's)")
    ap.add_argument("--max-signatures", type=common.int_range(0, 100_000), default=None,
                    help="distinct findings to minimise (default: the campaign config's)")
    common.add_render(ap)
    common.add_watchdog(ap)
    common.add_output_flags(ap)
    return ap


def run_campaign_cli(argv: list[str]) -> int:
    args = campaign_parser().parse_args(argv)  # before the simulation is imported: a fast --help
    with common.watchdog_env(args):
        return _campaign(args)


def _campaign(args: argparse.Namespace) -> int:
    from deft_gym.robustness.campaign import Campaign, load_campaign_config, run_campaign

    overrides: dict[str, Any] = {}
    if args.scenarios:
        overrides["scenarios"] = [_scenario_path(s) for s in args.scenarios]
    if args.brittle:
        overrides.setdefault("generation", {})["brittle"] = True
    if args.order:
        overrides.setdefault("generation", {})["order"] = args.order
    if args.invariants:
        overrides["invariants"] = args.invariants
    if args.max_replays or args.max_signatures is not None:
        overrides["minimise"] = {k: v for k, v in (("max_replays", args.max_replays),
                                                   ("max_signatures", args.max_signatures)) if v is not None}
    cfg = load_campaign_config(args.config, overrides)
    from deft_gym.bus.ads import load_ads_config

    ads_overrides: dict[str, Any] = {}
    for path in args.ads_overlay:  # an overlay that breaks the config is named, one line, before any run
        ads_overrides = deep_merge(ads_overrides, load_mapping(path))
        load_ads_config(args.ads_config, ads_overrides, source=f"{path} (--ads-overlay)")
    campaign = Campaign(cfg, args.seed, args.ads_config, ads_overrides, args.hardening == "on")
    # validate the ADS configuration once, up front (a bad file is one clear line, not N failed runs)
    from deft_gym.robustness.runner import build_ads, check_setup

    build_ads(campaign.base_case(cfg.scenarios[0], 0, "check"))
    from deft_gym.robustness.invariants import load_invariants

    load_invariants(cfg.invariants)  # a missing or bad invariants file: one line, before any run
    for scenario in dict.fromkeys(cfg.scenarios):  # each scenario, every module node and the planner, built
        check_setup(campaign.base_case(scenario, 0, "check"),
                    ", ".join([*(f"{p} (--ads-overlay)" for p in args.ads_overlay)]) or
                    str(args.ads_config or "configs/ads/default.yaml"))
    from deft_gym.robustness.generate import generate_policies
    from deft_gym.robustness.spec import TestSpecification

    if not TestSpecification.from_schemas().select(cfg.generation.roles, brittle=cfg.generation.brittle):
        raise ConfigError(f"{args.config or 'configs/stress/default.yaml'}: generation.roles: no field to "
                          "inject into")
    generate_policies(TestSpecification.from_schemas(), cfg.generation, __import__("random").Random(0))
    backend = backend_from_args(args, args.workers)
    out = Path(args.out)
    bars: dict[str, common.Bar] = {}

    def report(stage: str, done: int, total: int, counts: dict[str, Any]) -> None:
        if stage not in bars:
            for b in bars.values():  # one stage at a time
                b.close()
            bars[stage] = common.Bar(total or None, stage, common.show_progress(args), console, info=True)
        info = ""
        if counts:
            info = (f"crashes {counts['crashes']}  hangs {counts['hangs']}  "
                    f"violations {counts['violations']}  harness errors {counts['harness_errors']}")
        bars[stage].set(done, total or None, info)

    with common.locked_out(out):
        try:
            summary = run_campaign(campaign, out, args.budget, args.workers, args.minimise, report, args.until_found,
                                   backend)
        finally:
            for b in bars.values():
                b.close()
        undrawn = []
        if args.render != "none":  # pictures of the minimised findings' test logs
            from deft_gym.viz.episode import picture_paths, render_log

            for log in sorted((out / "minimised").rglob("*.mcap")):
                if not picture_paths(log)[0].exists():
                    try:
                        render_log(log)
                    except ValueError as err:
                        undrawn.append(f"{log}: {err}")
    if args.quiet:
        print(f"campaign: {out / 'summary.json'}")
    else:
        print_summary(summary, out)
    for line in undrawn:
        print(f"warning: no picture of {line}", file=sys.stderr)
    errors = summary.get("harness_errors", 0)
    if errors:  # an error of the tool, not a finding: never a silent success
        print(f"error: {errors} harness error(s) in {summary.get('harness_error_runs', 0)} test(s) and the baseline "
              f"- errors of the tool, not findings (runs.jsonl, baseline.jsonl); run the same command again to "
              "retry them", file=sys.stderr)
        return 1
    return 0


def print_summary(s: dict[str, Any], out: Path) -> None:
    """A readable table of a campaign summary."""
    t = Table(title=f"ASTAA campaign {out} (hardening {'on' if s['hardening'] else 'off'})", box=box.SIMPLE)
    t.add_column("measure")
    t.add_column("value", justify="right")
    for key in ("runs", "crashes", "hangs", "runs_with_violations", "runs_with_findings", "harness_errors"):
        t.add_row(key.replace("_", " "), str(s[key]))
    for name, n in s["violations"].items():
        t.add_row(f"  violation {name}", str(n))
    t.add_row(escape("wall time [s]"), f"{s['wall_time_s']:.0f}")
    common.print_table(console, t)
    for sig, n in (s.get("baseline_findings") or {}).items():  # the unmodified runs already fail
        console.print(f"[red]baseline finding:[/red] {sig} in {n} unmodified run(s)", soft_wrap=True)
    if s["findings"]:
        f = Table(title="distinct findings", box=box.SIMPLE)
        for col in ("signature", "runs", "first run"):
            f.add_column(col)
        for sig, info in s["findings"].items():
            f.add_row(sig, str(info["runs"]), str(info["first_run"]))
        common.print_table(console, f)
    if s["minimised"]:
        m = Table(title="minimised", box=box.SIMPLE)
        for col in ("signature", "interfaces", "instances", "fields", "replays", "deterministic"):
            m.add_column(col)
        for info in s["minimised"]:
            d = info.get("dimensionality") or {}
            m.add_row(info["signature"], str(d.get("interfaces", "-")), str(d.get("instances", "-")),
                      ", ".join(d.get("fields", [])) or "-", str(info.get("replays", "-")),
                      str(info.get("deterministic", "-")))
        common.print_table(console, m)
    for fault, info in s["planted"].items():
        if info.get("found"):
            d = (info.get("minimised") or {}).get("dimensionality") or {}
            console.print(f"planted fault [bold]{fault}[/]: found at test {info['runs_to_find']} "
                          f"({info['signature']}); minimal: {d.get('interfaces')}/{d.get('instances')} "
                          f"{', '.join(d.get('fields', []))}")
        else:
            console.print(f"planted fault [bold]{fault}[/]: [red]not found")
    console.print(f"summary: {out / 'summary.json'}")


def replay_cli(argv: list[str]) -> int:
    ap = common.parser("stress replay", "deft_gym.robustness.stress replay",
                       "Replay test case files and check they reproduce their finding.")
    ap.add_argument("cases", nargs="+", help="case JSON files, or campaign folders (all cases/ and minimised/)")
    ap.add_argument("--log", default=None, help="write the test log (MCAP) of a single case to this folder")
    args = ap.parse_args(argv)
    from deft_gym.robustness.campaign import replay

    files: list[Path] = []
    for c in args.cases:
        p = Path(c)
        if p.is_dir():
            files += sorted((p / "cases").glob("*.json")) + sorted(q for q in (p / "minimised").glob("*.json")
                                                                    if not q.name.endswith(".info.json"))
        else:
            files.append(p)
    ok = 0
    t = Table(box=box.SIMPLE)
    for col in ("case", "expected", "reproduced", "identical run", "same foundation"):
        t.add_column(col)
    changed = changed_ok = 0
    log = args.log if len(files) == 1 else None
    with common.locked_out(log) if log else contextlib.nullcontext():
        results = [replay(f, log) for f in files]
    for f, r in zip(files, results):
        ok += r["reproduced"] and r["identical"]
        changed += not r["same_foundation"]
        changed_ok += not r["same_foundation"] and r["reproduced"] and r["identical"]
        t.add_row(str(f), str(r["expected"]), str(r["reproduced"]), str(r["identical"]), str(r["same_foundation"]))
    common.print_table(console, t)
    console.print(f"{ok}/{len(files)} cases reproduced their finding with an identical run")
    if changed:
        console.print(f"[yellow]{changed} case(s) were recorded on another version of the simulation source "
                      f"(deft_gym): identical runs are not guaranteed for them ({changed_ok} still identical)")
    return 0 if ok == len(files) else 1


def check_cli(argv: list[str]) -> int:
    ap = common.parser("stress check", "deft_gym.robustness.stress check",
                       "Evaluate the safety invariants offline on an episode log (MCAP). Exit status: 0 when "
                       "none is violated, 1 when one is, 2 when the log is damaged (CRCs, counts, footer) or "
                       "not an episode log.")
    ap.add_argument("log", help="episode.mcap")
    ap.add_argument("--invariants", default=None, help="invariants YAML (default configs/invariants/default.yaml)")
    ap.add_argument("--json", action="store_true", help="print the violations as JSON")
    args = ap.parse_args(argv)
    from deft_gym.robustness.offline import check_log

    try:
        violations = check_log(args.log, args.invariants)
    except ValueError as err:  # a damaged log (LogDamaged), one that is no episode log
        return common.cli_error(str(err))
    if args.json:
        print(json.dumps([v.as_dict() for v in violations], indent=1, allow_nan=True))
    else:
        t = Table(title=f"invariant violations in {args.log}", box=box.SIMPLE)
        for col in ("invariant", "kind", "first [s]", "count", "detail"):
            t.add_column(col)
        for v in violations:
            t.add_row(v.name, v.kind, f"{v.time:.2f}", str(v.count), escape(v.detail))
        if violations:
            common.print_table(console, t)
        else:
            console.print("no invariant violated")
    return 1 if violations else 0


def spec_cli(argv: list[str]) -> int:
    ap = common.parser("stress spec", "deft_gym.robustness.stress spec",
                       "Print the test specification derived from the message schemas.")
    ap.add_argument("--json", action="store_true", help="as JSON")
    args = ap.parse_args(argv)
    from deft_gym.robustness.dictionary import candidates
    from deft_gym.robustness.spec import TestSpecification

    spec = TestSpecification.from_schemas()
    if args.json:
        print(json.dumps({"topics": spec.topics, "message_types": spec.message_types,
                          "fields": [dict(f.as_dict(), values=candidates(f)) for f in spec.fields]}, indent=1))
        return 0
    t = Table(box=box.SIMPLE)
    for col in ("role", "message type", "field", "type", "unit", "brittle", "values"):
        t.add_column(col)
    for f in spec.fields:
        t.add_row(f.role, spec.message_types[f.role], f.path, f.type + (f"<{f.item_type}>" if f.item_type else ""),
                  f.unit, "yes" if f.brittle else "", str(len(candidates(f))))
    common.print_table(console, t)
    return 0


def compare_cli(argv: list[str]) -> int:
    ap = common.parser("stress compare", "deft_gym.robustness.stress compare",
                       "Compare campaign summaries (e.g. hardening off vs on).")
    ap.add_argument("dirs", nargs="+", help="campaign folders")
    args = ap.parse_args(argv)
    sums = []
    for d in args.dirs:
        try:
            s = json.loads((Path(d) / "summary.json").read_text())
            if not isinstance(s, dict) or "runs" not in s:
                raise ValueError("not a campaign summary")
        except (OSError, ValueError) as err:  # no campaign there, or a damaged summary: one line
            return common.cli_error(f"{Path(d) / 'summary.json'}: {getattr(err, 'strerror', None) or err}; expected "
                                    "a campaign folder (deft-gym stress --out DIR)")
        sums.append(s)
    t = Table(box=box.SIMPLE)
    t.add_column("measure")
    for d, s in zip(args.dirs, sums):
        t.add_column(f"{d} (hardening {'on' if s['hardening'] else 'off'})", justify="right")
    for key in ("runs", "crashes", "hangs", "runs_with_violations", "harness_errors"):
        t.add_row(key.replace("_", " "), *[str(s[key]) for s in sums])
    names = sorted({n for s in sums for n in s["violations"]})
    for n in names:
        t.add_row(f"  {n}", *[str(s["violations"].get(n, 0)) for s in sums])
    common.print_table(console, t)
    return 0


def subsystem_cli(argv: list[str]) -> int:
    ap = common.parser("stress subsystem", "deft_gym.robustness.stress subsystem",
                       "Subsystem replay testing: the dictionary applied to DeFT-extracted planning frames, the "
                       "planner alone; findings become pytest tests.")
    ap.add_argument("frames", help="frames.jsonl written by the extractor (deft-gym extract)")
    common.add_out(ap, common.RUNS / "stress" / "subsystem",
                   help="output folder (frames copy, cases.json, test module, summary)")
    ap.add_argument("--budget", type=common.int_range(1, MAX_BUDGET), default=300, help="number of tests")
    common.add_seed(ap)
    ap.add_argument("--turnover", type=common.int_range(0, 10_000), default=5,
                    help="unmodified frames planned after the mutated one")
    ap.add_argument("--invariants", default=None, help="invariants YAML (its `on: planning` ones are used)")
    ap.add_argument("--hardening", choices=("off", "on"), default="off",
                    help="sanitise the planner's inputs as the hardened planning node does")
    common.add_output_flags(ap)
    args = ap.parse_args(argv)  # before the planner is imported: a fast --help
    from deft_gym.robustness.subsystem import run_subsystem

    with common.locked_out(args.out):
        s = run_subsystem(args.frames, args.out, args.budget, args.seed, args.invariants, args.turnover,
                          args.hardening == "on")
    if not args.quiet:
        print(", ".join(f"{k.replace('_', ' ')} {sum(s[k].values()) if isinstance(s[k], dict) else s[k]}"
                        for k in ("tests", "crashes", "hangs", "violations", "harness_errors")))
    print(f"{len(s['minimised'])} distinct findings -> {args.out}/test_robustness_*.py (pytest {args.out})")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] in SUBCOMMANDS:
            cmd = {"replay": replay_cli, "check": check_cli, "spec": spec_cli, "compare": compare_cli,
                   "subsystem": subsystem_cli}[argv[0]]
            return cmd(argv[1:])
        return run_campaign_cli(argv)
    except ConfigError as exc:
        return common.cli_error(str(exc))
    except KeyboardInterrupt:
        console.print("interrupted: run the same command again to resume")
        return 130


if __name__ == "__main__":
    sys.exit(main())
