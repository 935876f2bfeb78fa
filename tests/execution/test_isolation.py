"""Objects hosted in a child process of their own (deft_gym.execution.isolation) and planners run
that way (deft_gym.planner.base.HostedPlanner): nothing the object does ends the caller."""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import pytest

from deft_gym.execution.isolation import HostDied, Hosted, HostedError
from deft_gym.execution.watchdog import ModuleHang, Watchdog

ROOT = Path(__file__).resolve().parents[2]


class Thing:
    def __init__(self, start: int = 0) -> None:
        self.n = start

    def add(self, k: int) -> int:
        self.n += k
        return self.n

    def fail(self, what: str) -> None:
        if what == "exit":
            raise SystemExit(3)
        if what == "interrupt":
            raise KeyboardInterrupt
        raise ZeroDivisionError("boom")

    def end(self, how: str) -> None:
        if how == "os_exit":
            os._exit(7)
        os.kill(os.getpid(), getattr(signal, how))
        time.sleep(10)

    def sleep(self, s: float) -> str:
        time.sleep(s)
        return "woke"

    def unpicklable(self) -> object:
        return lambda: None


def test_calls_run_in_the_child_with_its_own_state() -> None:
    h = Hosted(lambda: Thing(5), "the thing")
    try:
        assert h.pid != os.getpid() and h.call("add", 2) == 7 and h.call("add", 1) == 8
    finally:
        h.close()
    assert h.ended == "closed"
    with pytest.raises(ChildProcessError):
        os.waitpid(h.pid, os.WNOHANG)  # reaped


@pytest.mark.parametrize("what, kind", [("exit", "SystemExit"), ("interrupt", "KeyboardInterrupt"),
                                        ("zero", "ZeroDivisionError")])
def test_whatever_it_raises_comes_back_as_an_exception_and_it_goes_on(what: str, kind: str) -> None:
    h = Hosted(Thing)
    with pytest.raises(HostedError) as err:
        h.call("fail", what)
    assert err.value.type_name == kind and err.value.location.endswith("test_isolation.py:fail")
    assert h.call("add", 1) == 1  # still there
    h.close()


@pytest.mark.parametrize("how, said", [("os_exit", "exited with status 7"), ("SIGSEGV", "killed by SIGSEGV"),
                                       ("SIGTERM", "killed by SIGTERM"), ("SIGKILL", "killed by SIGKILL")])
def test_its_process_ending_is_host_died_naming_how(how: str, said: str) -> None:
    h = Hosted(Thing, "the thing", source="/x/thing.py")
    with pytest.raises(HostDied) as err:
        h.call("end", how)
    assert said in str(err.value) and "during end()" in str(err.value) and err.value.location == "/x/thing.py:end"
    with pytest.raises(HostDied, match="had ended"):
        h.call("add", 1)


def test_a_call_that_blocks_is_the_watchdogs_hang_and_the_child_is_killed() -> None:
    h = Hosted(Thing)
    dog = Watchdog(0.3, 0)
    t0 = time.perf_counter()
    with dog.armed(), pytest.raises(ModuleHang):
        dog.call(h.call, "sleep", 30.0)
    assert time.perf_counter() - t0 < 5
    assert h.ended is not None
    with pytest.raises(HostDied):
        h.call("add", 1)


def test_a_hang_noticed_inside_a_destructor_is_raised_after_it_not_lost() -> None:
    """Python drops an exception raised in ``__del__``: a ModuleHang raised there used to be lost,
    and with it the call's one interruption (the call then ran on unwatched). The next heartbeat
    raises it once the destructor has returned."""
    import gc
    import warnings

    class SlowToDie:
        def __del__(self) -> None:
            time.sleep(0.6)  # the 0.3 s limit passes in here

    def module() -> None:
        obj = SlowToDie()
        del obj
        gc.collect()
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 3.0:  # a lost hang: returns, DID NOT RAISE
            pass

    dog = Watchdog(0.3, 0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an exception ignored in __del__ would be an error here
        with dog.armed(), pytest.raises(ModuleHang):
            dog.call(module)


def test_a_hang_noticed_inside_a_weakref_callback_is_raised_after_it_not_lost() -> None:
    """Python drops an exception raised in a weakref callback too - a WeakSet's, run by the garbage
    collector after another test's training left such objects behind, is where this was seen:
    the hang was lost and the call ran on unwatched. The next heartbeat raises it again."""
    import weakref

    class Node:
        pass

    def module() -> None:
        node = Node()
        ref = weakref.ref(node, lambda _: time.sleep(0.6))  # the 0.3 s limit passes in the callback
        del node
        assert ref() is None
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 3.0:  # a lost hang: returns, DID NOT RAISE
            pass

    def quick_after_a_drop() -> str:  # a call that returns at once: no hang carried over to it
        return "ok"

    def fails_after_a_drop() -> None:  # its own error right after the dropped hang, before a beat
        node = Node()
        ref = weakref.ref(node, lambda _: time.sleep(0.6))
        del node
        assert ref() is None
        raise ValueError("its own")

    dog = Watchdog(0.3, 0)
    before = sys.unraisablehook
    with dog.armed():
        with pytest.raises(ModuleHang):
            dog.call(module)
        assert dog.call(quick_after_a_drop) == "ok"
        with pytest.raises((ValueError, ModuleHang)):
            dog.call(fails_after_a_drop)
        assert dog.call(quick_after_a_drop) == "ok"  # the dropped hang is not carried over
    assert sys.unraisablehook is before  # the hook put back


def test_construction_errors_and_unpicklable_results_are_reported() -> None:
    def broken() -> Thing:
        raise ValueError("bad params")

    with pytest.raises(HostedError, match="bad params"):
        Hosted(broken)
    h = Hosted(Thing)
    with pytest.raises(HostedError, match="cannot send the result of unpicklable"):
        h.call("unpicklable")
    h.close()


def test_the_shipped_planner_runs_in_process_others_in_their_own(monkeypatch) -> None:
    """The default (auto): the reference lattice planner keeps the fast path (no process, nothing
    pickled); any other planner is hosted, and gives the same outputs bit for bit."""
    from deft_gym.bus.codec import encode
    from deft_gym.planner.base import HostedPlanner, load_planner, runs_isolated
    from deft_gym.planner.lattice import LatticePlanner
    from deft_gym.sim.simulation import Simulation
    from tests.support.fault_planners import FaultyPlanner

    monkeypatch.delenv("DEFT_GYM_PLANNER_ISOLATION", raising=False)
    assert not runs_isolated(LatticePlanner) and runs_isolated(FaultyPlanner)
    assert runs_isolated(LatticePlanner, "process") and not runs_isolated(FaultyPlanner, "inline")
    frames = []
    sim = Simulation(ROOT / "configs" / "scenarios" / "lane_follow_static.yaml", jitter_seed=7)
    plan = sim.planner.plan
    sim.planner.plan = lambda f: (frames.append(f), plan(f))[1]  # type: ignore[method-assign]
    sim.advance(4.0)
    spec = sim.scenario.map.model_dump()
    inline = load_planner("deft_gym.planner.lattice:LatticePlanner", spec, {})
    hosted = load_planner("deft_gym.planner.lattice:LatticePlanner", spec, {}, isolation="process")
    assert isinstance(inline, LatticePlanner) and isinstance(hosted, HostedPlanner)
    assert type(hosted).inputs == LatticePlanner.inputs
    try:
        for f in frames:
            assert encode(inline.plan(f) or {}) == encode(hosted.plan(f) or {})
        snap = hosted.snapshot()
        hosted.plan(frames[-1])
        hosted.restore(snap)
        assert encode(hosted.plan(frames[-1]) or {}) == encode(inline.plan(frames[-1]) or {})
        assert hosted.export_state() is not None
    finally:
        hosted.close()


def test_a_bad_isolation_setting_is_one_line(monkeypatch) -> None:
    from deft_gym.planner.base import isolation_mode

    monkeypatch.setenv("DEFT_GYM_PLANNER_ISOLATION", "sometimes")
    with pytest.raises(ValueError, match="DEFT_GYM_PLANNER_ISOLATION='sometimes'"):
        isolation_mode()
