"""The reference lattice planner with a fault planted after ``after`` plans (fault injection):
``fault: raise`` raises, ``sleep`` blocks ``sleep_s`` wall-clock seconds, ``nan`` returns a plan
whose positions are NaN, ``silent`` never returns a plan; a planner that tries to end the program:
``exit`` raises SystemExit, ``interrupt`` KeyboardInterrupt, ``base`` a BaseException of its own,
``os_exit`` calls ``os._exit(3)``, ``segfault`` reads address 0, ``sigterm``/``sigkill`` send that
signal to their own process. Used by tests/test_faults.py."""

from __future__ import annotations

import os
import signal
import time
from typing import Any

from deft_gym.planner.base import Frame
from deft_gym.planner.lattice import LatticePlanner


class PlantedBaseException(BaseException):
    """Neither an Exception nor SystemExit/KeyboardInterrupt."""


class FaultyPlanner(LatticePlanner):
    def __init__(self, map_spec: dict[str, Any], **params: Any) -> None:
        self.fault = str(params.pop("fault", "raise"))
        self.after = int(params.pop("after", 0))
        self.sleep_s = float(params.pop("sleep_s", 5.0))
        self.calls = 0
        super().__init__(map_spec, **params)

    def plan(self, frame: Frame) -> dict[str, Any] | None:
        self.calls += 1
        out = super().plan(frame)
        if self.calls <= self.after or out is None:
            return None if self.fault == "silent" else out
        if self.fault == "raise":
            raise ZeroDivisionError("planted fault")
        if self.fault == "exit":
            raise SystemExit(4)
        if self.fault == "interrupt":
            raise KeyboardInterrupt
        if self.fault == "base":
            raise PlantedBaseException("planted")
        if self.fault == "os_exit":
            os._exit(3)
        if self.fault == "segfault":
            import ctypes

            ctypes.string_at(0)
        if self.fault in ("sigterm", "sigkill"):
            os.kill(os.getpid(), signal.SIGTERM if self.fault == "sigterm" else signal.SIGKILL)
            time.sleep(5)
        if self.fault == "sleep":
            time.sleep(self.sleep_s)
        if self.fault == "nan":
            out["trajectory"]["x"] = [float("nan")] * len(out["trajectory"]["x"])
        if self.fault == "silent":
            return None
        return out
