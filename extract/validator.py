"""The Trajectory Validator: how far a reproduced planning output is from the recorded one.

The default measure is the paper's lock-step Euclidean distance (eq. 2): the reproduced
trajectory is interpolated at the recorded one's timestamps and the point distances are combined
as sqrt(sum of squares) (:func:`deft_gym.planner.trajectory.lsed`). Discrete Frechet and Hausdorff
distances can be selected instead. Bit-identical trajectories short-cut to 0.0 without numpy,
which is what almost every check of the input search is.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

from deft_gym.planner.trajectory import MEASURES

#: thresholds every summary reports [m]
SUMMARY_THETAS = (0.0, 0.1, 1.0, 7.0)

Measure = Callable[[Mapping[str, Any], Mapping[str, Any]], float]


def measure_fn(name: str) -> Measure:
    """The distance function called ``name`` (lsed, frechet, hausdorff)."""
    try:
        return MEASURES[name]
    except KeyError:
        raise ValueError(f"unknown measure {name!r}; expected one of {sorted(MEASURES)}") from None


def _traj(payload: Mapping[str, Any]) -> Mapping[str, Any] | None:
    tr = payload.get("trajectory") if isinstance(payload, Mapping) else None
    return tr if isinstance(tr, Mapping) else None


def identical(expected: Mapping[str, Any], actual: Mapping[str, Any] | None) -> bool:
    """Same timestamps and positions, bit for bit."""
    if actual is None:
        return False
    a, b = _traj(expected), _traj(actual)
    return a is not None and b is not None and a["x"] == b["x"] and a["y"] == b["y"] and a["t"] == b["t"]


def distance(expected: Mapping[str, Any], actual: Mapping[str, Any] | None, measure: Measure | str = "lsed") -> float:
    """Distance [m] of ``actual`` from ``expected`` (inf when there is no usable output)."""
    if actual is None:
        return math.inf
    if identical(expected, actual):
        return 0.0
    fn = measure_fn(measure) if isinstance(measure, str) else measure
    try:
        d = float(fn(expected, actual))
    except (KeyError, TypeError, ValueError):
        return math.inf
    return d if math.isfinite(d) else math.inf


def reproduced_counts(distances: list[float], thetas: tuple[float, ...] = SUMMARY_THETAS) -> dict[str, int]:
    """How many distances are within each threshold, keyed ``"0"``, ``"0.1"``, ``"1"``, ``"7"``."""
    return {theta_key(t): sum(1 for d in distances if d <= t) for t in thetas}


def theta_key(theta: float) -> str:
    """``0.0 -> "0"``, ``0.1 -> "0.1"``: compact JSON keys for thresholds."""
    return f"{theta:g}"
