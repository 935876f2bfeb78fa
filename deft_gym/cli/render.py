"""Draw episodes: a plot and a video of each, from its MCAP log alone.

    deft-gym render runs/run/left_turn/0/episode.mcap
    deft-gym render runs/adversary/demo/episodes/w0-000012-take_exit/episode.json
    deft-gym render runs/demo --only failures

A log, an adversary episode's ``episode.json`` (the log beside it) or a folder (every log
under it). The plot shows the whole episode (lanes, the ego's path coloured by speed, every
participant in its own colour with its id, planned trajectories, the collision with its time);
the video follows the ego with the time, speeds and ids. They go beside each log
(``plot.png``, ``video.mp4``) unless ``--out`` is given.
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from typing import Any

from deft_gym.cli import common
from deft_gym.files import first_line


def build_parser() -> common.Parser:
    p = common.parser("render", "deft_gym.cli.render", __doc__)
    p.add_argument("path", metavar="LOG|episode.json|DIR", help="what to draw")
    common.add_out(p, None, help="output folder (default: beside each log)")
    p.add_argument("--only", choices=("all", "failures"), default="all",
                   help="draw every log, or only those of failing episodes (collision, NoDS)")
    p.add_argument("--no-video", action="store_true", help="the plot only")
    common.add_output_flags(p)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    con = common.console(args)
    from deft_gym.viz.episode import find_logs, render_log

    root = Path(args.path)
    try:
        logs = find_logs(root)
    except ValueError as err:
        return common.cli_error(f"LOG|episode.json|DIR: {err}")
    out = Path(args.out) if args.out else None
    done: list[dict[str, Any]] = []
    failed: list[Path] = []
    with common.locked_out(out) if out else contextlib.nullcontext(), common.bar(args, len(logs), "render") as b:
        for log in logs:
            try:
                r = render_log(log, out, root if root.is_dir() else None, video=not args.no_video,
                               only_failures=args.only == "failures")
            except (ValueError, OverflowError, OSError) as err:  # a damaged log, a full disk: named, counted
                failed.append(log)
                print(f"error: {log}: not drawn: {first_line(err)}",
                      file=sys.stderr)
                r = None
            if r:
                done.append(r)
            b.update()
    for r in done:
        con.print(f"{r['title']}\n  plot  {r['plot']}" + (f"\n  video {r['video']}" if r["video"] else ""),
                  soft_wrap=True)
    if not args.quiet or failed:
        print(f"{len(done)} of {len(logs)} episode(s) drawn" + (f"; {len(failed)} could not be" if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
