"""Running one test case on the real bus and classifying what happened.

:func:`run_case` builds the simulation the case names (scenario, ADS configuration, hardening
switch, jitter seed), installs the interceptor, the guarded supervisor, the silence monitor and
the invariant monitor, runs it and returns a :class:`RunResult`: crashes and hangs (per node),
invariant violations (by name), the instances the policies touched, a fingerprint of every
message on the bus (equal fingerprints = identical runs) and harness errors - anything that went
wrong in the tool rather than in the system under test, which must stay at zero.

A run ends ``grace_s`` of sim time after the first crash or hang, at ``stop_at``, when the
episode ends, or (for minimisation) as soon as a wanted signature is seen.
"""

from __future__ import annotations

import hashlib
import json
import time
import traceback
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.bus.ads import AdsConfig, load_ads_config
from deft_gym.bus.codec import encode
from deft_gym.bus.messages import Message, to_ns
from deft_gym.config import CONFIG_DIR, ROOT, resolve_config_path
from deft_gym.files import first_line
from deft_gym.robustness.hardening import harden_overrides
from deft_gym.robustness.interception import Interceptor, attach
from deft_gym.robustness.invariants import (
    InvariantMonitor,
    InvariantSet,
    Violation,
    load_invariants,
)
from deft_gym.robustness.monitors import Failure, GuardedSupervisor, SilenceMonitor
from deft_gym.robustness.testcase import TestCase
from deft_gym.scenarios.scenario import Scenario, load_scenario
from deft_gym.sim.simulation import Simulation

ASTAA_METADATA = "deft_gym.astaa"


@dataclass
class RunResult:
    """What one test case run produced."""

    case_id: str
    scenario: str
    jitter_seed: int
    outcome: str = "error"
    sim_time: float = 0.0
    wall_time: float = 0.0
    failures: list[dict[str, Any]] = field(default_factory=list)
    violations: list[dict[str, Any]] = field(default_factory=list)
    applied: list[dict[str, Any]] = field(default_factory=list)
    harness_errors: list[str] = field(default_factory=list)
    fingerprint: str = ""
    messages: int = 0
    max_wall: dict[str, float] = field(default_factory=dict)
    log_path: str | None = None

    @property
    def signatures(self) -> list[str]:
        """Findings in time order (crash/hang before a violation at the same time)."""
        items = [(f["time"], 0, f["signature"]) for f in self.failures]
        items += [(v["time"], 1, v["signature"]) for v in self.violations]
        return [s for _, _, s in sorted(items)]

    @property
    def crashed(self) -> bool:
        return any(f["kind"] == "crash" for f in self.failures)

    @property
    def hung(self) -> bool:
        return any(f["kind"] == "hang" for f in self.failures)

    def as_dict(self) -> dict[str, Any]:
        return {"case": self.case_id, "scenario": self.scenario, "jitter_seed": self.jitter_seed,
                "outcome": self.outcome, "sim_time": round(self.sim_time, 6), "wall_time": round(self.wall_time, 4),
                "signatures": self.signatures, "failures": self.failures, "violations": self.violations,
                "instances": len(self.applied), "harness_errors": self.harness_errors,
                "fingerprint": self.fingerprint, "messages": self.messages,
                "max_compute_s": {k: round(v, 4) for k, v in self.max_wall.items()}, "log": self.log_path}


def _imports(path: Path) -> set[Path]:
    """``deft_gym`` source files a file imports (static, from its import statements)."""
    import ast

    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = [node.module or ""] if isinstance(node, ast.ImportFrom) else \
            [a.name for a in node.names] if isinstance(node, ast.Import) else []
        for name in names:
            if name.startswith("deft_gym.") and not name.startswith("deft_gym.robustness"):
                parts = name.split(".")
                for cand in (ROOT.joinpath(*parts).with_suffix(".py"), ROOT.joinpath(*parts, "__init__.py")):
                    if cand.exists():
                        out.add(cand)
    return out


def foundation_digest() -> str:
    """A digest of the simulation's source (everything ``deft_gym.sim.simulation`` imports, the module
    nodes and planners) and of the default ADS config: runs are guaranteed to replay
    bit-identically only on the foundation they were recorded with."""
    pkg = ROOT / "deft_gym"
    todo = [pkg / "sim" / "simulation.py", *sorted((pkg / "modules").glob("*.py")), *sorted((pkg / "planner").glob("*.py"))]
    seen: set[Path] = set()
    while todo:
        f = todo.pop()
        if f not in seen:
            seen.add(f)
            todo.extend(_imports(f) - seen)
    h = hashlib.blake2b(digest_size=8)
    for f in sorted(seen):
        h.update(str(f.relative_to(ROOT)).encode())
        h.update(f.read_bytes())
    h.update((CONFIG_DIR / "ads" / "default.yaml").read_bytes())
    return h.hexdigest()


def resolve(path: str | Path) -> Path:
    """A path relative to the repository root (or the shipped configs) unless absolute or
    existing as given."""
    p = resolve_config_path(path)
    return p if p.is_absolute() or p.exists() else ROOT / p


def build_ads(case: TestCase) -> AdsConfig:
    """The ADS configuration of a case (file + overrides + the hardening switch)."""
    ads = load_ads_config(resolve(case.ads_config) if case.ads_config else None, case.ads_overrides or None)
    if case.hardening:
        ads = load_ads_config(resolve(case.ads_config) if case.ads_config else None,
                              _merge(case.ads_overrides, harden_overrides(ads)))
    return ads


def _merge(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    from deft_gym.config import deep_merge

    return deep_merge(a or {}, b)


_SCENARIOS: dict[str, Scenario] = {}
_INVARIANTS: dict[str, InvariantSet] = {}


def _scenario(path: str) -> Scenario:
    key = str(resolve(path))
    if key not in _SCENARIOS:
        _SCENARIOS[key] = load_scenario(key)
    return _SCENARIOS[key]


def _invariants(path: str | None) -> InvariantSet:
    key = str(resolve(path)) if path else ""
    if key not in _INVARIANTS:
        _INVARIANTS[key] = load_invariants(key or None)
    return _INVARIANTS[key]


class _Fingerprint:
    """A bus tap hashing every dispatched message (topic, seq, publish time, payload bytes)."""

    def __init__(self) -> None:
        self.h = hashlib.blake2b(digest_size=16)
        self.errors: list[str] = []

    def __call__(self, msg: Message) -> None:
        h = self.h
        h.update(f"{msg.topic}|{msg.seq}|{msg.publish_ns}|".encode())
        try:
            h.update(encode(msg.payload))
        except Exception as exc:  # a tap must never raise into the publishing module
            self.errors.append(f"fingerprint: {msg.topic}: {type(exc).__name__}: {exc}"[:200])


def check_setup(case: TestCase, source: str = "the ADS configuration") -> None:
    """Everything ``case`` needs, built once without running: its scenario, ADS configuration,
    invariants and the simulation with every module node and the planner - a ConfigError (one
    line naming the file or the setting) instead of a harness error in every test."""
    from deft_gym.config import ConfigError

    path = resolve(case.scenario)
    if not path.is_file():
        raise ConfigError(f"scenario {case.scenario!r}: no such file ({path})")
    scenario = _scenario(case.scenario)
    ads = build_ads(case)
    _invariants(case.invariants)
    try:
        sim = Simulation(scenario, ads, jitter_seed=case.jitter_seed, keep_planning=False)
    except ConfigError:
        raise
    except (ImportError, ValueError, TypeError, AttributeError) as exc:  # a module node that cannot be built
        text = first_line(exc)
        raise ConfigError(f"{source}: cannot build the simulation of {case.scenario}: {text}") from None
    close = getattr(sim.planner, "close", None)
    if callable(close):
        close()


def run_case(case: TestCase, out_dir: Path | str | None = None, stop_on: str | None = None,
             until: float | None = None, ads: AdsConfig | None = None) -> RunResult:
    """Run ``case``; ``out_dir`` records the test log; ``stop_on`` ends the run at the first
    finding with that signature; ``until`` caps the sim time [s]."""
    wall0 = time.perf_counter()
    scenario = _scenario(case.scenario)
    result = RunResult(case.id, scenario.name, case.jitter_seed)
    ads = ads or build_ads(case)
    invariants = _invariants(case.invariants)
    sim = Simulation(scenario, ads, jitter_seed=case.jitter_seed, out_dir=out_dir, keep_planning=False)
    bus = sim.bus
    state: dict[str, Any] = {"fail_ns": None, "stop": False}

    def on_failure(f: Failure) -> None:
        if state["fail_ns"] is None:
            state["fail_ns"] = bus.now_ns
        if stop_on is not None and f.signature == stop_on:
            state["stop"] = True

    def on_violation(v: Violation) -> None:
        if stop_on is not None and v.signature == stop_on:
            state["stop"] = True

    monitor = InvariantMonitor(invariants, sim.roadmap, on_violation=on_violation)
    icpt = Interceptor(case, ads.topics, bus, sim.recorder)
    icpt.observers.append(monitor.observe_message)
    attach(icpt)
    fingerprint = _Fingerprint()
    bus.taps.append(fingerprint)
    supervisor = GuardedSupervisor(bus, case.deadline_s, on_failure)
    bus.supervisor = supervisor
    silence = SilenceMonitor(ads, bus.nodes, case.hang_periods, on_failure=on_failure)
    grace_ns = to_ns(case.grace_s)
    limits = [x for x in (case.stop_at, until) if x is not None]
    stop_ns = to_ns(min(limits)) if limits else None

    def on_step(s: Simulation) -> None:
        try:
            silence(s)
        except Exception:
            result.harness_errors.append("silence monitor: " + traceback.format_exc(limit=-2))
        now = bus.now_ns
        if state["stop"] or (state["fail_ns"] is not None and now - state["fail_ns"] >= grace_ns) \
                or (stop_ns is not None and now >= stop_ns):
            bus.stop()

    sim.on_step.append(on_step)
    outcome: dict[str, Any] | None = None
    with supervisor, warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)  # exceptional values make numpy talk
        try:
            sim.advance(scenario.duration)
        except KeyboardInterrupt:
            raise
        except BaseException:  # whatever escapes the bus is the tool's error
            result.harness_errors.append("bus: " + traceback.format_exc(limit=-4))
    try:
        if sim.recorder is not None:
            sim.recorder.add_metadata(ASTAA_METADATA, {
                "case": json.dumps(case.model_dump(mode="json", exclude_none=True)),
                "applied": json.dumps(icpt.applied)})
        res = sim.finish()
        outcome = res.outcome.as_dict()
        result.outcome = res.outcome.outcome
        result.sim_time = res.outcome.sim_time
        result.messages = res.messages
        result.log_path = res.log_path
    except Exception:
        result.harness_errors.append("finish: " + traceback.format_exc(limit=-4))
    try:
        violations = monitor.finish(outcome, result.sim_time)
    except Exception:
        violations = []
        result.harness_errors.append("invariants: " + traceback.format_exc(limit=-4))
    failures = sorted(supervisor.failures + silence.failures, key=lambda f: f.time)
    result.failures = [f.as_dict() for f in failures]
    result.violations = [v.as_dict() for v in violations]
    result.applied = icpt.applied
    result.harness_errors += icpt.errors + monitor.errors + fingerprint.errors
    result.fingerprint = fingerprint.h.hexdigest()
    result.max_wall = dict(supervisor.max_wall)
    result.wall_time = time.perf_counter() - wall0
    return result
