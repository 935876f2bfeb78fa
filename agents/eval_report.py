"""The report of the adversary evaluation (:mod:`agents.evaluate`): ``summary.json``, ``table.md``
(headline table, per-group tables, per-scenario failures, statistics, targets),
``cumulative_failures.png`` and ``per_scenario.png``, from the records through :mod:`agents.stats`.

Re-render the report of a finished (or interrupted) evaluation from its records:

    python -m agents.eval_report runs/eval/x [--model runs/adversary/x/model.zip]
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from agents import stats
from agents.stats import GROUP_LABELS, GROUPS, METHOD_LABELS, METHOD_ORDER, RecordError
from deft_gym.cli import common
from deft_gym.files import read_jsonl, write_atomic, write_json_atomic

GROUP_TITLES = {"seeds": "Seed scenarios", "held_out": "Held-out scenarios", "handwritten": "Hand-written scenarios",
                "all": "All scenarios"}
TRAINING_METHODS = ("rl",)  # methods trained before the evaluation (a second budget column)


# -- summary --------------------------------------------------------------------------------------
def _training_leg(model: str) -> dict[str, Any] | None:
    """One training run's ``episodes``, ``train_seconds`` and ``cpu_seconds`` from the
    ``summary.json`` next to ``model`` (or in its run folder), with the ``init_model`` its
    ``config.yaml`` started from (None for a run from scratch); None without a summary."""
    p = Path(model)
    for d in (p.parent, p.parent.parent):
        f = d / "summary.json"
        if f.exists():
            try:
                data = json.loads(f.read_text())
            except json.JSONDecodeError as err:
                raise RecordError(f"{f}: not JSON ({err})") from None
            if not isinstance(data, dict) or not isinstance(data.get("episodes"), int):
                raise RecordError(f"{f}: field 'episodes': expected an integer")
            init, c = None, d / "config.yaml"
            if c.exists():
                from deft_gym.config import ConfigError, load_mapping

                try:
                    init = load_mapping(c).get("init_model")
                except ConfigError as err:
                    raise RecordError(str(err)) from None
                if init is not None and not isinstance(init, str):
                    raise RecordError(f"{c}: field 'init_model': expected a model path or 'default', got {init!r}")
            return {"episodes": data["episodes"], "train_seconds": data.get("train_seconds"),
                    "cpu_seconds": data.get("cpu_seconds"), "summary": str(f), "init_model": init}
    return None


def rl_training(model: str | None) -> dict[str, Any] | None:
    """``episodes`` (training scenarios simulated), ``train_seconds`` [s] and ``cpu_seconds`` [s]
    of the training behind ``model``: its run's ``summary.json`` (next to it or in its run folder)
    plus those of the runs it was fine-tuned from (each run's ``config.yaml`` ``init_model``, back
    to a run from scratch), each run in ``legs``, newest first; a sum is None where a run lacks
    it. None without a summary."""
    from deft_gym.models import resolve_model

    legs: list[dict[str, Any]] = []
    seen: set[Path] = set()
    path = model
    while path:
        leg = _training_leg(str(resolve_model(path)))
        summary = Path(leg["summary"]).resolve() if leg is not None else None
        if summary is None or summary in seen:
            break
        seen.add(summary)
        path = leg.pop("init_model")
        legs.append(leg)
    if not legs:
        return None

    def total(key: str) -> float | None:
        values = [leg[key] for leg in legs]
        return None if any(v is None for v in values) else sum(values)

    return {"episodes": sum(leg["episodes"] for leg in legs), "train_seconds": total("train_seconds"),
            "cpu_seconds": total("cpu_seconds"), "summary": legs[0]["summary"], "legs": legs}


def build_summary(records: list[dict[str, Any]], config: dict[str, Any], seeds: list[str], held_out: list[str],
                  source: str = "records") -> dict[str, Any]:
    """:func:`agents.stats.summarize` over ``config``'s methods and placements, plus the config,
    RL's training budget and the simulation code the records ran. Hand-written scenarios
    (``handwritten/<name>``) among ``seeds`` form a group of their own."""
    hand = [s for s in seeds if stats.kind_of_name(s) == "handwritten"]
    seeds = [s for s in seeds if s not in hand]
    s = stats.summarize(records, config.get("methods"), config.get("placements"), seeds, held_out, source, hand)
    s["config"] = config
    s["training"] = {m: (rl_training(config.get("model")) if m in TRAINING_METHODS else None)
                     for m in s["methods"]}
    s["simulation_code"] = sorted({str(r.get("code", "?")) for r in records})
    s["unmutated"] = unmutated_counts(records)
    return s


def unmutated_counts(records: list[dict[str, Any]]) -> dict[str, int]:
    """Per metric oracle, how many records had a finding that the seed's own unmutated runs have
    too (``unmutated_by_oracle``, ``unmutated_signature``: counted as nothing, docs/metrics.md)."""
    out: dict[str, int] = {}
    for r in records:
        found = dict(r.get("unmutated_by_oracle") or {})
        if r.get("unmutated_signature") and r.get("oracle"):
            found[r["oracle"]] = r["unmutated_signature"]
        for o in found:
            out[o] = out.get(o, 0) + 1
    return dict(sorted(out.items()))


# -- markdown -------------------------------------------------------------------------------------
def _num(x: float | None, nd: int = 1) -> str:
    return "-" if x is None else f"{x:.{nd}f}"


def fmt(stat: dict[str, Any] | None, nd: int = 1, scale: float = 1.0) -> str:
    """``mean ± sd`` of a measure (sd "-" with one repeat; "-" without data)."""
    if not stat or stat.get("mean") is None:
        return "-"
    sd = stat.get("sd")
    return f"{scale * stat['mean']:.{nd}f} ± " + ("-" if sd is None else f"{scale * sd:.{nd}f}")


def _p(p: float | None) -> str:
    return "-" if p is None else (f"{p:.1e}" if p < 0.001 else f"{p:.3f}")


def _label(m: str) -> str:
    return METHOD_LABELS.get(m, m)


def _budget(summary: dict[str, Any], m: str, p: str) -> str:
    """Simulated scenarios per scenario and repeat (a range when cells differ)."""
    cells = summary["per_scenario"].get(m, {}).get(p, {})
    b = sorted({c["simulated"]["mean"] for c in cells.values() if c["simulated"]["mean"] is not None})
    return "-" if not b else f"{b[0]:g}" if len(b) == 1 else f"{b[0]:g}-{b[-1]:g}"


def _training(summary: dict[str, Any], m: str) -> str:
    if m not in TRAINING_METHODS:
        return "0"
    t = summary.get("training", {}).get(m)
    return "-" if not t else f"{t['episodes']:,}"


def _rows(summary: dict[str, Any]) -> list[tuple[str, str]]:
    return [(m, p) for m in summary["methods"] for p in summary["placements"]]


def _star(cell: dict[str, Any] | None) -> str:
    return "" if not cell or cell["complete"] else "*"


GROUP_COLUMNS = (("root_causes", "root causes", 1, 1.0), ("root_causes_in_lane", "incl. in-lane", 1, 1.0),
                 ("failures", "failures", 1, 1.0), ("nods", "NoDS", 1, 1.0), ("collisions", "collisions", 1, 1.0),
                 ("nods_local", "local NoDS", 1, 1.0), ("task_failures", "task failures", 1, 1.0),
                 ("validity", "validity %", 1, 100.0), ("distinct", "distinct", 1, 1.0),
                 ("seconds_per_scenario", "s/scenario", 2, 1.0), ("distinct_per_cpu_hour", "distinct/CPU-h", 1, 1.0))


def headline_markdown(summary: dict[str, Any]) -> str:
    """The headline table (for the README): one row per method x placement; distinct root causes
    of counted failures over all scenarios (without, then with, triggers inside the ego's lane),
    counted failures (NoDS + collisions) on seeds, held-out and all scenarios, then the other
    measures on all scenarios, mean ± sd over repeats of the per-repeat totals; the budget per
    scenario and repeat, and training episodes as a second budget column."""
    head = [key for key, *_ in GROUP_COLUMNS[:2]]
    cols = ["method", "placement", "budget", "training episodes"]
    cols += [label for key, label, *_ in GROUP_COLUMNS if key in head]
    cols += [f"failures {GROUP_LABELS[g]}" for g in stats.shown_groups(summary)]
    cols += [label for key, label, *_ in GROUP_COLUMNS if key not in head and key != "failures"]
    reps = sorted({len(c["repeats"]) for ps in summary["groups"].values() for gs in ps.values() for c in gs.values()})
    n_reps = "0" if not reps else str(reps[0]) if len(reps) == 1 else f"{reps[0]}-{reps[-1]}"
    caption = (f"Mean ± sd over {n_reps} repeat(s) of per-repeat "
               "totals. Root causes: distinct (kind, trigger, clearance band, mechanism) of the counted failures over "
               "all scenarios, leaving out triggers inside the ego's own lane (< 0.75 m from the optimal path; "
               "'incl. in-lane' counts them). Failures: valid mutations whose NoDS (grid IoU <= 0.6) or ego-at-fault "
               "collision reproduced with the same root cause on a second jitter seed, on seed, held-out and all "
               "scenarios; the other columns over all scenarios. Budget: simulated scenarios per scenario and "
               "repeat; training episodes: scenarios simulated to train the method beforehand (with the runs "
               "its model was fine-tuned from).")
    lines = [caption, "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    groups = summary["groups"]
    for m, p in _rows(summary):
        g_all = groups.get(m, {}).get(p, {}).get("all")
        cells = [_label(m), p, _budget(summary, m, p), _training(summary, m)]
        cells += [fmt(g_all and g_all[key], nd, scale) for key, _, nd, scale in GROUP_COLUMNS if key in head]
        for g in stats.shown_groups(summary):
            c = groups.get(m, {}).get(p, {}).get(g)
            cells.append(fmt(c and c["failures"]) + _star(c))
        cells += [fmt(g_all and g_all[key], nd, scale) for key, _, nd, scale in GROUP_COLUMNS
                  if key not in head and key != "failures"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def group_markdown(summary: dict[str, Any], group: str) -> str:
    """Every measure on one group of scenarios (per-repeat totals over its scenarios, mean ± sd)."""
    cols = ["method", "placement", "scenarios", "repeats"] + [label for _, label, *_ in GROUP_COLUMNS] + ["unconfirmed"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for m, p in _rows(summary):
        c = summary["groups"].get(m, {}).get(p, {}).get(group)
        if c is None:
            lines.append("| " + " | ".join([_label(m), p] + ["-"] * (len(cols) - 2)) + " |")
            continue
        n_scn = f"{len(c['scenarios'])}/{len(c['scenarios']) + len(c['missing_scenarios'])}"
        cells = [_label(m), p, n_scn, str(len(c["repeats"])) + _star(c)]
        cells += [fmt(c[key], nd, scale) for key, _, nd, scale in GROUP_COLUMNS] + [fmt(c["unconfirmed"])]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def per_scenario_markdown(summary: dict[str, Any], measure: str = "failures") -> str:
    """``measure`` per scenario (rows) and method x placement (columns), mean ± sd: the counted
    failures, or (``any_distinct``) the distinct findings of any oracle, then a column saying
    whether any method found one in some repeat and a line naming the scenarios where none did
    (where the search, as configured, finds nothing on this planner)."""
    rows = _rows(summary)
    any_oracle = measure == "any_distinct"
    cols = ["scenario", "kind"] + [f"{_label(m)} ({p})" for m, p in rows] + (["any method"] if any_oracle else [])
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    kind_labels = {"seed": "seed", "held_out": "held-out", "handwritten": "hand-written"}
    scenarios = summary["seeds"] + summary["held_out"] + summary.get("handwritten", [])
    none_found = []
    for s in scenarios:
        cells = [s, kind_labels.get(summary["scenario_kinds"].get(s, "held_out"), "held-out")]
        cells += [fmt(summary["per_scenario"].get(m, {}).get(p, {}).get(s, {}).get(measure)) for m, p in rows]
        if any_oracle:
            found = any(_found_in(summary, m, p, s, measure) for m, p in rows)
            cells.append("yes" if found else "**none**")
            if not found:
                none_found.append(s)
        lines.append("| " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    if any_oracle:
        text += (f"\nNo method found anything on {len(none_found)} of {len(scenarios)} scenarios"
                 + (": " + ", ".join(f"`{s}`" for s in none_found) if none_found else "") + ".\n")
    return text


def statistics_markdown(rows: list[dict[str, Any]], where: str = "group") -> str:
    """Comparison rows (:func:`agents.stats.compare`) as a table; ``where``: group or scenario."""
    cols = ["placement", where, "X vs Y", "measure", "n", "mean X", "mean Y", "X/Y", "U", "p", "A12", "note"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        ratio = _num(r["ratio"], 2) if r["ratio"] is not None else "- (denominator 0)" if r["mean_y"] == 0 else "-"
        label = GROUP_LABELS.get(r[where], r[where]) if where == "group" else r[where]
        lines.append("| " + " | ".join([
            r["placement"], label, f"{_label(r['x'])} vs {_label(r['y'])}", r["measure"], f"{r['n_x']}/{r['n_y']}",
            _num(r["mean_x"], 2), _num(r["mean_y"], 2), ratio, _num(r["u"], 1), _p(r["p"]), _num(r["a12"], 2),
            r["note"]]) + " |")
    return "\n".join(lines) + "\n"


def _met(ok: bool) -> str:
    return "**met**" if ok else "**not met**"


def targets_markdown(t: dict[str, Any]) -> str:
    """The issue's targets (:func:`agents.stats.check_targets`) as a list, with the numbers."""
    pr = t["protocol"]
    out = [f"Targets (group: {GROUP_LABELS[t['group']]}): {_met(t['met'])} overall.", "",
           f"- Protocol: {_met(pr['met'])} - repeats per cell >= {pr['repeats_required']} (min {pr['repeats_min']}), "
           f"held-out scenarios >= {pr['held_out_required']} ({pr['held_out_scenarios']}), equal budget "
           f"({'yes' if pr['equal_budget'] else 'no'}: {', '.join(f'{b:g}' for b in pr['budgets']) or '-'})."]
    no = t["nods_ordering"]
    parts = []
    for p, v in no["per_placement"].items():
        steps = "; ".join(f"{_label(s['x'])} {_num(s['mean_x'], 2)} vs {_label(s['y'])} {_num(s['mean_y'], 2)} "
                          f"(A12 {_num(s['a12'], 2)}, p {_p(s['p'])}) {'ok' if s['met'] else 'no'}" for s in v["steps"])
        parts.append(f"{p}: {steps}")
    out.append(f"- Decictor-GA > Random-delta > Random in NoDS, A12 >= {no['a12_required']} per step: "
               f"{_met(no['met'])} - " + (" | ".join(parts) or "no data") + ".")
    rg = t["rl_vs_ga"]
    parts = [f"{p}: RL {_num(v['mean_rl'], 2)} vs GA {_num(v['mean_ga'], 2)}, ratio "
             f"{_num(v['ratio'], 2) if v['ratio'] is not None else '- (' + (v['note'] or 'no data') + ')'}, "
             f"p {_p(v['p'])} {'ok' if v['met'] else 'no'}" for p, v in rg["per_placement"].items()]
    out.append(f"- RL >= {rg['ratio_required']}x Decictor-GA in failures (NoDS + collisions), p < {rg['p_required']}: "
               f"{_met(rg['met'])} - " + (" | ".join(parts) or "no data") + ".")
    va = t["validity"]
    parts = [f"{_label(m)} {p} {100 * v:.1f} %" for m, ps in va["methods"].items() for p, v in ps.items()]
    out.append(f"- Validity >= {100 * va['required']:g} % (non-invasive methods): {_met(va['met'])} - "
               + (", ".join(parts) or "no data") + (f"; not required of {', '.join(map(_label, va['not_required']))}"
                                                      if va["not_required"] else "") + ".")
    fs = t["failure_on_every_seed"]
    out.append(f"- A counted failure on every seed scenario: {_met(fs['met'])} - by any method: "
               f"{'all' if fs['any_method']['met'] else 'none on ' + (', '.join(fs['any_method']['without']) or '-')}; "
               f"by RL: {'all' if fs['rl']['met'] else 'none on ' + (', '.join(fs['rl']['without']) or '-')}.")
    if "rl_root_causes" in t:
        rc = t["rl_root_causes"]
        parts = [f"{p}: " + "; ".join(
            f"vs {_label(y)} {_num(v['mean_rl'], 2)} vs {_num(v['mean_other'], 2)}, ratio "
            f"{_num(v['ratio'], 2) if v['ratio'] is not None else '- (' + (v['note'] or 'no data') + ')'}, "
            f"p {_p(v['p'])} {'ok' if v['met'] else 'no'}" for y, v in rows.items())
            for p, rows in rc["per_placement"].items()]
        out.append(f"- RL >= {rc['ratio_required']}x Decictor-GA and random actions in distinct root causes, "
                   f"p < {rc['p_required']}: {_met(rc['met'])} - " + (" | ".join(parts) or "no data") + ".")
        me = t["mechanisms"]
        out.append(f"- At least {me['required']} mechanisms found in all: {_met(me['met'])} - {len(me['found'])}: "
                   + ", ".join(f"{k} ({v})" for k, v in me["found"].items()) + ".")
        do = t["dominance"]
        parts = [f"{_label(m)} {p}: {v['mechanism']} {100 * v['share']:.0f} %" for m, ps in do["per_method"].items()
                 for p, v in ps.items() if v["dominates"]]
        out.append(f"- No mechanism above {100 * do['limit']:.0f} % of a method's counted failures: {_met(do['met'])}"
                   + (" - dominated: " + ", ".join(parts) if parts else "") + ".")
    return "\n".join(out) + "\n"


def findings_markdown(summary: dict[str, Any], top: int = 12) -> str:
    """The root causes each method found (the ``top`` most frequent per method and placement,
    and over all methods with identical scenarios counted once) and the share of each mechanism
    in its counted failures."""
    f = summary.get("findings") or {}
    causes, mechs = f.get("root_causes", {}), f.get("mechanisms", {})
    out = ["Root cause: `kind:trigger:band:mechanism` (band: the trigger's clearance to the optimal path; in_lane "
           "< 0.75 m, near 0.75-1.0 m, far). Failures summed over the repeats; repeats and scenarios it was found in.", ""]
    order = [m for m in [*summary["methods"], "all"] if m in causes]
    out += _cause_tables(causes, order, summary["placements"], top, "root causes")
    tasks = f.get("task_root_causes", {})
    if tasks:
        out += ["Task failures (timeout, stuck; their own column, not in the headline) by root cause:", ""]
        out += _cause_tables(tasks, [m for m in [*summary["methods"], "all"] if m in tasks], summary["placements"], top,
                             "root causes of task failures")
    names = sorted({k for ps in mechs.values() for cs in ps.values() for k in cs})
    if names:
        out += ["Share of each mechanism in the counted failures:", "",
                "| method | placement | failures | " + " | ".join(names) + " |", "|" + "---|" * (3 + len(names))]
        for m in order:
            for p in summary["placements"]:
                cs = mechs.get(m, {}).get(p)
                if not cs:
                    continue
                n = sum(cs.values())
                out.append(f"| {'All methods' if m == 'all' else _label(m)} | {p} | {n} | "
                           + " | ".join(f"{100 * cs.get(k, 0) / n:.0f} %" if cs.get(k) else "-" for k in names) + " |")
        out.append("")
    return "\n".join(out) + "\n"


def _cause_tables(causes: dict[str, Any], order: list[str], placements: list[str], top: int, what: str) -> list[str]:
    """One table per method and placement of the ``top`` most frequent root causes."""
    out: list[str] = []
    for m in order:
        for p in placements:
            cs = causes[m].get(p)
            if not cs:
                continue
            rows = sorted(cs.items(), key=lambda kv: (-kv[1]["failures"], kv[0]))
            genuine = sum(1 for _, c in rows if c["band"] != stats.IN_LANE)
            out += [f"**{'All methods' if m == 'all' else _label(m)}, {p}**: {len(rows)} {what} "
                    f"({genuine} outside the ego's lane)", "",
                    "| root cause | band | mechanism | failures | repeats | scenarios |", "|---|---|---|---|---|---|"]
            for sig, c in rows[:top]:
                scn = ", ".join(c["scenarios"][:3]) + (f" (+{len(c['scenarios']) - 3})" if len(c["scenarios"]) > 3 else "")
                out.append(f"| `{sig}` | {c['band']} | {c['mechanism']} | {c['failures']} | {c['repeats']} | {scn} |")
            if len(rows) > top:
                out.append(f"| ... {len(rows) - top} more | | | {sum(c['failures'] for _, c in rows[top:])} | | |")
            out.append("")
    return out


def quality_markdown(summary: dict[str, Any], group: str = "all") -> str:
    """Driving quality per method and placement on one group (docs/metrics.md): the mean
    nuPlan-like score of the simulated scenarios, the share that violated each metric oracle and,
    with a metric oracle configured, its counted findings and distinct signatures (mean ± sd over
    repeats); empty when no record has metrics."""
    from agents.stats import METRIC_VIOLATIONS

    cells = {(m, p): summary["groups"].get(m, {}).get(p, {}).get(group) for m, p in _rows(summary)}
    if not any(c and c.get("metric_score", {}).get("n") for c in cells.values()):
        return ""
    cols = ["method", "placement", "score", "oracle findings", "oracle root causes"] + \
        [f"{v} %" for v in METRIC_VIOLATIONS]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for (m, p), c in cells.items():
        if c is None or "metric_score" not in c:
            continue
        row = [_label(m), p, fmt(c["metric_score"], 3), fmt(c["oracle_findings"]), fmt(c["oracle_root_causes"])]
        row += [fmt(c[f"viol_{v}"], 1, 100.0) for v in METRIC_VIOLATIONS]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def oracles_markdown(summary: dict[str, Any], group: str = "all") -> str:
    """Findings per counted oracle (``count_oracles``) per method and placement on ``group``:
    distinct (scenario, signature) pairs of confirmed findings (mean ± sd over repeats), the
    decision oracle's distinct failures beside them, every oracle together, the decision oracle
    with the oracles whose findings were judged genuine (:data:`agents.stats.SAFETY_ORACLES`), and the scenarios
    where the method counted one in some repeat; empty without counted oracles."""
    counted = summary.get("config", {}).get("count_oracles") or []
    names = ((summary.get(group) or []) if group != "all"
             else [s for g in ("seeds", "held_out", "handwritten") for s in summary.get(g, [])])
    if not counted or not names:
        return ""
    cols = ["method", "placement", "decision oracle"] + [f"`{o}`" for o in counted] + [
        "any oracle", "decision + `ttc` + `drivable_area`", "scenarios"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for m, p in _rows(summary):
        c = summary["groups"].get(m, {}).get(p, {}).get(group)
        if c is None or "any_distinct" not in c:
            continue
        found = sum(_found_in(summary, m, p, s, "any_distinct") for s in names)
        row = [_label(m), p, fmt(c["distinct"])] + [fmt(c.get(f"found_{o}")) for o in counted]
        lines.append("| " + " | ".join([*row, fmt(c["any_distinct"]), fmt(c.get("safety_distinct")),
                                        f"{found} of {len(names)}"]) + " |")
    return "\n".join(lines) + "\n"


def _found_in(summary: dict[str, Any], method: str, placement: str | None, scenario: str, measure: str) -> bool:
    """Whether ``method`` counted ``measure`` > 0 on ``scenario`` in some repeat (of ``placement``,
    else of any placement)."""
    pls = summary["per_scenario"].get(method, {})
    cells = [pl.get(scenario) for name, pl in pls.items() if placement in (None, name)]
    return any(sum(v or 0 for v in (c.get(measure) or {}).get("values", [])) > 0 for c in cells if c)


def table_markdown(summary: dict[str, Any]) -> str:
    """``table.md``: the headline table, every measure per group, failures per scenario, the
    statistics and the targets."""
    cfg = summary.get("config", {})
    missing = summary.get("missing_fields") or {}
    text = [
        "# Adversary evaluation", "",
        f"Budget: {cfg.get('budget', '-')} simulated scenarios per method, placement, scenario and repeat; "
        f"{cfg.get('repeats', '-')} repeat(s); {len(summary['seeds'])} seed"
        + (f", {len(summary['held_out'])} held-out and {len(summary['handwritten'])} hand-written "
           if summary.get("handwritten") else f" and {len(summary['held_out'])} held-out ") +
        "scenario(s). Cells: mean ± sd over repeats of the per-repeat totals over the group's scenarios (sd - with "
        "one repeat). A failure (NoDS under the grid consistency check, or an ego-at-fault collision) counts only "
        "for a valid mutation and when it reproduced on a second jitter seed"
        + (" (for RL and random actions, which place while the scenario runs, with every static object they "
           "placed there from the start)" if cfg.get("late_statics", "as_placed") == "from_start" else "")
        + "; local NoDS and task failures "
        "(timeout/stuck of a valid mutation) are separate columns. Distinct: distinct root-cause signatures. "
        "Training episodes: scenarios simulated to train the method before the evaluation, the runs its model "
        "was fine-tuned from included (a second budget). "
        "`*`: scenarios or repeats missing in the cell."
        + (f" RL's actions: sampled from its policy at temperature {cfg['temperature']:g} (logits / "
           f"{cfg['temperature']:g})." if cfg.get("temperature", 1.0) != 1.0 and not cfg.get("deterministic")
           else ""), ""]
    if summary.get("unfit"):
        text += ["Left out, not seeds for the planner under test (its reference run does not complete them "
                 "unmutated): " + "; ".join(f"`{k}`: {v}" for k, v in summary["unfit"].items()) + ".", ""]
    if missing:
        text += ["Fields absent from records (defaults used): "
                 + ", ".join(f"{k} ({v})" for k, v in sorted(missing.items())) + ".", ""]
    text += ["## Headline", "", headline_markdown(summary), "## Root causes", "", findings_markdown(summary)]
    quality = quality_markdown(summary)
    if quality:
        oracle = cfg.get("oracle") or "default"
        text += ["## Driving quality", "",
                 f"Per-episode metrics (docs/metrics.md) of every simulated scenario, all scenarios: the nuPlan-like "
                 f"score, the share of scenarios violating each metric, and the findings on the configured oracle "
                 f"`{oracle}` (valid, reproduced on a second jitter seed; root causes: distinct signatures).", "",
                 quality]
    counted = cfg.get("count_oracles") or []
    if counted:
        text += ["## Findings per oracle", "",
                 "Distinct (scenario, signature) pairs per repeat (mean ± sd) of each counted oracle's findings: a "
                 "valid mutation whose run violates the oracle where the seed's reference run does not (docs/metrics.md), "
                 "reproduced with the same signature on a second jitter seed; the methods do not aim at them. "
                 "`any oracle`: the decision oracle's distinct failures and every counted oracle's findings "
                 "(an at-fault collision once); scenarios: where the method counted one in some repeat. "
                 "A finding that one of the seed's own unmutated runs (jitter seeds 1-8) has too counts nothing: "
                 + (", ".join(f"`{o}` in {n} record(s)" for o, n in summary["unmutated"].items())
                    if summary.get("unmutated") else "none in these records") + ".", ""]
        for g in stats.shown_groups(summary):
            table = oracles_markdown(summary, g)
            if table:
                text += [f"**{GROUP_TITLES[g]}**", "", table]
    for g in stats.shown_groups(summary):
        text += [f"## {GROUP_TITLES[g]}", "", group_markdown(summary, g)]
    text += ["## Failures per scenario", "", per_scenario_markdown(summary)]
    if summary.get("config", {}).get("count_oracles"):
        text += ["## Findings per scenario, any oracle", "",
                 "Distinct findings of any oracle per repeat (mean ± sd), as in *Findings per oracle*; "
                 "`any method`: whether some method found one in some repeat.", "",
                 per_scenario_markdown(summary, "any_distinct")]
    text += ["## Statistics", "",
             "Two-sided Mann-Whitney U on the per-repeat totals; A12 = P(X > Y) + 0.5 P(X = Y); X/Y: ratio of means.",
             "", statistics_markdown(summary["statistics"]["groups"], "group")]
    if summary["statistics"]["per_scenario"]:
        text += ["<details><summary>Per scenario</summary>", "",
                 statistics_markdown(summary["statistics"]["per_scenario"], "scenario"), "</details>", ""]
    text += ["## Targets", "", targets_markdown(summary["targets"])]
    return "\n".join(text)


# -- plots ----------------------------------------------------------------------------------------
def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _color(m: str) -> Any:
    import matplotlib

    i = METHOD_ORDER.index(m) if m in METHOD_ORDER else len(METHOD_ORDER) + sum(map(ord, m)) % 4
    return matplotlib.colormaps["tab10"](i % 10)


def _save(fig: Any, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    _pyplot().close(fig)
    write_atomic(path, buf.getvalue())


def plot_cumulative(records: list[dict[str, Any]], summary: dict[str, Any], path: Path) -> None:
    """``cumulative_failures.png``: counted failures against simulated scenarios per scenario,
    summed over each group's scenarios, mean over repeats with a 95 % confidence band; one line
    per method, one panel per placement (rows) x group (columns)."""
    plt = _pyplot()
    curves = stats.cumulative_curves(records, summary)
    placements = summary["placements"] or ["closest"]
    # a group without scenarios (no held-out ones) gets no panel; "all" then equals "seeds"
    groups = [g for g in GROUPS if summary["held_out"] or g != "held_out"]
    groups = [g for g in groups if summary["held_out"] or g != "all"] or list(GROUPS[:1])
    members = {"seeds": summary["seeds"], "held_out": summary["held_out"], "handwritten": summary.get("handwritten", []),
               "all": summary["seeds"] + summary["held_out"] + summary.get("handwritten", [])}
    if members["handwritten"]:  # the non-empty groups, and all when there are two or more
        groups = [g for g in ("seeds", "held_out", "handwritten") if members[g]]
        groups += ["all"] if len(groups) > 1 else []
    fig, axes = plt.subplots(len(placements), len(groups), figsize=(4.2 * len(groups) + 1.5, 3.2 * len(placements)),
                             squeeze=False)
    handles: dict[str, Any] = {}
    for i, p in enumerate(placements):
        for j, g in enumerate(groups):
            ax = axes[i][j]
            n_scn = len(members[g])
            ax.set_title(f"{p} placement, {GROUP_LABELS[g]} ({n_scn} scenarios)", fontsize=9)
            lines = curves.get(p, {}).get(g, {})
            for m in summary["methods"]:
                c = lines.get(m)
                if c is None:
                    continue
                (h,) = ax.plot(c["x"], c["mean"], color=_color(m), lw=1.6)
                handles[m] = h
                if c["lo"] is not None:
                    ax.fill_between(c["x"], c["lo"], c["hi"], color=_color(m), alpha=0.18, lw=0)
            if not lines:
                ax.text(0.5, 0.5, "no data", ha="center", va="center", transform=ax.transAxes, color="0.5")
            ax.set_xlabel("simulated scenarios per scenario")
            ax.set_ylabel("cumulative failures\n(NoDS + collisions)", fontsize=9)
            ax.grid(alpha=0.3)
            ax.margins(x=0)
            ax.set_ylim(bottom=0)
    if handles:
        fig.legend(list(handles.values()), [_label(m) for m in handles], loc="center left",
                   bbox_to_anchor=(1.0, 0.5), title="mean, 95 % CI", frameon=False)
    fig.tight_layout()
    _save(fig, path)


def plot_per_scenario(summary: dict[str, Any], path: Path) -> None:
    """``per_scenario.png``: grouped bars of counted failures per scenario (mean over repeats,
    sd error bars), one bar per method, one panel per placement; seeds left of the dashed line,
    held-out scenarios right of it."""
    plt = _pyplot()
    scns = summary["seeds"] + summary["held_out"] + summary.get("handwritten", [])
    placements = summary["placements"] or ["closest"]
    methods = summary["methods"] or []
    width = 0.8 / max(len(methods), 1)
    fig_w = min(max(6.0, 0.22 * len(scns) * max(len(methods), 1) + 2.0), 40.0)
    fig, axes = plt.subplots(len(placements), 1, figsize=(fig_w, 3.4 * len(placements)), squeeze=False)
    x = np.arange(len(scns))
    handles: dict[str, Any] = {}
    for i, p in enumerate(placements):
        ax = axes[i][0]
        for k, m in enumerate(methods):
            cells = summary["per_scenario"].get(m, {}).get(p, {})
            mean = [np.nan if s not in cells or cells[s]["failures"]["mean"] is None else cells[s]["failures"]["mean"]
                    for s in scns]
            sd = [np.nan if s not in cells or cells[s]["failures"]["sd"] is None else cells[s]["failures"]["sd"]
                  for s in scns]
            if all(np.isnan(mean)):
                continue
            handles[m] = ax.bar(x + (k - (len(methods) - 1) / 2) * width, np.nan_to_num(mean), width, yerr=sd,
                                color=_color(m), capsize=2, error_kw={"lw": 0.8})
        if summary["seeds"] and summary["held_out"]:
            ax.axvline(len(summary["seeds"]) - 0.5, color="0.4", ls="--", lw=0.8)
        if summary.get("handwritten") and (summary["seeds"] or summary["held_out"]):
            ax.axvline(len(summary["seeds"]) + len(summary["held_out"]) - 0.5, color="0.4", ls=":", lw=0.8)
        ax.set_xticks(x, scns, rotation=40, ha="right", fontsize=8)
        ax.set_xlim(-0.6, max(len(scns), 1) - 0.4)
        ax.set_ylabel("failures per repeat\n(NoDS + collisions)", fontsize=9)
        ax.set_title(f"{p} placement: mean ± sd over repeats (seeds | held-out)", fontsize=9)
        ax.grid(axis="y", alpha=0.3)
        ax.set_ylim(bottom=0)
        if not handles:
            ax.text(0.5, 0.5, "no data", ha="center", va="center", transform=ax.transAxes, color="0.5")
    if handles:
        fig.legend(list(handles.values()), [_label(m) for m in handles], loc="center left",
                   bbox_to_anchor=(1.0, 0.5), frameon=False)
    fig.tight_layout()
    _save(fig, path)


def write_report(records: list[dict[str, Any]], summary: dict[str, Any], out: Path) -> str:
    """Write ``summary.json``, ``table.md``, ``cumulative_failures.png`` and ``per_scenario.png``
    into ``out``; returns the table's text."""
    write_json_atomic(out / "summary.json", summary)
    table = table_markdown(summary)
    write_atomic(out / "table.md", table)
    plot_cumulative(records, summary, out / "cumulative_failures.png")
    plot_per_scenario(summary, out / "per_scenario.png")
    return table


# -- several planners ------------------------------------------------------------------------------
#: the hand-written group's targets (issue 33): RL finds a confirmed failure on this share of its
#: scenarios, and this many times Decictor-GA's distinct failures, p below TARGET_P
TARGET_COVERAGE, TARGET_RATIO, TARGET_P = 0.75, 1.5, 0.05
PLANNER_MEASURES = (("failures", "failures", 1), ("distinct", "distinct", 1), ("root_causes", "root causes", 1),
                    ("collisions", "collisions", 1), ("validity", "valid %", 1),
                    ("distinct_per_cpu_hour", "distinct/CPU-h", 1))


def coverage(summary: dict[str, Any], method: str, group: str = "handwritten",
             measure: str = "failures") -> tuple[int, int]:
    """``(scenarios of the group where the method counted a confirmed failure - with ``measure``
    ``any_distinct``, a confirmed finding of any counted oracle - in some repeat and placement,
    scenarios of the group)``."""
    names = summary.get(group, [])
    return sum(_found_in(summary, method, None, name, measure) for name in names), len(names)


def planner_targets(summary: dict[str, Any]) -> dict[str, Any]:
    """The hand-written group's targets on one planner's evaluation, per placement."""
    out: dict[str, Any] = {}
    found, n = coverage(summary, "rl")
    out["coverage"] = {"found": found, "scenarios": n, "share": found / n if n else None,
                       "met": bool(n) and found / n >= TARGET_COVERAGE}
    if summary.get("config", {}).get("count_oracles"):  # the target's "any oracle"
        found, n = coverage(summary, "rl", measure="any_distinct")
        out["coverage_any"] = {"found": found, "scenarios": n, "share": found / n if n else None,
                               "met": bool(n) and found / n >= TARGET_COVERAGE}
    for pl in summary["placements"]:
        cx = summary["groups"].get("rl", {}).get(pl, {}).get("handwritten")
        cy = summary["groups"].get("decictor", {}).get(pl, {}).get("handwritten")
        row = stats.compare("rl", "decictor", "distinct", cx, cy, placement=pl, group="handwritten")
        row["met"] = (row["ratio"] is not None and row["ratio"] >= TARGET_RATIO and row["p"] is not None
                      and row["p"] < TARGET_P) or (row["mean_y"] == 0 and (row["mean_x"] or 0) > 0
                                                    and row["p"] is not None and row["p"] < TARGET_P)
        out[pl] = row
    return out


def rl_rate_with_training(summary: dict[str, Any], placement: str | None = None) -> dict[str, float] | None:
    """RL's distinct failures per CPU-hour on all scenarios with its training's CPU added once
    (the training run's ``cpu_seconds``), over all repeats of ``placement`` (default: the
    first); None without RL, its records or its training summary."""
    train = (summary.get("training") or {}).get("rl") or {}
    pl = placement or (summary.get("placements") or [None])[0]
    cell = summary["groups"].get("rl", {}).get(pl, {}).get("all")
    if not train.get("cpu_seconds") or not cell:
        return None
    distinct = sum(v or 0 for v in cell["distinct"]["values"])
    cpu = sum(v or 0 for v in cell["cpu_seconds"]["values"])
    total = cpu + float(train["cpu_seconds"])
    return {"distinct": distinct, "eval_cpu_seconds": cpu, "training_cpu_seconds": float(train["cpu_seconds"]),
            "cpu_seconds": total, "per_cpu_hour": distinct / (total / 3600.0)}


def planners_markdown(summaries: dict[str, dict[str, Any]]) -> str:
    """``planners.md``: per planner and group, every method's counted failures, distinct failures,
    root causes outside the lane, at-fault collisions and validity (mean ± sd over repeats, per
    placement), then the hand-written group's targets (issue 33)."""
    lines = ["# Evaluation across planners and groups", "",
             "Cells: mean ± sd over repeats of per-repeat totals over the group's scenarios. Failures: valid "
             "mutations whose NoDS or ego-at-fault collision reproduced with the same root cause on a second jitter "
             "seed; distinct: distinct failure signatures; root causes: distinct root causes leaving out triggers "
             "inside the ego's lane.", ""]
    for label, summary in summaries.items():
        cfg = summary.get("config", {})
        lines += [f"## {label}", "", f"ADS config `{cfg.get('ads') or 'configs/ads/default.yaml'}`; budget "
                  f"{cfg.get('budget')} per scenario and repeat; methods {', '.join(summary['methods'])}.", ""]
        if summary.get("unfit"):
            lines += ["Left out: not seeds for this planner (it does not complete them unmutated): "
                      + "; ".join(f"`{k}` ({v.split(': ', 1)[-1]})" for k, v in summary["unfit"].items()), ""]
        cols = ["group", "scenarios", "method", "placement"] + [name for _, name, _ in PLANNER_MEASURES]
        lines += ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        members = {g: summary.get(g, []) for g in ("seeds", "held_out", "handwritten")}
        for g in ("seeds", "held_out", "handwritten"):
            if not members[g]:
                continue
            for m, p in _rows(summary):
                c = summary["groups"].get(m, {}).get(p, {}).get(g)
                cells = [GROUP_LABELS[g], str(len(members[g])), _label(m), p]
                cells += [fmt(c and c[key], nd, 100.0 if key == "validity" else 1.0) for key, _, nd in PLANNER_MEASURES]
                lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
        rate = rl_rate_with_training(summary)
        if rate is not None:
            lines += [f"RL with its training counted: {rate['distinct']:.0f} distinct failures over all repeats and "
                      f"scenarios in {rate['cpu_seconds'] / 3600:.2f} CPU-h ({rate['eval_cpu_seconds'] / 3600:.2f} "
                      f"evaluating + {rate['training_cpu_seconds'] / 3600:.2f} training, charged in full to this "
                      f"planner's evaluation): {rate['per_cpu_hour']:.1f} distinct per CPU-hour.", ""]
        if members["handwritten"] and "rl" in summary["methods"] and "decictor" in summary["methods"]:
            t = planner_targets(summary)
            cov = t["coverage"]
            lines.append(f"- RL found a confirmed failure on {cov['found']} of {cov['scenarios']} hand-written "
                         f"scenarios (target >= {TARGET_COVERAGE:.0%}): {_met(cov['met'])}")
            if "coverage_any" in t:
                cov = t["coverage_any"]
                lines.append(f"- counting every oracle (`count_oracles`), on {cov['found']} of {cov['scenarios']}: "
                             f"{_met(cov['met'])}")
            for pl in summary["placements"]:
                r = t[pl]
                ratio = f"{r['ratio']:.2f}x" if r["ratio"] is not None else r["note"] or "n/a"
                lines.append(f"- {pl}: RL {_num(r['mean_x'])} vs Decictor-GA {_num(r['mean_y'])} distinct failures on "
                             f"the hand-written group, {ratio}, p = {_p(r['p'])}, A12 = {_num(r.get('a12'), 2)} "
                             f"(target >= {TARGET_RATIO}x, p < {TARGET_P}): {_met(r['met'])}")
            lines.append("")
    return "\n".join(lines) + "\n"


def write_planners_report(out: Path) -> str:
    """``planners.md`` and ``planners.json`` in ``out`` from the evaluations in its sub-folders
    (one per planner, each with a ``summary.json``); returns the table's text."""
    summaries = {}
    for sub in sorted(p.parent for p in out.glob("*/summary.json")):
        try:
            summaries[sub.name] = json.loads((sub / "summary.json").read_text())
        except json.JSONDecodeError as err:
            raise RecordError(f"{sub / 'summary.json'}: not JSON ({err})") from None
    if not summaries:
        raise RecordError(f"{out}: no planner evaluations (sub-folders with summary.json)")
    text = planners_markdown(summaries)
    write_atomic(out / "planners.md", text)
    write_json_atomic(out / "planners.json", {label: {"config": s.get("config"), "targets": planner_targets(s)
                                                      if s.get("handwritten") else None}
                                              for label, s in summaries.items()})
    return text


def main(argv: list[str] | None = None) -> int:
    p = common.parser("eval-report", "agents.eval_report", __doc__)
    p.add_argument("out", type=Path, help="evaluation folder (records.jsonl, eval_config.json), or a folder of "
                   "one evaluation per planner (deft-gym evaluate --ads-config A.yaml B.yaml): planners.md")
    p.add_argument("--model", default=None, help="trained model.zip (its training summary; default: the config's)")
    args = p.parse_args(argv)
    cfg_path, rec_path = args.out / "eval_config.json", args.out / "records.jsonl"
    if not rec_path.exists() and any(args.out.glob("*/summary.json")):
        try:
            print(write_planners_report(args.out))
        except RecordError as err:
            return common.cli_error(str(err))
        return 0
    try:
        if not rec_path.exists():
            raise RecordError(f"{rec_path}: no such file")
        try:
            cfg = json.loads(cfg_path.read_text()) if cfg_path.exists() else {}
        except json.JSONDecodeError as err:
            raise RecordError(f"{cfg_path}: not JSON ({err})") from None
        if not isinstance(cfg, dict):
            raise RecordError(f"{cfg_path}: expected an object")
        if args.model:
            cfg["model"] = args.model
        records = read_jsonl(rec_path)
        unfit = dict(cfg.get("unfit") or {})
        summary = build_summary(records, cfg, [s for s in cfg.get("scenarios") or [] if s not in unfit],
                                [s for s in cfg.get("held_out") or [] if s not in unfit], str(rec_path))
        summary["unfit"] = unfit
    except RecordError as err:
        return common.cli_error(str(err))
    print(write_report(records, summary, args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
