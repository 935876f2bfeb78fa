"""The harness never crashes: a failing or hanging module is a finding, not an error of the tool."""

from __future__ import annotations

import time
from typing import Any

from deft_gym.modules.control import ControlNode
from deft_gym.modules.planning import PlanningNode
from deft_gym.robustness.monitors import DeadlineExceeded, deadline
from deft_gym.robustness.runner import run_case
from deft_gym.robustness.testcase import Policy, TestCase

SCENARIO = "configs/scenarios/left_turn.yaml"


class GarbageControl(ControlNode):
    """Returns something that is not a list of (topic, payload) after 3 s."""

    def compute(self, now_ns: int) -> Any:
        return "garbage" if now_ns > 3e9 else super().compute(now_ns)


class SilentPlanning(PlanningNode):
    """Stops producing plans after 3 s, without raising."""

    def compute(self, now_ns: int) -> Any:
        return None if now_ns > 3e9 else super().compute(now_ns)


class SpinningPlanning(PlanningNode):
    """Spins forever after 3 s, inside a broad try/except (which must not swallow the watchdog)."""

    def compute(self, now_ns: int) -> Any:
        if now_ns > 3e9:
            try:
                while True:
                    pass
            except Exception:
                return None
        return super().compute(now_ns)


def _run(module: str, cls: str, **kw: Any) -> Any:
    return run_case(TestCase(scenario=SCENARIO, jitter_seed=0, stop_at=8.0, deadline_s=0.3,
                             ads_overrides={module: {"node": f"tests.robustness.test_monitors:{cls}"}}, **kw))


def test_invalid_module_output_is_a_crash_finding() -> None:
    r = _run("control", "GarbageControl")
    assert r.signatures[0].startswith("crash:control:InvalidOutput"), r.signatures
    assert r.harness_errors == []


def test_silent_module_is_a_hang_finding() -> None:
    r = _run("planning", "SilentPlanning")
    assert "hang:planning:silent" in r.signatures and r.harness_errors == []
    assert 3.9 < r.failures[0]["time"] < 4.3  # 10 periods of 0.1 s after the last plan (~3 s)


def test_endless_loop_is_interrupted_as_a_hang() -> None:
    t0 = time.perf_counter()
    r = _run("planning", "SpinningPlanning")
    assert r.signatures[0] == "hang:planning:deadline", r.signatures
    assert r.sim_time < 6.0  # the run ended grace_s after the hang
    assert time.perf_counter() - t0 < 60


def test_exceptional_values_everywhere_never_break_the_harness() -> None:
    policies = [Policy(topic=t, start=1.0, end=6.0, set=[{"path": p, "value": v}]) for t, p, v in [
        ("routing", "segments", "any.wrong_type"), ("localization", "heading", "float.inf"),
        ("perception_obstacles", "obstacles", "array.long"), ("traffic_light", "lights[*].color", "enum.bogus"),
        ("prediction", "obstacles[*].x[*]", "float.nan"), ("planning", "trajectory.v", "any.null")]]
    policies[0] = policies[0].model_copy(update={"start": 0.0})
    r = run_case(TestCase(scenario=SCENARIO, jitter_seed=0, stop_at=8.0, policies=policies))
    assert r.harness_errors == [] and r.signatures


def test_deadline_context_manager() -> None:
    try:
        with deadline(0.2):
            while True:
                pass
    except DeadlineExceeded:
        pass
    with deadline(0.5):
        sum(range(1000))


def test_a_deadline_that_lands_in_a_destructor_is_raised_after_it_not_lost() -> None:
    """Python drops an exception raised in ``__del__`` ("Exception ignored in ..."): a deadline that
    fired there used to vanish, and the computation ran on unguarded (seen as a warning in the
    harness test above). It now fires again just after the destructor returns."""
    import gc
    import warnings

    import pytest

    class Slow:
        def __del__(self) -> None:
            t = time.process_time()
            while time.process_time() - t < 0.3:  # the whole 0.1 s deadline passes in here
                pass

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an exception ignored in __del__ would be an error here
        t0 = time.process_time()
        with pytest.raises(DeadlineExceeded), deadline(0.1):
            obj = Slow()
            del obj  # the destructor runs now and spends the deadline
            gc.collect()
            while time.process_time() - t0 < 2.0:  # a lost deadline: out of here, DID NOT RAISE
                pass


def test_a_computing_module_is_left_to_the_cpu_deadline_when_the_wall_budget_runs_out(monkeypatch) -> None:
    """A loaded machine makes a spinning computation run past its wall budget before it has used
    its CPU deadline; it is still the CPU deadline's hang (reason deadline), not a blocked one,
    whatever the load."""
    monkeypatch.setenv("DEFT_GYM_WATCHDOG_S", "0.05")  # the wall budget, far below the 0.3 s CPU deadline
    r = _run("planning", "SpinningPlanning")
    assert "hang:planning:deadline" in r.signatures, r.signatures
    assert not any("wall_deadline" in s for s in r.signatures) and r.harness_errors == []


def test_deadline_block_tells_blocking_from_computing() -> None:
    import pytest

    from deft_gym.robustness.monitors import WallDeadlineExceeded

    with pytest.raises(WallDeadlineExceeded), deadline(0.05):  # wall budget 2 s: a sleep burns no CPU
        time.sleep(5.0)
    with pytest.raises(DeadlineExceeded) as err, deadline(0.3):
        while True:
            pass
    assert type(err.value) is DeadlineExceeded
