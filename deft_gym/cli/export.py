"""Export failures to OpenSCENARIO 1.2 + OpenDRIVE 1.7 and CommonRoad XML, next to their logs.

    deft-gym export runs/demo                                   # every failure under a folder
    deft-gym export runs/eval/x/logs/.../00003/episode.json     # one adversary / search failure
    deft-gym export runs/run/left_turn/3/episode.mcap --format xosc
    deft-gym export left_turn --jitter-seed 7 --out runs/export/left_turn   # a scenario, simulated once
    deft-gym export runs/demo --check                           # and check every file independently

A log, an episode folder's ``episode.json``, a run / evaluation / training folder (every failing
episode under it: a collision, a non-optimal decision, a task failure, a crash) or a scenario
(YAML, name or ``gen:<seed>``, simulated once on ``--jitter-seed``). ``DIR/episode.mcap`` is
written as ``DIR/episode.xosc`` + ``DIR/episode.xodr`` and ``DIR/episode.cr.xml``, and what was
done as ``DIR/episode.export.json``. Each episode is simulated again at every world step with
its log's scenario, ADS configuration and jitter seed and kept only where it agrees with the
log's ground truth (else the log's own samples are exported). ``--check`` runs the independent
checks: ASAM's schemas and quality checkers, CommonRoad's schema, reader and drivability checker
(the logged collision), the parsed-back trajectories against the log, and the round trip
(``deft-gym import`` of each file, rerun on the episode's jitter seed). Needs the ``export``
extra (``pip install 'deft-gym[export]'``); formats and losses: docs/interop.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from deft_gym.cli import common

FORMATS = {"xosc": ("xosc",), "commonroad": ("commonroad",), "all": ("xosc", "commonroad")}


def build_parser() -> common.Parser:
    p = common.parser("export", "deft_gym.cli.export", __doc__)
    p.add_argument("path", metavar="LOG|episode.json|DIR|SCENARIO", help="what to export")
    p.add_argument("--format", choices=tuple(FORMATS), default="all",
                   help="OpenSCENARIO + OpenDRIVE (xosc), CommonRoad XML (commonroad) or both")
    p.add_argument("--all", action="store_true", help="every episode under a folder, not only the failures")
    p.add_argument("--check", action="store_true",
                   help="check every file: ASAM quality checkers, CommonRoad schema and drivability checker, "
                        "trajectories against the log, the round trip (import and rerun)")
    p.add_argument("--no-resimulate", action="store_true",
                   help="export the log's own ground-truth samples instead of simulating the episode again")
    p.add_argument("--jitter-seed", type=int, default=0, metavar="S",
                   help="a scenario: the jitter seed of its one run")
    common.add_out(p, None, help="a scenario: where its run and files go (default: runs/export/<scenario>-<seed>)")
    common.add_output_flags(p)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    con = common.console(args)
    try:
        import commonroad  # noqa: F401
        import scenariogeneration  # noqa: F401
    except ImportError as err:
        return common.cli_error(f"the export needs the export extra ({err.name} is missing): "
                                "pip install 'deft-gym[export]'")
    from deft_gym.export.failures import find_logs

    path = Path(args.path)
    formats = FORMATS[args.format]
    if path.exists() and (path.is_dir() or path.suffix in (".mcap", ".json")):
        try:
            logs = find_logs(path, all_episodes=args.all)
        except ValueError as err:
            return common.cli_error(f"LOG|episode.json|DIR: {err}")
    else:
        try:
            logs = [_simulate_scenario(args, con)]
        except Exception as err:  # a scenario that does not load: one line
            return common.cli_error(f"SCENARIO {args.path}: {err}".splitlines()[0])
    records = []
    with common.bar(args, len(logs), "export") as b:
        for log in logs:
            records.append(export_one(log, formats, args.check, not args.no_resimulate))
            b.update()
    for r in records:
        _print(con, r)
    if args.check and len(records) > 1:
        from deft_gym.files import write_json_atomic

        summary = summarize(records)
        root = path if path.is_dir() else Path(records[0]["log"]).parent
        write_json_atomic(root / "export_check.json", {"summary": summary, "exports": records})
        con.print(f"\n{_summary_text(summary)}\nchecks of every export: {root / 'export_check.json'}", soft_wrap=True)
    failed = [r for r in records if r.get("error")]
    print(f"{len(records) - len(failed)} of {len(records)} episode(s) exported"
          + (f", {len(failed)} failed" if failed else "") + (f" ({args.format})" if not args.quiet else ""))
    return 1 if failed else 0


def _simulate_scenario(args: argparse.Namespace, con: Any) -> Path:
    """Run the scenario once (its log in ``--out``); the log."""
    from deft_gym.search.context import resolve_scenario
    from deft_gym.sim.simulation import Simulation

    sc = resolve_scenario(args.path)
    out = Path(args.out) if args.out else common.RUNS / "export" / f"{sc.name}-{args.jitter_seed}"
    res = Simulation(sc, jitter_seed=args.jitter_seed, out_dir=out).run()
    con.print(f"{sc.name}: simulated once on jitter seed {args.jitter_seed}: {res.outcome.outcome}"
              + (f" (collision with {res.outcome.collision.participant})" if res.outcome.collision else ""),
              soft_wrap=True)
    return Path(res.log_path or out / "episode.mcap")


def export_one(log: Path, formats: tuple[str, ...], check: bool, resimulate: bool = True) -> dict[str, Any]:
    """Export one log (and check it); the record also written as ``<stem>.export.json``."""
    from deft_gym.export.episode import from_log
    from deft_gym.export.failures import check_export, export_paths, write_exports
    from deft_gym.files import write_json_atomic

    t0 = time.perf_counter()
    rec: dict[str, Any] = {"log": str(log)}
    try:
        e = from_log(log, resimulate=resimulate)
        rec.update(summary=e.summary(), failure=e.failure, outcome=e.outcome,
                   trajectories=e.source.get("trajectories"), resimulation=e.source.get("check"))
        written = write_exports(e, export_paths(log), formats)
        rec["files"] = {k: str(p) for k, p in written.items()}
        if check:
            rec["check"] = check_export(log, written)
    except Exception as err:  # one bad log must not stop a folder's export
        rec["error"] = f"{type(err).__name__}: {err}".splitlines()[0][:300]
    rec["seconds"] = round(time.perf_counter() - t0, 3)
    write_json_atomic(log.with_name(f"{log.stem}.export.json"), rec)
    return rec


def _print(con: Any, r: dict[str, Any]) -> None:
    if r.get("error"):
        con.print(f"[red]{r['log']}[/red]: {r['error']}", soft_wrap=True)
        return
    files = ", ".join(Path(p).name for p in r["files"].values())
    con.print(f"{r['summary']}\n  {Path(r['log']).parent}/: {files}\n  trajectories: {r['trajectories']}",
              soft_wrap=True)
    c = r.get("check")
    if c:
        con.print("  check: " + _check_line(c), soft_wrap=True)


def _check_line(c: dict[str, Any]) -> str:
    parts = []
    if "xosc_errors" in c:
        parts.append(f"xosc {c['xosc_errors']} / xodr {c['xodr_errors']} checker errors")
        t = c["xosc_trajectories"]
        parts.append(f"xosc trajectories max {t['max_position_error'] * 100:.2f} cm, {t['max_heading_error']:.1e} rad")
        if "xosc_roundtrip" in c:
            parts.append("xosc round trip " + _rt(c["xosc_roundtrip"]))
    if "commonroad_schema" in c:
        parts.append(f"CommonRoad schema {len(c['commonroad_schema'])} errors")
        t = c["commonroad_trajectories"]
        parts.append(f"CommonRoad trajectories max {t['max_position_error'] * 100:.2f} cm")
        if "commonroad_collision" in c:
            cc = c["commonroad_collision"]
            parts.append(f"drivability checker: collision at step {cc['step']} (logged {cc['logged_step']})")
        if "commonroad_roundtrip" in c:
            parts.append("CommonRoad round trip " + _rt(c["commonroad_roundtrip"]))
    return "; ".join(parts)


def _rt(r: dict[str, Any]) -> str:
    if not r["reproduced"]:
        return f"DIFFERS ({r['outcome']})"
    dev = r.get("ego_max_deviation")
    return "reproduced" + (f" (ego path within {dev * 100:.2g} cm)" if dev is not None else "")


def summarize(records: list[dict[str, Any]]) -> dict[str, Any]:
    """The targets' figures over checked exports (docs/interop.md)."""
    ok = [r for r in records if not r.get("error")]
    checked = [r["check"] for r in ok if r.get("check")]
    s: dict[str, Any] = {"episodes": len(records), "exported": len(ok),
                         "errors": [r["error"] for r in records if r.get("error")]}

    def count(key: str, test: Any) -> list[int]:
        have = [c[key] for c in checked if key in c]
        return [sum(1 for v in have if test(v)), len(have)]

    s["xosc_checker_clean"] = count("xosc_errors", lambda v: v == 0)
    s["xodr_checker_clean"] = count("xodr_errors", lambda v: v == 0)
    s["commonroad_schema_clean"] = count("commonroad_schema", lambda v: not v)
    s["collisions_confirmed"] = count("commonroad_collision", lambda v: v["confirmed"])
    for key in ("xosc_roundtrip", "xosc_roundtrip_reactive", "commonroad_roundtrip"):
        s[f"{key}_reproduced"] = count(key, lambda v: v["reproduced"])
        s[f"{key}_same_path"] = count(key, lambda v: v["same_path"])
    for fmt in ("xosc", "commonroad"):
        ts = [c[f"{fmt}_trajectories"] for c in checked if f"{fmt}_trajectories" in c]
        if ts:
            s[f"{fmt}_max_position_error_m"] = max(t["max_position_error"] for t in ts)
            s[f"{fmt}_max_heading_error_rad"] = max(t["max_heading_error"] for t in ts)
            s[f"{fmt}_uncovered_samples"] = sum(t["uncovered"] for t in ts)
    s["resimulated"] = sum(1 for r in ok if str(r.get("trajectories", "")).startswith("simulated"))
    return s


def _summary_text(s: dict[str, Any]) -> str:
    def frac(v: list[int]) -> str:
        return f"{v[0]} of {v[1]}" if v[1] else "-"

    lines = [f"exported: {s['exported']} of {s['episodes']} ({s['resimulated']} simulated again at every step)",
             f"ASAM checkers, 0 errors: xosc {frac(s['xosc_checker_clean'])}, xodr {frac(s['xodr_checker_clean'])}; "
             f"CommonRoad schema clean: {frac(s['commonroad_schema_clean'])}",
             f"collisions confirmed by CommonRoad's drivability checker (within one step): "
             f"{frac(s['collisions_confirmed'])}",
             f"round trip, the logged outcome (and collision) reproduced: xosc {frac(s['xosc_roundtrip_reproduced'])}, "
             f"CommonRoad {frac(s['commonroad_roundtrip_reproduced'])}, xosc with reactive participants reactive "
             f"{frac(s['xosc_roundtrip_reactive_reproduced'])}",
             f"  ... and the ego's path within 1 cm at every step: xosc {frac(s['xosc_roundtrip_same_path'])}, "
             f"CommonRoad {frac(s['commonroad_roundtrip_same_path'])}, reactive "
             f"{frac(s['xosc_roundtrip_reactive_same_path'])}"]
    for fmt in ("xosc", "commonroad"):
        if f"{fmt}_max_position_error_m" in s:
            lines.append(f"{fmt} trajectories vs the log: max {s[f'{fmt}_max_position_error_m'] * 100:.3f} cm, "
                         f"{s[f'{fmt}_max_heading_error_rad']:.2e} rad, {s[f'{fmt}_uncovered_samples']} samples uncovered")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
