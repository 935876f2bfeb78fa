"""The evaluation report: tables (markdown), results (JSON) and plots from the evaluation records.

Kept apart from :mod:`deft_gym.experiments.extract_eval` (which runs things) so a report can be re-rendered
from the records of a finished run.
"""

from __future__ import annotations

import json
import math
import statistics
from collections import defaultdict
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from deft_gym.files import atomic_path, write_atomic
from extract.runtime import read_header


class RecordFile(Protocol):
    """An append-only record file read back as rows."""

    rows: list[dict[str, Any]]


class Evaluation(Protocol):
    """What the report reads of a finished evaluation (:class:`deft_gym.experiments.extract_eval.Evaluation`):
    its arguments, output folder and record files. A protocol, so this module never imports the
    one that runs things."""

    args: Any
    out: Path
    s0: RecordFile
    reruns: RecordFile
    rounds: RecordFile
    full: RecordFile
    replays: RecordFile

    def deft_dir(self, mode: str, name: str) -> Path: ...


RQ1_THETAS = (0.0, 0.1, 0.23, 1.62, 6.99, 17.15)


def _pct(a: float, b: float) -> str:
    return f"{100.0 * a / b:.1f} %" if b else "-"


def _f(x: float | None, nd: int = 2) -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{nd}f}"


def _cases_for(rec: dict[str, Any], stem: str) -> list[dict[str, Any]]:
    """The test cases of one generated module (its functions are ``<stem>_reproduces`` and
    ``<stem>_does_not_plan_into_collision``; other modes' modules extend the stem)."""
    return [c for c in rec["cases"]
            if c["name"].startswith((f"{stem}_reproduces[", f"{stem}_does_not_plan_into_collision["))]


def collect(ev: Evaluation, names: set[str], cold: float) -> dict[str, Any]:
    """Everything the report shows, computed from the records and extraction outputs."""
    modes = list(ev.args.modes)
    s0 = {r["name"]: r for r in ev.s0.rows if r["name"] in names}
    reruns: dict[str, dict[int, dict[str, Any]]] = defaultdict(dict)
    for r in ev.reruns.rows:
        if r["name"] in s0:
            reruns[r["name"]][r["k"]] = r
    ks = list(range(1, ev.args.reruns))
    summaries: dict[str, dict[str, dict[str, Any]]] = {m: {} for m in modes}
    distances: dict[str, dict[str, list[float]]] = {m: {} for m in modes}
    for m in modes:
        for name in s0:
            p = ev.deft_dir(m, name) / "summary.json"
            if p.exists():
                summaries[m][name] = json.loads(p.read_text())
                h = read_header(ev.deft_dir(m, name) / "frames.jsonl")
                distances[m][name] = [math.inf if f["distance"] is None else f["distance"] for f in h["frames_index"]]

    # RQ1 ------------------------------------------------------------------------------------
    total_outputs = sum(r["outputs"] for r in s0.values())
    rq1_sys = {k: {f"{t:g}": sum(reruns[n][k]["within"][f"{t:g}"] for n in s0 if k in reruns[n]) for t in RQ1_THETAS}
               for k in ks}
    rq1_deft = {m: {f"{t:g}": sum(sum(1 for d in ds if d <= t) for ds in distances[m].values()) for t in RQ1_THETAS}
                for m in modes}
    deft_frames = {m: sum(len(ds) for ds in distances[m].values()) for m in modes}

    # RQ2 ------------------------------------------------------------------------------------
    coll = sorted(n for n, r in s0.items() if r["collision"])
    who = {n: s0[n]["collision"]["participant"] for n in coll}
    rq2_sys = {k: sum(1 for n in coll if k in reruns[n] and reruns[n][k]["collision"] == who[n]) for k in ks}
    rq2_sys_any = {k: sum(1 for n in coll if k in reruns[n] and reruns[n][k]["collision"]) for k in ks}
    all_reruns = sum(1 for n in coll if all(k in reruns[n] and reruns[n][k]["collision"] == who[n] for k in ks))
    merged: dict[int, dict[str, Any]] = {}
    for rec in ev.rounds.rows:  # a round may have been run in parts (scenarios added on resume)
        m = merged.setdefault(rec["round"], {"round": rec["round"], "cases": []})
        m["cases"] = m["cases"] + rec["cases"]
    rounds = [merged[k] for k in sorted(merged)]
    per_scn: dict[str, dict[str, Any]] = {m: {} for m in modes}
    for m in modes:
        for n in coll:
            s = summaries[m].get(n)
            if not s or not s.get("faulty_trajectory") or not s.get("test_path"):
                per_scn[m][n] = {"faulty": False, "failed": 0, "runs": len(rounds), "times": []}
                continue
            stem = Path(s["test_path"]).stem
            fails, times = 0, []
            for rec in rounds:
                cs = [c for c in _cases_for(rec, stem) if "does_not_plan_into_collision" in c["name"]]
                if cs and cs[0]["status"] == "failed":
                    fails += 1
                times += [c["time"] for c in cs]
            per_scn[m][n] = {"faulty": True, "failed": fails, "runs": len(rounds), "times": times}
    rq2_mod = {m: [sum(1 for n in coll if per_scn[m][n]["faulty"] and _round_failed(rec, summaries[m][n]))
                   for rec in rounds] for m in modes}

    # RQ3 ------------------------------------------------------------------------------------
    ms = {}
    for m in modes:
        ss = list(summaries[m].values())
        fr = sum(s["frames"] for s in ss) or 1
        ms[m] = {k: sum(s[k] * s["frames"] for s in ss) / fr for k in
                 ("ms_per_frame", "planner_ms_per_frame", "overhead_ms_per_frame")}
        ms[m]["overhead_max"] = max((s["overhead_ms_per_frame"] for s in ss), default=None)
        ms[m]["frames"] = fr
        ms[m]["truth_agreement"] = (sum((s["truth_agreement"] or 0) * s["frames"] for s in ss) / fr
                                    if all(s.get("truth_agreement") is not None for s in ss) else None)
    full = {"cases": [c for rec in ev.full.rows for c in rec["cases"]]} if ev.full.rows else None
    ttrf = []
    for n in coll:
        walls = [reruns[n][k]["wall"] for k in ks if k in reruns[n]]
        hits = [k for k in ks if k in reruns[n] and reruns[n][k]["collision"] == who[n]]
        K = hits[0] if hits else None
        sys_t = sum(reruns[n][k]["wall"] for k in ks if k in reruns[n] and (K is None or k <= K))
        sys_rt = sum(reruns[n][k].get("sim_time") or math.nan for k in ks if k in reruns[n] and (K is None or k <= K))
        row = {"name": n, "group": s0[n]["group"], "reruns_needed": K, "censored": K is None,
               "system_ttrf": sys_t, "system_ttrf_realtime": sys_rt,
               "system_rerun_mean": statistics.mean(walls) if walls else None,
               "collided_reruns": len(hits), "reruns": len(walls), "s0_wall": s0[n]["wall"]}
        for m in modes:
            p = per_scn[m][n]
            s = summaries[m].get(n, {})
            extraction = s.get("ms_per_frame", 0.0) * s.get("frames", 0) / 1000.0
            f = s.get("faulty_trajectory") or {}
            row[m] = {"failure_test_fails": f"{p['failed']}/{p['runs']}" if p["faulty"] else "no P_faulty",
                      "module_ttrf": statistics.mean(p["times"]) if p["times"] and p["failed"] == p["runs"] else None,
                      "extraction_s": extraction,
                      "replayed": (f"{f['index'] - f.get('replay_from', 0) + 1}/{f['index'] + 1}"
                                   + (" seeded" if f.get("seeded") else "") if f else None)}
        if full is not None and "heuristic" in summaries and n in summaries["heuristic"]:
            stem = Path(summaries["heuristic"][n]["test_path"]).stem
            row["module_suite_s"] = sum(c["time"] for c in _cases_for(full, stem))
        ttrf.append(row)
    ttrf_tot = {}
    for m in modes:
        ok = [r for r in ttrf if r[m]["module_ttrf"] is not None]
        sys_sum = sum(r["system_ttrf"] for r in ok)
        mod_sum = sum(r[m]["module_ttrf"] for r in ok)
        ext_sum = sum(r[m]["extraction_s"] for r in ok)
        rt_sum = sum(r["system_ttrf_realtime"] for r in ok)
        ttrf_tot[m] = {"scenarios": len(ok), "system_s": sys_sum, "module_s": mod_sum,
                       "reduction": 1 - mod_sum / sys_sum if sys_sum else None,
                       "system_realtime_s": rt_sum,
                       "reduction_realtime": 1 - mod_sum / rt_sum if rt_sum and math.isfinite(rt_sum) else None,
                       "module_with_extraction_s": mod_sum + ext_sum,
                       "reduction_with_extraction": 1 - (mod_sum + ext_sum) / sys_sum if sys_sum else None,
                       "system_cold_s": sys_sum + cold * sum(r["reruns_needed"] or r["reruns"] for r in ok),
                       "module_cold_s": mod_sum + cold * len(ok)}
        t = ttrf_tot[m]
        t["reduction_cold"] = 1 - t["module_cold_s"] / t["system_cold_s"] if t["system_cold_s"] else None
    replays = {m: {"frames": sum(r["frames"] for r in ev.replays.rows if r["mode"] == m),
                   "same": sum(r["same_distance"] for r in ev.replays.rows if r["mode"] == m)} for m in modes}
    # S0 logs that are not intact: extracted as far as they are, never counted as good silently
    damaged = {f"{m}/{n}": s["log_status"] for m in modes for n, s in sorted(summaries[m].items())
               if s.get("log_status", "complete") != "complete"}
    return {"modes": modes, "scenarios": len(s0), "collision_scenarios": len(coll), "outputs": total_outputs,
            "damaged_logs": damaged,
            "reruns": ev.args.reruns, "test_runs": ev.args.test_runs, "cold_start_s": cold,
            "rq1": {"thetas": list(RQ1_THETAS), "system": rq1_sys, "deft": rq1_deft, "deft_frames": deft_frames},
            "rq2": {"system_same": rq2_sys, "system_any": rq2_sys_any, "system_all_reruns": all_reruns,
                    "module": rq2_mod, "per_scenario": per_scn, "collided_with": who},
            "rq3": {"ms_per_frame": ms, "ttrf": ttrf, "ttrf_total": ttrf_tot},
            "replay_check": replays,
            "s0": list(s0.values())}


def _round_failed(rec: dict[str, Any], summary: dict[str, Any]) -> bool:
    stem = Path(summary["test_path"]).stem
    cs = [c for c in _cases_for(rec, stem) if "does_not_plan_into_collision" in c["name"]]
    return bool(cs) and cs[0]["status"] == "failed"


def write_report(ev: Evaluation, names: set[str], cold: float, elapsed: float,
                 provenance: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write ``report.md``, ``results.json`` and the plots; returns the results."""
    res = collect(ev, names, cold)
    res["elapsed_s"] = elapsed
    res["provenance"] = provenance or {}
    res["plots"] = _plots(res, ev.out)
    md, headline = _markdown(res)
    res["headline_text"] = headline
    write_atomic(ev.out / "report.md", md)
    write_atomic(ev.out / "results.json", json.dumps(res, indent=2, default=float))
    return res


def _markdown(r: dict[str, Any]) -> tuple[str, str]:
    modes, rq1, rq2, rq3 = r["modes"], r["rq1"], r["rq2"], r["rq3"]
    n_out = r["outputs"]
    L: list[str] = ["# DeFT on DeFT-Gym: evaluation", ""]
    L += [f"{r['scenarios']} scenarios (seed scenarios, perturbations and cut-ins), {r['collision_scenarios']} of "
          f"them collided in S0; {r['reruns']} system runs each (S0 + {r['reruns'] - 1} reruns), generated tests "
          f"executed {r['test_runs']} times. {n_out} planning outputs in the S0 logs. Run took {r['elapsed_s'] / 60:.1f} min.", ""]
    prov = r.get("provenance") or {}
    if prov.get("planner"):
        L += [f"Planner: `{prov['planner']}`, a copy of the default planner's source pinned at the start "
              f"(sha256 {str(prov.get('planner_sha256'))[:12]}...), used by every run, extraction and test. "
              f"Commit {str((prov.get('git') or {}).get('commit'))[:10]} plus uncommitted changes.", ""]
    # headline
    h = []
    for m in modes:
        d = rq1["deft"][m]
        h.append(f"{m}: {_pct(d['0'], rq1['deft_frames'][m])} of planning outputs reproduced at theta = 0")
    sys0 = [v["0"] for v in rq1["system"].values()]
    if sys0:
        h.append(f"system reruns: {_pct(statistics.mean(sys0), n_out)} at theta = 0 (mean over reruns)")
    damaged = r.get("damaged_logs") or {}
    if damaged:
        h.insert(0, f"**{len(damaged)} extraction(s) read a damaged S0 log** (their numbers count only the intact "
                    f"messages): " + "; ".join(f"{k}: {v}" for k, v in damaged.items()))
    L += ["## Headline", ""] + [f"- {x}" for x in h]
    ms = rq3["ms_per_frame"]
    for m in modes:
        L.append(f"- {m}: {ms[m]['ms_per_frame']:.2f} ms/frame = planner {ms[m]['planner_ms_per_frame']:.2f} + "
                 f"extraction and validation {ms[m]['overhead_ms_per_frame']:.2f} (worst episode "
                 f"{_f(ms[m]['overhead_max'])}); truth agreement {_f(100 * ms[m]['truth_agreement'] if ms[m]['truth_agreement'] is not None else None, 1)} %")
    tt = rq3["ttrf_total"]
    for m in modes:
        t = tt[m]
        if t["reduction"] is not None:
            rt = t.get("reduction_realtime")
            L.append(f"- TTRF ({m}, {t['scenarios']} collision scenarios): system reruns {t['system_s']:.1f} s vs module "
                     f"tests {t['module_s']:.1f} s: reduction {100 * t['reduction']:.1f} %; against system reruns "
                     f"in real time (as a real-time stack like Apollo runs them) {_f(100 * rt if rt is not None else None, 1)} %"
                     f" (with extraction {100 * t['reduction_with_extraction']:.1f} %, cold processes "
                     f"{100 * t['reduction_cold']:.1f} %)")
    per = rq2["per_scenario"]
    for m in modes:
        det = sum(1 for n in per[m] if per[m][n]["faulty"] and per[m][n]["failed"] == per[m][n]["runs"])
        L.append(f"- RQ2 ({m}): failure tests fail in {r['test_runs']}/{r['test_runs']} executions for {det} of "
                 f"{r['collision_scenarios']} collision scenarios; system reruns reproduce the same collision in all "
                 f"{r['reruns'] - 1} reruns for {rq2['system_all_reruns']}")
    headline = "\n".join(L[L.index("## Headline") + 2:])
    # RQ1
    L += ["", "## RQ1: planning outputs reproduced (Table 3 analogue)", "",
          "Share of the S0 planning outputs reproduced within theta [m]: by the module tests (extraction distance, "
          "confirmed by replaying every frames file through a fresh planner) and by each system rerun S_k "
          "(i-th output of S_k vs i-th of S0, lock-step Euclidean distance).", ""]
    th = [f"{t:g}" for t in rq1["thetas"]]
    L.append("| theta | " + " | ".join(f"DeFT {m}" for m in modes) + " | " +
             " | ".join(f"S{k}" for k in rq1["system"]) + " | S mean |")
    L.append("|---" * (2 + len(modes) + len(rq1["system"])) + "|")
    for t in th:
        sys_v = [rq1["system"][k][t] for k in rq1["system"]]
        L.append(f"| {t} | " + " | ".join(_pct(rq1["deft"][m][t], rq1["deft_frames"][m]) for m in modes) + " | "
                 + " | ".join(_pct(v, n_out) for v in sys_v) + f" | {_pct(statistics.mean(sys_v), n_out) if sys_v else '-'} |")
    rc = r["replay_check"]
    L += ["", "Replay check (frames files replayed through the runtime the tests use, distance identical to the "
          "extraction's): " + ", ".join(f"{m} {rc[m]['same']}/{rc[m]['frames']}" for m in modes), ""]
    L.append(f"![RQ1]({r['plots'].get('rq1', '')})")
    # RQ2
    L += ["", "## RQ2: collisions reproduced (Figure 7 analogue)", "",
          f"{r['collision_scenarios']} scenarios collided in S0. System rerun k reproduces a collision when it "
          "collides with the same participant; module-test execution k reproduces it when the failure test "
          "(oracle transformation, P_faulty) fails.", ""]
    n_idx = max(len(rq2["system_same"]), max((len(v) for v in rq2["module"].values()), default=0))
    L.append("| run | system rerun (same participant) | system rerun (any collision) | " +
             " | ".join(f"module tests {m}" for m in modes) + " |")
    L.append("|---" * (3 + len(modes)) + "|")
    for k in range(1, n_idx + 1):
        L.append(f"| {k} | {rq2['system_same'].get(k, '-')} | {rq2['system_any'].get(k, '-')} | " +
                 " | ".join(str(rq2["module"][m][k - 1]) if k - 1 < len(rq2["module"][m]) else "-" for m in modes) + " |")
    L += ["", "Per scenario (heuristic failure test, reruns reproducing the collision):", "",
          "| scenario | collided with | P_faulty | failure test fails | reruns reproducing |", "|---|---|---|---|---|"]
    for row in rq3["ttrf"]:
        hf = row.get("heuristic", {})
        L.append(f"| {row['name']} | {rq2['collided_with'][row['name']]} | "
                 f"{'yes' if hf.get('failure_test_fails') != 'no P_faulty' else 'no'} | {hf.get('failure_test_fails', '-')} | "
                 f"{row['collided_reruns']}/{row['reruns']} |")
    L.append("")
    L.append(f"![RQ2]({r['plots'].get('rq2', '')})")
    # RQ3
    L += ["", "## RQ3: efficiency (Tables 4-6 analogues)", "", "### Extraction cost per frame", "",
          "| mode | frames | ms/frame | planner ms/frame | extraction + validation ms/frame | worst episode | truth agreement |",
          "|---|---|---|---|---|---|---|"]
    for m in modes:
        x = ms[m]
        L.append(f"| {m} | {x['frames']} | {x['ms_per_frame']:.2f} | {x['planner_ms_per_frame']:.2f} | "
                 f"{x['overhead_ms_per_frame']:.2f} | {_f(x['overhead_max'])} | "
                 f"{_f(100 * x['truth_agreement'] if x['truth_agreement'] is not None else None, 1)} % |")
    L += ["", "### Module tests vs system test (collision scenarios, heuristic)", "",
          "| scenario | extraction s | module tests s (all frames) | system test s (S0) |", "|---|---|---|---|"]
    for row in rq3["ttrf"]:
        L.append(f"| {row['name']} | {_f(row.get('heuristic', {}).get('extraction_s'))} | {_f(row.get('module_suite_s'))} | "
                 f"{_f(row['s0_wall'])} |")
    L += ["", "### Time to reproduce the failure (TTRF)", "",
          "System: wall time of reruns S1, S2, ... up to the first that collides with the same participant "
          "(censored at all reruns when none does). Module: duration of the failure test (a fresh planner "
          "seeded with its state recorded at the P_faulty frame and planning that frame ('1/N seeded'), where "
          "the planner can be seeded and the seeded planner reproduces P_faulty exactly; otherwise replaying "
          "the frames up to P_faulty from the latest frame that reproduces it exactly - see 'frames replayed' "
          "for the first mode), mean of its executions; both warm (after imports).", "",
          "| scenario | reruns needed | system TTRF s | frames replayed | " +
          " | ".join(f"module TTRF s ({m})" for m in modes) + " |",
          "|---|---|---|---|" + "---|" * len(modes)]
    for row in rq3["ttrf"]:
        need = "never (censored)" if row["censored"] else str(row["reruns_needed"])
        L.append(f"| {row['name']} | {need} | {row['system_ttrf']:.2f} | {row[modes[0]].get('replayed') or '-'} | " +
                 " | ".join(_f(row[m]["module_ttrf"], 3) for m in modes) + " |")
    L += ["", "| mode | scenarios | system s | module s | reduction | vs real-time reruns | with extraction | "
          "cold processes |", "|---|---|---|---|---|---|---|---|"]
    for m in modes:
        t = tt[m]
        rt = t.get("reduction_realtime")
        L.append(f"| {m} | {t['scenarios']} | {t['system_s']:.1f} | {t['module_s']:.1f} | "
                 f"{_f(100 * t['reduction'] if t['reduction'] is not None else None, 1)} % | "
                 f"{_f(100 * rt if rt is not None else None, 1)} % | "
                 f"{_f(100 * t['reduction_with_extraction'] if t['reduction_with_extraction'] is not None else None, 1)} % | "
                 f"{_f(100 * t['reduction_cold'] if t['reduction_cold'] is not None else None, 1)} % |")
    L += ["", "System reruns here run as fast as the machine allows (the simulation is not real-time); 'vs "
          "real-time reruns' charges each rerun its simulated duration instead, as on a stack that must run in "
          f"real time. Cold processes: {r['cold_start_s']:.2f} s of interpreter start and imports added per system "
          "rerun and once per module-test run. 'With extraction' adds the one-off extraction time to the module "
          "side.", ""]
    for key in ("rq3_ms", "rq3_ttrf"):
        if key in r["plots"]:
            L.append(f"![{key}]({r['plots'][key]})")
    return "\n".join(L) + "\n", headline


def _plots(r: dict[str, Any], out: Path) -> dict[str, str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files: dict[str, str] = {}
    modes, rq1 = r["modes"], r["rq1"]
    th = [f"{t:g}" for t in rq1["thetas"]]
    x = np.arange(len(th))
    fig, ax = plt.subplots(figsize=(10, 4))
    w = 0.8 / (len(modes) + 1)
    for i, m in enumerate(modes):
        ax.bar(x + i * w, [100 * rq1["deft"][m][t] / max(rq1["deft_frames"][m], 1) for t in th], w, label=f"DeFT {m}")
    if rq1["system"]:
        vals = np.array([[100 * rq1["system"][k][t] / max(r["outputs"], 1) for t in th] for k in rq1["system"]])
        mean = vals.mean(axis=0)
        ax.bar(x + len(modes) * w, mean, w, yerr=[mean - vals.min(axis=0), vals.max(axis=0) - mean],
               label="system reruns (mean, min-max)", color="grey")
    ax.set_xticks(x + w * len(modes) / 2, [f"{t} m" for t in th])
    ax.set_ylabel("planning outputs reproduced [%]")
    ax.set_xlabel("threshold theta")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_title("RQ1: reproduced planning outputs")
    files["rq1"] = _save(fig, out / "rq1_reproduction.png")
    rq2 = r["rq2"]
    fig, ax = plt.subplots(figsize=(10, 4))
    ks = sorted(rq2["system_same"])
    ax.plot(ks, [rq2["system_same"][k] for k in ks], "o-", color="grey", label="system rerun (same collision)")
    styles = ["s-", "^--", "v:"]
    for i, m in enumerate(modes):
        v = rq2["module"][m]
        off = (i - (len(modes) - 1) / 2) * 0.08  # equal series stay visible side by side
        ax.plot([k + off for k in range(1, len(v) + 1)], v, styles[i % 3], label=f"module tests ({m})")
    ax.axhline(r["collision_scenarios"], ls=":", color="k", label="collisions in S0")
    ax.set_xlabel("rerun / test execution")
    ax.set_ylabel("collisions reproduced")
    ax.set_ylim(0, r["collision_scenarios"] + 1)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_title("RQ2: collisions reproduced per execution")
    files["rq2"] = _save(fig, out / "rq2_collisions.png")
    ms = r["rq3"]["ms_per_frame"]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.bar(modes, [ms[m]["planner_ms_per_frame"] for m in modes], label="planner")
    ax.bar(modes, [ms[m]["overhead_ms_per_frame"] for m in modes],
           bottom=[ms[m]["planner_ms_per_frame"] for m in modes], label="extraction + validation")
    ax.set_ylabel("ms per frame")
    ax.legend(fontsize=8)
    ax.set_title("RQ3: extraction cost per frame")
    files["rq3_ms"] = _save(fig, out / "rq3_ms_per_frame.png")
    rows = r["rq3"]["ttrf"]
    if rows:
        fig, ax = plt.subplots(figsize=(max(6, len(rows) * 0.6), 4))
        xi = np.arange(len(rows))
        ax.bar(xi - 0.2, [row["system_ttrf"] for row in rows], 0.4, label="system reruns", color="grey")
        ax.bar(xi + 0.2, [row["heuristic"]["module_ttrf"] or 0.0 for row in rows] if "heuristic" in modes else
               [0.0] * len(rows), 0.4, label="module tests (heuristic)")
        ax.set_xticks(xi, [row["name"] for row in rows], rotation=60, ha="right", fontsize=7)
        ax.set_yscale("log")
        ax.set_ylabel("TTRF [s]")
        ax.legend(fontsize=8)
        ax.set_title("RQ3: time to reproduce the failure")
        files["rq3_ttrf"] = _save(fig, out / "rq3_ttrf.png")
    return files


def _save(fig: Any, path: Path) -> str:
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path.name
