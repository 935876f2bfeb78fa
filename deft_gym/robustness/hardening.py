"""Hardening: sanitisation and consistency wrappers around the modules (ASTAA section 4.2.2).

A hardened node validates every message it receives (:func:`.sanitize.problem`: types, finite
numbers, bounds, enum members, array sizes, consistent series, stamps close to the bus clock and
strictly increasing, routes on the map) and rejects invalid ones: it keeps the last valid message
of the topic, and a rejected trigger still runs the module on the last valid inputs, so it keeps
publishing. It also checks what it publishes: a controller never outputs a non-finite or
out-of-range command and brakes when its localization is stale; a planner or predictor output
that fails the same validation is not published (prediction drops the bad obstacles).
Exceptions are *not* caught: hardening must prevent failures, not hide them.

Switch: ``configs/ads/hardened.yaml`` (built-in modules), or ``--hardening on`` in the campaign,
which wraps whatever node class each module uses (:func:`harden_overrides`, e.g. a planted-fault
node) as ``deft_gym.robustness.hardening:Hardened[<module:Class>]``.
"""

from __future__ import annotations

import math
from functools import cache
from typing import Any

from deft_gym.bus.messages import NS_PER_S, Message
from deft_gym.modules.control import ControlNode
from deft_gym.modules.planning import PlanningNode
from deft_gym.modules.prediction import PredictionNode
from deft_gym.planner.base import import_object
from deft_gym.robustness.sanitize import problem
from deft_gym.world.roadmap import shared_roadmap

BUILT_IN = {"prediction": "deft_gym.modules.prediction:PredictionNode",
            "planning": "deft_gym.modules.planning:PlanningNode",
            "control": "deft_gym.modules.control:ControlNode"}
PREFIX = "Hardened["


class _Sanitizing:
    """Mixin: input validation in :meth:`receive`; subclasses say which topic is which role."""

    roles: dict[str, str]

    def _setup(self, roles: dict[str, str], check_map: Any = None) -> None:
        self.roles = roles
        self._check_map = check_map
        self.rejected: dict[str, int] = {}
        self._accepted: dict[str, dict[str, Any]] = {}

    def receive(self, msg: Message) -> None:
        role = self.roles.get(msg.topic)
        if role is None:
            super().receive(msg)  # type: ignore[misc]
            return
        now = self.bus.now_ns / NS_PER_S  # type: ignore[attr-defined]
        accepted = self._accepted.get(msg.topic)
        reason = problem(role, msg.payload, now, accepted["header"]["stamp"] if accepted else None,
                         self._check_map, last=accepted)
        if reason is None:
            self._accepted[msg.topic] = msg.payload
            super().receive(msg)  # type: ignore[misc]
            return
        self.rejected[role] = self.rejected.get(role, 0) + 1
        last = self.latest.get(msg.topic)  # type: ignore[attr-defined]
        if last is not None and msg.topic == self.trigger:  # type: ignore[attr-defined]
            super().receive(last)  # type: ignore[misc] - run on the last valid input

    def _age(self, topic: str, now_ns: int) -> float:
        m = self.latest.get(topic)  # type: ignore[attr-defined]
        return math.inf if m is None else now_ns / NS_PER_S - m.payload["header"]["stamp"]


class _HardenedControl(_Sanitizing):
    """Control: valid inputs, a finite in-range command, braking on a stale pose."""

    max_pose_age = 0.5  # [s]

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._setup({self.t_plan: "planning", self.t_loc: "localization"})

    def compute(self, now_ns: int) -> Any:
        out = super().compute(now_ns)  # type: ignore[misc]
        for _, cmd in out or ():
            acc, steer = cmd.get("acceleration"), cmd.get("steering")
            if self.latest.get(self.t_loc) is not None and self._age(self.t_loc, now_ns) > self.max_pose_age:
                acc, steer = -3.0, 0.0
            if not _finite(acc) or not _finite(steer):
                acc, steer = -3.0, 0.0
            cmd["acceleration"] = max(-self.max_dec, min(self.max_acc, acc))
            cmd["steering"] = max(-self.max_steer, min(self.max_steer, steer))
        return out


class _HardenedPlanning(_Sanitizing):
    """Planning: valid inputs (routes checked on the planner's map), valid outputs only; when the
    planner cannot plan (no valid route) or its output is invalid, it reports the failure with an
    emergency stop from the last valid pose (its own decision: behaviour ``ESTOP``, source
    ``hardening``) instead of falling silent. The stop covers the horizon of the planner's last
    valid output at its point spacing (``stop_horizon`` s at ``stop_dt`` s before there is one),
    so nothing here assumes a planner's trajectory shape or decision vocabulary."""

    stop_decel = 3.0  # [m/s^2]
    stop_horizon = 6.0  # [s] before the planner's first valid output
    stop_dt = 0.2  # [s]

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        roadmap = shared_roadmap(self.planner.map_spec)
        self._setup({t: r for r, t in self.role_topics.items()}, roadmap)
        self.fallbacks = 0
        self._shape = (round(self.stop_horizon / self.stop_dt) + 1, self.stop_dt)

    def compute(self, now_ns: int) -> Any:
        out = super().compute(now_ns)  # type: ignore[misc]
        if out and not any(problem("planning", p) for _, p in out):
            t = out[0][1]["trajectory"]["t"]
            self._shape = (len(t), round((t[-1] - t[0]) / (len(t) - 1), 9))  # spacing to the ns
            return out
        loc = self.latest.get(self.role_topics.get("localization", ""))
        if loc is None:
            return out
        self.fallbacks += 1
        return [(self.out_topic, self._emergency_stop(now_ns / NS_PER_S, loc.payload))]

    def _emergency_stop(self, t0: float, pose: dict[str, Any]) -> dict[str, Any]:
        n, dt = self._shape
        h, v0 = pose["heading"], max(0.0, pose["v"])
        ts = [t0 + k * dt for k in range(n)]
        vs = [max(0.0, v0 - self.stop_decel * k * dt) for k in range(n)]
        s, ss = 0.0, [0.0]
        for k in range(1, n):
            s += 0.5 * (vs[k - 1] + vs[k]) * dt
            ss.append(s)
        return {"header": {"seq": 0, "stamp": t0, "module": self.name},
                "trajectory": {"t": ts, "x": [pose["x"] + d * math.cos(h) for d in ss],
                               "y": [pose["y"] + d * math.sin(h) for d in ss], "v": vs, "heading": [h] * n,
                               "a": [-self.stop_decel if v > 0 else 0.0 for v in vs]},
                "decision": {"behavior": "ESTOP", "source": "hardening"}}


class _HardenedPrediction(_Sanitizing):
    """Prediction: valid perception inputs; obstacles whose prediction is invalid are dropped."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._setup({self.in_topic: "perception_obstacles"})

    def compute(self, now_ns: int) -> Any:
        out = super().compute(now_ns)  # type: ignore[misc]
        for _, payload in out or ():
            obs = payload.get("obstacles", [])
            payload["obstacles"] = [o for o in obs if problem("prediction", {**payload, "obstacles": [o]}) is None]
        return out


def _finite(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


_MIXINS = ((ControlNode, _HardenedControl), (PlanningNode, _HardenedPlanning), (PredictionNode, _HardenedPrediction))


@cache
def harden_class(base: type) -> type:
    """A hardened subclass of a control, planning or prediction node class."""
    for kind, mixin in _MIXINS:
        if issubclass(base, kind):
            return type(f"Hardened{base.__name__}", (mixin, base), {"__module__": __name__})
    raise TypeError(f"no hardening wrapper for {base.__module__}.{base.__name__}")


def hardened_path(node_path: str) -> str:
    """The class path of the hardened version of ``node_path`` (``module:Class``)."""
    if node_path.startswith(f"{__name__}:"):
        return node_path
    return f"{__name__}:{PREFIX}{node_path}]"


def harden_overrides(ads: Any) -> dict[str, Any]:
    """ADS config overrides that harden prediction, planning and control, keeping their classes."""
    return {module: {"node": hardened_path(getattr(ads, module).node or default)}
            for module, default in BUILT_IN.items()}


def __getattr__(name: str) -> Any:
    """Resolve ``Hardened[module:Class]`` to the hardened version of that class."""
    if name.startswith(PREFIX) and name.endswith("]"):
        return harden_class(import_object(name[len(PREFIX):-1]))
    raise AttributeError(name)


HardenedControl = harden_class(ControlNode)
HardenedPlanning = harden_class(PlanningNode)
HardenedPrediction = harden_class(PredictionNode)
