"""Why the ego left the road: each drivable-area violation of a run taken apart.

    python -m deft_gym.experiments.off_road runs/suite/default runs/suite/commonroad --out runs/off_road

For every episode log under the given folders (``**/episode.mcap``, or the log files themselves)
whose ego box, at the log's localization poses, reaches more than 0.3 m outside the drivable
area of the log's map (the drivable-area metric's tolerance; the area as P_off_road builds it),
it prints when and where the ego left the road and how far; how far the last plan before put the
box outside within 5 m of that place; the ego's offset there to the left of that plan (at the
plan's time) and its heading difference; and the verdict: ``planned`` when P_off_road
(:func:`extract.oracle.find_off_road`) finds the plan that took it there - a planning-module
failure, which ``deft-gym extract`` turns into a test - else ``left its plan``: the plans kept the
box within 0.3 m of the road and the vehicle went over by following them loosely (control, or
plans that hug the edge with no room for tracking). Writes ``OUT/off_road.json`` and a picture
per log (``OUT/<suite>_<scenario>_<rerun>.png``, the suite being the folder above the scenario's:
the road, the ego's path, the plan's boxes near the place).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
from rich import box
from rich.table import Table

from deft_gym.cli import common
from deft_gym.files import write_atomic
from deft_gym.world.geometry import box_polygon
from extract.episode import ego_poses, map_payload
from extract.logs import LogError, read_log
from extract.mapping import load_mapping
from extract.oracle import (
    DEFAULT_EGO,
    OFF_ROAD_LIMIT,
    OFF_ROAD_RADIUS,
    find_off_road,
    left_road,
    map_area,
    off_road_depths,
    off_road_near,
)


def logs_under(paths: list[Path]) -> list[Path]:
    """Episode logs: each path that is a file, and every ``episode.mcap`` under each folder."""
    out: list[Path] = []
    for p in paths:
        out.extend([p] if p.is_file() else sorted(p.rglob("episode.mcap")))
    return out


def take_apart(log: Path, ego: tuple[float, float] = DEFAULT_EGO) -> dict[str, Any] | None:
    """One log's drivable-area violation taken apart (None when the ego kept on the road)."""
    mp = load_mapping()
    topics = [mp.topic(r) for r in ("planning", "map", "localization")]
    elog = read_log(log, [t for t in topics if t])
    payload = map_payload(elog, mp)
    plans = elog.topics.get(mp.topic("planning") or "")
    poses = ego_poses(elog, mp)
    if payload is None or plans is None or not poses or not poses["t"]:
        raise LogError(f"{log}: needs the map, planning and localization topics of the mapping")
    area = map_area(payload)
    left = left_road(poses, area, ego)
    if left is None:
        return None
    p, depth = left
    t_left, place = poses["t"][p], (poses["x"][p], poses["y"][p])
    outputs = [(i, float(pl["header"]["stamp"]), pl) for i in range(len(plans)) if (pl := plans.payload(i))]
    before = [o for o in outputs if o[1] < t_left]
    row: dict[str, Any] = {"log": str(log), "suite": log.parents[2].name if len(log.parents) > 2 else "",
                           "scenario": log.parent.parent.name, "rerun": log.parent.name,
                           "left_at": t_left, "place": list(place), "depth_at_leaving": float(depth[p]),
                           "depth_max": float(depth.max()), "last_plan": None, "p_off_road": None}
    if before:
        tr = before[-1][2].get("trajectory") or {}
        _, reach = off_road_near(tr, area, ego, place)
        row["last_plan"] = {"index": before[-1][0], "time": before[-1][1], "depth_near": reach,
                            **_offset(tr, t_left, place, poses["heading"][p])}
    row["p_off_road"] = find_off_road(outputs, poses, area, ego)
    row["verdict"] = "planned" if row["p_off_road"] else "left its plan"
    row["_draw"] = (area, poses, (row["p_off_road"] or {}).get("index", before[-1][0] if before else None), plans, ego)
    return row


def _offset(tr: dict[str, Any], t: float, place: tuple[float, float], heading: float) -> dict[str, float]:
    """The pose's offset [m] to the left of a plan at time ``t`` and its heading minus the plan's [deg]."""
    if not tr.get("t"):
        return {}
    px, py = float(np.interp(t, tr["t"], tr["x"])), float(np.interp(t, tr["t"], tr["y"]))
    ph = float(np.interp(t, tr["t"], np.unwrap(tr["heading"])))
    lateral = -(place[0] - px) * math.sin(ph) + (place[1] - py) * math.cos(ph)
    dh = (heading - ph + math.pi) % (2 * math.pi) - math.pi
    return {"offset_left": lateral, "heading_diff_deg": math.degrees(dh)}


def draw(row: dict[str, Any], path: Path) -> None:
    """The road near where the ego left it, the ego's path and the boxes of the plan that took it
    there (P_off_road), else of the last plan before."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    area, poses, index, plans, ego = row["_draw"]
    fig, ax = plt.subplots(figsize=(6, 6))
    for poly in getattr(area, "geoms", [area]):
        ax.fill(*poly.exterior.xy, color="0.88", zorder=0)
        for hole in poly.interiors:
            ax.fill(*hole.xy, color="white", zorder=0)
    ax.plot(poses["x"], poses["y"], color="tab:blue", lw=1.2, label="ego (localization)")
    if index is not None:
        tr = plans.payload(index)["trajectory"]
        near = np.hypot(np.asarray(tr["x"]) - row["place"][0], np.asarray(tr["y"]) - row["place"][1]) <= 2 * OFF_ROAD_RADIUS
        depths = off_road_depths(tr, area, ego)
        for k in np.flatnonzero(near):
            box_ = box_polygon(tr["x"][k], tr["y"][k], tr["heading"][k], ego[0], ego[1])
            ax.plot(*box_.exterior.xy, color="tab:red" if depths[k] > OFF_ROAD_LIMIT else "tab:orange", lw=0.8)
        ax.plot(tr["x"], tr["y"], color="tab:orange", lw=1, ls="--",
                label=f"plan {index} ({'P_off_road' if row['p_off_road'] else 'last before leaving'})")
    ax.plot(*row["place"], "kx", ms=10, label=f"left the road at t={row['left_at']:.2f} s")
    ax.set_xlim(row["place"][0] - 15, row["place"][0] + 15)
    ax.set_ylim(row["place"][1] - 15, row["place"][1] + 15)
    ax.set_aspect("equal")
    ax.legend(loc="upper left", fontsize=7)
    ax.set_title(f"{row['suite']}: {row['scenario']} #{row['rerun']}: {row['verdict']}; ego {row['depth_max']:.2f} m off the road",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = common.parser("off_road", "deft_gym.experiments.off_road", __doc__)
    ap.add_argument("paths", nargs="+", metavar="PATH", help="episode logs, or folders searched for episode.mcap")
    common.add_out(ap, common.RUNS / "off_road")
    common.add_output_flags(ap)
    args = ap.parse_args(argv)
    console = common.console(args, width=140)
    logs = logs_under([Path(p) for p in args.paths])
    if not logs:
        return common.cli_error(f"{' '.join(args.paths)}: no episode.mcap found")
    found = []
    for log in logs:
        try:
            row = take_apart(log)
        except LogError as exc:
            return common.cli_error(str(exc))
        if row is not None:
            found.append(row)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for row in found:
        draw(row, out / f"{row['suite']}_{row['scenario']}_{row['rerun']}.png")
        rows.append({k: v for k, v in row.items() if not k.startswith("_")})
    t = Table(title=f"Left the road: {len(rows)} of {len(logs)} logs", box=box.SIMPLE_HEAD)
    for col in ("suite", "scenario", "#", "t [s]", "ego off [m]", "max [m]", "last plan off [m]", "ego left of it [m]",
                "heading diff [deg]", "verdict"):
        t.add_column(col, overflow="fold")
    for r in rows:
        lp = r["last_plan"] or {}
        t.add_row(r["suite"], r["scenario"], r["rerun"], f"{r['left_at']:.2f}", f"{r['depth_at_leaving']:.2f}", f"{r['depth_max']:.2f}",
                  f"{lp.get('depth_near', math.nan):.2f}", f"{lp.get('offset_left', math.nan):+.2f}",
                  f"{lp.get('heading_diff_deg', math.nan):+.1f}", r["verdict"])
    common.print_table(console, t)
    planned = sum(r["verdict"] == "planned" for r in rows)
    console.print(f"planned (P_off_road, a planning test): {planned}; left its plan: {len(rows) - planned}")
    write_atomic(out / "off_road.json", json.dumps(rows, indent=1))
    console.print(f"wrote {out / 'off_road.json'} and {len(rows)} pictures")
    return 0


if __name__ == "__main__":
    sys.exit(main())
