"""Verify episode logs: CRCs, the chunk index, message counts; say what is damaged and what is lost.

    python -m extract.verify runs/x/0/episode.mcap            # one log
    python -m extract.verify runs/x                           # every log under a folder
    python -m extract.verify runs/x/0/episode.mcap --json

One line per log (intact, or the problems with their offsets, time ranges and the messages they
cost). Exit status: 0 when every log is intact, 1 when one is damaged, 2 on bad input.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from extract.logs import EpisodeLog, LogError, read_log


def verify(path: Path | str) -> EpisodeLog:
    """Read and verify every topic of a log (:func:`extract.logs.read_log`)."""
    probe = read_log(path, [])
    return read_log(path, sorted(probe.channel_roles))


def main(argv: list[str] | None = None) -> int:
    from deft_gym.cli import common

    ap = common.parser("verify", "extract.verify", __doc__)
    ap.add_argument("paths", nargs="+", metavar="LOG_OR_DIR", help="MCAP logs, or folders searched for *.mcap")
    ap.add_argument("--json", action="store_true", help="print the integrity reports as JSON")
    args = ap.parse_args(argv)
    logs: list[Path] = []
    for p in map(Path, args.paths):
        logs += sorted(p.rglob("*.mcap")) if p.is_dir() else [p]
    if not logs:
        return common.cli_error(f"{', '.join(args.paths)}: no .mcap logs found")
    damaged = 0
    reports = {}
    for path in logs:
        try:
            log = verify(path)
        except LogError as err:
            return common.cli_error(str(err))
        integ = log.integrity
        damaged += not integ.intact
        reports[str(path)] = {"status": log.status, **integ.as_dict()}
        if args.json:
            continue
        found = sum(integ.found.values())
        checked = (f"{integ.chunks_ok}/{integ.chunks} chunks pass their CRC" if integ.crcs
                   else "no CRCs (unverified)") + (", counts checked against the summary" if integ.expected else "")
        print(f"{path}: {log.status} - {found} messages; {checked}")
        for w in log.warnings:
            print(f"  {w.removeprefix(f'{path}: ')}")
    if args.json:
        print(json.dumps(reports, indent=1))
    return 1 if damaged else 0


if __name__ == "__main__":
    sys.exit(main())
