"""Count an evaluation's findings again, apart from those that rest on a false predicted cut-in.

    deft-gym findings runs/eval/x --recount          # -> runs/eval/x/findings/recount.md

The testbed's predictor calls any vehicle more than ``intent_offset`` [m] off its lane centre a
lane changer (``modules/prediction.py``; Decictor's pattern 4, designed in for the default
planner's decision layer). A planner that trusts its prediction then plans around a cut-in that
never comes - and can swerve into the car it expected to leave its lane. Whether such a finding is
the planner's failure or the testbed's, it is not the planner failure a user searches for.

For every distinct finding an evaluation counted (``any_distinct``: each (scenario, root cause)
pair once per method, placement, group and repeat; its first record) this simulates the failure
again with its jitter seed and asks two things:

1. did the ADS's prediction put a vehicle into the ego's lane (or the optimal path's) around the
   moment the ego left the optimal path, and none of those predictions came true
   (:func:`agents.findings.cut_ins`)?
2. if so: simulated once more on the same jitter seed and judged against the same reference, with
   only the predictor's intent rule off (``intent_offset`` infinite), is the finding gone?

A finding for which both hold *rests on a false predicted cut-in*. ``recount.md`` gives, per
method, the distinct findings per repeat as counted and without those, Mann-Whitney and A12 of RL
against each baseline on what remains, and the scenarios where something remains.
``recount.jsonl`` holds one line per finding and the ADS config it ran on (append-only: an
interrupted recount resumes; lines of another ADS config are not reused).
"""

from __future__ import annotations

import dataclasses
import math
from collections import defaultdict
from pathlib import Path
from typing import Any

from agents.stats import DECISION_ORACLES_OWN, METHOD_LABELS, compare, counted_findings, describe
from deft_gym.files import append_jsonl, read_jsonl, write_atomic

#: the prediction parameter the counterfactual switches off (modules/prediction.py)
INTENT_PARAM = "intent_offset"


def counted_pairs(rows: list[dict[str, Any]], raw: list[dict[str, Any]]) -> dict[tuple[str, str, str, int, str, str], dict[str, Any]]:
    """The distinct findings the evaluation's ``any_distinct`` counted, as
    ``(method, placement, group, repeat, scenario, signature) -> first record`` (the record carries
    ``_oracle`` for a metric oracle's finding, as :func:`agents.findings.main` does): a decision
    oracle's counted failure, or a valid record's confirmed finding of a counted metric oracle but
    ``collision`` (the decision oracle's already) - ``any_distinct``'s rule
    (:func:`agents.stats.counted_findings`, :data:`agents.stats.DECISION_ORACLES_OWN`)."""
    pairs: dict[tuple[str, str, str, int, str, str], dict[str, Any]] = {}
    for r, full in zip(rows, raw):
        cell = (r["method"], r["placement"], r["scenario_kind"], int(r["repeat"]), r["scenario"])
        for oracle, sig in counted_findings(r):
            if oracle not in DECISION_ORACLES_OWN:
                pairs.setdefault((*cell, sig), full if oracle is None else {**full, "_oracle": oracle})
    return pairs


def without_intent(ctx: Any) -> Any:
    """``ctx`` (a seed context) whose ADS's predictor predicts no lane changes: the same scenario,
    reference and oracle; only ``prediction.params.intent_offset`` is infinite."""
    pred = ctx.ads.prediction
    ads = ctx.ads.model_copy(update={"prediction": pred.model_copy(
        update={"params": {**pred.params, INTENT_PARAM: math.inf}})})
    return dataclasses.replace(ctx, ads=ads)


def judge_one(rec: dict[str, Any], cause: str, ads: str | None, feasible: Any,
              runs: dict[tuple[Any, ...], Any] | None = None) -> dict[str, Any]:
    """One finding's line of ``recount.jsonl``: simulated again (reproduced?), its predicted cut-ins,
    and, when none came true, whether it is found again without the predictor's intent rule.
    ``runs``: simulations of records already done (a record with findings of several oracles is
    simulated once; the same jitter seed gives the same run)."""
    from agents.findings import (
        PredictedLaneChanges,
        cut_ins,
        judged_again,
        left_path_at,
        never_came,
        resimulate,
    )

    runs = {} if runs is None else runs
    ident = (rec["method"], rec["scenario"], rec.get("placement"), rec["repeat"], rec["index"])
    if ident not in runs:
        watched: list[PredictedLaneChanges] = []
        ctx, run = resimulate(rec, ads, None, feasible, watch=lambda sim: watched.append(PredictedLaneChanges(sim)))
        dist = ctx.oracle.distances(run.trace.xy)
        predicted = cut_ins(ctx, run.trace, watched[0].changes,
                            left_path_at(run.trace, dist, ctx.roadmap.spec.lane_width / 2))
        runs[ident] = (ctx, run, predicted)
    ctx, run, predicted = runs[ident]
    same, got, _ = judged_again(ctx, run, rec, cause)
    line: dict[str, Any] = {"reproduced": same, "got": got, "cut_ins": {k: list(v) for k, v in predicted.items()},
                            "false_cut_ins": never_came(predicted), "without_intent": None}
    if line["false_cut_ins"]:
        if (*ident, "without intent") not in runs:
            runs[(*ident, "without intent")] = resimulate(rec, ads, None, feasible, adjust=without_intent)
        bare, again = runs[(*ident, "without intent")]
        kept, got_bare, _ = judged_again(bare, again, rec, cause)
        line["without_intent"] = "found again" if kept else "gone"
        line["got_without_intent"] = got_bare
    line["rests_on_false_cut_in"] = bool(line["false_cut_ins"] and line["without_intent"] == "gone")
    return line


def recount(args: Any, con: Any, out: Path, rows: list[dict[str, Any]], raw: list[dict[str, Any]],
            ads: str | None, feasible: Any, group_scenarios: dict[str, list[str]]) -> int:
    """``findings --recount``: judge every counted distinct finding (:func:`judge_one`, resuming
    ``out/recount.jsonl``) and write ``out/recount.md``. ``group_scenarios``: group -> its
    scenarios (the coverage's denominator; from the evaluation's summary.json)."""
    from deft_gym.cli import common

    out.mkdir(parents=True, exist_ok=True)
    pairs = counted_pairs(rows, raw)
    if args.methods is not None:
        wanted = set(common.split_list(args.methods))
        pairs = {k: v for k, v in pairs.items() if k[0] in wanted}
    path = out / "recount.jsonl"
    # lines of an earlier recount on the same ADS config (one on another config is done again)
    done = {tuple(d["key"]): d for d in read_jsonl(path) if "key" in d and d.get("ads") == ads}
    # records of one scenario next to each other: its seed context is built once
    todo = [k for k in sorted(pairs, key=lambda k: (k[4], k[5], k[0], k[1], k[3])) if k not in done]
    runs: dict[tuple[Any, ...], Any] = {}  # the current scenario's simulations
    with common.bar(args, len(todo), "findings counted again") as b:
        for key in todo:
            rec = pairs[key]
            if runs and next(iter(runs))[1] != rec["scenario"]:
                runs.clear()
            line = {"key": list(key), "ads": ads, "index": rec["index"], "oracle": rec.get("_oracle"),
                    **judge_one(rec, key[5], ads, feasible, runs)}
            append_jsonl(path, line)
            done[key] = line
            b.update(1)
    judged = {k: done[k] for k in pairs}
    lines = recount_markdown(args.folder, rows, judged, group_scenarios)
    write_atomic(out / "recount.md", "\n".join(lines) + "\n")
    rests = sum(d["rests_on_false_cut_in"] for d in judged.values())
    con.print(f"{len(pairs)} distinct findings counted again, {rests} rest on a false predicted cut-in -> {out / 'recount.md'}")
    return 0


def recount_markdown(folder: Path, rows: list[dict[str, Any]], judged: dict[tuple, dict[str, Any]],
                     group_scenarios: dict[str, list[str]]) -> list[str]:
    """``recount.md``: per group and placement, each method's distinct findings per repeat as
    counted and without those that rest on a false predicted cut-in, RL against each baseline on
    what remains, and per scenario what remains."""
    cells: dict[tuple[str, str], dict[str, set[int]]] = defaultdict(lambda: defaultdict(set))
    for r in rows:  # every repeat of every cell, the ones that found nothing too
        cells[(r["scenario_kind"], r["placement"])][r["method"]].add(int(r["repeat"]))
    lines = [f"# Findings of {folder} counted again", "",
             "Every distinct finding the evaluation counted (`any_distinct`: a (scenario, root cause) pair once per "
             "method, placement and repeat) simulated again with its jitter seed. *False cut-in*: the ADS's "
             "prediction put a vehicle into the ego's or the optimal path's lane around the moment the ego left the "
             "optimal path, and none of those predictions came true within 6 s. *Rests on it*: simulated once "
             "more on the same jitter seed with the predictor's intent rule off (`intent_offset` infinite, "
             "`modules/prediction.py`), the finding is gone. *Remain*: the findings that do not rest on one.", ""]
    n_judged = len(judged)
    lines += [f"{n_judged} findings: {sum(d['reproduced'] for d in judged.values())} reproduced, "
              f"{sum(d['false_cut_ins'] for d in judged.values())} with a false cut-in, "
              f"{sum(d['rests_on_false_cut_in'] for d in judged.values())} rest on it.", ""]
    for (group, placement), methods in sorted(cells.items()):
        values: dict[str, dict[str, Any]] = {}
        for m, repeats in methods.items():
            counted = {rep: 0 for rep in repeats}
            remain = {rep: 0 for rep in repeats}
            for key, d in judged.items():
                if key[0] == m and key[1] == placement and key[2] == group:
                    counted[key[3]] += 1
                    remain[key[3]] += not d["rests_on_false_cut_in"]
            values[m] = {"counted": describe([counted[k] for k in sorted(counted)]),
                         "remain": describe([remain[k] for k in sorted(remain)])}
        order = [m for m in METHOD_LABELS if m in values] + sorted(set(values) - set(METHOD_LABELS))
        lines += [f"## {group}, {placement} placement", "",
                  "| method | distinct findings per repeat, as counted | remain | scenarios with a finding that remains |",
                  "|---|---|---|---|"]
        for m in order:
            scen = {k[4] for k, d in judged.items()
                    if k[:3] == (m, placement, group) and not d["rests_on_false_cut_in"]}
            lines.append(f"| {METHOD_LABELS.get(m, m)} | {_fmt(values[m]['counted'])} | {_fmt(values[m]['remain'])} | "
                         f"{len(scen)} of {len(group_scenarios.get(group, [])) or '?'} |")
        every = {k[4] for k, d in judged.items() if k[1:3] == (placement, group) and not d["rests_on_false_cut_in"]}
        lines += [f"| all methods | | | {len(every)} of {len(group_scenarios.get(group, [])) or '?'} |", ""]
        if "rl" in values:
            for y in order:
                if y == "rl":
                    continue
                c = compare("rl", y, "remain", values["rl"], values[y])
                ratio = f"{c['ratio']:.2f}x" if c["ratio"] is not None else c["note"]
                p = f"p = {c['p']:.3f}, A12 = {c['a12']:.2f}" if c["p"] is not None else "no test"
                lines.append(f"- what remains, RL against {METHOD_LABELS.get(y, y)}: {ratio} ({p})")
            lines.append("")
        lines += ["| scenario | remain (method: root cause) | rest on a false cut-in |", "|---|---|---|"]
        for s in sorted({k[4] for k in judged if k[1:3] == (placement, group)}):
            mine = sorted((k, d) for k, d in judged.items() if k[1:3] == (placement, group) and k[4] == s)
            keep = sorted({f"{k[0]}: `{k[5]}`" for k, d in mine if not d["rests_on_false_cut_in"]})
            gone = sorted({f"`{k[5]}`" for k, d in mine if d["rests_on_false_cut_in"]})
            lines.append(f"| {s} | {'; '.join(keep) or '-'} | {'; '.join(gone) or '-'} |")
        lines.append("")
    return lines


def _fmt(d: dict[str, Any]) -> str:
    mean, sd = d["mean"], d["sd"]
    return "-" if mean is None else f"{mean:.1f}" + (f" ± {sd:.1f}" if sd is not None else "")
