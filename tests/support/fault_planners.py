"""The reference lattice planner with a fault planted after ``after`` plans (fault injection):
``fault: raise`` raises, ``sleep`` blocks ``sleep_s`` wall-clock seconds, ``nan`` returns a plan
whose positions are NaN, ``silent`` never returns a plan. Used by tests/test_faults.py."""

from __future__ import annotations

import time
from typing import Any

from deft_gym.planner.base import Frame
from deft_gym.planner.lattice import LatticePlanner


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
        if self.fault == "sleep":
            time.sleep(self.sleep_s)
        if self.fault == "nan":
            out["trajectory"]["x"] = [float("nan")] * len(out["trajectory"]["x"])
        if self.fault == "silent":
            return None
        return out
