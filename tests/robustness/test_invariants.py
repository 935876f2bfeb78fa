"""Safety invariants: YAML loading, NaN-safe evaluation, online vs offline on real runs."""

from __future__ import annotations

import math

import pytest

from deft_gym.config import ConfigError
from deft_gym.robustness.invariants import InvariantMonitor, load_invariants
from deft_gym.robustness.offline import check_log
from deft_gym.robustness.runner import run_case
from deft_gym.robustness.testcase import Policy, TestCase

MAP = {"type": "intersection", "lanes": 2, "length": 100.0, "speed_limit": 11.0}


def _write(tmp_path, text: str):
    p = tmp_path / "inv.yaml"
    p.write_text(text)
    return p


def test_default_invariants_load_simple_and_complex() -> None:
    inv = load_invariants()
    kinds = {i.spec.kind for i in inv.invariants}
    assert kinds == {"simple", "complex"}
    assert {"speed_limit", "stop_at_red", "control_finite", "planning_valid"} <= set(inv.names)


def test_bad_invariant_files_are_one_clear_error(tmp_path) -> None:
    p = _write(tmp_path, "invariants:\n  - {name: x, on: control, assert: 1, never: 2}\n")
    with pytest.raises(ConfigError) as err:
        load_invariants(p)
    assert str(p) in str(err.value) and "invariants.0" in str(err.value)
    p = _write(tmp_path, "invariants:\n  - {name: x, on: control, assert: 'open(1)'}\n")
    with pytest.raises(ConfigError, match="only the provided functions"):
        load_invariants(p)
    p = _write(tmp_path, "invariants:\n  - {name: x, on: control, assert: 'control.__class__'}\n")
    with pytest.raises(ConfigError, match="private attribute"):
        load_invariants(p)


def test_temporal_never_for_and_nan_safety(tmp_path) -> None:
    p = _write(tmp_path, """
invariants:
  - name: fast
    kind: complex
    on: chassis
    never: not (chassis.speed <= 10.0)
    for: 1.0
""")
    mon = InvariantMonitor(load_invariants(p), MAP)
    for k in range(10):  # 0.5 s over the limit: tolerated
        mon.observe("chassis", {"header": {"stamp": k * 0.05}, "speed": 12.0}, k * 0.05)
    mon.observe("chassis", {"header": {"stamp": 0.6}, "speed": 5.0}, 0.6)
    assert not mon.violations
    for k in range(30):  # NaN for 1.5 s: `not (NaN <= 10)` is True -> violation
        mon.observe("chassis", {"header": {"stamp": 1 + k * 0.05}, "speed": math.nan}, 1 + k * 0.05)
    assert "fast" in mon.violations and mon.violations["fast"].time > 2.0


def test_nominal_run_violates_nothing() -> None:
    r = run_case(TestCase(scenario="configs/scenarios/left_turn.yaml", jitter_seed=0))
    assert r.outcome == "completed", r.as_dict()
    assert r.signatures == [] and r.harness_errors == []


def test_online_and_offline_agree_on_an_intercepted_run(tmp_path) -> None:
    case = TestCase(scenario="configs/scenarios/left_turn.yaml", jitter_seed=0, policies=[
        Policy(topic="localization", start=5.0, end=8.0, set=[{"path": "v", "value": "float.nan"}]),
        Policy(topic="localization", mode="inject", start=9.0, end=9.5, set=[{"path": "x", "value": "float.ten"}])])
    r = run_case(case, out_dir=tmp_path)
    online = {v["name"]: v["count"] for v in r.violations}
    assert "speed_limit" in online  # NaN speed -> the controller's clamp turns it into full throttle
    offline = {v.name: v.count for v in check_log(r.log_path)}
    assert offline == online
