"""A robustness campaign: generate tests, run them, classify, attribute, minimise, summarise.

Layout of a campaign folder ``OUT``:

- ``campaign.json`` - the settings (a resumed campaign must match them);
- ``baseline.jsonl`` - one unmodified run per (scenario, jitter seed): an invariant violated there
  is not counted as a finding of a test with the same scenario and seed;
- ``runs.jsonl`` - append-only, one line per test (a resumed campaign skips the tests it holds);
- ``cases/run_NNNNN.json`` - one replayable test case per test with a finding;
- ``minimised/<signature>.json`` (+ ``<signature>/episode.mcap``, the test log with originals and
  modified messages) - the minimal case of each distinct finding;
- ``summary.json`` - ``runs``, ``crashes``, ``hangs``, ``violations`` by invariant, ``minimised``
  cases, harness errors, planted-fault detection, baseline.
"""

from __future__ import annotations

import json
import re
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from deft_gym.config import CONFIG_DIR, ConfigError, deep_merge, load_mapping, validate
from deft_gym.execution import Backend, Executor, Record
from deft_gym.files import append_jsonl, read_jsonl, write_atomic
from deft_gym.record.recorder import init_pool_worker
from deft_gym.robustness.faults import PLANTED_FAULTS, SIGNATURES
from deft_gym.robustness.generate import GenerationConfig, case_rng, describe, generate_policies
from deft_gym.robustness.minimise import Minimised, minimise
from deft_gym.robustness.runner import RunResult, foundation_digest, run_case
from deft_gym.robustness.spec import TestSpecification
from deft_gym.robustness.testcase import Expect, TestCase, load_case, save_case

DEFAULT_CAMPAIGN = CONFIG_DIR / "stress" / "default.yaml"


class MinimiseConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    max_signatures: int = Field(default=30, ge=0, le=100_000)
    max_replays: int = Field(default=100, ge=1, le=100_000)


class CampaignConfig(BaseModel):
    """``configs/stress/*.yaml``."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # an infinite horizon: refused

    scenarios: list[str] = Field(min_length=1, max_length=10_000,
                                 default_factory=lambda: ["configs/scenarios/left_turn.yaml"])
    seeds_per_scenario: int = Field(default=3, ge=1, le=10_000)
    invariants: str | None = None
    deadline_s: float = Field(default=1.0, gt=0.0, le=3600.0)
    hang_periods: int = Field(default=10, ge=1, le=1_000_000)
    grace_s: float = Field(default=2.0, ge=0.0, le=3600.0)
    horizon_s: float | None = Field(default=8.0, gt=0.0, le=3600.0, description="end a test this long after its last "
                                    "policy window (None: run the whole episode)")
    generation: GenerationConfig = GenerationConfig()
    minimise: MinimiseConfig = MinimiseConfig()


def load_campaign_config(path: Path | str | None = None, overrides: dict[str, Any] | None = None) -> CampaignConfig:
    """Load a campaign config; errors name the file and the field."""
    path = Path(path) if path else DEFAULT_CAMPAIGN
    return validate(CampaignConfig, deep_merge(load_mapping(path), overrides or {}), path)


@dataclass
class Campaign:
    """Everything that defines a campaign's tests."""

    config: CampaignConfig
    seed: int = 0
    ads_config: str | None = None
    ads_overrides: dict[str, Any] | None = None
    hardening: bool = False

    def settings(self) -> dict[str, Any]:
        """What defines the tests (a resumed campaign must match; minimisation limits may change)."""
        return {"seed": self.seed, "ads_config": self.ads_config, "ads_overrides": self.ads_overrides or {},
                "hardening": self.hardening, "config": self.config.model_dump(mode="json", exclude={"minimise"})}

    def jitter_seeds(self) -> list[int]:
        return [self.seed * 1000 + k for k in range(self.config.seeds_per_scenario)]

    def base_case(self, scenario: str, jitter_seed: int, case_id: str) -> TestCase:
        c = self.config
        return TestCase(id=case_id, scenario=scenario, ads_config=self.ads_config,
                        ads_overrides=self.ads_overrides or {}, hardening=self.hardening, jitter_seed=jitter_seed,
                        invariants=c.invariants, deadline_s=c.deadline_s, hang_periods=c.hang_periods,
                        grace_s=c.grace_s)

    def case(self, index: int, spec: TestSpecification) -> TestCase:
        """Test ``index`` (deterministic in the seed and the index only)."""
        rng = case_rng(self.seed, index)
        scenarios = self.config.scenarios
        scenario = scenarios[index % len(scenarios)]
        jitter_seed = rng.choice(self.jitter_seeds())
        policies = generate_policies(spec, self.config.generation, rng, index)
        case = self.base_case(scenario, jitter_seed, f"run_{index:05d}")
        horizon = self.config.horizon_s
        stop_at = None if horizon is None else round(max(p.end for p in policies) + horizon, 3)
        return case.model_copy(update={"policies": policies, "stop_at": stop_at})

    def planted(self) -> dict[str, str]:
        """Planted faults the ADS overrides enable: fault -> module."""
        out = {}
        for module, cfg in (self.ads_overrides or {}).items():
            if isinstance(cfg, dict):
                for f in (cfg.get("params") or {}).get("planted_faults") or []:
                    if f in PLANTED_FAULTS:
                        out[f] = module
        return out

    def without_fault(self, case: TestCase, fault: str) -> TestCase:
        """``case`` with one planted fault switched off."""
        module = self.planted()[fault]
        overrides = json.loads(json.dumps(case.ads_overrides))
        params = overrides[module].setdefault("params", {})
        params["planted_faults"] = [f for f in params.get("planted_faults", []) if f != fault]
        return case.model_copy(update={"ads_overrides": overrides})


# -- running (also in worker processes) ----------------------------------------------------------
def _safe_run(case: TestCase) -> RunResult:
    """:func:`run_case` that turns an error of the tool itself into a harness error."""
    try:
        return run_case(case)
    except KeyboardInterrupt:
        raise
    except Exception:
        r = RunResult(case.id, case.scenario, case.jitter_seed)
        r.harness_errors.append("run: " + traceback.format_exc(limit=-4))
        return r


def _run_one(job: tuple[Campaign, int]) -> dict[str, Any]:
    campaign, index = job
    spec = TestSpecification.from_schemas()
    case = campaign.case(index, spec)
    result = _safe_run(case)
    return {"index": index, "case": case.model_dump(mode="json", exclude_none=True),
            "result": result.as_dict(), "applied": result.applied}


def _run_baseline(job: tuple[Campaign, str, int]) -> dict[str, Any]:
    campaign, scenario, seed = job
    result = _safe_run(campaign.base_case(scenario, seed, "baseline"))
    return {"scenario": scenario, "jitter_seed": seed, "result": result.as_dict()}


def slug(signature: str) -> str:
    """A file name for a signature."""
    return re.sub(r"[^A-Za-z0-9]+", "_", signature).strip("_")[:120]


# -- the campaign ----------------------------------------------------------------------------
def run_campaign(campaign: Campaign, out: Path, budget: int, workers: int = 1, minimise_findings: str = "all",
                 progress: Callable[[str, int, int, dict[str, Any]], None] | None = None,
                 until_found: bool = False, backend: Backend | None = None) -> dict[str, Any]:
    """Run (or resume) a campaign of ``budget`` tests into ``out``; returns the summary.

    ``minimise_findings``: ``all`` distinct findings, only ``planted`` faults' findings, or
    ``none``; ``until_found``: stop the tests once every planted fault was found. Tests run on
    ``backend`` (default: ``workers`` local processes); rows are appended in test order, so the
    records do not depend on the backend or the number of workers."""
    backend = backend or Backend("local", workers)
    with Executor(backend, initializer=init_pool_worker, initargs=(backend.workers,), run_dir=out) as ex:
        return _run_campaign(campaign, out, budget, ex, minimise_findings, progress, until_found)


def _run_campaign(campaign: Campaign, out: Path, budget: int, ex: Executor, minimise_findings: str,
                  progress: Callable[[str, int, int, dict[str, Any]], None] | None,
                  until_found: bool) -> dict[str, Any]:
    wall0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    (out / "cases").mkdir(exist_ok=True)
    settings = campaign.settings()
    meta_path = out / "campaign.json"
    if meta_path.exists():
        old = json.loads(meta_path.read_text()).get("settings", {})
        old.get("config", {}).pop("minimise", None)
        if old != settings:
            raise ConfigError(f"{out}: holds a campaign with other settings; use another --out (or delete it)")
    foundation = foundation_digest()
    write_atomic(meta_path, json.dumps({"settings": settings, "budget": budget, "foundation": foundation},
                                       indent=1, sort_keys=True))
    report = progress or (lambda *a: None)

    # 1. baseline: one unmodified run per scenario and jitter seed
    base = Record(out / "baseline.jsonl", fsync=True)
    baseline = {(r["scenario"], r["jitter_seed"]): r for r in base.rows}
    jobs = [(campaign, s, j) for s in campaign.config.scenarios for j in campaign.jitter_seeds()
            if (s, j) not in baseline]
    for row in ex.map(_run_baseline, jobs):
        base.add(row)
        baseline[(row["scenario"], row["jitter_seed"])] = row
        report("baseline", len(baseline), len(campaign.config.scenarios) * len(campaign.jitter_seeds()), {})
    nominal = {k: set(v["result"]["signatures"]) for k, v in baseline.items()}

    # 2. tests
    runs = Record(out / "runs.jsonl", fsync=True)
    # a row whose harness failed (not the ADS) is run again on resume, never reused
    rows = {r["index"]: r for r in runs.rows if r.get("index", budget) < budget and not r.get("harness_errors")}
    todo = [i for i in range(budget) if i not in rows]
    # 3. planted faults (inline, in test order): which finding disappears without the fault
    attribution = _Attribution(campaign, out / "attribution.jsonl")
    for i in sorted(rows):
        attribution.check(rows[i])
    if not (until_found and attribution.done):
        for res in ex.map(_run_one, [(campaign, i) for i in todo]):
            row = _row(res, nominal)
            if row["findings"]:  # the case file first: a kill after the row must not lose it
                case = TestCase.model_validate(res["case"])
                r = res["result"]
                save_case(case.model_copy(update={"expect": Expect(
                    signature=row["findings"][0], fingerprint=r["fingerprint"], foundation=foundation)}),
                          out / "cases" / f"{case.id}.json")
            runs.add(row)
            rows[row["index"]] = row
            attribution.check(row)
            report("tests", len(rows), budget, _counts(rows.values()))
            if until_found and attribution.done:
                break

    ordered = [rows[i] for i in sorted(rows)]
    planted = attribution.result()
    # 4. minimisation of each distinct finding (first occurrence) and of each planted fault's
    if minimise_findings == "none":
        minimised: list[dict[str, Any]] = []
    else:
        minimised = _minimise_all(campaign, ordered, planted, out, report, ex, minimise_findings == "planted")
    summary = _summary(campaign, ordered, baseline, planted, minimised, budget, time.perf_counter() - wall0)
    write_atomic(out / "summary.json", json.dumps(summary, indent=1, sort_keys=False, allow_nan=True) + "\n")
    return summary


def _row(res: dict[str, Any], nominal: dict[tuple[str, int], set[str]]) -> dict[str, Any]:
    r = res["result"]
    case = res["case"]
    seen = nominal.get((case["scenario"], case["jitter_seed"]), set())
    findings = [s for s in r["signatures"] if s not in seen]
    return {"index": res["index"], "scenario": case["scenario"], "jitter_seed": case["jitter_seed"],
            "policies": describe(TestCase.model_validate(case).policies), "findings": findings,
            "nominal_signatures": [s for s in r["signatures"] if s in seen], "outcome": r["outcome"],
            "sim_time": r["sim_time"], "wall_time": r["wall_time"], "instances": r["instances"],
            "harness_errors": r["harness_errors"], "fingerprint": r["fingerprint"],
            "failures": r["failures"], "violations": r["violations"]}


def _counts(rows: Any) -> dict[str, Any]:
    c: dict[str, Any] = {"runs": 0, "crashes": 0, "hangs": 0, "violations": 0, "harness_errors": 0}
    for row in rows:
        c["runs"] += 1
        f = row["findings"]
        c["crashes"] += any(s.startswith("crash:") for s in f)
        c["hangs"] += any(s.startswith("hang:") for s in f)
        c["violations"] += any(s.startswith("violation:") for s in f)
        c["harness_errors"] += len(row["harness_errors"])
    return c


def _case_of(campaign: Campaign, index: int) -> TestCase:
    return campaign.case(index, TestSpecification.from_schemas())


class _Attribution:
    """Planted-fault attribution: a fault is found by the first test whose finding is the fault's
    own (:data:`~.faults.SIGNATURES`: the speeding, the hang, the exception at the planted line)
    *and* disappears when the test is replayed with that fault switched off - so a finding the
    built-in modules share (a long NaN window speeds the ego up without any planted fault) is not
    counted. Replays are kept in a JSON-lines file so a resumed campaign does not repeat them."""

    def __init__(self, campaign: Campaign, path: Path) -> None:
        self.campaign = campaign
        self.faults = campaign.planted()
        self.found: dict[str, dict[str, Any]] = {f: {"found": False, "module": m} for f, m in self.faults.items()}
        self.replays = 0
        self._memo = {(r["index"], r["fault"]): r for r in read_jsonl(path)}
        self._path = path

    @property
    def done(self) -> bool:
        return bool(self.faults) and all(v["found"] for v in self.found.values())

    def check(self, row: dict[str, Any]) -> None:
        if not row["findings"] or self.done or not self.faults:
            return
        case: TestCase | None = None
        for fault, info in self.found.items():
            if info["found"] or SIGNATURES[fault] not in row["findings"]:
                continue  # only the fault's own signature can make it found
            memo = self._memo.get((row["index"], fault))
            if memo is None:
                case = case or _case_of(self.campaign, row["index"])
                r = _safe_run(self.campaign.without_fault(case, fault))
                if r.harness_errors:
                    continue
                memo = {"index": row["index"], "fault": fault, "gone": [s for s in row["findings"]
                                                                         if s not in r.signatures]}
                append_jsonl(self._path, memo, fsync=True)
                self.replays += 1
            own = SIGNATURES[fault]
            if own in memo["gone"]:
                self.found[fault] = {"found": True, "module": info["module"], "first_run": row["index"],
                                     "runs_to_find": row["index"] + 1, "signature": own,
                                     "case": f"cases/run_{row['index']:05d}.json",
                                     "masked_before": info.get("masked_before", 0)}
            else:  # the built-in modules show the same finding: not evidence of the fault
                info["masked_before"] = info.get("masked_before", 0) + 1

    def result(self) -> dict[str, dict[str, Any]]:
        for info in self.found.values():
            info["attribution_replays"] = self.replays
        return self.found


def _minimise_all(campaign: Campaign, rows: list[dict[str, Any]], planted: dict[str, dict[str, Any]], out: Path,
                  report: Callable[..., None], ex: Executor, planted_only: bool = False) -> list[dict[str, Any]]:
    cfg = campaign.config.minimise
    targets: dict[tuple[int, str], list[str]] = {}
    for fault, info in planted.items():
        if info.get("found"):
            targets.setdefault((info["first_run"], info["signature"]), []).append(fault)
    first: dict[str, int] = {}
    for row in rows:
        for s in row["findings"]:
            first.setdefault(s, row["index"])
    for s, i in ([] if planted_only else list(first.items())[:cfg.max_signatures]):
        if not any(sig == s and idx == i for idx, sig in targets):
            targets.setdefault((i, s), [])
    (out / "minimised").mkdir(exist_ok=True)
    names = {key: slug(key[1]) + (f"__run{key[0]:05d}" if faults else "") for key, faults in targets.items()}
    infos = {key: json.loads(p.read_text()) for key in targets
             if (p := out / "minimised" / f"{names[key]}.info.json").exists()}
    # each distinct finding is minimised as one work item (in parallel; written in target order)
    jobs = [(campaign, key[0], key[1], str(out / "minimised" / f"{names[key]}.json"), cfg.max_replays)
            for key in sorted(targets) if key not in infos]
    ticks = iter(range(len(infos) + 1, len(targets) + 1))
    for key, info in zip([k for k in sorted(targets) if k not in infos],
                         ex.map(_minimise_job, jobs, artifacts=lambda j: [j[3], j[3][:-len(".json")]],
                                progress=lambda n: report("minimise", next(ticks), len(targets), {}))):
        info["planted_faults"] = targets[key]
        write_atomic(out / "minimised" / f"{names[key]}.info.json", json.dumps(info, indent=1, sort_keys=True))
        infos[key] = info
    done = []
    for key, faults in sorted(targets.items()):
        done.append(infos[key])
        for fault in faults:
            planted[fault]["minimised"] = {k: done[-1].get(k) for k in
                                           ("case", "dimensionality", "replays", "reproduced", "deterministic")}
    return done


def _minimise_job(job: tuple[Campaign, int, str, str, int]) -> dict[str, Any]:
    """Minimise one finding (a work item); a harness error is reported, not raised."""
    campaign, index, signature, path, max_replays = job
    try:
        return _minimise_one(campaign, index, signature, Path(path), max_replays, TestSpecification.from_schemas())
    except Exception:
        return {"signature": signature, "run": index, "reproduced": False,
                "harness_error": traceback.format_exc(limit=-4)}


def _minimise_one(campaign: Campaign, index: int, signature: str, path: Path, max_replays: int,
                  spec: TestSpecification) -> dict[str, Any]:
    case = _case_of(campaign, index)
    result = run_case(case)
    if signature not in result.signatures:
        return {"signature": signature, "run": index, "reproduced": False, "note": "the test does not replay"}
    m: Minimised = minimise(case, result, signature, max_replays, spec)
    info = {**m.as_dict(), "run": index}
    if m.case is None:
        return info
    log_dir = path.with_suffix("")
    a = run_case(m.case, out_dir=log_dir)
    b = run_case(m.case)
    info["deterministic"] = a.fingerprint == b.fingerprint and signature in a.signatures \
        and signature in b.signatures
    info["reproduces_full_run"] = signature in a.signatures
    final = m.case.model_copy(update={"id": path.stem, "expect": Expect(
        signature=signature, time=_time_of(a, signature), fingerprint=a.fingerprint, foundation=foundation_digest())})
    save_case(final, path)
    info["case"] = str(path.relative_to(path.parent.parent))
    info["log"] = str((log_dir / "episode.mcap").relative_to(path.parent.parent))
    info["instances"] = [i.model_dump(mode="json") for i in final.instances or []]
    return info


def _time_of(r: RunResult, signature: str) -> float | None:
    for item in [*r.failures, *r.violations]:
        if item["signature"] == signature:
            return item["time"]
    return None


FAILURE_PREFIXES = ("crash:", "hang:", "violation:")  # signatures that are failures of the ADS


def _summary(campaign: Campaign, rows: list[dict[str, Any]], baseline: dict[Any, Any],
             planted: dict[str, Any], minimised: list[dict[str, Any]], budget: int, wall: float) -> dict[str, Any]:
    c = _counts(rows)
    violations: dict[str, int] = {}
    findings: dict[str, dict[str, Any]] = {}
    for row in rows:
        for s in row["findings"]:
            if s.startswith("violation:"):
                violations[s.split(":", 1)[1]] = violations.get(s.split(":", 1)[1], 0) + 1
            f = findings.setdefault(s, {"runs": 0, "first_run": row["index"],
                                        "case": f"cases/run_{row['index']:05d}.json"})
            f["runs"] += 1
    base_viol: dict[str, int] = {}
    for b in baseline.values():
        for s in b["result"]["signatures"]:
            base_viol[s] = base_viol.get(s, 0) + 1
    harness_runs = sum(1 for r in rows if r["harness_errors"])
    return {
        "runs": c["runs"], "budget": budget, "crashes": c["crashes"], "hangs": c["hangs"],
        "violations": dict(sorted(violations.items())), "runs_with_violations": c["violations"],
        "runs_with_findings": sum(1 for r in rows if r["findings"]),
        "harness_errors": c["harness_errors"] + sum(len(b["result"]["harness_errors"]) for b in baseline.values()),
        "harness_error_runs": harness_runs,
        "findings": dict(sorted(findings.items(), key=lambda kv: kv[1]["first_run"])),
        "minimised": minimised, "planted": planted,
        "baseline": {"runs": len(baseline), "signatures": base_viol},
        # the unmodified ADS already fails: findings too (they are nominal for the tests' diff)
        "baseline_findings": {k: n for k, n in sorted(base_viol.items()) if k.startswith(FAILURE_PREFIXES)},
        "hardening": campaign.hardening, "seed": campaign.seed, "foundation": foundation_digest(),
        "sim_time_s": round(sum(r["sim_time"] for r in rows), 2),
        "test_wall_time_s": round(sum(r["wall_time"] for r in rows), 2),
        "wall_time_s": round(wall, 2),
    }


def replay(path: Path | str, log_dir: Path | str | None = None) -> dict[str, Any]:
    """Replay a test case file; did it reproduce its expected signature and fingerprint?"""
    case = load_case(path)
    result = run_case(case, out_dir=log_dir)
    exp = case.expect
    return {"case": str(path), "expected": exp.signature if exp else None,
            "same_foundation": bool(exp and exp.foundation == foundation_digest()),
            "signatures": result.signatures,
            "reproduced": bool(exp and exp.signature in result.signatures),
            "identical": bool(exp and exp.fingerprint and exp.fingerprint == result.fingerprint),
            "harness_errors": result.harness_errors, "log": result.log_path}
