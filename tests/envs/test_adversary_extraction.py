"""A failing adversary episode goes to the DeFT extractor, whose pytest module reproduces it."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from deft_gym.envs.adversary import ALONG, AT_LAST, LATERAL, OPS, AdversaryEnv
from deft_gym.search.context import seed_context
from deft_gym.search.episode import run_scenario
from deft_gym.search.feasible import PAPER

pytestmark = pytest.mark.slow


def _parked(along: float | str, lateral: float) -> np.ndarray:
    i = ALONG.index(along) if along in ALONG else len(ALONG) + AT_LAST.index(along)
    return np.array([OPS.index("static_vehicle"), i, LATERAL.index(lateral), 1, 0])


def test_failing_episode_is_extracted_into_a_reproducing_pytest_module_with_a_failure_test(tmp_path):
    # two parked cars beside the path, the second placed mid-run ahead of the ego and inside its lane
    # (Decictor's rule allows it): the planner borrows the next lane -> NoDS
    plan = {1: _parked(-10.0, -3.5), 4: _parked("last+8", -2.0)}
    env = AdversaryEnv(scenario="lane_follow_static", log_dir=str(tmp_path), keep_passing=0.0, feasible=PAPER)
    env.reset(seed=0)
    done, k, info = False, 0, {}
    while not done:
        _, _, done, _, info = env.step(plan.get(k, np.zeros(5, dtype=np.int64)))
        k += 1
    assert info["failure"] == "nods" and info["valid"], info
    ex = info["extraction"]
    assert ex and ex["status"] == "ok" and ex["test"], ex
    episode = json.loads((tmp_path / info["log"].split(str(tmp_path) + "/")[-1] / "episode.json").read_text())
    # the failure replays deterministically from the episode's equivalent scenario
    eq = episode["scenario_equivalent"]
    ctx = seed_context("lane_follow_static", PAPER)
    specs = eq["scenario"]["participants"][len(ctx.scenario.participants):]
    again = run_scenario(ctx, specs, eq["jitter_seed"], added_at=eq["added_at"])
    assert again.verdict.failure == "nods" and again.verdict.iou == pytest.approx(info["iou"], abs=1e-4)
    # and the extracted planning-module tests reproduce every output, while the non-optimal
    # decision's failure test (P_departure: the log carries the optimal path) fails
    base = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=", ex["test"]]
    proc = subprocess.run([*base, "-k", "reproduces"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    dep = subprocess.run([*base, "-k", "keeps_to_the_optimal_path"], capture_output=True, text=True)
    assert dep.returncode == 1 and "still leaves the optimal path" in dep.stdout, dep.stdout[-2000:]
