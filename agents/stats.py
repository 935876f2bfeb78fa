"""Statistics of the adversary evaluation (:mod:`agents.evaluate`): records of simulated scenarios
to per-repeat counts, mean +- sd over repeats, group totals (seeds, held-out, all), Mann-Whitney U
and Vargha-Delaney A12 between methods, cumulative-failure curves, and the check of issue 17's
targets. Pure functions on record dicts: no simulation, no files.

A failure *counts* only when the record's ``failure`` is ``"nods"`` or ``"collision"``, the
mutation is ``valid`` and ``confirmed`` is true (it reproduced on a second jitter seed) - the same
rule for every method. Task failures count when confirmed as well; local NoDS (a separate column,
never merged into the headline) count when valid.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

METHOD_ORDER = ("rl", "decictor", "random_delta", "random", "random_online")
METHOD_LABELS = {"rl": "RL", "decictor": "Decictor-GA", "random_delta": "Random-delta", "random": "Random",
                 "random_online": "Random-online"}
PLACEMENTS = ("closest", "uniform")
GROUPS = ("seeds", "held_out", "all")
GROUP_LABELS = {"seeds": "seeds", "held_out": "held-out", "handwritten": "hand-written", "all": "all"}
KINDS = ("seed", "held_out", "handwritten")
HANDWRITTEN_PREFIX = "handwritten/"  #: specs of the hand-written group (configs/scenarios/handwritten)
# methods whose mutations are non-invasive by construction (validity target); Random is not
NON_INVASIVE = ("rl", "decictor", "random_delta", "random_online")
# (x, y, measure): RL against each baseline in distinct root causes (the headline) and in raw
# failures; the paper's ordering steps on NoDS
COMPARISONS: tuple[tuple[str, str, str], ...] = (
    ("rl", "decictor", "root_causes"), ("rl", "random_online", "root_causes"), ("rl", "random_delta", "root_causes"),
    ("rl", "random", "root_causes"), ("decictor", "random_online", "root_causes"),
    ("rl", "decictor", "failures"), ("rl", "random_delta", "failures"), ("rl", "random", "failures"),
    ("rl", "random_online", "failures"), ("decictor", "random_delta", "nods"), ("random_delta", "random", "nods"))
# per-repeat measures, in table order
MEASURES = ("root_causes", "root_causes_in_lane", "failures", "nods", "collisions", "nods_local", "task_failures",
            "unconfirmed", "validity", "distinct", "simulated", "sims", "seconds_per_scenario", "cpu_seconds",
            "distinct_per_cpu_hour", "metric_score", "oracle_findings", "oracle_root_causes")
# the driving-quality metric oracles a record's metric_violations may name (deft_gym.metrics.oracle);
# each gets a measure viol_<name>: the share of simulated scenarios that violated it
METRIC_VIOLATIONS = ("collision", "ttc", "drivable_area", "direction", "red_light", "comfort", "speed_limit",
                     "standstill", "headway")
MEASURES = MEASURES + tuple(f"viol_{v}" for v in METRIC_VIOLATIONS)
# the metric oracles an evaluation may count beside the aimed one (count_oracles; the metric
# oracles but score, deft_gym.metrics.oracle.COUNTED_ORACLES): found_<name> is the distinct
# (scenario, signature) pairs of its confirmed findings; any_distinct the same over every oracle,
# the decision oracle's counted failures included
FOUND_ORACLES = ("collision", "ttc", "drivable_area", "direction", "red_light", "progress", "comfort",
                 "speed_limit", "standstill", "headway")
#: the metric oracles whose findings were judged genuine when drawn (near misses, leaving the road;
#: docs/search.md v13-v14): safety_distinct is the decision oracle's distinct failures and theirs
SAFETY_ORACLES = ("ttc", "drivable_area")
MEASURES = (*MEASURES, "any_distinct", "safety_distinct", *tuple(f"found_{o}" for o in FOUND_ORACLES))
# a root cause whose trigger stood inside the ego's own lane (< 0.75 m from the optimal path): the
# headline leaves it out (docs/search.md, "What counts"), the in_lane column counts it too
IN_LANE = "in_lane"
# targets of issue 17
TARGET_REPEATS, TARGET_HELD_OUT, TARGET_A12, TARGET_RATIO, TARGET_P, TARGET_VALIDITY = 5, 10, 0.6, 1.5, 0.05, 0.99
TARGET_MECHANISMS, TARGET_DOMINANCE = 5, 0.5  # issue 31: mechanisms found in all; no mechanism above this share


class RecordError(ValueError):
    """An evaluation record is malformed; the message names the source, the record and the field."""


# -- records --------------------------------------------------------------------------------------
def kind_of_name(scenario: str) -> str:
    """The kind of a scenario spec: ``held_out`` for a generated spec (``gen:<seed>``) or a
    perturbed variant (``<seed>~v<n>``), ``handwritten`` for ``handwritten/<name>``, ``seed``
    otherwise."""
    if scenario.startswith("gen:") or "~v" in scenario:
        return "held_out"
    return "handwritten" if scenario.startswith(HANDWRITTEN_PREFIX) else "seed"


def shown_groups(summary: dict[str, Any]) -> list[str]:
    """The groups a report shows: :data:`GROUPS`, with ``handwritten`` before ``all`` when the
    summary has hand-written scenarios."""
    return ["seeds", "held_out", "handwritten", "all"] if summary.get("handwritten") else list(GROUPS)


def _kind_of(scenario: str, kinds: dict[str, str]) -> str:
    """The kind ``kinds`` gives ``scenario``; else :func:`kind_of_name`."""
    if scenario in kinds:
        return kinds[scenario]
    return kind_of_name(scenario)


def _field(rec: dict[str, Any], key: str, where: str, types: tuple[type, ...], default: Any = ...,
           choices: Sequence[Any] | None = None, missing: dict[str, int] | None = None) -> Any:
    """``rec[key]`` checked against ``types`` (bool is not a number) and ``choices``."""
    if key not in rec:
        if default is ...:
            raise RecordError(f"{where}: field '{key}' is missing")
        if missing is not None:
            missing[key] = missing.get(key, 0) + 1
        return default
    val = rec[key]
    number = any(t in (int, float) for t in types)
    if (isinstance(val, bool) and bool not in types) or not isinstance(val, types):
        names = "/".join("null" if t is type(None) else t.__name__ for t in types)
        raise RecordError(f"{where}: field '{key}': expected {names}, got {val!r}")
    if choices is not None and val not in choices:
        raise RecordError(f"{where}: field '{key}': expected one of {list(choices)}, got {val!r}")
    if number and not (math.isfinite(val) and val >= 0):
        raise RecordError(f"{where}: field '{key}': expected a finite number >= 0, got {val!r}")
    return val


def normalize(records: Iterable[dict[str, Any]], source: str = "records",
              kinds: dict[str, str] | None = None) -> tuple[list[dict[str, Any]], dict[str, int]]:
    """Checked copies of ``records`` holding the schema's fields (absent optional fields filled:
    ``placement`` "closest", ``scenario_kind`` from ``kinds`` (scenario -> kind) or the name,
    ``confirmed`` None, ...) and how many records lacked each optional field. Raises
    :class:`RecordError` naming ``source``, the record (1-based) and the field."""
    kinds = kinds or {}
    out: list[dict[str, Any]] = []
    missing: dict[str, int] = {}
    for i, rec in enumerate(records):
        where = f"{source}: record {i + 1}"
        if not isinstance(rec, dict):
            raise RecordError(f"{where}: expected an object, got {type(rec).__name__}")
        scn = _field(rec, "scenario", where, (str,))
        r = {"method": _field(rec, "method", where, (str,)), "scenario": scn,
             "repeat": _field(rec, "repeat", where, (int,)), "index": _field(rec, "index", where, (int,)),
             "valid": _field(rec, "valid", where, (bool,)),
             "failure": _field(rec, "failure", where, (str, type(None)), None, ("nods", "collision", None), missing),
             "placement": _field(rec, "placement", where, (str,), "closest", None, missing),
             "scenario_kind": _field(rec, "scenario_kind", where, (str,), _kind_of(scn, kinds), KINDS, missing),
             "nods_local": _field(rec, "nods_local", where, (bool,), False, None, missing),
             "task_failure": _field(rec, "task_failure", where, (str, type(None)), None, ("timeout", "stuck", None),
                                    missing),
             "confirmed": _field(rec, "confirmed", where, (bool, type(None)), None, None, missing),
             "signature": _field(rec, "signature", where, (str, type(None)), "", None, missing) or "",
             "band": _field(rec, "band", where, (str, type(None)), None, None, missing) or "-",
             "mechanism": _field(rec, "mechanism", where, (str, type(None)), None, None, missing) or "other",
             "seconds": _field(rec, "seconds", where, (int, float), None, None, missing),
             "cpu_seconds": _field(rec, "cpu_seconds", where, (int, float), None, None, missing),
             "sims": _field(rec, "sims", where, (int,), 1, None, missing),
             # driving-quality metrics (docs/metrics.md); records from before them lack these (the
             # driving-quality table is left out then, not reported as missing)
             "metric_score": _field(rec, "metric_score", where, (int, float, type(None)), None, None),
             "metric_violations": _field(rec, "metric_violations", where, (list, type(None)), None, None),
             # only with a metric oracle (oracle: in the config): not missing without one
             "oracle_signature": _field(rec, "oracle_signature", where, (str, type(None)), None, None),
             "oracle_confirmed": _field(rec, "oracle_confirmed", where, (bool, type(None)), None, None),
             # only with count_oracles: {oracle: signature} found, {oracle: reproduced}
             "found_by_oracle": _field(rec, "found_by_oracle", where, (dict, type(None)), None, None) or {},
             "confirmed_by_oracle": _field(rec, "confirmed_by_oracle", where, (dict, type(None)), None, None) or {}}
        if isinstance(rec.get("scenario_equivalent"), dict):
            r["scenario_equivalent"] = rec["scenario_equivalent"]
        out.append(r)
    return out, missing


def counted_failure(rec: dict[str, Any]) -> str | None:
    """``"nods"`` or ``"collision"`` when the record's failure counts (valid and confirmed), else None."""
    return rec["failure"] if rec["failure"] and rec["valid"] and rec["confirmed"] is True else None


#: counted oracles whose findings ``any_distinct`` leaves to the decision oracle: a counted
#: collision is its already (the same fault analysis)
DECISION_ORACLES_OWN = frozenset({"collision"})


def counted_findings(rec: dict[str, Any]) -> list[tuple[str | None, str]]:
    """A record's counted findings as ``(oracle, signature)``: the decision oracle's counted failure
    (oracle None; one without a signature named by its kind) and, on a valid record, each counted
    metric oracle's confirmed finding (``found_by_oracle``, ``confirmed_by_oracle``)."""
    kind = counted_failure(rec)
    out: list[tuple[str | None, str]] = [(None, rec["signature"] or f"<unsigned {kind}>")] if kind else []
    if rec["valid"]:
        out += [(o, sig) for o, sig in rec["found_by_oracle"].items() if rec["confirmed_by_oracle"].get(o) is True]
    return out


# -- per-repeat tallies ---------------------------------------------------------------------------
@dataclass
class Tally:
    """What one repeat of one cell found: counts, time [s], distinct (scenario, root cause) pairs
    and the distinct root causes (kind, trigger, band, mechanism) of counted failures, with and
    without the in-lane band."""

    counts: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    seconds: float | None = 0.0
    cpu_seconds: float | None = 0.0
    signatures: set[tuple[str, str]] = field(default_factory=set)
    causes: set[str] = field(default_factory=set)
    causes_in_lane: set[str] = field(default_factory=set)
    scores: list[float] = field(default_factory=list)  # metric_score of the records that have one
    oracle_causes: set[str] = field(default_factory=set)  # signatures of counted metric-oracle findings
    # (scenario, signature) of confirmed findings per counted oracle (count_oracles)
    found: dict[str, set[tuple[str, str]]] = field(default_factory=lambda: defaultdict(set))

    def add(self, r: dict[str, Any]) -> None:
        c = self.counts
        if r.get("metric_score") is not None:
            self.scores.append(float(r["metric_score"]))
            for v in r.get("metric_violations") or ():
                c[f"viol_{v}"] += 1
        if r.get("oracle_signature") and r["valid"] and r.get("oracle_confirmed") is True:
            c["oracle_findings"] += 1
            self.oracle_causes.add(r["oracle_signature"])
        for o, sig in counted_findings(r):
            if o is None:
                self.signatures.add((r["scenario"], sig))
                (self.causes_in_lane if r["band"] == IN_LANE else self.causes).add(sig)
            else:
                self.found[o].add((r["scenario"], sig))
        kind = counted_failure(r)
        c["simulated"] += 1
        c["sims"] += r["sims"]
        c["valid"] += int(r["valid"])
        if kind:
            c["failures"] += 1
            c["nods" if kind == "nods" else "collisions"] += 1
        elif r["failure"] and r["valid"]:
            c["unconfirmed"] += 1
        c["nods_local"] += int(bool(r["nods_local"] and r["valid"]))
        c["task_failures"] += int(bool(counted_task_failure(r)))
        self.seconds = None if self.seconds is None or r["seconds"] is None else self.seconds + r["seconds"]
        self.cpu_seconds = (None if self.cpu_seconds is None or r["cpu_seconds"] is None
                            else self.cpu_seconds + r["cpu_seconds"])

    def merge(self, other: Tally) -> None:
        for k, v in other.counts.items():
            self.counts[k] += v
        self.seconds = None if self.seconds is None or other.seconds is None else self.seconds + other.seconds
        self.cpu_seconds = (None if self.cpu_seconds is None or other.cpu_seconds is None
                            else self.cpu_seconds + other.cpu_seconds)
        self.signatures |= other.signatures
        self.causes |= other.causes
        self.causes_in_lane |= other.causes_in_lane
        self.scores += other.scores
        self.oracle_causes |= other.oracle_causes
        for o, pairs in other.found.items():
            self.found[o] |= pairs

    def measures(self) -> dict[str, float | None]:
        """The per-repeat values of :data:`MEASURES` (validity a share, times in s, rates per CPU-hour)."""
        c, n = self.counts, self.counts["simulated"]
        distinct = len(self.signatures)
        cpu = self.cpu_seconds
        return {**{k: float(c[k]) for k in ("failures", "nods", "collisions", "nods_local", "task_failures",
                                              "unconfirmed", "simulated", "sims")},
                "root_causes": float(len(self.causes)),
                "root_causes_in_lane": float(len(self.causes | self.causes_in_lane)),
                "validity": c["valid"] / n if n else None, "distinct": float(distinct),
                "seconds_per_scenario": self.seconds / n if n and self.seconds is not None else None,
                "cpu_seconds": cpu, "distinct_per_cpu_hour": distinct / (cpu / 3600.0) if cpu else None,
                "metric_score": float(np.mean(self.scores)) if self.scores else None,
                "oracle_findings": float(c["oracle_findings"]), "oracle_root_causes": float(len(self.oracle_causes)),
                "any_distinct": float(len(self.signatures.union(
                    *(v for o, v in self.found.items() if o not in DECISION_ORACLES_OWN)))),
                "safety_distinct": float(len(self.signatures.union(*(self.found.get(o, set()) for o in SAFETY_ORACLES)))),
                **{f"found_{o}": float(len(self.found.get(o, ()))) for o in FOUND_ORACLES},
                **{f"viol_{v}": c[f"viol_{v}"] / len(self.scores) if self.scores else None for v in METRIC_VIOLATIONS}}


def describe(values: Sequence[float | None]) -> dict[str, Any]:
    """Mean and sample sd (ddof 1; None with fewer than two values) of the values that are not None."""
    xs = [float(v) for v in values if v is not None]
    mean = float(np.mean(xs)) if xs else None
    sd = float(np.std(xs, ddof=1)) if len(xs) >= 2 else None
    return {"mean": _r(mean), "sd": _r(sd), "n": len(xs), "values": [_r(v) for v in values]}


def _r(x: float | None, nd: int = 6) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), nd)


def _cell(tallies: dict[int, Tally]) -> dict[str, Any]:
    reps = sorted(tallies)
    per = [tallies[r].measures() for r in reps]
    return {"repeats": reps, **{m: describe([p[m] for p in per]) for m in MEASURES}}


# -- statistics -----------------------------------------------------------------------------------
def mann_whitney(x: Sequence[float], y: Sequence[float]) -> dict[str, float | None]:
    """Two-sided Mann-Whitney U of ``x`` against ``y`` (:func:`scipy.stats.mannwhitneyu`) and
    Vargha-Delaney A12 = P(X > Y) + 0.5 P(X = Y) = U_x / (n_x n_y); all None unless both samples
    hold at least two values."""
    if len(x) < 2 or len(y) < 2:
        return {"u": None, "p": None, "a12": None}
    from scipy import stats as sps  # here: importing scipy.stats takes 0.5 s (eval-report --help)

    res = sps.mannwhitneyu(x, y, alternative="two-sided")
    u = float(res.statistic)
    p = float(res.pvalue)
    return {"u": _r(u), "p": p if math.isfinite(p) else None, "a12": _r(u / (len(x) * len(y)))}


def compare(x: str, y: str, measure: str, cx: dict[str, Any] | None, cy: dict[str, Any] | None,
            **where: Any) -> dict[str, Any]:
    """One comparison row: means, the ratio mean_x / mean_y (None, with a note, when mean_y is 0),
    U, p and A12 on the per-repeat values of ``measure`` in cells ``cx`` and ``cy``."""
    vx = [v for v in (cx or {}).get(measure, {}).get("values", []) if v is not None]
    vy = [v for v in (cy or {}).get(measure, {}).get("values", []) if v is not None]
    mx = float(np.mean(vx)) if vx else None
    my = float(np.mean(vy)) if vy else None
    row: dict[str, Any] = {"x": x, "y": y, "measure": measure, **where, "n_x": len(vx), "n_y": len(vy),
                           "mean_x": _r(mx), "mean_y": _r(my), "ratio": None, "note": ""}
    if mx is None or my is None:
        row["note"] = "no data for " + " and ".join(m for m, v in ((x, vx), (y, vy)) if not v)
    elif my == 0:
        row["note"] = f"ratio undefined: {METHOD_LABELS.get(y, y)} mean is 0"
    else:
        row["ratio"] = _r(mx / my, 4)
    row.update(mann_whitney(vx, vy))
    if row["p"] is None and vx and vy:
        row["note"] = "; ".join(n for n in (row["note"], "no test: fewer than 2 repeats") if n)
    return row


# -- the summary ----------------------------------------------------------------------------------
def _ordered(found: Iterable[str], expected: Sequence[str] | None, order: Sequence[str]) -> list[str]:
    found = set(found)
    first = list(expected) if expected else [m for m in order if m in found]
    return first + sorted(found - set(first), key=lambda m: (order.index(m) if m in order else len(order), m))


def summarize(records: Iterable[dict[str, Any]], methods: Sequence[str] | None = None,
              placements: Sequence[str] | None = None, seeds: Sequence[str] = (), held_out: Sequence[str] = (),
              source: str = "records", handwritten: Sequence[str] = ()) -> dict[str, Any]:
    """The comparison from the records: ``per_scenario[method][placement][scenario]`` and
    ``groups[method][placement][group]`` (each measure: mean, sd, n and the per-repeat values;
    cells without records are absent), ``statistics`` (per group and per scenario), ``targets``
    (:func:`check_targets`), the scenario lists and kinds, and the optional fields records lacked."""
    kinds: dict[str, str] = ({s: "seed" for s in seeds} | {s: "held_out" for s in held_out}
                             | {s: "handwritten" for s in handwritten})
    rows, missing = normalize(records, source, kinds)
    for r in rows:
        if kinds.setdefault(r["scenario"], r["scenario_kind"]) != r["scenario_kind"]:
            raise RecordError(f"{source}: scenario '{r['scenario']}': field 'scenario_kind' is "
                              f"{r['scenario_kind']!r} in one record and {kinds[r['scenario']]!r} in another "
                              "record or the configured lists")
    seed_list = list(seeds) + sorted({s for s, k in kinds.items() if k == "seed"} - set(seeds))
    held_list = list(held_out) + sorted({s for s, k in kinds.items() if k == "held_out"} - set(held_out))
    hand_list = list(handwritten) + sorted({s for s, k in kinds.items() if k == "handwritten"} - set(handwritten))
    members = {"seeds": seed_list, "held_out": held_list, "all": seed_list + held_list + hand_list}
    if hand_list:  # a group of its own, shown only when there are hand-written scenarios
        members = {"seeds": seed_list, "held_out": held_list, "handwritten": hand_list, "all": members["all"]}
    methods = _ordered((r["method"] for r in rows), methods, METHOD_ORDER)
    placements = _ordered((r["placement"] for r in rows), placements, PLACEMENTS)

    tallies: dict[tuple[str, str, str], dict[int, Tally]] = defaultdict(lambda: defaultdict(Tally))
    for r in rows:
        tallies[(r["method"], r["placement"], r["scenario"])][r["repeat"]].add(r)
    per: dict[str, dict[str, dict[str, Any]]] = {}
    groups: dict[str, dict[str, dict[str, Any]]] = {}
    for m in methods:
        for p in placements:
            cells = {s: tallies[(m, p, s)] for s in members["all"] if (m, p, s) in tallies}
            if cells:
                per.setdefault(m, {})[p] = {s: {"kind": kinds[s], **_cell(t)} for s, t in cells.items()}
            for g, names in members.items():
                have = [s for s in names if s in cells]
                if not have:
                    continue
                reps = set.intersection(*(set(cells[s]) for s in have))  # repeats every scenario has
                everyone = set.union(*(set(cells[s]) for s in have))
                total: dict[int, Tally] = {}
                for rep in sorted(reps):
                    total[rep] = Tally()
                    for s in have:
                        total[rep].merge(cells[s][rep])
                missing_scn = [s for s in names if s not in cells]
                groups.setdefault(m, {}).setdefault(p, {})[g] = {
                    "scenarios": have, "missing_scenarios": missing_scn, "dropped_repeats": sorted(everyone - reps),
                    "complete": not missing_scn and everyone == reps, **_cell(total)}
    summary: dict[str, Any] = {"methods": methods, "placements": placements, "seeds": seed_list,
                               "held_out": held_list, "handwritten": hand_list, "scenario_kinds": kinds, "per_scenario": per,
                               "groups": groups, "missing_fields": missing, "records": len(rows),
                               "findings": findings(rows, methods, placements)}
    summary["statistics"] = statistics(summary)
    summary["targets"] = check_targets(summary)
    return summary


def counted_task_failure(rec: dict[str, Any]) -> str | None:
    """``"timeout"`` or ``"stuck"`` when the record's task failure counts (valid and confirmed)."""
    return rec["task_failure"] if rec["task_failure"] and rec["valid"] and rec["confirmed"] is True else None


def findings(rows: list[dict[str, Any]], methods: Sequence[str], placements: Sequence[str]) -> dict[str, Any]:
    """The counted failures by root cause and by mechanism: ``root_causes[method][placement]`` ->
    root cause -> ``{failures, repeats, scenarios, band, mechanism}`` (failures summed over the
    repeats, repeats and scenarios it was found in), ``mechanisms[method][placement]`` ->
    mechanism -> failures, and the same over ``all`` methods (identical scenarios found by several
    methods counted once: the same scenario, participants and root cause); ``task_root_causes``:
    the counted task failures (timeout, stuck) the same way."""
    out: dict[str, Any] = {"root_causes": {}, "mechanisms": {}, "task_root_causes": {}}
    seen: set[tuple[str, str, str]] = set()
    for r in rows:
        if counted_failure(r):
            where = "root_causes"
        elif counted_task_failure(r):
            where = "task_root_causes"
        else:
            continue
        sig = r["signature"] or "<unsigned>"
        for m in (r["method"], "all"):
            if m == "all":
                key = (r["scenario"], json_key(r.get("scenario_equivalent") or {"method": r["method"], "index": r["index"],
                                                                               "repeat": r["repeat"]}), sig)
                if key in seen:
                    continue
                seen.add(key)
            cell = out[where].setdefault(m, {}).setdefault(r["placement"], {}).setdefault(
                sig, {"failures": 0, "repeats": set(), "scenarios": set(), "band": r["band"], "mechanism": r["mechanism"]})
            cell["failures"] += 1
            cell["repeats"].add(r["repeat"])
            cell["scenarios"].add(r["scenario"])
            if where == "root_causes":
                mc = out["mechanisms"].setdefault(m, {}).setdefault(r["placement"], {})
                mc[r["mechanism"]] = mc.get(r["mechanism"], 0) + 1
    for key in ("root_causes", "task_root_causes"):
        for ps in out[key].values():
            for cs in ps.values():
                for c in cs.values():
                    c["repeats"], c["scenarios"] = len(c["repeats"]), sorted(c["scenarios"])
    return out


def json_key(x: Any) -> str:
    """A canonical string of a JSON-like value (for de-duplicating identical scenarios)."""
    import json

    return json.dumps(x, sort_keys=True, default=str)


def _get(tree: dict[str, Any], *keys: str) -> Any:
    for k in keys:
        if not isinstance(tree, dict) or k not in tree:
            return None
        tree = tree[k]
    return tree


def statistics(summary: dict[str, Any]) -> dict[str, list[dict[str, Any]]]:
    """:data:`COMPARISONS` for every placement on the per-repeat group totals (``groups``) and on
    each scenario both methods ran (``per_scenario``)."""
    out: dict[str, list[dict[str, Any]]] = {"groups": [], "per_scenario": []}
    present = set(summary["methods"])
    for p in summary["placements"]:
        for x, y, measure in COMPARISONS:
            if x not in present or y not in present:
                continue
            for g in shown_groups(summary):
                cx, cy = _get(summary["groups"], x, p, g), _get(summary["groups"], y, p, g)
                if cx or cy:
                    out["groups"].append(compare(x, y, measure, cx, cy, placement=p, group=g))
            for s in summary["seeds"] + summary["held_out"] + summary.get("handwritten", []):
                cx, cy = _get(summary["per_scenario"], x, p, s), _get(summary["per_scenario"], y, p, s)
                if cx and cy:
                    out["per_scenario"].append(compare(x, y, measure, cx, cy, placement=p, scenario=s))
    return out


def find_comparison(summary: dict[str, Any], x: str, y: str, placement: str, group: str,
                    measure: str | None = None) -> dict[str, Any] | None:
    """The group-level statistics row of ``x`` against ``y`` (on ``measure``, else the first), if
    computed."""
    for row in summary["statistics"]["groups"]:
        if (row["x"], row["y"], row["placement"], row["group"]) == (x, y, placement, group) and \
                measure in (None, row["measure"]):
            return row
    return None


# -- targets --------------------------------------------------------------------------------------
def check_targets(summary: dict[str, Any], group: str = "all") -> dict[str, Any]:
    """Issue 17's targets, computed on ``group`` for every placement with records: the protocol
    (>= 5 repeats, >= 10 held-out scenarios, equal budget), GA > Random-delta > Random in NoDS with
    A12 >= 0.6 per step, RL >= 1.5x GA in failures with p < 0.05, validity >= 99 % for the
    non-invasive methods, and a counted failure on every seed (by any method, and by RL). Each
    entry: ``met`` and the numbers."""
    groups, per = summary["groups"], summary["per_scenario"]
    placements = [p for p in summary["placements"] if any(p in groups.get(m, {}) for m in groups)]
    t: dict[str, Any] = {"group": group, "placements": placements}

    cells = [(m, p, s, c) for m, ps in per.items() for p, ss in ps.items() for s, c in ss.items()]
    reps = [len(c["repeats"]) for *_, c in cells]
    budgets = sorted({c["simulated"]["mean"] for *_, c in cells})
    t["protocol"] = {"met": bool(cells) and min(reps) >= TARGET_REPEATS and len(summary["held_out"]) >= TARGET_HELD_OUT
                     and len(budgets) == 1,
                     "repeats_min": min(reps) if reps else 0, "repeats_required": TARGET_REPEATS,
                     "held_out_scenarios": len(summary["held_out"]), "held_out_required": TARGET_HELD_OUT,
                     "budgets": budgets, "equal_budget": len(budgets) == 1}

    order: dict[str, Any] = {}
    for p in placements:
        steps = []
        for x, y in (("decictor", "random_delta"), ("random_delta", "random")):
            row = find_comparison(summary, x, y, p, group, "nods") or {}
            mx, my, a12 = row.get("mean_x"), row.get("mean_y"), row.get("a12")
            met = None not in (mx, my, a12) and mx > my and a12 >= TARGET_A12
            steps.append({"x": x, "y": y, "mean_x": mx, "mean_y": my, "a12": a12, "p": row.get("p"), "met": met})
        order[p] = {"met": all(s["met"] for s in steps), "steps": steps}
    t["nods_ordering"] = {"met": bool(order) and all(v["met"] for v in order.values()), "measure": "nods",
                          "a12_required": TARGET_A12, "per_placement": order}

    rl_ga: dict[str, Any] = {}
    for p in placements:
        row = find_comparison(summary, "rl", "decictor", p, group, "failures") or {}
        mx, my, pv = row.get("mean_x"), row.get("mean_y"), row.get("p")
        met = None not in (mx, my, pv) and mx > my and mx >= TARGET_RATIO * my and pv < TARGET_P
        rl_ga[p] = {"met": met, "mean_rl": mx, "mean_ga": my, "ratio": row.get("ratio"), "p": pv,
                    "a12": row.get("a12"), "note": row.get("note", "no data")}
    t["rl_vs_ga"] = {"met": bool(rl_ga) and all(v["met"] for v in rl_ga.values()), "measure": "failures",
                     "ratio_required": TARGET_RATIO, "p_required": TARGET_P, "per_placement": rl_ga}

    val: dict[str, dict[str, float | None]] = {}
    for m in summary["methods"]:
        if m in NON_INVASIVE:
            for p in placements:
                v = _get(groups, m, p, group, "validity", "mean")
                if v is not None:
                    val.setdefault(m, {})[p] = v
    t["validity"] = {"met": bool(val) and all(v >= TARGET_VALIDITY for ps in val.values() for v in ps.values()),
                     "required": TARGET_VALIDITY, "methods": val,
                     "not_required": [m for m in summary["methods"] if m not in NON_INVASIVE]}

    found: dict[str, dict[str, int]] = {}
    for s in summary["seeds"]:
        found[s] = {"any": 0, "rl": 0}
        for m, ps in per.items():
            n = sum(int(sum(v or 0 for v in ss[s]["failures"]["values"])) for ss in ps.values() if s in ss)
            found[s]["any"] += n
            if m == "rl":
                found[s]["rl"] += n
    no_any = [s for s, f in found.items() if not f["any"]]
    no_rl = [s for s, f in found.items() if not f["rl"]]
    t["failure_on_every_seed"] = {"met": bool(found) and not no_any and not no_rl,
                                  "any_method": {"met": bool(found) and not no_any, "without": no_any},
                                  "rl": {"met": bool(found) and not no_rl, "without": no_rl},
                                  "per_seed": found}
    # issue 31: distinct root causes are the headline
    rc: dict[str, Any] = {}
    for p in placements:
        rows = {}
        for y in ("decictor", "random_online"):
            row = find_comparison(summary, "rl", y, p, group, "root_causes") or {}
            mx, my, pv = row.get("mean_x"), row.get("mean_y"), row.get("p")
            met = None not in (mx, my, pv) and mx > my and mx >= TARGET_RATIO * my and pv < TARGET_P
            rows[y] = {"met": met, "mean_rl": mx, "mean_other": my, "ratio": row.get("ratio"), "p": pv,
                       "a12": row.get("a12"), "note": row.get("note", "no data")}
        rc[p] = rows
    t["rl_root_causes"] = {"met": bool(rc) and all(v["met"] for r in rc.values() for v in r.values()),
                           "measure": "root_causes", "ratio_required": TARGET_RATIO, "p_required": TARGET_P,
                           "per_placement": rc}
    mech_all: dict[str, int] = {}
    for ps in summary.get("findings", {}).get("mechanisms", {}).get("all", {}).values():
        for k, v in ps.items():
            mech_all[k] = mech_all.get(k, 0) + v
    t["mechanisms"] = {"met": len(mech_all) >= TARGET_MECHANISMS, "required": TARGET_MECHANISMS,
                       "found": dict(sorted(mech_all.items(), key=lambda kv: -kv[1]))}
    dom: dict[str, dict[str, Any]] = {}
    for m, ps in summary.get("findings", {}).get("mechanisms", {}).items():
        if m == "all":
            continue
        for p, counts in ps.items():
            total = sum(counts.values())
            top = max(counts.items(), key=lambda kv: (kv[1], kv[0]))
            dom.setdefault(m, {})[p] = {"mechanism": top[0], "share": _r(top[1] / total, 4), "failures": total,
                                        "dominates": top[1] / total > TARGET_DOMINANCE}
    t["dominance"] = {"met": not any(v["dominates"] for ps in dom.values() for v in ps.values()),
                      "limit": TARGET_DOMINANCE, "per_method": dom}
    t["met_17"] = all(t[k]["met"] for k in ("protocol", "nods_ordering", "rl_vs_ga", "validity",
                                            "failure_on_every_seed"))
    t["met"] = t["met_17"] and all(t[k]["met"] for k in ("rl_root_causes", "mechanisms", "dominance"))
    return t


# -- curves ---------------------------------------------------------------------------------------
def cumulative_curves(records: Iterable[dict[str, Any]], summary: dict[str, Any],
                      confidence: float = 0.95) -> dict[str, dict[str, dict[str, dict[str, Any]]]]:
    """``[placement][group][method]``: cumulative counted failures against the simulated
    scenarios of each scenario (x = 1..budget), summed over the group's scenarios, mean over the
    repeats in the group's totals with a Student-t confidence band (``lo`` clipped at 0; ``lo``/``hi``
    None with one repeat)."""
    rows, _ = normalize(records, "records", summary["scenario_kinds"])
    hits: dict[tuple[str, str, str, int], list[int]] = defaultdict(list)
    for r in rows:
        if counted_failure(r):
            hits[(r["method"], r["placement"], r["scenario"], r["repeat"])].append(r["index"])
    budget = 1 + max((r["index"] for r in rows), default=-1)
    x = np.arange(1, budget + 1)
    out: dict[str, dict[str, dict[str, dict[str, Any]]]] = {}
    for m, ps in summary["groups"].items():
        for p, gs in ps.items():
            for g, cell in gs.items():
                curves = []
                for rep in cell["repeats"]:
                    per_index = np.zeros(budget)
                    for s in cell["scenarios"]:
                        np.add.at(per_index, hits.get((m, p, s, rep), []), 1)
                    curves.append(np.cumsum(per_index))
                if not curves:
                    continue
                arr = np.array(curves)
                mean = arr.mean(axis=0)
                lo = hi = None
                if len(curves) >= 2:
                    from scipy import stats as sps

                    half = sps.t.ppf(0.5 + confidence / 2, len(curves) - 1) * arr.std(axis=0, ddof=1) / math.sqrt(len(curves))
                    lo, hi = np.maximum(mean - half, 0.0).tolist(), (mean + half).tolist()
                out.setdefault(p, {}).setdefault(g, {})[m] = {"x": x.tolist(), "mean": mean.tolist(), "lo": lo,
                                                              "hi": hi, "n": len(curves)}
    return out
