"""Helpers shared by the extractor tests (no tests here): small real episodes and pytest runs.

Episodes are real deft_gym runs with a fixed jitter seed, shortened where the scenario allows,
so each costs about a second.
"""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

from deft_gym.experiments.record import record_episode
from deft_gym.planner.lattice import LatticePlanner
from deft_gym.scenarios.scenario import load_scenario, scenario_from_dict, scenario_to_dict
from deft_gym.scenarios.variants import inject_cut_in
from deft_gym.sim.simulation import reference_path

ROOT = Path(__file__).resolve().parents[2]  # on the path of the subprocesses: tests.support.* imports

#: cut-in variants that collided with the reference planner, tried in order
COLLISION_CANDIDATES = [("cross_intersection", 0, 1000), ("take_exit", 0, 1000), ("right_turn", 0, 1000),
                        ("left_turn", 7, 1000), ("blocked_red_light", 0, 1000)]


def short_scenario(name: str, duration: float) -> Any:
    """A seed scenario cut to ``duration`` seconds."""
    data = scenario_to_dict(load_scenario(name))
    data["duration"] = duration
    data["name"] = f"{data['name']}_short"
    return scenario_from_dict(data, source=f"{name} (short)")


def record(out: Path, scenario: Any, seed: int = 7, **kwargs: Any) -> Path:
    """Record one episode into ``out``; returns the log path."""
    res = record_episode(scenario, out, jitter_seed=seed, **kwargs)
    assert res.log_path is not None
    return Path(res.log_path)


def colliding_episode(out: Path) -> tuple[Path, str] | None:
    """The first candidate cut-in scenario whose run collides: ``(log, scenario name)``."""
    refs: dict[str, Any] = {}
    for k, (name, cut, seed) in enumerate(COLLISION_CANDIDATES):
        sc = load_scenario(name)
        if name not in refs:
            refs[name] = reference_path(sc, jitter_seed=0)
        variant = inject_cut_in(sc, refs[name], seed=cut)
        res = record_episode(variant, out / f"cand{k}", jitter_seed=seed)
        if res.outcome.collision is not None:
            return Path(res.log_path), variant.name
    return None


def run_pytest(path: Path, *args: str, env: dict[str, str] | None = None) -> tuple[int, dict[str, str], str]:
    """Run pytest on generated tests in a subprocess: ``(returncode, {test name: outcome}, output)``."""
    xml = path / f"junit-{os.getpid()}-{len(list(path.glob('junit-*.xml')))}.xml"
    full_env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
                **(env or {})}
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
                           f"--junitxml={xml}", str(path), *args], capture_output=True, text=True, env=full_env)
    outcomes: dict[str, str] = {}
    if xml.exists():
        for tc in ET.parse(xml).getroot().iter("testcase"):
            if tc.find("failure") is not None or tc.find("error") is not None:
                status = "failed"
            elif tc.find("skipped") is not None:
                status = "skipped"
            else:
                status = "passed"
            outcomes[tc.get("name", "")] = status
        xml.unlink()
    return proc.returncode, outcomes, proc.stdout + proc.stderr


class ElsewherePlanner(LatticePlanner):
    """A deliberately changed planner: plans like the reference one, 100 m to the side (so it
    never plans into anything the reference planner hit)."""

    def plan(self, frame: Any) -> dict[str, Any] | None:
        out = super().plan(frame)
        if out is not None:
            out["trajectory"]["y"] = [y + 100.0 for y in out["trajectory"]["y"]]
        return out


class HiddenStatePlanner(LatticePlanner):
    """The reference planner with state kept outside ``self.state``, as CommonRoad's reactive
    planner keeps its low-speed flag: a low-pass filtered start speed, updated by every call, that
    shifts the plan by a few millimetres. A clean replay is deterministic; snapshot(), a call with
    another frame and restore() leave the filter where the other frame put it."""

    def __init__(self, map_spec: dict[str, Any], **params: Any) -> None:
        super().__init__(map_spec, **params)
        self._v_filtered = 0.0

    def reset(self) -> None:
        super().reset()
        self._v_filtered = 0.0

    def plan(self, frame: Any) -> dict[str, Any] | None:
        out = super().plan(frame)
        if out is not None:
            v0 = out["trajectory"]["v"][0]
            self._v_filtered = 0.8 * self._v_filtered + 0.2 * v0
            shift = 0.0025 * (self._v_filtered > 4.0)
            out["trajectory"]["x"] = [x + shift for x in out["trajectory"]["x"]]
        return out


class WindowedPlanner(LatticePlanner):
    """The reference planner whose outputs (never its state) are shifted 0.5 m sideways while the
    frame time is inside one of ``DEFT_WINDOWS`` (JSON ``[[t0, t1], ...]`` from the environment):
    a regression confined to those frames - between and after them it plans exactly as the
    reference planner does."""

    def plan(self, frame: Any) -> dict[str, Any] | None:
        import copy
        import json

        out = super().plan(frame)
        windows = json.loads(os.environ.get("DEFT_WINDOWS", "[]"))
        if out is not None and any(t0 <= frame.time <= t1 for t0, t1 in windows):
            out = copy.deepcopy(out)
            out["trajectory"]["y"] = [y + 0.5 for y in out["trajectory"]["y"]]
        return out


class _BrokenFrom(LatticePlanner):
    """The reference planner whose plans ``break_plan`` changes in place from ``BROKEN_FROM`` s on."""

    BROKEN_FROM = 0.0  # [s]

    def plan(self, frame: Any) -> dict[str, Any] | None:
        out = super().plan(frame)
        if out is not None and frame.time >= self.BROKEN_FROM:
            self.break_plan(out["trajectory"])
        return out

    def break_plan(self, tr: dict[str, Any]) -> None:
        raise NotImplementedError


class OncomingPlanner(_BrokenFrom):
    """A deliberately broken planner: from ``BROKEN_FROM`` s on, every plan bends one lane width
    (3.5 m) to the left of its own heading (the driver's left) over its first second - into the
    oncoming lane where the road has one next to the ego's - and holds that offset."""

    BROKEN_FROM = 3.0  # [s]

    def break_plan(self, tr: dict[str, Any]) -> None:
        import math

        t0 = tr["t"][0]
        for k, (t, h) in enumerate(zip(tr["t"], tr["heading"])):
            d = 3.5 * min((t - t0) / 1.0, 1.0)
            tr["x"][k] += math.sin(h) * d  # highway-env's y points to the right of heading 0
            tr["y"][k] -= math.cos(h) * d


class StallingPlanner(_BrokenFrom):
    """A deliberately broken planner: from ``BROKEN_FROM`` s on, every plan brakes the ego to a
    stop where it is (all points at the first, speed 0) on whatever road lies ahead."""

    BROKEN_FROM = 2.0  # [s]

    def break_plan(self, tr: dict[str, Any]) -> None:
        for key in ("x", "y", "heading"):
            tr[key] = [tr[key][0]] * len(tr[key])
        tr["v"] = [0.0] * len(tr["v"])
        tr["a"] = [0.0] * len(tr["a"])


class StraightPlanner(_BrokenFrom):
    """A deliberately broken planner for roads along x: every plan goes straight on along the
    line y = ``LINE_Y`` (lane_follow_static's left lane centre), heading 0, from its first point's
    x over the path lengths the reference planner chose - it never steers round what stands at
    the edge of its lane."""

    LINE_Y = 0.0  # [m]

    def break_plan(self, tr: dict[str, Any]) -> None:
        import math

        steps = [math.hypot(tr["x"][k] - tr["x"][k - 1], tr["y"][k] - tr["y"][k - 1]) for k in range(1, len(tr["x"]))]
        for k, step in enumerate(steps, start=1):
            tr["x"][k] = tr["x"][k - 1] + step
        tr["y"] = [self.LINE_Y] * len(tr["y"])
        tr["heading"] = [0.0] * len(tr["heading"])


class GreenLightPlanner(LatticePlanner):
    """A deliberately broken planner: the reference planner given every frame with all its
    traffic lights green - it drives through red ones (a light it is not told of it treats as red)."""

    def plan(self, frame: Any) -> dict[str, Any] | None:
        from deft_gym.planner.base import Frame

        lights = frame.get("traffic_light")
        if lights:
            lights = {**lights, "lights": [{**lt, "color": "GREEN"} for lt in lights.get("lights", [])]}
        return super().plan(Frame(frame.time, {**frame.inputs, "traffic_light": lights}))
