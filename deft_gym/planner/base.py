"""The planner interface: a stateful, deterministic function from frames to trajectories.

A :class:`Frame` is what the planning module consumed in one cycle: the payload of the latest
message received on each subscribed topic role (``None`` when nothing arrived yet) and the frame
time. :meth:`Planner.plan` returns the planning payload (``trajectory`` + ``decision``) or
``None`` when it cannot plan yet; a call that returns ``None`` must leave the state unchanged.

Contract (what DeFT relies on): same construction arguments + same sequence of frames ->
bit-identical outputs. Anything time-dependent must come from ``frame.time``, never a clock.
"""

from __future__ import annotations

import copy
import importlib
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Frame:
    """One planning input: frame creation time [s] and the payload per topic role."""

    time: float
    inputs: Mapping[str, dict[str, Any] | None]

    def get(self, role: str) -> dict[str, Any] | None:
        return self.inputs.get(role)


class Planner(ABC):
    """Base class of planners that plug into the planning module and into extracted tests.

    Subclasses keep everything that changes from cycle to cycle in ``self.state`` so that
    :meth:`snapshot`/:meth:`restore` are cheap (the DeFT input search uses them to try several
    candidate frames from the same planner state).
    """

    #: topic roles the planner needs in its frame
    inputs: tuple[str, ...] = ("routing", "localization", "traffic_light", "prediction")

    def __init__(self, map_spec: Mapping[str, Any], **params: Any) -> None:
        self.map_spec = dict(map_spec)
        self.params = params
        self.state: Any = None

    @abstractmethod
    def reset(self) -> None:
        """Forget everything learned from earlier frames."""

    @abstractmethod
    def plan(self, frame: Frame) -> dict[str, Any] | None:
        """Plan one cycle; return ``{"trajectory": {...}, "decision": {...}}`` or None."""

    @classmethod
    def hard_clearance(cls, params: Mapping[str, Any]) -> float:
        """The lateral clearance [m] this planner (with ``params``) always keeps from obstacles.
        Search tools never place objects closer than this to the optimal path: a planner may
        rightly refuse a path that violates its own hard constraint. 0 when it declares none."""
        return 0.0

    def snapshot(self) -> Any:
        """A copy of the mutable state."""
        return copy.deepcopy(self.state)

    def restore(self, snapshot: Any) -> None:
        """Return to a state taken with :meth:`snapshot`."""
        self.state = copy.deepcopy(snapshot)


def import_object(path: str) -> Any:
    """Import ``package.module:Name``."""
    if ":" not in path:
        raise ValueError(f"expected 'module:Class', got {path!r}")
    mod, _, name = path.partition(":")
    try:
        return getattr(importlib.import_module(mod), name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"cannot import {path!r}: {exc}") from None


def planner_fingerprint(cls_path: str) -> str:
    """SHA-256 of the source file defining a planner class: a log records it, so a test can tell
    that the planner it was extracted for has changed."""
    import hashlib
    import inspect
    from pathlib import Path

    src = inspect.getsourcefile(import_object(cls_path))
    return hashlib.sha256(Path(src).read_bytes()).hexdigest() if src else ""


def load_planner(cls_path: str, map_spec: Mapping[str, Any], params: Mapping[str, Any] | None = None) -> Planner:
    """Instantiate a planner from its class path, the map spec and its parameters."""
    cls = import_object(cls_path)
    if not (isinstance(cls, type) and issubclass(cls, Planner)):
        raise ValueError(f"{cls_path} is not a deft_gym.planner.base.Planner subclass")
    return cls(map_spec, **dict(params or {}))
