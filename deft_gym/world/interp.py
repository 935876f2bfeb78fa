"""Scalar linear interpolation that gives exactly ``np.interp``'s result.

``np.interp`` costs a few microseconds per call in argument handling alone; the control loop
and the simulator look up one value at a time many thousand times per simulated minute. This
is the same arithmetic on plain floats (same index search, same slope formula, same fallbacks),
so a module can switch between the two without changing a single bit of its output.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Sequence


def interp1(x: float, xp: Sequence[float], fp: Sequence[float]) -> float:
    """``float(np.interp(x, xp, fp))`` for one ``x``; ``xp`` ascending (plain lists are fastest)."""
    n = len(xp)
    if n == 1:  # numpy's special case: one sample point, one value (even for NaN)
        return fp[0]
    if x != x:  # NaN in, NaN out
        return x
    j = bisect_right(xp, x) - 1
    if j < 0:
        return fp[0]
    if j >= n - 1:
        return fp[n - 1]
    x0 = xp[j]
    if x0 == x:
        return fp[j]
    f0, f1 = fp[j], fp[j + 1]
    slope = (f1 - f0) / (xp[j + 1] - x0)
    y = slope * (x - x0) + f0
    if math.isnan(y):
        y = slope * (x - xp[j + 1]) + f1
        if math.isnan(y) and f0 == f1:
            y = f0
    return y
