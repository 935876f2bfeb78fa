"""Planted faults are found on the real bus, minimised to their essential field, and prevented by
hardening; hardening also prevents a crash of the built-in planner."""

from __future__ import annotations

import pytest

from deft_gym.robustness.faults import SIGNATURES
from deft_gym.robustness.minimise import dimensionality, minimise
from deft_gym.robustness.runner import run_case
from deft_gym.robustness.testcase import Policy, TestCase

SCENARIO = "configs/scenarios/left_turn.yaml"
CONTROL = "deft_gym.robustness.faults:FaultyControl"


def _case(fault: str, policy: Policy, hardening: bool = False, stop_at: float = 9.0) -> TestCase:
    module, node = ("prediction", "deft_gym.robustness.faults:FaultyPrediction") if fault == "angle_wrap" \
        else ("control", CONTROL)
    return TestCase(scenario=SCENARIO, jitter_seed=0, hardening=hardening, stop_at=stop_at, deadline_s=0.5,
                    ads_overrides={module: {"node": node, "params": {"planted_faults": [fault]}}},
                    policies=[policy])


FAULTS = {
    # one NaN speed poisons the speed filter: the guard never brakes, the ego speeds up
    "nan_speed": (Policy(topic="localization", start=5.0, end=6.0, max_count=1,
                         set=[{"path": "v", "value": "float.nan"}])),
    # a huge obstacle heading: the subtractive angle-wrapping loop never ends
    "angle_wrap": (Policy(topic="perception_obstacles", start=5.0, end=5.5,
                          set=[{"path": "obstacles[*].heading", "value": "float.huge"}])),
    # an empty trajectory: trajectory.t[0] raises IndexError
    "empty_trajectory": (Policy(topic="planning", start=5.0, end=6.0, max_count=1,
                                set=[{"path": "trajectory.t", "value": "array.empty"}])),
    # a stale duplicate of a localization message (interleaved 80 ms later): dt = 0
    "stale_stamp": (Policy(topic="localization", mode="inject", start=5.0, end=6.0, max_count=1, delay_ms=80.0)),
}


@pytest.mark.parametrize("fault", sorted(FAULTS))
def test_planted_fault_is_detected_and_absent_without_it(fault: str) -> None:
    policy, signature = FAULTS[fault], SIGNATURES[fault]
    stop = 14.0 if fault == "nan_speed" else 9.0
    r = run_case(_case(fault, policy, stop_at=stop))
    assert signature in r.signatures, r.as_dict()
    assert r.harness_errors == []
    # the same test without the planted fault: no such finding
    clean = _case(fault, policy, stop_at=stop).model_copy(update={"ads_overrides": {}})
    assert signature not in run_case(clean).signatures


@pytest.mark.parametrize("fault", sorted(FAULTS))
def test_hardening_prevents_the_planted_fault(fault: str) -> None:
    policy, signature = FAULTS[fault], SIGNATURES[fault]
    r = run_case(_case(fault, policy, hardening=True, stop_at=14.0 if fault == "nan_speed" else 9.0))
    assert signature not in r.signatures and not r.failures, r.as_dict()


def test_nan_speed_minimises_to_one_field_of_one_message() -> None:
    policy = Policy(topic="localization", start=5.0, end=5.5, set=[{"path": "v", "value": "float.nan"},
                                                                   {"path": "a", "value": "float.zero"}])
    case = _case("nan_speed", policy, stop_at=14.0)
    result = run_case(case)
    assert "violation:speed_limit" in result.signatures
    m = minimise(case, result, "violation:speed_limit", max_replays=40)
    assert m.reproduced and m.case is not None
    assert m.original_instances >= 9  # ~0.5 s of localization at 20 Hz, two fields each
    d = m.dimensionality
    assert d["interfaces"] == "field" and d["fields"] == ["localization:v"], d
    assert d["instances"] == "single"
    again = run_case(m.case)  # the minimal case replays to the same finding
    assert "violation:speed_limit" in again.signatures
    assert dimensionality(m.case.instances) == d


def test_hardening_prevents_a_builtin_planner_crash() -> None:
    policy = Policy(topic="localization", start=5.0, end=5.1, set=[{"path": "x", "value": "float.nan"}])
    off = run_case(TestCase(scenario=SCENARIO, jitter_seed=0, stop_at=9.0, policies=[policy]))
    assert any(s.startswith("crash:planning:") for s in off.signatures), off.signatures
    on = run_case(TestCase(scenario=SCENARIO, jitter_seed=0, stop_at=9.0, hardening=True, policies=[policy]))
    assert not on.failures and on.harness_errors == []


def test_hardened_nominal_run_is_identical_to_the_builtin_one() -> None:
    a = run_case(TestCase(scenario=SCENARIO, jitter_seed=2, stop_at=10.0))
    b = run_case(TestCase(scenario=SCENARIO, jitter_seed=2, stop_at=10.0, hardening=True))
    assert a.fingerprint == b.fingerprint
