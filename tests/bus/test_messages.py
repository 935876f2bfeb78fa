"""The message schemas document every field, and the map reaches planners as data."""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from deft_gym.bus.messages import FRAMES, ROLES, SCHEMAS
from deft_gym.planner.base import validate_output
from deft_gym.robustness.sanitize import problem
from deft_gym.world.roadmap import shared_roadmap


def _fields(schema: dict[str, Any], path: str = "") -> Iterator[tuple[str, dict[str, Any]]]:
    yield path, schema
    if schema.get("type") == "object":
        for k, sub in schema.get("properties", {}).items():
            yield from _fields(sub, f"{path}.{k}" if path else k)
    elif schema.get("type") == "array":
        items = schema.get("items", {})
        for i, sub in enumerate(items if isinstance(items, list) else [items]):
            yield from _fields(sub, f"{path}[{i if isinstance(items, list) else '*'}]")


@pytest.mark.parametrize("role", ROLES)
def test_every_field_has_a_description_unit_and_frame(role: str) -> None:
    """Every field is described; every number has a unit; positions, headings and times name
    their frame or time base (one of FRAMES)."""
    for path, sub in _fields(SCHEMAS[role]):
        assert sub.get("description"), f"{role}:{path} has no description"
        if sub.get("type") == "number":
            assert sub.get("x-unit"), f"{role}:{path} has no unit"
            if sub["x-unit"] == "m" and path.split(".")[-1].split("[")[0] in ("x", "y", "s"):
                assert sub.get("x-frame") in FRAMES, f"{role}:{path}: a position names its frame"
            if sub["x-unit"] == "rad" and "heading" in path:
                assert sub.get("x-frame") == "world", f"{role}:{path}: a heading names its frame"
        if "x-frame" in sub:
            assert sub["x-frame"] in FRAMES


@pytest.mark.parametrize("kind", ["intersection", "highway", "uturn"])
def test_the_map_message_describes_the_roadmap(kind: str) -> None:
    rm = shared_roadmap({"type": kind})
    data = rm.as_data()
    payload = {"header": {"seq": 0, "stamp": 0.0, "module": "routing"}, **data}
    assert problem("map", payload) is None  # valid against its own schema
    lanes = {tuple(lane["id"]): lane for lane in data["lanes"]}
    assert set(lanes) == set(rm.lane_ids)
    for lid, lane in lanes.items():
        g = rm.geoms[lid]
        pts = g.xy(np.array(lane["s"]))
        assert np.allclose(pts[:, 0], lane["x"], atol=1e-9) and np.allclose(pts[:, 1], lane["y"], atol=1e-9)
        assert lane["s"][0] == 0.0 and math.isclose(lane["s"][-1], lane["length"]) and len(lane["x"]) >= 2
        assert max(np.diff(lane["s"])) <= 0.5 + 1e-9 or len(lane["s"]) == 2
        assert [tuple(x) for x in lane["successors"]] == rm.successors[lid]
        change = rm.changeable_neighbours(lid)
        assert lane["change_left"] == (tuple(lane["left"]) in change if lane["left"] else False)
        assert lane["change_right"] == (tuple(lane["right"]) in change if lane["right"] else False)
    for sl in data["stop_lines"]:
        assert sl["light_id"] in data["lights"] and tuple(sl["lane"]) in lanes
    if kind == "intersection":
        assert data["lights"] == ["tl0", "tl1", "tl2", "tl3"] and len(data["stop_lines"]) == 8
    assert rm.as_data() is not data and rm.as_data() == data  # a fresh copy each time


def test_the_output_contract() -> None:
    good = {"trajectory": {"t": [1.0, 1.5], "x": [0.0, 1.0], "y": [0.0, 0.0], "v": [2.0, 2.0],
                           "heading": [0.0, 0.0], "a": [0.0, 0.0]}, "decision": {"mode": "keep"}}
    assert validate_output(good, 1.0) == [] and validate_output(None, 1.0) == []
    assert validate_output({**good, "decision": None}, 1.0) == []  # the decision is optional
    cases = [({"t": [1.0, 1.0]}, "not strictly increasing"), ({"t": [1.2, 1.5]}, "expected the frame time"),
             ({"v": [2.0]}, "has 1 points"), ({"a": [0.0, math.nan]}, "non-finite"), ({"heading": None}, "missing"),
             ({"x": ["0", 1.0]}, "not a list of numbers")]
    for patch, needle in cases:
        tr = {**good["trajectory"], **patch}
        if patch.get("heading", 0) is None:
            del tr["heading"]
        assert any(needle in p for p in validate_output({"trajectory": tr}, 1.0)), (patch, needle)
    assert validate_output({"decision": {}}, 1.0) == ["output has no 'trajectory' object"]
    assert "decision is a list" in validate_output({**good, "decision": []}, 1.0)[0]


def test_planner_inputs_are_the_single_source_of_the_frame(tmp_path) -> None:
    """The planning module subscribes to the planner's Planner.inputs; an ADS config naming other
    roles is a one-line error naming the file and the planner."""
    import subprocess
    import sys

    from deft_gym.bus.ads import load_ads_config
    from deft_gym.config import ConfigError
    from deft_gym.modules.planning import frame_roles
    from deft_gym.planner.lattice import LatticePlanner

    assert frame_roles(LatticePlanner, load_ads_config().planning) == list(LatticePlanner.inputs)
    bad = tmp_path / "ads.yaml"
    bad.write_text("planning:\n  subscribe: [routing, localization]\n")
    with pytest.raises(ConfigError, match=r"\['prediction', 'traffic_light'\] missing"):
        frame_roles(LatticePlanner, load_ads_config(bad).planning, str(bad))
    proc = subprocess.run([sys.executable, "-m", "deft_gym.cli.run", "left_turn", "--ads-config", str(bad),
                           "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert proc.returncode == 2 and str(bad) in proc.stdout and "LatticePlanner.inputs" in proc.stdout
    assert proc.stdout.strip().count("\n") == 0
