"""The wall-clock watchdog of module calls: a call that blocks or spins is a reported hang, never
a hung tool.

One mechanism for the simulation (every module call on the bus, :mod:`deft_gym.sim.simulation`)
and the extraction (every ``plan()`` of the replays, :mod:`extract.search`): while a
:class:`Watchdog` is :meth:`~Watchdog.armed`, a SIGALRM heartbeat every ``seconds / 4`` (at most
1 s) checks the call in progress (:meth:`~Watchdog.call`); one that has run ``seconds`` of wall
clock gets :class:`ModuleHang` raised in it (a BaseException, so that the module's own ``except
Exception`` cannot swallow it). Per call it only notes the start time, so watched runs cost
nothing measurable and behave exactly as unwatched ones. Main thread only (elsewhere calls run
unwatched); 0 seconds switches it off.

The limit: ``--watchdog-s`` of the programs (:func:`deft_gym.cli.common.add_watchdog`), else the
``DEFT_GYM_WATCHDOG_S`` environment variable, else :data:`DEFAULT_WATCHDOG_S`. The execution
layer carries the variable to every worker process (:func:`carried_env`, :func:`apply_env`).

A whole run has a cap too (``total_s``: ``--run-wall-s`` of the programs, ``DEFT_GYM_RUN_WALL_S``, else
:data:`DEFAULT_RUN_WALL_S`): once the calls watched by one :class:`Watchdog` (an episode's module
calls, an extraction's ``plan()`` calls) have run that long in all, the call in progress gets
:class:`ModuleHang` and :attr:`Watchdog.expired` says so, so that a module slow enough never to
trip the per-call limit (a planner sleeping 5 s per 0.1 s cycle) still ends as a hang.

While a heartbeat runs, Ctrl-C is counted (:func:`interrupts`), so that a ``KeyboardInterrupt``
that a module *raised* (a fault of the module: :func:`module_fault`) is told from the user's
interrupt (which always ends the program).

Layer 0: the standard library only.
"""

from __future__ import annotations

import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

DEFAULT_WATCHDOG_S = 10.0  #: wall-clock seconds one module call may take before it is a hang
ENV = "DEFT_GYM_WATCHDOG_S"
DEFAULT_RUN_WALL_S = 600.0  #: wall-clock seconds all the watched calls of one run may take
RUN_ENV = "DEFT_GYM_RUN_WALL_S"


class ModuleHang(BaseException):
    """Raised in a module call by the wall-clock watchdog (a BaseException, so that a module's
    own ``except Exception`` cannot swallow it)."""


def watchdog_seconds(value: float | None = None) -> float:
    """The watchdog limit: ``value``, else ``DEFT_GYM_WATCHDOG_S``, else the default (0 = off);
    ValueError (one line naming the variable or the setting) when it is not finite seconds >= 0."""
    return _seconds(value, ENV, DEFAULT_WATCHDOG_S, "watchdog_s")


def run_wall_seconds(value: float | None = None) -> float:
    """The whole-run cap: ``value``, else ``DEFT_GYM_RUN_WALL_S``, else the default (0 = off);
    ValueError (one line) when it is not finite seconds >= 0."""
    return _seconds(value, RUN_ENV, DEFAULT_RUN_WALL_S, "run_wall_s")


def _seconds(value: float | None, env_name: str, default: float, setting: str) -> float:
    """``value``, else the environment variable ``env_name``, else ``default``, checked to be
    finite seconds >= 0 (ValueError naming the variable or the ``setting``)."""
    if value is None:
        env = os.environ.get(env_name, "")
        try:
            value = float(env) if env.strip() else default
        except ValueError:
            raise ValueError(f"{env_name}: expected seconds >= 0, got {env!r}") from None
        if not (value >= 0 and math.isfinite(value)):
            raise ValueError(f"{env_name}: expected finite seconds >= 0 (0 = off), got {env!r}")
    if not (value >= 0 and math.isfinite(value)):
        raise ValueError(f"{setting}: expected finite seconds >= 0 (0 = off), got {value}")
    return float(value)


# -- the user's interrupt, told from a KeyboardInterrupt a module raises ------------------------------
_INTERRUPTS = [0, 0]  # Ctrl-C received while counted; heartbeats counting them


def _count_interrupt(signum: int, frame: Any) -> None:
    _INTERRUPTS[0] += 1
    raise KeyboardInterrupt


class CountingInterrupts:
    """While it runs (main thread), Ctrl-C is counted (:func:`interrupts`) and still raises
    KeyboardInterrupt; another handler someone installed is left alone. Nestable."""

    def __enter__(self) -> CountingInterrupts:
        self.old: Any = None
        if threading.current_thread() is threading.main_thread():
            old = signal.getsignal(signal.SIGINT)
            if old is signal.default_int_handler or old is _count_interrupt:
                self.old = old
                signal.signal(signal.SIGINT, _count_interrupt)
                _INTERRUPTS[1] += 1
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.old is not None:
            _INTERRUPTS[1] -= 1
            if _INTERRUPTS[1] == 0:
                signal.signal(signal.SIGINT, signal.default_int_handler)


def in_destructor(frame: Any) -> bool:
    """Whether a signal handler's ``frame`` is in a ``__del__`` (or code it called): Python prints
    and drops an exception raised there, so a timeout raised then would be lost and the call
    would run on unwatched; the handlers raise it after the destructor instead."""
    while frame is not None:
        if frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
    return False


def interrupts() -> int:
    """How many Ctrl-C (SIGINT) this process received while a heartbeat counted them."""
    return _INTERRUPTS[0]


def module_fault(exc: BaseException, interrupts_before: int) -> bool:
    """Whether ``exc``, raised out of a module call that started when :func:`interrupts` was
    ``interrupts_before``, is the module's own fault (then an outcome) rather than the program's
    end: everything but the watchdog's :class:`ModuleHang` and the user's interrupt - a
    ``KeyboardInterrupt`` is the user's when a Ctrl-C arrived during the call, or when none can
    be counted here (no heartbeat, off the main thread)."""
    if isinstance(exc, ModuleHang):
        return False
    if isinstance(exc, KeyboardInterrupt):
        return _INTERRUPTS[1] > 0 and _INTERRUPTS[0] == interrupts_before
    return True


def describe_exception(exc: BaseException, limit: int = 300) -> str:
    """``Type: first line of the message``, the type and message a hosted object raised
    (:class:`deft_gym.execution.isolation.HostedError`) when it is one; at most ``limit`` chars."""
    describe = getattr(exc, "describe", None)
    if callable(describe):
        return str(describe())[:limit]
    text = str(exc).strip()
    msg = text.splitlines()[0] if text else ""
    return (f"{type(exc).__name__}: {msg}" if msg else type(exc).__name__)[:limit]


def carried_env() -> dict[str, str | None]:
    """The watchdog settings of this process, as worker processes must get them."""
    return {ENV: os.environ.get(ENV), RUN_ENV: os.environ.get(RUN_ENV)}


def apply_env(env: dict[str, str | None] | None) -> None:
    """Take a :func:`carried_env` in a worker process (set, or unset where the parent had none)."""
    for k, v in (env or {}).items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


class Watchdog:
    """Watches calls made through :meth:`call` while :meth:`armed`: one that runs ``seconds`` of
    wall clock gets :class:`ModuleHang` raised in it (once per call); so does the call in progress
    once all of them together ran ``total_s`` (None: :func:`run_wall_seconds`; 0: no cap), and
    :attr:`expired` is then True."""

    def __init__(self, seconds: float, total_s: float | None = None) -> None:
        self.seconds = seconds
        self.total_s = run_wall_seconds(total_s)
        self._active = False
        self._t0 = 0.0
        self._used = 0.0  # wall seconds of finished top-level calls
        self.expired = False  #: the whole-run cap was reached
        self._cause = "call"
        self._dropped = False  # a hang raised where Python drops exceptions: raised again at the next beat

    def call(self, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)``, watched; :class:`ModuleHang` propagates out of it."""
        if self.expired:
            self._cause = "total"
            raise ModuleHang()
        outer, t0 = self._active, self._t0
        start = time.perf_counter()
        self._active, self._t0 = True, start
        try:
            result = fn(*args)
        finally:
            self._active, self._t0 = outer, t0
            if not outer:
                self._used += time.perf_counter() - start
            dropped, self._dropped = self._dropped, False  # never carried into the next call
        if dropped:  # its hang was dropped and it returned before the next beat
            raise ModuleHang()
        return result

    @property
    def used(self) -> float:
        """Wall seconds the watched calls took so far (the one in progress included)."""
        now = time.perf_counter()
        return self._used + (now - self._t0 if self._active and self._t0 != float("inf") else 0.0)

    def message(self, what: str = "no return") -> str:
        """What a hang is reported as."""
        if self._cause == "total":
            return f"ModuleHang: the run's calls took {self.total_s:g} s of wall clock in all (its whole-run cap)"
        return f"ModuleHang: {what} within the {self.seconds:g} s wall-clock watchdog"

    def _beat(self, signum: int, frame: Any) -> None:
        if not self._active:
            return
        if self._dropped:  # Python dropped the hang (see _Heartbeat.unraisable): raise it again here
            if not in_destructor(frame):
                self._dropped = False
                raise ModuleHang()
            return
        now = time.perf_counter()
        total = bool(self.total_s and not self.expired and self._t0 != float("inf")
                     and self._used + now - self._t0 >= self.total_s)
        call = bool(self.seconds and now - self._t0 >= self.seconds)
        if not (total or call) or in_destructor(frame):  # in a destructor: the next beat raises it
            return
        if total:
            self.expired = True
            self._cause = "total"
            self._t0 = float("inf")
            raise ModuleHang()
        self._cause = "call"
        self._t0 = float("inf")  # one interruption per call
        raise ModuleHang()

    def armed(self) -> _Heartbeat:
        """A context manager running the heartbeat (a no-op when both limits are off, or off the
        main thread); nested use keeps the outer heartbeat's handler and timer. Ctrl-C is counted
        while it runs (:func:`interrupts`)."""
        return _Heartbeat(self)


class _Heartbeat:
    def __init__(self, dog: Watchdog) -> None:
        self.dog = dog
        self.main = threading.current_thread() is threading.main_thread()
        self.on = (dog.seconds > 0 or dog.total_s > 0) and self.main
        self.counting = CountingInterrupts()

    def __enter__(self) -> None:
        self.counting.__enter__()
        if self.on:
            limits = [x for x in (self.dog.seconds, self.dog.total_s) if x > 0]
            tick = min(min(limits) / 4, 1.0)
            self.old_hook = sys.unraisablehook
            sys.unraisablehook = self.unraisable
            self.old = signal.signal(signal.SIGALRM, self.dog._beat)
            self.old_timer = signal.setitimer(signal.ITIMER_REAL, tick, tick)

    def unraisable(self, info: Any) -> None:
        """``sys.unraisablehook`` while armed: a :class:`ModuleHang` raised where Python drops
        exceptions - a weakref callback or finaliser the garbage collector runs, outside any
        ``__del__`` - is not lost: the next beat raises it again (else the call, interrupted once,
        would run on unwatched). Anything else goes to the hook that was there."""
        if isinstance(info.exc_value, ModuleHang) and self.dog._active:
            self.dog._dropped = True
            return
        self.old_hook(info)

    def __exit__(self, *exc: Any) -> None:
        if self.on:
            sys.unraisablehook = self.old_hook
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, self.old if self.old is not None else signal.SIG_DFL)
            if self.old_timer[0] > 0:
                signal.setitimer(signal.ITIMER_REAL, *self.old_timer)
        self.counting.__exit__(*exc)


__all__ = [
    "DEFAULT_RUN_WALL_S",
    "DEFAULT_WATCHDOG_S",
    "ENV",
    "RUN_ENV",
    "CountingInterrupts",
    "ModuleHang",
    "Watchdog",
    "apply_env",
    "carried_env",
    "describe_exception",
    "in_destructor",
    "interrupts",
    "module_fault",
    "run_wall_seconds",
    "watchdog_seconds",
]
