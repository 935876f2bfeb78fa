"""Why a planner stands: each extracted stall (P_stall) taken apart at the frame it begins.

    python -m deft_gym.experiments.stalls runs/suite/commonroad_tests/*/
    python -m deft_gym.experiments.stalls DIR... --variant '{"boundary_overlap": 0.5}' --variant '{"d_min": -1, "d_max": 1}'

For every extraction folder (``frames.jsonl`` of ``deft-gym extract``) whose oracle holds a stall,
the planner is replayed from the first frame to P_stall's (its state as in the run), and at that
frame it prints: the ego's speed; how much of the car's box [m^2] lies outside the lanes of the
road map (the frame's ``map`` input, else the log's map topic; lanes as P_wrong_way reads them); the recorded decision
(``result``, ``fallback`` and, where the planner states them, its samples and rejections); and
the decision re-planned from the same state with each ``--variant`` of the planner's parameters
(JSON; CommonRoad's ``boundary_overlap`` widens the lanes of its road boundary). Where the
planner keeps per-constraint rejection counts (CommonRoad's ``_infeasible_reason_dict``) they are
printed too. Writes ``OUT/stalls.json``.
"""

from __future__ import annotations

import copy
import json
import math
import sys
from pathlib import Path
from typing import Any

import shapely
from rich import box
from rich.table import Table

from deft_gym.cli import common
from deft_gym.files import write_atomic
from extract.logs import read_log
from extract.mapping import load_mapping
from extract.oracle import map_lanes
from extract.runtime import load_frames, make_planner, to_frame

DEFAULT_VARIANT = '{"boundary_overlap": 0.5}'


def road_map(header: dict[str, Any], frame: dict[str, Any]) -> Any:
    """The road map payload: the frame's ``map`` input, else the log's map topic (a planner that
    does not read the map has none in its frames); None when neither has one."""
    payload = (frame.get("inputs") or {}).get("map")
    if payload is not None:
        return payload
    try:
        mp = load_mapping(header.get("mapping"))
        topic = mp.topic("map")
        msgs = read_log(header["log"], [topic]).topics.get(topic) if topic else None
    except (KeyError, ValueError, OSError):
        return None
    return msgs.payload(0) if msgs is not None and len(msgs) else None


def outside_lanes(frame: dict[str, Any], map_payload: Any, ego: tuple[float, float]) -> float | None:
    """Area [m^2] of the ego's box at the frame's localization outside the union of the map's
    lanes; None without a map."""
    lanes = map_lanes(map_payload)
    loc = (frame.get("inputs") or {}).get("localization")
    if not lanes or not loc:
        return None
    road = shapely.union_all([shapely.LineString(xy).buffer(half, cap_style="flat") for xy, half in lanes])
    c, s = math.cos(loc["heading"]), math.sin(loc["heading"])
    half_l, half_w = ego[0] / 2, ego[1] / 2
    car = shapely.Polygon([(loc["x"] + a * c - b * s, loc["y"] + a * s + b * c)
                           for a, b in ((half_l, half_w), (half_l, -half_w), (-half_l, -half_w), (-half_l, half_w))])
    return float(car.difference(road).area)


def _decision(out: dict[str, Any] | None) -> str:
    d = (out or {}).get("decision") or {}
    if not d:
        return "no output" if out is None else "-"
    text = str(d.get("result", "?")) + (f" ({d['fallback']})" if d.get("fallback") else "")
    if d.get("samples", -1) >= 0:
        text += f" {d['infeasible_kinematics']}+{d['infeasible_collision']}/{d['samples']}"
    return text


def _reasons(planner: Any, frame: dict[str, Any]) -> dict[str, int] | None:
    model = getattr(planner, "_model", None)
    if model is None:
        return None
    try:
        reasons = model(frame["inputs"]["map"]).planner._infeasible_reason_dict
    except (AttributeError, KeyError, TypeError):
        return None
    return {k: int(v) for k, v in reasons.items() if v}


def take_apart(folder: Path, variants: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The stall of one extraction folder at its first frame (None when it has none)."""
    header, frames = load_frames(folder / "frames.jsonl")
    stall = (header.get("oracle") or {}).get("stall")
    if not stall:
        return None
    k = int(stall["index"])
    planner = make_planner(header)
    for f in frames[:k]:
        planner.plan(to_frame(f))
    state = planner.export_state()
    ego = header.get("oracle", {}).get("ego") or {}
    row: dict[str, Any] = {
        "folder": str(folder), "scenario": header.get("scenario"), "frame": k, "time": frames[k]["time"],
        "speed": frames[k]["inputs"]["localization"]["v"],
        "outside_lanes_m2": outside_lanes(frames[k], road_map(header, frames[k]),
                                          (ego.get("length", 4.8), ego.get("width", 2.0))),
        "recorded": _decision(frames[k].get("expected")), "variants": []}
    for params in [{}, *variants]:
        h = copy.deepcopy(header)
        h["planner"]["params"] = {**(h["planner"].get("params") or {}), **params}
        p = make_planner(h)
        p.reset()
        p.load_state(state)
        out = p.plan(to_frame(frames[k]))
        row["variants"].append({"params": params, "decision": _decision(out), "reasons": _reasons(p, frames[k])})
    return row


def main(argv: list[str] | None = None) -> int:
    ap = common.parser("stalls", "deft_gym.experiments.stalls", __doc__)
    ap.add_argument("folders", nargs="+", metavar="DIR", help="extraction folders (frames.jsonl)")
    ap.add_argument("--variant", action="append", default=None, metavar="JSON",
                    help=f"planner parameters to re-plan the stall frame with (repeatable; default {DEFAULT_VARIANT})")
    common.add_out(ap, common.RUNS / "stalls")
    common.add_output_flags(ap)
    args = ap.parse_args(argv)
    console = common.console(args, width=140)
    try:
        variants = [json.loads(v) for v in (args.variant or [DEFAULT_VARIANT])]
    except json.JSONDecodeError as exc:
        return common.cli_error(f"--variant: not JSON ({exc})")
    if not all(isinstance(v, dict) for v in variants):
        return common.cli_error("--variant: expected a JSON object of planner parameters")
    rows = []
    for folder in map(Path, args.folders):
        if not (folder / "frames.jsonl").is_file():
            return common.cli_error(f"{folder}: no frames.jsonl (an extraction folder of deft-gym extract)")
        row = take_apart(folder, variants)
        if row is not None:
            rows.append(row)
    t = Table(title=f"Stalls: {len(rows)} of {len(args.folders)} folders", box=box.SIMPLE_HEAD)
    for col in ("scenario", "t [s]", "v [m/s]", "car off the lanes [m2]", "recorded", "re-planned",
                *(json.dumps(v) for v in variants)):
        t.add_column(col, overflow="fold")
    for r in rows:
        area = r["outside_lanes_m2"]
        t.add_row(str(r["scenario"]), f"{r['time']:.1f}", f"{r['speed']:.2f}", "-" if area is None else f"{area:.2f}",
                  r["recorded"], *(v["decision"] for v in r["variants"]))
    common.print_table(console, t)
    console.print("decisions: result (fallback) and, where the planner states them, samples rejected for kinematics + "
                  "for collision / sampled; per-constraint counts in stalls.json")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "stalls.json", json.dumps(rows, indent=1))
    console.print(f"wrote {out / 'stalls.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
