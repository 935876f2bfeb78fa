"""Test specification, field paths and the exceptional-values dictionary (no simulation)."""

from __future__ import annotations

import math
import sys

import pytest

from deft_gym.robustness import paths
from deft_gym.robustness.dictionary import DICTIONARY, candidates, lookup, mutate
from deft_gym.robustness.spec import TestSpecification
from deft_gym.robustness.testcase import Policy, TestCase, load_case, save_case

SPEC = TestSpecification.from_schemas()


def test_spec_covers_every_topic_with_typed_fields() -> None:
    assert set(SPEC.message_types) == {"routing", "map", "localization", "chassis", "perception_obstacles",
                                       "traffic_light", "prediction", "planning", "control"}
    f = SPEC.field("localization", "v")
    assert f is not None and f.type == "float" and f.unit == "m/s"
    assert SPEC.field("perception_obstacles", "obstacles[3].type").enum[0] == "VEHICLE"
    assert SPEC.field("planning", "trajectory.t").type == "array"
    assert SPEC.field("routing", "destination.lane[2]").type == "int"  # a lane id is a tuple


def test_brittle_fields_are_skipped_by_default() -> None:
    default = {f.key for f in SPEC.select()}
    with_brittle = {f.key for f in SPEC.select(brittle=True)}
    assert "localization:header.stamp" not in default and "localization:header.stamp" in with_brittle
    assert "prediction:perception_stamp" not in default
    assert "localization:v" in default
    # chassis (no subscriber) and control (consumed by the simulator only) are not default targets
    assert not any(k.startswith(("chassis:", "control:")) for k in default)


def test_dictionary_has_the_exceptional_values_per_type() -> None:
    floats = {DICTIONARY[n].fn(1.0, None) for n in candidates(SPEC.field("localization", "x"), True)
              if n not in ("any.null", "any.wrong_type")}
    assert any(isinstance(v, float) and math.isnan(v) for v in floats)
    for v in (math.inf, -math.inf, 0.0, sys.float_info.max, -sys.float_info.max, sys.float_info.min, 5e-324,
              1e300, 1e-300):
        assert v in floats
    assert math.copysign(1.0, mutate("float.neg_zero", 1.0)) == -1.0
    ints = {mutate(n, 5) for n in candidates(SPEC.field("perception_obstacles", "obstacles[*].id"), True)}
    assert {0, -1, 2**31 - 1, -(2**31), 2**63 - 1, 2**64 - 1} <= ints
    arr = [1.0, 2.0, 3.0]
    assert mutate("array.empty", arr) == [] and mutate("array.one", arr) == [1.0]
    assert len(mutate("array.long", arr)) == 10_000 and mutate("array.repeated", arr) == [1.0] * 3
    assert mutate("enum.bogus", "RED") not in ("GREEN", "YELLOW", "RED", "UNKNOWN")
    # likely-valid values exist so tests can mix valid and exceptional fields
    assert candidates(SPEC.field("localization", "x"), False)
    assert "enum.member:GREEN" in candidates(SPEC.field("traffic_light", "lights[*].color"), False)
    assert lookup("enum.member:RED").fn("GREEN", None) == "RED"
    # time-like brittle fields get stale / backwards stamps
    assert mutate("float.stale", 5.0, 4.95) == 4.95 and mutate("float.backwards", 5.0) == 4.0


def test_paths_expand_and_apply() -> None:
    payload = {"obstacles": [{"x": 1.0}, {"x": 2.0}], "trajectory": {"v": [1.0, 2.0]}}
    assert paths.expand(payload, "obstacles[*].x") == ["obstacles[0].x", "obstacles[1].x"]
    n = paths.apply(payload, "trajectory.v[*]", lambda old, p: -old)
    assert n == 2 and payload["trajectory"]["v"] == [-1.0, -2.0]
    assert paths.apply(payload, "missing.field", lambda old, p: 0) == 0
    assert paths.get(payload, "obstacles[1].x") == 2.0
    assert SPEC.normalise("prediction", "obstacles[3].x[7]") == "obstacles[*].x[*]"
    with pytest.raises(paths.PathError):
        paths.parse("a..[")


def test_test_case_round_trip_and_errors(tmp_path) -> None:
    case = TestCase(scenario="configs/scenarios/left_turn.yaml", jitter_seed=3,
                    policies=[Policy(topic="localization", start=1.0, end=2.0,
                                     set=[{"path": "v", "value": "float.nan"}])])
    path = save_case(case, tmp_path / "c.json")
    assert load_case(path) == case
    bad = tmp_path / "bad.json"
    bad.write_text('{"scenario": "x.yaml", "jitter_seed": 1, "policies": [{"topic": "nope", "start": 0, "end": 1}]}')
    with pytest.raises(Exception) as err:
        load_case(bad)
    msg = str(err.value)
    assert str(bad) in msg and "policies.0.topic" in msg and "\n" not in msg
