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

Layer 0: the standard library only.
"""

from __future__ import annotations

import math
import os
import signal
import threading
import time
from collections.abc import Callable
from typing import Any

DEFAULT_WATCHDOG_S = 10.0  #: wall-clock seconds one module call may take before it is a hang
ENV = "DEFT_GYM_WATCHDOG_S"


class ModuleHang(BaseException):
    """Raised in a module call by the wall-clock watchdog (a BaseException, so that a module's
    own ``except Exception`` cannot swallow it)."""


def watchdog_seconds(value: float | None = None) -> float:
    """The watchdog limit: ``value``, else ``DEFT_GYM_WATCHDOG_S``, else the default (0 = off);
    ValueError (one line naming the variable or the setting) when it is not finite seconds >= 0."""
    if value is None:
        env = os.environ.get(ENV, "")
        try:
            value = float(env) if env.strip() else DEFAULT_WATCHDOG_S
        except ValueError:
            raise ValueError(f"{ENV}: expected seconds >= 0, got {env!r}") from None
        if not (value >= 0 and math.isfinite(value)):
            raise ValueError(f"{ENV}: expected finite seconds >= 0 (0 = off), got {env!r}")
    if not (value >= 0 and math.isfinite(value)):
        raise ValueError(f"watchdog_s: expected finite seconds >= 0 (0 = off), got {value}")
    return float(value)


def carried_env() -> dict[str, str | None]:
    """The watchdog setting of this process, as worker processes must get it."""
    return {ENV: os.environ.get(ENV)}


def apply_env(env: dict[str, str | None] | None) -> None:
    """Take a :func:`carried_env` in a worker process (set, or unset where the parent had none)."""
    for k, v in (env or {}).items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


class Watchdog:
    """Watches calls made through :meth:`call` while :meth:`armed`: one that runs ``seconds`` of
    wall clock gets :class:`ModuleHang` raised in it (once per call)."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self._active = False
        self._t0 = 0.0

    def call(self, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)``, watched; :class:`ModuleHang` propagates out of it."""
        outer, t0 = self._active, self._t0
        self._active, self._t0 = True, time.perf_counter()
        try:
            return fn(*args)
        finally:
            self._active, self._t0 = outer, t0

    def message(self, what: str = "no return") -> str:
        """What a hang is reported as."""
        return f"ModuleHang: {what} within the {self.seconds:g} s wall-clock watchdog"

    def _beat(self, signum: int, frame: Any) -> None:
        if self._active and time.perf_counter() - self._t0 >= self.seconds:
            self._t0 = float("inf")  # one interruption per call
            raise ModuleHang()

    def armed(self) -> _Heartbeat:
        """A context manager running the heartbeat (a no-op when off, or off the main thread);
        nested use keeps the outer heartbeat's handler and timer."""
        return _Heartbeat(self)


class _Heartbeat:
    def __init__(self, dog: Watchdog) -> None:
        self.dog = dog
        self.on = dog.seconds > 0 and threading.current_thread() is threading.main_thread()

    def __enter__(self) -> None:
        if self.on:
            tick = min(self.dog.seconds / 4, 1.0)
            self.old = signal.signal(signal.SIGALRM, self.dog._beat)
            self.old_timer = signal.setitimer(signal.ITIMER_REAL, tick, tick)

    def __exit__(self, *exc: Any) -> None:
        if self.on:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, self.old if self.old is not None else signal.SIG_DFL)
            if self.old_timer[0] > 0:
                signal.setitimer(signal.ITIMER_REAL, *self.old_timer)


__all__ = ["DEFAULT_WATCHDOG_S", "ENV", "ModuleHang", "Watchdog", "apply_env", "carried_env", "watchdog_seconds"]
