"""Look at what an evaluation counted: a sample of each root cause re-simulated, measured and drawn.

    deft-gym findings runs/eval/x --per-cause 2          # -> runs/eval/x/findings/findings.md

A finding is a mechanism, not a count. For every root cause (``kind:trigger:band:mechanism``) of the
counted failures in ``records.jsonl`` this takes up to ``--per-cause`` failures, spread over the
scenarios it was found on (the first of each scenario by repeat and index: deterministic), simulates each again from its equivalent scenario with
the jitter seed it ran with, checks that it fails again with the same root cause, and draws it:
the optimal (reference) path, the ego's path, every added object with the trigger in red and its
clearance to the optimal path, the collision if any. An evaluation that counted metric oracles
(``--count-oracles``) has their confirmed findings as root causes too (``metric:<oracle>:<detail>``;
an at-fault collision is the decision oracle's already): each re-simulated, checked for the same
signature, drawn with the participant of the smallest TTC in red, and its metric's values listed. ``findings.md`` lists the root causes with
their counts per method and, under each, the pictures, the numbers (IoU, longest stretch off the
path, clearance) and the decision the planner took when it left the optimal path - what a reader
needs to judge whether a competent driver would call it a failure. ``--statics-from-start``
simulates each drawn failure once more with its static objects that joined mid-run (the RL env
adds objects every 2 s) there from the start: a finding that vanishes rested on a parked car or
cone appearing in front of the ego, a loophole of mid-run placement rather than a planner failure.
Records of an evaluation that counted that way (``late_statics: from_start``, the default since
2026-11-28) are always drawn and replayed with their static objects there from the start.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from agents.stats import METHOD_LABELS, RecordError, counted_failure, normalize
from deft_gym.cli import common
from deft_gym.files import first_line, read_jsonl, write_atomic


def build_parser() -> common.Parser:
    p = common.parser("findings", "agents.findings", __doc__)
    p.add_argument("folder", type=Path, help="evaluation folder (records.jsonl)")
    p.add_argument("--per-cause", type=common.positive_int, default=2, metavar="N",
                   help="failures re-simulated and drawn per root cause (default: 2)")
    p.add_argument("--methods", nargs="+", action=common.ListAction, default=None, metavar="METHOD",
                   help="only these methods' failures (default: all)")
    p.add_argument("--tests", type=common.int_range(0, 100), default=0, metavar="N",
                   help="also record each drawn failure's re-simulation, extract its planning-module tests, run "
                   "them once with pytest and each failure test (a collision's P_faulty, a non-optimal decision's "
                   "P_departure) N times: how often it fails (default: 0, off)")
    p.add_argument("--statics-from-start", action="store_true",
                   help="also simulate each drawn failure again with its static objects that joined after t = 0 "
                   "(the RL env adds objects every 2 s) there from the start, and say whether the same finding "
                   "comes back: does it rest on a parked car or cone appearing mid-run? (default: off)")
    p.add_argument("--recount", action="store_true",
                   help="instead: simulate every distinct finding the evaluation counted again and count apart those "
                   "that rest on a false predicted cut-in (none of the predicted cut-ins around it came true, and with "
                   "the predictor's intent rule off it is gone); writes recount.md and recount.jsonl, resumes the "
                   "latter (agents/recount.py) (default: off)")
    common.add_ads_config(p, "the evaluation's (eval_config.json), else configs/ads/default.yaml")
    common.add_out(p, None, "output folder (default: FOLDER/findings)")
    common.add_output_flags(p)
    return p


def split_equivalent(rec: dict[str, Any]) -> tuple[dict[str, Any], dict[str, float] | None, int]:
    """``(scenario dict, added_at, jitter seed)`` of a record's failure scenario, read with
    :func:`deft_gym.search.episode.read_replay` (the one shape, and records written before it)."""
    from deft_gym.search.episode import read_replay

    eq = read_replay(rec.get("scenario_equivalent"), rec.get("jitter_seed"))
    if eq is None:
        raise RecordError(f"record {rec.get('method')}/{rec.get('scenario')}/{rec.get('index')}: "
                          "field 'scenario_equivalent' is missing")
    return eq["scenario"], eq["added_at"] or None, eq["jitter_seed"]


def eval_feasible(folder: Path) -> Any:
    """The validity rule an evaluation folder's records were judged under: its
    ``eval_config.json``'s ``feasible``; an evaluation written before that was recorded ran under
    Decictor's 0.5 m for static objects too; no eval_config.json: the default rule."""
    from deft_gym.search.feasible import PAPER, FeasibleConfig

    path = folder / "eval_config.json"
    if not path.exists():
        return FeasibleConfig()
    data = json.loads(path.read_text())
    if "feasible" not in data:
        return PAPER
    try:
        return FeasibleConfig(**data["feasible"])
    except ValueError as err:
        raise RecordError(f"{path}: field 'feasible': {first_line(err)}") from None


def counted_equivalent(rec: dict[str, Any], statics_from_start: bool = False) -> dict[str, Any]:
    """The record's failure scenario in the one shape (:func:`deft_gym.search.episode.replay_record`)
    as it counted: a record that counted with its late static objects there from the start
    (:func:`counted_from_start`), or any record with ``statics_from_start``, has its static objects
    that joined after t = 0 in the scenario from the start
    (:func:`deft_gym.search.episode.statics_from_start`); a record that counted that way is
    replayed on its confirmation's jitter seed (:func:`confirmation_seed`), the one run of it
    with those objects there from the start."""
    from deft_gym.search.episode import replay_record
    from deft_gym.search.episode import statics_from_start as statics_from_start_of

    data, added_at, jitter = split_equivalent(rec)
    if statics_from_start or counted_from_start(rec):
        added_at = statics_from_start_of(data["participants"], added_at)
    if counted_from_start(rec):  # what counted is the confirmation's run: on its jitter seed where kept
        kept = confirmation_seed(rec)
        jitter = jitter if kept is None else kept
    return replay_record(data, jitter, added_at)


def confirmation_seed(rec: dict[str, Any]) -> int | None:
    """The jitter seed of the run that confirmed the record's finding: the decision oracle's
    (``confirm_seed``), the aimed metric oracle's (``oracle_confirm_seed``) or, for an oracle
    counted besides (``found_by_oracle``), the one derived from the run's seed
    (:func:`agents.search.count_confirm_seed`); the finding's oracle is ``rec["_oracle"]``
    (none: the decision oracle's). None where the record does not keep it (written before
    2026-11-28: the decision oracle's and the aimed oracle's seeds were drawn and not kept)."""
    from agents.search import count_confirm_seed

    oracle = rec.get("_oracle")
    if not oracle:
        return rec.get("confirm_seed")
    if oracle == rec.get("oracle") and rec.get("oracle_signature") and rec.get("oracle_confirmed") is True:
        return rec.get("oracle_confirm_seed")
    if oracle in (rec.get("found_by_oracle") or {}):
        return count_confirm_seed(int(rec["jitter_seed"]))
    return None


def resimulate(rec: dict[str, Any], ads: str | None = None, out_dir: Path | None = None,
               feasible: Any = None, statics_from_start: bool = False,
               watch: Any = None, adjust: Any = None) -> tuple[Any, Any]:
    """``(context, run)``: the record's failure (:func:`counted_equivalent`) simulated again with
    its jitter seed (on the ADS config ``ads``, default: the default one; judged under
    ``feasible``, a :class:`~deft_gym.search.feasible.FeasibleConfig`, default: the default one;
    its MCAP log in ``out_dir`` when given; ``watch(sim)`` attached before it starts; the seed
    context replaced by ``adjust(context)`` when given, e.g. :func:`agents.recount.without_intent`)."""
    from deft_gym.search.context import ads_config, seed_context
    from deft_gym.search.episode import run_scenario

    ctx = seed_context(rec["scenario"], feasible, ads=ads_config(ads))
    if adjust is not None:
        ctx = adjust(ctx)
    eq = counted_equivalent(rec, statics_from_start)
    specs = eq["scenario"]["participants"][len(ctx.scenario.participants):]
    return ctx, run_scenario(ctx, specs, eq["jitter_seed"], out_dir, added_at=eq["added_at"] or None, watch=watch)


class PredictedLaneChanges:
    """The lane changes the ADS's prediction module predicted during a run (a bus tap, made by the
    ``watch`` callable of :func:`resimulate`, which keeps the instance: :func:`_draw` does): for
    every prediction message, each obstacle predicted to change lane (the payload's ``intent``)
    with its time [s] and the end of its predicted path. The testbed's predictor predicts one for
    any vehicle more than ``intent_offset`` off its lane centre (``modules/prediction.py``) - a rule
    of the testbed, not of the planner under test, which plans around whatever it is given."""

    def __init__(self, sim: Any) -> None:
        self.topic = sim.ads.topic("prediction")
        #: ``(t, perception id, x, y, heading)`` of each predicted lane change, the end of its path
        self.changes: list[tuple[float, int, float, float, float]] = []
        sim.bus.taps.append(self._on_message)

    def _on_message(self, msg: Any) -> None:
        if msg.topic != self.topic:
            return
        t = float(msg.payload["header"]["stamp"])
        for ob in msg.payload["obstacles"]:
            if ob.get("intent"):
                self.changes.append((t, int(ob["id"]), float(ob["x"][-1]), float(ob["y"][-1]),
                                     float(ob["heading"][-1])))


def cut_ins(ctx: Any, trace: Any, changes: list[tuple[float, int, float, float, float]], t_event: float,
            before: float = 10.0, after: float = 3.0, horizon: float = 6.0) -> dict[str, tuple[int, int]]:
    """The predicted cut-ins around ``t_event`` [s] (from ``before`` s before it to ``after`` s
    after): lane changes (:class:`PredictedLaneChanges`) whose predicted path ends in the lane the
    ego was in then, or in a lane the optimal (reference) path drove in within ``horizon`` s of
    then (the lane the ego wanted). Per participant id: ``(predictions, how many came true)`` - a
    prediction comes true when the participant's centre is inside that lane within ``horizon`` s."""
    rm, ref = ctx.roadmap, ctx.ref
    by_num = {a.num: i for i, a in enumerate(trace.actors) if a.num >= 0}
    out: dict[str, list[int]] = {}
    tracks: dict[int, np.ndarray] = {}
    for t, num, x, y, h in changes:
        if not t_event - before <= t <= t_event + after or num not in by_num:
            continue
        end = rm.locate(np.array([x, y]), h)
        if end is None:
            continue
        k = min(int(np.searchsorted(trace.t, t)), len(trace.t) - 1)
        ego = rm.locate(trace.xy[k], float(trace.ego[k, 2]))
        k0, k1 = np.searchsorted(ref.t, [t, t + horizon])
        wanted = {loc[0] for j in range(int(k0), min(int(k1), len(ref.t)), 10)
                  if (loc := rm.locate(ref.xy[j], float(ref.ego[j, 2]))) is not None}
        if end[0] not in wanted and (ego is None or end[0] != ego[0]):
            continue
        i = by_num[num]
        track = tracks.get(i)
        if track is None:
            track = tracks[i] = trace.track(i)
        rows = track[(track[:, 0] * trace.world_dt >= t) & (track[:, 0] * trace.world_dt <= t + horizon)]
        g = rm.geom(end[0])
        came = False
        for r in rows[::5]:
            s, d = g.frenet(r[1:3])
            if 0.0 <= float(s) <= g.length and abs(float(d)) < 0.5 * g.width:
                came = True
                break
        tally = out.setdefault(trace.actors[i].id, [0, 0])
        tally[0] += 1
        tally[1] += came
    return {k: (v[0], v[1]) for k, v in out.items()}


def never_came(found: dict[str, tuple[int, int]]) -> bool:
    """Whether :func:`cut_ins` found predicted cut-ins and none of them came true."""
    return bool(found) and all(came == 0 for _, came in found.values())


def cut_in_line(found: dict[str, tuple[int, int]]) -> str:
    """The findings line of :func:`cut_ins`."""
    if not found:
        return "predicted cut-ins into the ego's or the optimal path's lane around it: none"
    parts = [f"{pid} in {n} prediction cycles, true in {came}" for pid, (n, came) in sorted(found.items())]
    return ("predicted cut-ins into the ego's or the optimal path's lane around it: " + "; ".join(parts)
            + (" - **none came true** (the testbed predictor's intent rule: see the end of this file)"
               if never_came(found) else ""))


def counted_from_start(rec: dict[str, Any]) -> bool:
    """Whether the record's failure counted with its late static objects there from the start
    (``late_statics: from_start``, docs/search.md): then that is the scenario drawn and replayed."""
    return rec.get("late_statics") == "from_start"


def judged_again(ctx: Any, run: Any, rec: dict[str, Any], cause: str) -> tuple[bool, str | None, Any]:
    """Whether ``run`` (a failure simulated again) has the root cause ``cause`` of ``rec`` again:
    ``(same, what it found, metrics)`` - the decision verdict's signature and failure, or for a
    metric oracle's finding (``rec["_oracle"]``) that oracle's finding and the run's metrics."""
    v = run.verdict
    oracle = rec.get("_oracle")
    if not oracle:
        return v.signature == rec.get("signature") and v.failure == rec.get("failure"), v.signature or v.outcome, None
    from deft_gym.metrics.oracle import run_metrics, seed_finding

    m = run_metrics(ctx, run.trace, v.collision_detail)
    got = seed_finding(ctx, v.valid, m, oracle)
    return got == cause, got, m


#: the failure tests an extraction emits: a collision's (P_faulty), a non-optimal decision's
#: (P_departure, when the log carries the optimal path), driving against the lane direction's
#: (P_wrong_way), a stuck run's (P_stall), leaving the road's (P_off_road), passing a
#: participant too close (P_near_miss), running a red light (P_red_light) and driving on at a
#: yellow light it could stop for (P_yellow)
FAILURE_TESTS = {"does_not_plan_into_collision": "collision (P_faulty)",
                 "keeps_to_the_optimal_path": "non-optimal decision (P_departure)",
                 "keeps_to_its_side_of_the_road": "driving direction (P_wrong_way)",
                 "plans_progress": "stuck (P_stall)",
                 "keeps_on_the_road": "drivable area (P_off_road)",
                 "keeps_its_distance": "near miss (P_near_miss)",
                 "stops_at_red": "red light (P_red_light)",
                 "stops_for_a_stoppable_yellow": "yellow light (P_yellow)"}


def run_tests(folder: Path, times: int) -> dict[str, Any]:
    """Run the pytest modules in ``folder`` once (every reproduction test must pass), then each
    failure test they hold (:data:`FAILURE_TESTS`) ``times`` times, each in a fresh process: how
    often it failed."""
    text = "".join(f.read_text() for f in folder.glob("test_*.py"))
    failed = _pytest(folder)
    reproduced = failed is not None and not any("_reproduces" in n for n in failed)
    counts = {}
    for name in (n for n in FAILURE_TESTS if n in text):
        counts[name] = sum(bool((f := _pytest(folder, name)) and any(name in n for n in f)) for _ in range(times))
    return {"runs": times, "failure_tests": counts, "reproduced": reproduced}


def _pytest(folder: Path, select: str | None = None) -> list[str] | None:
    """Names of the failed test cases of one pytest run of ``folder`` (``-k select``); None when
    pytest did not run them (a usage or collection error)."""
    import subprocess
    import sys

    report = folder / "junit.xml"
    report.unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=", "--junitxml",
           str(report), str(folder)] + (["-k", select] if select else [])
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if res.returncode not in (0, 1) or not report.exists():
        return None
    return _failed_cases(report.read_text())


def _failed_cases(junit_xml: str) -> list[str]:
    """Names of the failed or erroring test cases in a JUnit XML report."""
    import xml.etree.ElementTree as ET

    if not junit_xml:
        return []
    root = ET.fromstring(junit_xml)
    return [case.get("name", "") for case in root.iter("testcase")
            if case.find("failure") is not None or case.find("error") is not None]


def left_path_at(trace: Any, dist: np.ndarray, half_lane: float) -> float:
    """When [s] the ego first got ``half_lane`` off the optimal path (``dist``: each trace
    point's distance to it [m]), or the run's end when it never did."""
    off = np.flatnonzero(dist > half_lane)
    return float(trace.t[off[0]]) if len(off) else float(trace.t[-1])


def leaving_decision(trace: Any, dist: np.ndarray, half_lane: float) -> str:
    """The planner's decision when the ego first got half a lane off the optimal path (or its
    last one), in a line: reason, lane, blocked / tight lanes, refused changes."""
    timeline = trace.meta.get("timeline") or []
    if not timeline:
        return "-"
    t = left_path_at(trace, dist, half_lane)
    e = [x for x in timeline if x["t"] <= t + 1e-9][-1:] or timeline[:1]
    e = e[0]
    reason = e["reason"] or "(no reason published)"
    parts = [f"t {e['t']:.1f} s: {reason} in {'-'.join(map(str, e['lane'])) or '-'}"]
    if e.get("target") and e["target"] != e["lane"]:
        parts.append("target " + "-".join(map(str, e["target"])))
    if e["blocked"]:
        parts.append("blocked " + ", ".join(e["blocked"]))
    if e["tight"]:
        parts.append("tight " + ", ".join(e["tight"]))
    if e["refused"]:
        parts.append("refused " + ", ".join(f"{k} ({v})" for k, v in e["refused"].items()))
    return "; ".join(parts)


def draw(ctx: Any, run: Any, path: Path, title: str, highlight: set[str] | None = None) -> None:
    """The optimal path, the ego's path, the added objects (green; the trigger, or the participants
    in ``highlight``, in red), the seed's participants (grey) and the collision."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from deft_gym.files import atomic_path
    from deft_gym.viz.plot import _box, draw_map

    tr, v = run.trace, run.verdict
    trig = set(v.finding.trigger_ids) if v.finding else set()
    trig |= highlight or set()
    fig, ax = plt.subplots(figsize=(9, 6))
    draw_map(ax, ctx.roadmap)
    ref = ctx.ref.xy
    ax.plot(ref[:, 0], ref[:, 1], "k--", lw=1.4, label="optimal (reference) path", zorder=5)
    ax.plot(tr.xy[:, 0], tr.xy[:, 1], color="#1f77b4", lw=2.2, label="ego", zorder=6)
    pts = [ref, tr.xy]
    for i, a in enumerate(tr.actors):
        rows = tr.parts[tr.parts[:, 1] == i]
        if not len(rows):
            continue
        color = "#d62728" if a.id in trig else "#2ca02c" if a.added else "0.45"
        if a.kind == "static":
            _box(ax, rows[0, 2], rows[0, 3], rows[0, 4], a.length, a.width, color=color, alpha=0.85)
        else:
            ax.plot(rows[:, 2], rows[:, 3], color=color, lw=1.2, alpha=0.8, zorder=4)
            k = rows[:: max(len(rows) // 4, 1)]
            for r in k:
                _box(ax, r[2], r[3], r[4], a.length, a.width, color=color, alpha=0.35)
        ax.annotate(a.id, (rows[0, 2], rows[0, 3]), fontsize=7, color=color, zorder=7)
        pts.append(rows[:, 2:4])
    if v.collision_detail:
        c = v.collision_detail
        ax.plot(c["x"], c["y"], "x", color="#d62728", ms=14, mew=3, zorder=8)
    # frame the triggers and the paths within 60 m of them (all of the paths without a trigger),
    # at most 2.5:1 either way
    trig_xy = [tr.parts[tr.parts[:, 1] == i][:, 2:4] for i, a in enumerate(tr.actors) if a.id in trig]
    trig_xy = [t for t in trig_xy if len(t)]
    if v.collision_detail:
        trig_xy.append(np.array([[v.collision_detail["x"], v.collision_detail["y"]]]))
    focus = list(pts[:2])
    if trig_xy:
        centre = np.concatenate(trig_xy)
        focus = [p[np.min(np.hypot(p[:, None, 0] - centre[None, ::5, 0], p[:, None, 1] - centre[None, ::5, 1]),
                          axis=1) < 60.0] for p in pts[:2]] + trig_xy
    fp = np.concatenate([f for f in focus if len(f)])
    x0, y0 = fp.min(axis=0) - 6.0
    x1, y1 = fp.max(axis=0) + 6.0
    w, h = x1 - x0, y1 - y0
    if h < w / 2.5:
        y0, y1 = (y0 + y1) / 2 - w / 5, (y0 + y1) / 2 + w / 5
    elif w < h / 2.5:
        x0, x1 = (x0 + x1) / 2 - h / 5, (x0 + x1) / 2 + h / 5
    ax.set_xlim(x0, x1)
    ax.set_ylim(y1, y0)  # y points down in highway-env
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=9)
    ax.legend(loc="upper left", fontsize=7, bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


def spread(recs: list[dict[str, Any]], n: int) -> list[dict[str, Any]]:
    """Up to ``n`` of ``recs`` (one root cause's), spread over its scenarios: the first of each
    scenario (by repeat, index, method) in scenario order, then the second of each, ...
    (deterministic): a root cause found on several scenarios is drawn on several."""
    by_scenario: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in sorted(recs, key=lambda r: (r["scenario"], r["repeat"], r["index"], r["method"])):
        by_scenario[r["scenario"]].append(r)
    rounds = max((len(v) for v in by_scenario.values()), default=0)
    return [v[k] for k in range(rounds) for v in by_scenario.values() if k < len(v)][:n]


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    folder: Path = args.folder
    rec_path = folder / "records.jsonl"
    out: Path = Path(args.out) if args.out else folder / "findings"
    con = common.console(args)
    try:
        if not rec_path.exists():
            raise RecordError(f"{rec_path}: no such file")
        raw = read_jsonl(rec_path)
        rows, _ = normalize(raw, str(rec_path))
        ads = str(args.ads_config) if args.ads_config is not None else None
        feasible = eval_feasible(folder)
        if ads is None and (folder / "eval_config.json").exists():  # the ADS the evaluation ran on
            ads = json.loads((folder / "eval_config.json").read_text()).get("ads")
    except (RecordError, ValueError) as err:
        return common.cli_error(str(err))
    if args.recount:
        from agents.recount import recount

        summary_path = folder / "summary.json"
        summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
        groups = {"seed": summary.get("seeds", []), "held_out": summary.get("held_out", []),
                  "handwritten": summary.get("handwritten", [])}
        with common.locked_out(out):
            return recount(args, con, out, rows, raw, ads, feasible, groups)
    by_cause: dict[str, list[dict[str, Any]]] = defaultdict(list)
    counts: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    for r, full in zip(rows, raw):
        if args.methods is not None and r["method"] not in common.split_list(args.methods):
            continue
        if counted_failure(r):
            by_cause[r["signature"]].append(full)
            counts[r["signature"]][r["method"]] += 1
        found = dict(r["found_by_oracle"])  # counted metric oracles (--count-oracles)
        confirmed = dict(r["confirmed_by_oracle"])
        if r["oracle_signature"] and r["oracle_confirmed"] is True:  # the aimed metric oracle (--oracle)
            found[full["oracle"]], confirmed[full["oracle"]] = r["oracle_signature"], True
        for oracle, sig in found.items():
            if r["valid"] and oracle != "collision" and confirmed.get(oracle) is True:
                by_cause[sig].append({**full, "_oracle": oracle})
                counts[sig][r["method"]] += 1
    if not by_cause:
        con.print("no counted failures in the records")
        return 0
    with common.locked_out(out):
        return _draw(args, con, out, by_cause, counts, ads, feasible)


def _draw(args: Any, con: Any, out: Path, by_cause: dict[str, list[dict[str, Any]]],
          counts: dict[str, dict[str, int]], ads: str | None, feasible: Any = None) -> int:
    from deft_gym.search.episode import write_replay

    out.mkdir(parents=True, exist_ok=True)
    causes = sorted(by_cause, key=lambda c: (-len(by_cause[c]), c))
    sample = [(c, r) for c in causes for r in spread(by_cause[c], args.per_cause)]
    lines = [f"# Findings of {args.folder}", "",
             f"{sum(len(v) for v in by_cause.values())} counted failures and findings, {len(causes)} root causes; up to "
             f"{args.per_cause} of each simulated again with their jitter seed and drawn (dashed: the optimal path; "
             "blue: the ego; red: the trigger; green: other added objects; grey: the seed's participants).", "",
             "| root cause | failures | " + " | ".join(METHOD_LABELS.values()) + " |",
             "|---|---|" + "---|" * len(METHOD_LABELS)]
    for c in causes:
        lines.append(f"| `{c}` | {len(by_cause[c])} | " + " | ".join(str(counts[c].get(m, 0) or "-")
                                                               for m in METHOD_LABELS) + " |")
    from_start: dict[str, tuple[int, int]] = {}
    false_cut_ins = 0  # drawn failures with predicted cut-ins around them, none of which came
    with common.bar(args, len(sample), "failures simulated again") as b:
        current = None
        for n, (cause, rec) in enumerate(sample):
            if cause != current:
                lines += ["", f"## `{cause}`", ""]
                current = cause
            stem = f"{n:03d}_{rec['method']}_{rec['scenario'].replace(':', '_').replace('/', '_')}_r{rec['repeat']}_{rec['index']}"
            log_dir = out / f"{stem}_log" if args.tests else None
            watched: list[PredictedLaneChanges] = []
            ctx, run = resimulate(rec, ads, log_dir, feasible,
                                  watch=lambda sim, into=watched: into.append(PredictedLaneChanges(sim)))
            v = run.verdict
            oracle = rec.get("_oracle")
            same, got, m = judged_again(ctx, run, rec, cause)
            highlight = {m.ttc_actor} if oracle == "ttc" and m.ttc_actor else None
            name = f"{stem}.png"
            counted = counted_equivalent(rec)
            replay = write_replay(out / f"{stem}.replay.yaml", counted)
            replay_cmd = f"deft-gym run {replay} --reruns 1" + (f" --ads-config {ads}" if ads else "")
            title = (f"{METHOD_LABELS.get(rec['method'], rec['method'])} {rec['placement']} on {rec['scenario']} "
                     f"(repeat {rec['repeat']}, #{rec['index']}): {got or 'none'}")
            draw(ctx, run, out / name, title, highlight)
            dist = ctx.oracle.distances(run.trace.xy)
            half_lane = ctx.roadmap.spec.lane_width / 2
            predicted = cut_ins(ctx, run.trace, watched[0].changes, left_path_at(run.trace, dist, half_lane))
            false_cut_ins += never_came(predicted)
            clear = v.finding.clearance if v.finding else None
            lines += [f"![{cause}]({name})", "",
                      f"- {rec['method']} / {rec['placement']} / {rec['scenario']} repeat {rec['repeat']} #{rec['index']}, "
                      f"jitter seed {counted['jitter_seed']}"
                      + (", its static objects there from the start (how it counted: the confirmation's run)"
                         if counted_from_start(rec) else "")
                      + f": again **{'the same' if same else 'NOT the same: ' + (got or 'no finding')}**",
                      *([f"- {metric_line(m, oracle, run.trace)}"] if oracle else []),
                      f"- IoU {v.iou:.2f}, off the optimal path for {v.off_length:.0f} m, outcome {v.outcome}"
                      + (f", clearance of the trigger {clear:.2f} m" if clear is not None and math.isfinite(clear) else ""),
                      f"- the planner when it left the path: {leaving_decision(run.trace, dist, half_lane)}",
                      f"- {cut_in_line(predicted)}",
                      *([f"- {destination_line(ctx, run.trace)}"] if v.outcome != "completed" else []),
                      f"- replay: `{replay_cmd}`"]
            if args.tests:
                lines.append(_test_line(run, out / f"{stem}_tests", args.tests))
            if args.statics_from_start:
                lines.append(_from_start_line(ctx, rec, cause, ads, feasible, from_start))
            lines.append("")
            b.update(1)
    if args.statics_from_start:
        lines += from_start_summary(from_start)
    lines += ["## Predicted cut-ins that never came", "",
              f"{false_cut_ins} of {len(sample)} drawn failures had the ADS's prediction put a vehicle into "
              "the ego's lane (or the optimal path's) in the 10 s before it left the optimal path (or its run's end) and 3 s after, and none of "
              "those predictions came true within 6 s. Such predictions come from the testbed predictor's intent rule (a "
              "vehicle more than `intent_offset` off its lane centre is predicted to change lanes, "
              "`modules/prediction.py`): a finding among them may rest on that designed-in threshold of the testbed "
              "rather than on a choice of the planner under test - judge each by its lines above.", ""]
    write_atomic(out / "findings.md", "\n".join(lines) + "\n")
    con.print(f"{len(causes)} root causes, {len(sample)} failures drawn -> {out / 'findings.md'}")
    if args.statics_from_start:
        kept, tried = sum(k for k, _ in from_start.values()), sum(n for _, n in from_start.values())
        con.print(f"with their late static objects there from the start: {kept} of {tried} drawn failures found again")
    return 0


def _from_start_line(ctx: Any, rec: dict[str, Any], cause: str, ads: str | None, feasible: Any,
                     tally: dict[str, tuple[int, int]]) -> str:
    """The line of ``--statics-from-start`` for one drawn failure (``tally``: cause -> (found
    again, simulated), updated)."""
    from deft_gym.search.episode import late_statics

    data, added_at, _ = split_equivalent(rec)
    late = late_statics(data["participants"], added_at)
    if not late:
        return "- no static object joined after t = 0"
    _, run = resimulate(rec, ads, None, feasible, statics_from_start=True)
    same, got, _ = judged_again(ctx, run, rec, cause)
    kept, tried = tally.get(cause, (0, 0))
    tally[cause] = (kept + same, tried + 1)
    return (f"- with its static objects that joined after t = 0 ({', '.join(late)}) there from the start: "
            + ("**found again**" if same else f"**gone** ({got or 'no finding'}"
               + (", an invalid mutation" if not run.verdict.valid else "") + ")"))


def from_start_summary(tally: dict[str, tuple[int, int]]) -> list[str]:
    """The ``--statics-from-start`` section of ``findings.md``: per root cause, how many drawn
    failures with a static object that joined after t = 0 came back with it there from the start."""
    lines = ["## Static objects there from the start", "",
             "Drawn failures whose static objects joined after t = 0, simulated again on their jitter seed with "
             "those objects there from the start: found again means the same root cause (the same oracle finding).",
             ""]
    if not tally:
        return [*lines, "No drawn failure has a static object that joined after t = 0.", ""]
    lines += ["| root cause | found again | simulated |", "|---|---|---|"]
    lines += [f"| `{c}` | {k} | {n} |" for c, (k, n) in tally.items()]
    return [*lines, ""]


def destination_approach(ctx: Any, trace: Any) -> tuple[float, float, float]:
    """``(distance [m], along [m], beside [m])``: where the ego of ``trace`` came nearest its
    destination (``ctx``'s scenario), how far from it, and there how far past it along the
    destination lane (negative: short of it) and beside that lane's centre line."""
    from deft_gym.scenarios.scenario import destination_xy

    dest = ctx.scenario.ego.destination
    point, s_dest = destination_xy(ctx.roadmap, dest)
    dist = np.hypot(*(trace.xy - point).T)
    k = int(np.argmin(dist))
    s, d = ctx.roadmap.geom(tuple(dest.lane)).frenet_point(*trace.xy[k])
    return float(dist[k]), float(s - s_dest), float(d)


def destination_line(ctx: Any, trace: Any) -> str:
    """How near a run that did not finish came to its destination, in a line; it says so when the
    ego passed level with it at most a lane beside it (standing there, it would have arrived:
    :class:`~deft_gym.sim.oracles.EpisodeOracle`): it missed it, or the seed's own run only just
    reached it (within 3 m of one point of the destination lane)."""
    from deft_gym.sim.oracles import REACH_RADIUS, level_with_destination

    dist, along, beside = destination_approach(ctx, trace)
    line = f"nearest the destination: {dist:.2f} m ({along:+.1f} m along its lane, {beside:+.2f} m beside it)"
    width = ctx.roadmap.geom(tuple(ctx.scenario.ego.destination.lane)).width
    if dist > REACH_RADIUS and level_with_destination(along, beside, width):
        line += ("; **passed level with it, a lane over**: a miss, or a seed whose own run only just "
                 "reached it (its reference ends within 3 m) - judge it by the picture")
    return line


def closest_pass(trace: Any, actor_id: str) -> tuple[float, float]:
    """``(distance [m], ego speed [m/s])`` where the ego's footprint came closest to participant
    ``actor_id``'s: how near a near miss was, and how fast."""
    from deft_gym.search.nods import ego_distances

    k = [a.id for a in trace.actors].index(actor_id)
    a, rows = trace.actors[k], trace.parts[trace.parts[:, 1] == k]
    e = trace.ego[np.clip(np.searchsorted(trace.ticks, rows[:, 0]), 0, len(trace.ego) - 1)]
    d = ego_distances(e[:, :3], rows[:, 2:5], a.length, a.width)
    j = int(np.argmin(d))
    return float(d[j]), float(e[j, 3])


def metric_line(m: Any, oracle: str, trace: Any = None) -> str:
    """What a metric oracle's finding measured, in a line (docs/metrics.md); for TTC with the
    episode's ``trace``, also how close the ego came to that participant and how fast."""
    if oracle == "ttc":
        if m.min_ttc is None:
            return "no TTC"
        line = f"min TTC {m.min_ttc:.2f} s to {m.ttc_actor} ({m.ttc_trigger}), below 1.5 s for {m.ttc_below_s:.2f} s"
        if trace is not None and m.ttc_actor:
            dist, speed = closest_pass(trace, m.ttc_actor)
            line += f"; closest {dist:.2f} m, at {speed:.1f} m/s"
        return line
    if oracle == "comfort":
        return "out of bounds: " + ", ".join(f"{k} {m.comfort[k]:.2f}" for k in m.uncomfortable)
    if oracle == "headway":
        if m.min_headway is None:
            return "never following"
        return (f"{m.headway_below_max_s:.1f} s at a stretch below a 0.8 s time gap behind {m.headway_actor} "
                f"({m.headway_trigger}), down to {m.min_headway:.2f} s")
    if oracle == "standstill":
        return f"standing unheld for {m.standstill_max_s:.1f} s at a stretch ({m.standstill_s:.1f} s in all)"
    if oracle == "drivable_area":
        return f"a corner {m.off_road_max:.2f} m off the road, {m.off_road_s:.2f} s beyond 0.3 m"
    if oracle == "direction":
        return f"{m.wrong_way_max_1s:.1f} m against the lanes within 1 s ({m.wrong_way_m:.1f} m in all)"
    if oracle == "progress":
        return f"progress {m.progress_ratio:.1%} of the reference's ({m.progress:.0f} m)"
    if oracle == "speed_limit":
        return f"up to {m.max_overspeed:.2f} m/s over the limit ({m.overspeed_integral:.1f} m in all)"
    if oracle == "red_light":
        return "ran " + ", ".join(f"{r['light']} at {r['t']:.1f} s" for r in m.red_lights)
    return f"score {m.score:.2f}"


def _test_line(run: Any, tests_dir: Path, times: int) -> str:
    """Extract the re-simulation's log into ``tests_dir``, run the tests ``times`` times: one line."""
    from extract import extract_episode

    log = run.result.log_path
    if log is None:
        return "- tests: no log was written"
    ext = extract_episode(log, tests_dir)
    if not ext.ok or ext.test_path is None:
        return f"- tests: extraction failed ({ext.summary.get('error', 'no test module')})"
    r = run_tests(tests_dir, times)
    failure = "; ".join(f"its {FAILURE_TESTS[name]} test fails **{n} of {r['runs']}** runs"
                        for name, n in r["failure_tests"].items()) or "no failure test"
    return (f"- extracted tests `pytest {ext.test_path}`: {failure}; the reproduction tests "
            f"{'pass' if r['reproduced'] else 'FAIL'} ({ext.summary['reproduced_at_theta']} of "
            f"{ext.summary['frames']} outputs reproduced at extraction)")


if __name__ == "__main__":
    raise SystemExit(main())
