"""Scenario files: the seeds load, and every kind of mistake gives one clear line."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

from deft_gym.bus.ads import load_ads_config
from deft_gym.config import ConfigError
from deft_gym.scenarios.scenario import list_scenarios, load_scenario, scenario_from_dict

SEED = Path(__file__).resolve().parents[2] / "configs" / "scenarios" / "left_turn.yaml"


def _data() -> dict:
    return yaml.safe_load(SEED.read_text())


def _error(data: dict, tmp_path: Path) -> str:
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as err:
        load_scenario(path)
    return str(err.value)


def test_every_seed_scenario_loads() -> None:
    names = {load_scenario(p).name for p in list_scenarios()}
    assert {"left_turn", "right_turn", "lane_follow_static", "u_turn", "cross_intersection", "take_exit",
            "blocked_red_light"} <= names


def test_unknown_key_names_file_and_field(tmp_path: Path) -> None:
    data = _data()
    data["participants"][0]["sped"] = 3.0
    msg = _error(data, tmp_path)
    assert "bad.yaml" in msg and "participants.0" in msg and "sped" in msg and "unknown key" in msg


def test_wrong_type_names_the_field(tmp_path: Path) -> None:
    data = _data()
    data["ego"]["speed"] = "fast"
    msg = _error(data, tmp_path)
    assert "bad.yaml: ego.speed" in msg and "number" in msg


def test_lane_that_does_not_exist(tmp_path: Path) -> None:
    data = _data()
    last = len(data["participants"]) - 1
    data["participants"][last]["lane"] = ["il1", "o9", 0]
    msg = _error(data, tmp_path)
    assert msg.count("\n") == 0
    assert f"participants.{last}.lane" in msg and "does not exist" in msg and "intersection" in msg


def test_position_outside_the_lane(tmp_path: Path) -> None:
    data = _data()
    data["ego"]["s"] = 500.0
    assert "ego.lane: s = 500.0 is outside lane" in _error(data, tmp_path)


def test_unreachable_destination(tmp_path: Path) -> None:
    data = _data()
    data["ego"]["destination"]["lane"] = ["o0", "ir0", 0]  # behind the start, against traffic
    data["ego"]["s"] = 90.0
    data["ego"]["destination"]["s"] = 10.0
    data["ego"]["lane"] = ["il1", "o1", 0]
    assert "not reachable" in _error(data, tmp_path)


def test_invalid_yaml_and_missing_file(tmp_path: Path) -> None:
    bad = tmp_path / "broken.yaml"
    bad.write_text("name: x\n  map: [unclosed\n")
    with pytest.raises(ConfigError, match=r"broken.yaml: invalid YAML"):
        load_scenario(bad)
    with pytest.raises(ConfigError, match=r"nope.yaml: cannot read"):
        load_scenario(tmp_path / "nope.yaml")


def test_participant_form_checks() -> None:
    data = copy.deepcopy(_data())
    data["participants"].append({"id": "c", "type": "static", "lane": ["o0", "ir0", 0]})
    new = len(data["participants"]) - 1
    with pytest.raises(ConfigError, match=rf"participants.{new}.static: Value error, a lane position needs both"):
        scenario_from_dict(data, source="inline")
    data["participants"][-1] = {"id": "oncoming", "type": "static", "x": 1.0, "y": 2.0}
    with pytest.raises(ConfigError, match="participant ids must be unique"):
        scenario_from_dict(data, source="inline")


def test_an_ads_config_can_build_on_another(tmp_path: Path) -> None:
    """``base:`` names a config (relative to the file) that the file's keys are deep-merged onto:
    the shipped legacy testbeds are the default and CommonRoad configs with the control law and
    the steering limit changed back (CommonRoad's planner given the library's default car again, the
    reference planner its following before v38), nothing else; a missing base, a loop or a base that
    is no path is one clear error naming the file."""
    from deft_gym.config import CONFIG_DIR

    for name, base in (("legacy", "default"), ("commonroad_legacy", "commonroad")):
        ours, theirs = load_ads_config(CONFIG_DIR / "ads" / f"{name}.yaml"), load_ads_config(CONFIG_DIR / "ads" / f"{base}.yaml")
        assert theirs.max_steering_deg == 50.0 and theirs.control.params["lateral"] == "curvature"
        want = theirs.model_copy(update={"max_steering_deg": 35.0, "control": theirs.control.model_copy(
            update={"params": {**theirs.control.params, "lateral": "pure_pursuit"}})})
        if name == "commonroad_legacy":  # the library's default car: CommonRoadParams' defaults
            from deft_gym.planner.commonroad import CommonRoadParams

            params = {k: CommonRoadParams.model_fields[k].default for k in theirs.planning.planner.params}
        else:  # the reference planner's following before v38 (docs/planner.md, "Following")
            params = {**theirs.planning.planner.params, "w_closing": 0.0, "follow_times": []}
        planner = theirs.planning.planner.model_copy(update={"params": params})
        want = want.model_copy(update={"planning": theirs.planning.model_copy(update={"planner": planner})})
        assert ours.model_dump() == want.model_dump()
    (tmp_path / "a.yaml").write_text("base: b.yaml\n")
    (tmp_path / "b.yaml").write_text("base: a.yaml\n")
    (tmp_path / "c.yaml").write_text("base: nope.yaml\n")
    (tmp_path / "d.yaml").write_text("base: [1]\n")
    for name, named, needle in (("a", "b", "leads back to itself"), ("c", "c", "no such file"),
                                ("d", "d", "expected the path of an ADS config")):
        with pytest.raises(ConfigError, match=needle) as err:
            load_ads_config(tmp_path / f"{name}.yaml")
        assert f"{named}.yaml: base:" in str(err.value) and "\n" not in str(err.value)


def test_ads_config_errors_name_the_field(tmp_path: Path) -> None:
    path = tmp_path / "ads.yaml"
    path.write_text("planning:\n  subscribe: [routing, gps]\n")
    with pytest.raises(ConfigError, match=r"ads.yaml: planning.subscribe: .*unknown topic role"):
        load_ads_config(path)
