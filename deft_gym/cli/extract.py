"""``deft-gym extract``: ``python -m extract`` plus pictures of the failures it extracted.

Same options as ``python -m extract`` (the extractor needs nothing of the simulation); with
``--render failures`` (the default) every extracted episode with a collision also gets
``plot.png`` and ``video.mp4`` in its extraction folder (:mod:`deft_gym.viz.episode`).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from deft_gym.cli import common


def render(results: list[Any], what: str) -> list[str]:
    """Plots (and videos) of the extracted episodes (``what``: failures = those with a
    collision, all, none), into each episode's extraction folder; the plots drawn."""
    if what == "none":
        return []
    from deft_gym.viz.episode import load_episode, save_plot, save_video

    done = []
    for r in results:
        s = r.summary
        if not r.ok or r.frames_path is None or (what == "failures" and not s.get("collision")):
            continue
        folder = Path(r.frames_path).parent
        if (folder / "plot.png").exists() and s.get("skipped"):
            continue
        try:
            ep = load_episode(s["log"])
            save_video(ep, folder / "video.mp4")  # the plot last: it says both are done
            done.append(str(save_plot(ep, folder / "plot.png")))
        except ValueError:
            continue
    return done


def main(argv: list[str] | None = None) -> int:
    from extract.__main__ import build_parser, parse_args, run

    ap = build_parser()
    common.add_render(ap)
    args = parse_args(argv, ap)
    with common.watchdog_env(args):
        code, results = run(args)
    if code != 2:
        for plot in render(results, args.render):
            common.console(args).print(f"picture of the failure: {plot}", soft_wrap=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
