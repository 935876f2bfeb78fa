"""Do the extracted tests catch behavioural regressions? Small realistic edits of the reference planner.

    python -m deft_gym.experiments.planner_edits --out runs/planner_edits
    python -m deft_gym.experiments.planner_edits --out runs/planner_edits --edits w_jerk nudge_label    # a few

Each edit (:data:`EDITS`) is one small change of ``deft_gym/planner/lattice.py`` of the kind a
developer makes - a buffer, a comparison, a horizon, a cost term, a decision label, a profile -
or a change that must not matter (a rename, a comment, an exact rewrite, a reordering). The
tool records a few short episodes with the reference planner, extracts them (heuristic mode,
theta = 0) and then, per edit, on a copy of the planner module with the edit applied:

- *changes an output* (ground truth, independent of the tests): the edited and the original
  planner replay every extracted frame side by side; the edit changes an output when some
  frame's whole output (every trajectory field, the decision) differs as JSON values;
- *caught*: the generated tests, run by pytest with ``DEFT_PLANNER`` naming the edited copy,
  fail.

Both run with ``DEFT_GYM_PURE_PYTHON=1`` (edits to numpy code that the compiled kernel mirrors
then take effect; the kernel gives the same bits). Prints a table and the two rates (caught of
those that change an output; flagged of those that change none) and writes ``OUT/edits.json``.
An edit whose text no longer occurs in the planner is reported as not applicable.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich import box
from rich.table import Table

from deft_gym.cli import common
from deft_gym.files import write_atomic

SCENARIOS = ("left_turn", "take_exit", "blocked_red_light", "lane_follow_static", "u_turn")


@dataclass(frozen=True)
class Edit:
    """One edit: replace ``old`` (which must occur exactly once) by ``new``."""

    name: str
    kind: str  #: buffer | comparison | horizon | cost | decision | profile | neutral
    old: str
    new: str
    what: str


def _param(name: str, old: str, new: str, kind: str, what: str) -> Edit:
    return Edit(name, kind, f"    {name}: float = {old}\n", f"    {name}: float = {new}\n", what)


EDITS: tuple[Edit, ...] = (
    _param("lat_buffer_hard", "0.5", "0.45", "buffer", "hard lateral buffer 0.5 -> 0.45 m"),
    _param("lon_buffer_hard", "1.0", "1.2", "buffer", "hard longitudinal buffer 1.0 -> 1.2 m"),
    _param("lat_buffer_soft", "1.0", "1.1", "buffer", "soft buffer 1.0 -> 1.1 m"),
    _param("stop_gap", "1.0", "1.5", "buffer", "gap before stop lines 1.0 -> 1.5 m"),
    _param("time_gap", "1.5", "1.7", "buffer", "time gap to a leader 1.5 -> 1.7 s"),
    _param("edge_margin", "0.3", "0.35", "buffer", "road-edge margin 0.3 -> 0.35 m"),
    _param("stitch_lat", "0.5", "0.4", "comparison", "stitching tolerance 0.5 -> 0.4 m"),
    Edit("stitch_strict", "comparison", "if abs(-dx * sh + dy * ch) <= self.p.stitch_lat and",
         "if abs(-dx * sh + dy * ch) < self.p.stitch_lat and", "stitching test <= -> <"),
    Edit("locate_threshold", "comparison", "if best is not None and score < 1.5:",
         "if best is not None and score < 1.2:", "lane search around the previous lane: 1.5 -> 1.2"),
    Edit("vmin_strict", "comparison", "ok_lon = ((lv > -0.1) & (lv <= limit))", "ok_lon = ((lv > -0.05) & (lv <= limit))",
         "a profile may dip to -0.1 -> -0.05 m/s"),
    _param("horizon", "Field(6.0, gt=1.0, le=15.0)", "Field(6.4, gt=1.0, le=15.0)", "horizon", "horizon 6 -> 6.4 s"),
    _param("lane_change_time", "3.5", "3.2", "horizon", "lane-change duration 3.5 -> 3.2 s"),
    _param("w_jerk", "0.01", "0.012", "cost", "jerk weight 0.01 -> 0.012"),
    _param("w_hysteresis", "1.0", "0.8", "cost", "hysteresis weight 1.0 -> 0.8"),
    _param("w_lane_change", "3.0", "2.5", "cost", "lane-change weight 3.0 -> 2.5"),
    _param("w_lat", "0.5", "0.6", "cost", "lateral-offset weight 0.5 -> 0.6"),
    _param("max_lat_accel", "2.5", "2.3", "cost", "curve speed: lateral acceleration 2.5 -> 2.3 m/s^2"),
    Edit("nudge_label", "decision", "        if off != 0.0:\n            return \"NUDGE\"",
         "        if abs(off) > 0.5:\n            return \"NUDGE\"", "behaviour NUDGE only beyond 0.5 m (label only)"),
    Edit("cost_rounding", "decision", '"cost": cost if math.isfinite(cost) else -1.0}',
         '"cost": round(cost, 6) if math.isfinite(cost) else -1.0}', "published cost rounded to 1e-6"),
    Edit("speed_along_path", "profile", '"v": np.hypot(vs, dd),', '"v": vs,',
         "published speed without the lateral component (v only; x, y, t unchanged)"),
    Edit("stopped_heading", "profile", "moving = (np.abs(vs) > 1e-3) | (np.abs(dd) > 1e-3)",
         "moving = (np.abs(vs) > 1e-2) | (np.abs(dd) > 1e-3)", "standstill threshold for the heading 1e-3 -> 1e-2"),
    Edit("start_decel", "profile", "as0 = max(as0, -max(vs0, 0.0) / 0.3)", "as0 = max(as0, -max(vs0, 0.0) / 0.4)",
         "stitched braking clamp 0.3 -> 0.4 s"),
    _param("yellow_decel", "3.0", "2.5", "profile", "yellow-light braking 3.0 -> 2.5 m/s^2"),
    _param("emergency_decel", "7.0", "6.5", "profile", "emergency braking 7.0 -> 6.5 m/s^2"),
    # edits that must change nothing
    Edit("rename_local", "neutral", "    def _behavior(self, lane: LaneId, target: LaneId, off: float, label: str) -> str:\n"
         "        if target != lane:\n            return \"CHANGE_LANE\"\n        if off != 0.0:\n"
         "            return \"NUDGE\"\n        return label",
         "    def _behavior(self, lane: LaneId, target: LaneId, off: float, label: str) -> str:\n"
         "        if target != lane:\n            return \"CHANGE_LANE\"\n        if off != 0.0:\n"
         "            return \"NUDGE\"\n        chosen = label\n        return chosen", "a local variable (neutral)"),
    Edit("comment", "neutral", "        # lateral-only: stay inside the drivable band", "        # lateral: stay within the band",
         "a comment (neutral)"),
    Edit("exact_half", "neutral", "la, wa = p.ego_length / 2, p.ego_width / 2", "la, wa = p.ego_length * 0.5, p.ego_width * 0.5",
         "x / 2 -> x * 0.5, bit-identical (neutral)"),
    Edit("cache_order", "neutral", "        self._route_cache: dict[Any, _Route] = {}\n        self._ref_cache: dict[Any, _Ref] = {}\n",
         "        self._ref_cache: dict[Any, _Ref] = {}\n        self._route_cache: dict[Any, _Route] = {}\n",
         "two independent initialisations swapped (neutral)"),
    Edit("decision_key_order", "neutral", 'decision = {"behavior": behavior, "lane": list(lane) if lane else [],',
         'decision = {"lane": list(lane) if lane else [], "behavior": behavior,',
         "decision keys in another order, same values (neutral)"),
)


def _apply(src: str, edit: Edit) -> str | None:
    return src.replace(edit.old, edit.new) if src.count(edit.old) == 1 else None


def pin_edits(out: Path, edits: tuple[Edit, ...]) -> tuple[dict[str, str], list[str]]:
    """Write the original planner module and one copy per applicable edit into ``out/pinned``;
    returns ``(edit name -> class path, names of edits that do not apply)``."""
    spec = importlib.util.find_spec("deft_gym.planner.lattice")
    src = Path(spec.origin).read_text()
    pinned = out / "pinned"
    paths = {"original": "edit_original:LatticePlanner"}
    write_atomic(pinned / "edit_original.py", src)
    skipped = []
    for e in edits:
        edited = _apply(src, e)
        if edited is None:
            skipped.append(e.name)
            continue
        write_atomic(pinned / f"edit_{e.name}.py", edited)
        paths[e.name] = f"edit_{e.name}:LatticePlanner"
    return paths, skipped


def record_and_extract(out: Path, scenarios: tuple[str, ...], duration: float, seed: int) -> list[Path]:
    """Short episodes of the reference planner, extracted; their test folders (reused when present)."""
    from deft_gym.scenarios.scenario import load_scenario, scenario_from_dict, scenario_to_dict
    from deft_gym.sim.simulation import run_episode
    from extract import extract_episode

    dirs = []
    for name in scenarios:
        d = out / "episodes" / name
        if not (d / "deft" / "summary.json").exists():
            data = scenario_to_dict(load_scenario(name))
            data["duration"] = min(duration, data["duration"])
            res = run_episode(scenario_from_dict(data, source=name), jitter_seed=seed, out_dir=d / "log",
                              keep_planning=False)
            s = extract_episode(res.log_path, d / "deft").summary
            if s["reproduced_at_theta"] != s["frames"]:
                raise SystemExit(f"{name}: the reference planner reproduces {s['reproduced_at_theta']} of "
                                 f"{s['frames']} frames; the experiment needs every frame reproduced")
        dirs.append(d / "deft")
    return dirs


def _canonical(out: Any) -> str:
    return json.dumps(out, sort_keys=True, allow_nan=True)


def changed_frames(cls_path: str, original: str, dirs: list[Path]) -> dict[str, Any]:
    """Ground truth: frames whose whole output differs between the edited and the original
    planner replaying the same frames (per episode, in order)."""
    from deft_gym.planner.base import load_planner
    from extract.runtime import load_frames, to_frame
    from extract.validator import compare

    changed, frames, first = 0, 0, None
    for d in dirs:
        header, records = load_frames(d / "frames.jsonl")
        spec = header["planner"]
        a, b = (load_planner(c, spec["map"], spec["params"]) for c in (original, cls_path))
        for i, fr in enumerate(records):
            frames += 1
            oa, ob = a.plan(to_frame(fr)), b.plan(to_frame(fr))
            if _canonical(oa) != _canonical(ob):
                changed += 1
                if first is None:
                    c = compare(oa, ob) if oa is not None else None
                    fields = ", ".join(dict.fromkeys(x.field for x in c.diffs)) if c else "output"
                    first = f"{d.parent.name} frame {i}: {fields}"
    return {"frames": frames, "changed": changed, "first": first}


def caught(cls_path: str, pinned: Path, dirs: list[Path]) -> dict[str, Any]:
    """Run the generated tests against the edited planner: failed tests and the first message."""
    env = {**os.environ, "DEFT_PLANNER": cls_path, "DEFT_GYM_PURE_PYTHON": "1",
           "PYTHONPATH": os.pathsep.join([str(pinned), *filter(None, [os.environ.get("PYTHONPATH")])])}
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
                           *map(str, dirs)], capture_output=True, text=True, env=env)
    tail = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else proc.stderr[-200:]
    failed = int(tail.split(" failed")[0].split()[-1]) if " failed" in tail else 0
    first = next((ln for ln in proc.stdout.splitlines() if ": the replayed output differs" in ln), None)
    return {"returncode": proc.returncode, "failed": failed, "summary": tail, "first_failure": first,
            "seconds": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> int:
    ap = common.parser("planner-edits", "deft_gym.experiments.planner_edits", __doc__)
    common.add_out(ap, common.RUNS / "planner_edits")
    common.add_scenarios(ap, default=SCENARIOS, help="seed scenarios of the episodes")
    ap.add_argument("--duration", type=common.finite_float(1.0, 600.0), default=12.0, help="episode length [s]")
    common.add_jitter_seed(ap, "jitter seed of every episode")
    ap.add_argument("--edits", nargs="*", default=None, help="names of the edits to run (default: all)")
    common.add_output_flags(ap)
    args = ap.parse_args(argv)
    if args.jitter_seed is None:
        args.jitter_seed = common.fresh_seed()
    console = common.console(args, width=140)
    out = Path(args.out).resolve()
    edits = tuple(e for e in EDITS if args.edits is None or e.name in args.edits)
    if args.edits and len(edits) != len(set(args.edits)):
        known = ", ".join(e.name for e in EDITS)
        print(f"error: unknown edit(s) in {args.edits}; expected some of {known}", file=sys.stderr)
        return 2
    with common.locked_out(out):
        return _run(args, console, out, edits)


def _run(args: Any, console: Any, out: Path, edits: tuple[Any, ...]) -> int:
    os.environ["DEFT_GYM_PURE_PYTHON"] = "1"
    dirs = record_and_extract(out, tuple(args.scenarios), args.duration, args.jitter_seed)
    paths, skipped = pin_edits(out, edits)
    sys.path.insert(0, str(out / "pinned"))
    rows = []
    for e in edits:
        if e.name in skipped:
            rows.append({"edit": e.name, "kind": e.kind, "what": e.what, "applies": False})
            continue
        truth = changed_frames(paths[e.name], paths["original"], dirs)
        verdict = caught(paths[e.name], out / "pinned", dirs)
        rows.append({"edit": e.name, "kind": e.kind, "what": e.what, "applies": True,
                     "changes_output": truth["changed"] > 0, "frames_changed": truth["changed"],
                     "frames": truth["frames"], "first_change": truth["first"], "caught": verdict["failed"] > 0,
                     "tests_failed": verdict["failed"], "pytest": verdict["summary"],
                     "first_failure": verdict["first_failure"], "seconds": verdict["seconds"]})
    t = Table(title=f"Planner edits against the generated tests of {len(dirs)} episodes", box=box.SIMPLE_HEAD)
    for col in ("edit", "kind", "changes an output", "frames changed", "caught", "tests failed"):
        t.add_column(col, no_wrap=True)
    t.add_column("first change (episode, frame: fields)", max_width=60)
    for r in rows:
        if not r["applies"]:
            t.add_row(r["edit"], r["kind"], "does not apply", "", "", "", "")
            continue
        t.add_row(r["edit"], r["kind"], "yes" if r["changes_output"] else "no", f"{r['frames_changed']}/{r['frames']}",
                  "yes" if r["caught"] else "no", str(r["tests_failed"]), r["first_change"] or "-")
    common.print_table(console, t)
    live = [r for r in rows if r["applies"]]
    behav = [r for r in live if r["changes_output"]]
    inert = [r for r in live if not r["changes_output"]]
    n_caught = sum(r["caught"] for r in behav)
    n_false = sum(r["caught"] for r in inert)
    rate = n_caught / len(behav) if behav else math.nan
    headline = (f"{len(live)} edits applied ({len(skipped)} do not apply): {len(behav)} change an output on a logged "
                f"frame, of which {n_caught} caught ({100 * rate:.1f} %); {len(inert)} change none, of which "
                f"{n_false} flagged")
    console.print(headline)
    write_atomic(out / "edits.json", json.dumps({"headline": headline, "caught_share": rate, "false_alarms": n_false,
                                                 "episodes": [str(d) for d in dirs], "rows": rows}, indent=1))
    console.print(f"wrote {out / 'edits.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
