"""Crash and hang monitors.

- :class:`GuardedSupervisor` replaces the bus supervisor: it runs every node computation, turns an
  exception into a *crash* finding and a computation that overruns its deadline (CPU seconds, the
  garbage collector's pauses not counted) into a *hang* finding (a SIGPROF watchdog interrupts it -
  runs are single-threaded and own the main thread); a computation that blocks without burning CPU
  (sleeps, waits on a lock or a socket) is a hang after ``wall_s`` seconds of wall clock (a SIGALRM watchdog, default
  :func:`wall_budget` of the CPU deadline, or ``--watchdog-s``), checks the shape of what the node returns, and marks the failed node dead, as a
  process that died would be. Failures never propagate into the harness.
- :class:`SilenceMonitor` (an ``on_step`` callback) reports a node that stopped publishing for
  ``k`` of its periods - the paper's other kind of hang, a module that ceases communication -
  and nodes that missed ``k`` timer ticks because they were still busy.
"""

from __future__ import annotations

import gc
import os
import signal
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from typing import Any

from deft_gym.bus.messages import NS_PER_S
from deft_gym.execution.watchdog import (
    ENV,
    CountingInterrupts,
    in_destructor,
    interrupts,
    module_fault,
    watchdog_seconds,
)

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

#: which module publishes each topic role (silence of a triggered node is judged by its trigger)
# The watchdog counts the process's CPU time (user + system), not wall time: a module in an
# endless loop burns CPU and is interrupted, while a run that is merely descheduled on a loaded
# machine is not mistaken for a hang - findings stay deterministic.
_TIMER = signal.ITIMER_PROF
_SIGNAL = signal.SIGPROF

PUBLISHER = {"routing": "routing", "localization": "localization", "perception_obstacles": "perception",
             "traffic_light": "traffic_light", "prediction": "prediction", "planning": "planning",
             "control": "control"}


class DeadlineExceeded(BaseException):
    """Raised in a module computation by the watchdog (a BaseException, so that a module's own
    ``except Exception`` cannot swallow it)."""


class WallDeadlineExceeded(DeadlineExceeded):
    """Raised by the wall-clock watchdog: the computation blocked (it did not burn CPU)."""


_RETRY_S = 0.001  # [s] how soon a deadline that landed in a destructor fires again

# The deadline counts the module's CPU, not the garbage collector's pauses: a full collection's
# length depends on everything the process holds (a test worker's heap after hundreds of tests, a
# campaign's caches), so counted, it made a hang of a computation that was not one.
# [process CPU s spent in collections so far, when the running one began (-1: none), the first
# at the last arming or credit of the deadline]
_GC = [0.0, -1.0, 0.0]


def _gc_clock(phase: str, info: dict[str, Any]) -> None:
    """A ``gc.callbacks`` entry: adds up the process CPU time of each collection."""
    if phase == "start":
        _GC[1] = time.process_time()
    elif _GC[1] >= 0.0:
        _GC[0] += time.process_time() - _GC[1]
        _GC[1] = -1.0


def _gc_seconds() -> float:
    """Process CPU [s] the garbage collector has taken so far (the running collection included)."""
    return _GC[0] + (time.process_time() - _GC[1] if _GC[1] >= 0.0 else 0.0)


def _arm_deadline(deadline_s: float) -> None:
    _GC[2] = _gc_seconds()
    signal.setitimer(_TIMER, deadline_s)


def _raise_deadline(signum: int, frame: Any) -> None:
    paused = _gc_seconds() - _GC[2]
    if paused > 0.0:  # the collector ran inside the computation: the deadline moves by its CPU
        _GC[2] += paused
        signal.setitimer(_TIMER, paused)
        return
    if in_destructor(frame):  # raised after the destructor, not lost in it
        signal.setitimer(_TIMER, _RETRY_S)
        return
    raise DeadlineExceeded()


# when the guarded computation started: (process CPU time [s], wall clock [s], wall budget [s])
_STARTED = [0.0, 0.0, 0.0]
COMPUTING_SHARE = 0.05  # a computation that got this share of its wall time as CPU is not blocked


def _start_wall(budget: float) -> None:
    _STARTED[:] = [time.process_time(), time.perf_counter(), budget]
    signal.setitimer(signal.ITIMER_REAL, budget)


def _raise_wall_deadline(signum: int, frame: Any) -> None:
    """The wall-clock budget ran out: a hang if the computation blocked; one that is computing
    (merely slowed by a loaded machine) is left to the CPU deadline, so the finding does not
    depend on the machine's load."""
    cpu0, wall0, budget = _STARTED
    if time.process_time() - cpu0 > COMPUTING_SHARE * (time.perf_counter() - wall0):
        signal.setitimer(signal.ITIMER_REAL, budget)
        return
    if in_destructor(frame):  # raised after the destructor, not lost in it
        signal.setitimer(signal.ITIMER_REAL, _RETRY_S)
        return
    raise WallDeadlineExceeded()


def wall_budget(deadline_s: float) -> float:
    """The default wall-clock budget of a computation with a CPU deadline of ``deadline_s``: three
    times it, at least 2 s (a loaded machine slows computations, it does not triple them) - unless
    the watchdog is set (``--watchdog-s``, ``DEFT_GYM_WATCHDOG_S``; 0 = no wall-clock limit)."""
    if os.environ.get(ENV, "").strip():
        return watchdog_seconds()
    return max(3.0 * deadline_s, 2.0)


@contextmanager
def deadline(seconds: float) -> Iterator[None]:
    """Raise :class:`DeadlineExceeded` in the block after ``seconds`` of CPU time, or
    :class:`WallDeadlineExceeded` after :func:`wall_budget` seconds of wall clock (main thread
    only; elsewhere the block runs unguarded)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(_SIGNAL, _raise_deadline)
    old_wall = signal.signal(signal.SIGALRM, _raise_wall_deadline)
    signal.setitimer(_TIMER, seconds)
    _start_wall(wall_budget(seconds))
    try:
        yield
    finally:
        signal.setitimer(_TIMER, 0)
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(_SIGNAL, old or signal.SIG_DFL)
        signal.signal(signal.SIGALRM, old_wall or signal.SIG_DFL)


@dataclass
class Failure:
    """A crash or hang of one node."""

    kind: str  # crash | hang
    node: str
    reason: str  # exception | invalid_output | deadline | silent | missed_ticks
    time: float  # sim time [s]
    exc_type: str = ""
    message: str = ""
    location: str = ""  # innermost project frame, "path:function"
    wall_s: float = 0.0

    @property
    def signature(self) -> str:
        """Stable name of the finding (no line numbers, no values)."""
        if self.kind == "crash":
            return f"crash:{self.node}:{self.exc_type}@{self.location}"
        return f"hang:{self.node}:{self.reason}"

    def as_dict(self) -> dict[str, Any]:
        return {**asdict(self), "signature": self.signature}


def location(tb: Any) -> str:
    """``path:function`` of the innermost frame inside the repository (else the innermost)."""
    frames = traceback.extract_tb(tb)
    if not frames:
        return "?"
    inside = [f for f in frames if f.filename.startswith(ROOT) and "/.venv/" not in f.filename]
    f = inside[-1] if inside else frames[-1]
    path = os.path.relpath(f.filename, ROOT) if f.filename.startswith(ROOT) else os.path.basename(f.filename)
    return f"{path}:{f.name}"


def _relative(where: str) -> str:
    """``path:function`` of a frame named elsewhere, as :func:`location` names it."""
    path, _, fn = where.rpartition(":")
    if path.startswith(ROOT):
        return f"{os.path.relpath(path, ROOT)}:{fn}"
    return f"{os.path.basename(path)}:{fn}"


def _valid_outputs(out: Any) -> bool:
    if out is None:
        return True
    if not isinstance(out, list):
        return False
    return all(isinstance(o, tuple) and len(o) == 2 and isinstance(o[0], str) and isinstance(o[1], dict)
               and isinstance(o[1].get("header"), dict) for o in out)


class GuardedSupervisor:
    """Runs node computations; a crash or an overrun is a finding, never an error of the tool."""

    def __init__(self, bus: Any, deadline_s: float = 1.0,
                 on_failure: Callable[[Failure], None] | None = None, wall_s: float | None = None) -> None:
        self.bus = bus
        self.deadline_s = deadline_s
        self.wall_s = wall_budget(deadline_s) if wall_s is None else wall_s
        self.on_failure = on_failure
        self.failures: list[Failure] = []
        self.max_wall: dict[str, float] = {}
        self._armed = threading.current_thread() is threading.main_thread()
        self._old_handler: Any = None
        self._old_wall: Any = None
        self._gc_clock = False  # whether this supervisor put the collector's clock in gc.callbacks

    # -- watchdog ---------------------------------------------------------------------------
    def __enter__(self) -> GuardedSupervisor:
        self._counting = CountingInterrupts().__enter__()  # a KeyboardInterrupt a module raises: a crash
        if self._armed:
            self._old_handler = signal.signal(_SIGNAL, _raise_deadline)
            self._old_wall = signal.signal(signal.SIGALRM, _raise_wall_deadline)
            self._gc_clock = _gc_clock not in gc.callbacks
            if self._gc_clock:
                gc.callbacks.append(_gc_clock)
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._armed:
            self._disarm()
            signal.signal(_SIGNAL, self._old_handler or signal.SIG_DFL)
            signal.signal(signal.SIGALRM, self._old_wall or signal.SIG_DFL)
            if self._gc_clock and _gc_clock in gc.callbacks:
                gc.callbacks.remove(_gc_clock)
        self._counting.__exit__(*exc)

    def _disarm(self) -> None:
        signal.setitimer(_TIMER, 0)
        signal.setitimer(signal.ITIMER_REAL, 0)

    # -- the supervisor ---------------------------------------------------------------------
    def run(self, node: Any, fn: Callable[..., Any], *args: Any) -> Any:
        if not node.alive:
            return None
        t0 = time.perf_counter()
        before = interrupts()
        try:
            if self._armed:
                _arm_deadline(self.deadline_s)
                _start_wall(self.wall_s)
            out = fn(*args)
            if self._armed:
                self._disarm()
        except WallDeadlineExceeded as exc:
            if self._armed:
                self._disarm()
            self._fail(node, Failure("hang", node.name, "wall_deadline", self.bus.now, "WallDeadlineExceeded",
                                     f"computation blocked past {self.wall_s:g} s of wall clock",
                                     location(exc.__traceback__), time.perf_counter() - t0))
            return None
        except DeadlineExceeded as exc:
            if self._armed:
                self._disarm()
            self._fail(node, Failure("hang", node.name, "deadline", self.bus.now, "DeadlineExceeded",
                                     f"computation overran {self.deadline_s} s", location(exc.__traceback__),
                                     time.perf_counter() - t0))
            return None
        except BaseException as exc:  # any failure of a module is a finding (SystemExit too)
            if self._armed:
                self._disarm()
            if not module_fault(exc, before):
                raise  # the user's Ctrl-C
            # a planner in a process of its own: what it raised there, and where (isolation.HostedError)
            where = _relative(exc.location) if getattr(exc, "location", "") else location(exc.__traceback__)
            self._fail(node, Failure("crash", node.name, "exception", self.bus.now,
                                     getattr(exc, "type_name", type(exc).__name__),
                                     str(getattr(exc, "message", exc))[:300], where, time.perf_counter() - t0))
            return None
        wall = time.perf_counter() - t0
        if wall > self.max_wall.get(node.name, 0.0):
            self.max_wall[node.name] = wall
        if getattr(fn, "__name__", "") == "compute" and not _valid_outputs(out):
            self._fail(node, Failure("crash", node.name, "invalid_output", self.bus.now, "InvalidOutput",
                                     f"compute returned {type(out).__name__}", f"{type(node).__name__}.compute",
                                     wall))
            return None
        return out

    def _fail(self, node: Any, failure: Failure) -> None:
        node.alive = False
        node.busy = False
        self.failures.append(failure)
        if self.on_failure is not None:
            self.on_failure(failure)


class SilenceMonitor:
    """Reports nodes that stopped publishing for ``k`` periods or missed ``k`` timer ticks."""

    def __init__(self, ads: Any, nodes: list[Any], k: int = 10, warmup_s: float = 1.0,
                 on_failure: Callable[[Failure], None] | None = None) -> None:
        self.k = k
        self.on_failure = on_failure
        self.failures: list[Failure] = []
        self.warmup_ns = round(warmup_s * NS_PER_S)
        self.nodes = [n for n in nodes if n.name in PUBLISHER.values() and n.name != "routing"]
        self.period_ns = {n.name: self._period(ads, n.name) for n in self.nodes}
        self._reported: set[str] = set()

    @staticmethod
    def _period(ads: Any, module: str) -> int | None:
        seen = set()
        while module not in seen:
            seen.add(module)
            cfg = getattr(ads, module, None)
            if cfg is None:
                return None
            if cfg.rate_hz:
                return round(NS_PER_S / cfg.rate_hz)
            if not cfg.trigger:
                return None
            module = PUBLISHER.get(cfg.trigger, "")
        return None

    def __call__(self, sim: Any) -> None:
        nodes = self.nodes
        if any(not n.alive for n in nodes):
            return  # silence downstream of a dead node is a consequence, not a new finding
        now = sim.bus.now_ns
        for n in nodes:
            if n.name in self._reported:
                continue
            period = self.period_ns.get(n.name)
            if period is None:
                continue
            since = max(n.last_publish_ns or 0, self.warmup_ns)
            if now - since > self.k * period:
                self._report(Failure("hang", n.name, "silent", now / NS_PER_S,
                                     message=f"no output for {(now - since) / NS_PER_S:.2f} s "
                                             f"(> {self.k} periods)"))
            elif n.missed_ticks >= self.k:
                self._report(Failure("hang", n.name, "missed_ticks", now / NS_PER_S,
                                     message=f"{n.missed_ticks} timer ticks missed while busy"))

    def _report(self, failure: Failure) -> None:
        self._reported.add(failure.node)
        self.failures.append(failure)
        if self.on_failure is not None:
            self.on_failure(failure)
