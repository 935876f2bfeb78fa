"""Trajectory similarity measures (DeFT's Trajectory Validator and rerun comparisons).

A trajectory is ``(t, x, y)`` arrays. :func:`lsed` is the paper's lock-step Euclidean distance
(eq. 2): the reproduced trajectory is interpolated at the original's timestamps and the
point-wise distances are combined as sqrt(sum of squares). Discrete Frechet and Hausdorff
distances are offered as alternatives.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np


def arrays(traj: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(t, x, y)`` float arrays of a planning payload's trajectory (or the trajectory dict)."""
    tr = traj.get("trajectory", traj)
    return (np.asarray(tr["t"], dtype=float), np.asarray(tr["x"], dtype=float),
            np.asarray(tr["y"], dtype=float))


def resample(ref: Mapping[str, Any], other: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Points of ``ref`` and ``other`` interpolated at ``ref``'s timestamps, shape ``(n, 2)``."""
    t, x, y = arrays(ref)
    t2, x2, y2 = arrays(other)
    if len(t2) == 0 or len(t) == 0:
        raise ValueError("empty trajectory")
    if len(t) == len(t2) and np.array_equal(t, t2):
        return np.stack([x, y], -1), np.stack([x2, y2], -1)
    return np.stack([x, y], -1), np.stack([np.interp(t, t2, x2), np.interp(t, t2, y2)], -1)


def lsed(ref: Mapping[str, Any], other: Mapping[str, Any]) -> float:
    """Lock-step Euclidean distance [m] (DeFT eq. 2)."""
    a, b = resample(ref, other)
    return float(np.sqrt(((a - b) ** 2).sum()))


def frechet(ref: Mapping[str, Any], other: Mapping[str, Any]) -> float:
    """Discrete Frechet distance [m] between the two point sequences."""
    _, x, y = arrays(ref)
    _, x2, y2 = arrays(other)
    a, b = np.stack([x, y], -1), np.stack([x2, y2], -1)
    d = np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1))
    ca = np.full(d.shape, np.inf)
    ca[0, 0] = d[0, 0]
    for i in range(1, len(a)):
        ca[i, 0] = max(ca[i - 1, 0], d[i, 0])
    for j in range(1, len(b)):
        ca[0, j] = max(ca[0, j - 1], d[0, j])
    for i in range(1, len(a)):
        prev = ca[i - 1]
        row = ca[i]
        for j in range(1, len(b)):
            row[j] = max(min(prev[j], prev[j - 1], row[j - 1]), d[i, j])
    return float(ca[-1, -1])


def hausdorff(ref: Mapping[str, Any], other: Mapping[str, Any]) -> float:
    """Symmetric Hausdorff distance [m] between the two point sets."""
    _, x, y = arrays(ref)
    _, x2, y2 = arrays(other)
    a, b = np.stack([x, y], -1), np.stack([x2, y2], -1)
    d = np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1))
    return float(max(d.min(axis=1).max(), d.min(axis=0).max()))


MEASURES: dict[str, Callable[[Mapping[str, Any], Mapping[str, Any]], float]] = {
    "lsed": lsed, "frechet": frechet, "hausdorff": hausdorff,
}
