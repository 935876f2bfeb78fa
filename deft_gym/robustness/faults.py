"""Planted faults, modelled on the bugs ASTAA reports, to prove that the harness finds them.

They are subclasses of the built-in nodes, selected per module by configuration and off by
default: ``<module>.node: deft_gym.robustness.faults:FaultyControl`` with
``params.planted_faults: [nan_speed, ...]`` (see ``configs/ads/faults/*.yaml``). With an empty
list a faulty node behaves exactly like the built-in one.

=================  ==========  =================================================================
fault              module      the bug (paper section 5)
=================  ==========  =================================================================
nan_speed          control     a low-pass speed filter feeds a speed-limit guard and the speed
                               loop; one NaN speed poisons the filter for good, ``v > limit`` is
                               then always False (the guard never brakes) and the clamped NaN
                               command is full throttle - the robot that "sped up indefinitely"
angle_wrap         prediction  obstacle headings wrapped by a subtractive ``while`` loop, which
                               never ends for a huge angle (1e300 - 2*pi == 1e300) - a hang
empty_trajectory   control     the age of the plan is read from ``trajectory.t[0]`` before the
                               emptiness check - IndexError on an empty list
stale_stamp        control     an acceleration estimate divides by the difference of successive
                               localization stamps, assumed to increase - ZeroDivisionError on
                               a repeated (stale) stamp, a wrong sign on a backwards one
=================  ==========  =================================================================
"""

from __future__ import annotations

import math
from typing import Any

from deft_gym.bus.ads import ModuleConfig
from deft_gym.modules.control import ControlNode
from deft_gym.modules.prediction import PredictionNode

CONTROL_FAULTS = ("nan_speed", "empty_trajectory", "stale_stamp")
PREDICTION_FAULTS = ("angle_wrap",)
PLANTED_FAULTS = (*CONTROL_FAULTS, *PREDICTION_FAULTS)

#: how each planted fault shows when the harness finds it (what "found" means in a campaign)
SIGNATURES = {
    "nan_speed": "violation:speed_limit",
    "angle_wrap": "hang:prediction:deadline",
    "empty_trajectory": "crash:control:IndexError@deft_gym/robustness/faults.py:_plan_age",
    "stale_stamp": "crash:control:ZeroDivisionError@deft_gym/robustness/faults.py:_accel_estimate",
}


def planted(cfg: ModuleConfig, allowed: tuple[str, ...]) -> frozenset[str]:
    """The planted faults a module config selects (``params.planted_faults``)."""
    names = cfg.params.get("planted_faults", []) or []
    if isinstance(names, str):
        names = [names]
    bad = sorted(set(names) - set(allowed))
    if bad:
        raise ValueError(f"params.planted_faults: unknown fault(s) {bad} for this module; expected some of "
                         f"{list(allowed)}")
    return frozenset(names)


class FaultyControl(ControlNode):
    """The built-in controller plus the planted faults named in ``params.planted_faults``;
    ``params.guard_speed`` [m/s] is the speed-limit guard of ``nan_speed`` (default 15)."""

    def __init__(self, cfg: ModuleConfig, topics: dict[str, str]) -> None:
        super().__init__(cfg, topics)
        self.faults = planted(cfg, CONTROL_FAULTS)
        self.guard_speed = float(cfg.params.get("guard_speed", 15.0))
        self._v_filt: float | None = None
        self._v_seq = -1
        self._last_stamp: tuple[float, float] | None = None
        self._a_seq = -1
        self.a_est = 0.0

    def compute(self, now_ns: int) -> list[tuple[str, dict[str, Any]]]:
        if "empty_trajectory" in self.faults:
            self._plan_age(now_ns)
        out = super().compute(now_ns)
        loc = self.latest.get(self.t_loc)
        if loc is None or not self.faults:
            return out
        cmd = out[0][1]
        if "stale_stamp" in self.faults:
            self._accel_estimate(loc)
        if "nan_speed" in self.faults:
            cmd["acceleration"] = self._speed_guard(loc, cmd["acceleration"])
        return out

    def _plan_age(self, now_ns: int) -> float | None:
        plan = self.latest.get(self.t_plan)
        if plan is None:
            return None
        # PLANTED BUG: indexes the first point before anyone checked the list is not empty
        return now_ns / 1e9 - plan.payload["trajectory"]["t"][0]

    def _speed_guard(self, loc: Any, acc: float) -> float:
        v = loc.payload["v"]
        if loc.seq != self._v_seq:
            self._v_seq = loc.seq
            self._v_filt = v if self._v_filt is None else self._v_filt + 0.5 * (v - self._v_filt)
        # PLANTED BUG: after one NaN speed the filter stays NaN; `NaN > limit` is False so the
        # guard never brakes, and the clamp below turns the NaN command into full throttle.
        if self._v_filt > self.guard_speed:
            return min(acc, -2.0)
        acc = acc + self.kp_v * (v - self._v_filt)
        return max(-self.max_dec, min(self.max_acc, acc))

    def _accel_estimate(self, loc: Any) -> float:
        if loc.seq == self._a_seq:
            return self.a_est
        self._a_seq = loc.seq
        stamp, v = loc.payload["header"]["stamp"], loc.payload["v"]
        if self._last_stamp is not None:
            # PLANTED BUG: assumes stamps strictly increase; a stale stamp divides by zero
            dt = stamp - self._last_stamp[0]
            self.a_est = (v - self._last_stamp[1]) / dt
        self._last_stamp = (stamp, v)
        return self.a_est


def _wrap_loop(a: float) -> float:
    # PLANTED BUG: subtractive angle wrapping - for a huge angle a - 2*pi == a, so it never ends
    while a > math.pi:
        a -= 2 * math.pi
    while a < -math.pi:
        a += 2 * math.pi
    return a


class FaultyPrediction(PredictionNode):
    """The built-in predictor plus the planted ``angle_wrap`` fault."""

    def __init__(self, roadmap: Any, cfg: ModuleConfig, in_topic: str, out_topic: str) -> None:
        super().__init__(roadmap, cfg, in_topic, out_topic)
        self.faults = planted(cfg, PREDICTION_FAULTS)

    def _predict(self, ob: dict[str, Any], t0: float) -> dict[str, Any]:
        if "angle_wrap" in self.faults:
            ob = {**ob, "heading": _wrap_loop(ob["heading"])}
        return super()._predict(ob, t0)
