"""deft-gym bench's statistics: the headline's bootstrap interval of a median paired ratio."""

from __future__ import annotations

import statistics

from deft_gym.cli.bench import _interval_text, median_interval


def test_the_interval_holds_the_median_narrows_with_more_runs_and_needs_three() -> None:
    few = [0.08, 0.12, 0.095, 0.11, 0.10]
    many = few * 6
    lo, hi = median_interval(few)
    assert lo <= statistics.median(few) <= hi and median_interval(few) == (lo, hi)  # seeded
    lo2, hi2 = median_interval(many)
    assert hi2 - lo2 < hi - lo
    assert median_interval([0.1, 0.2]) is None and "n/a" in _interval_text(None, 2)
    assert _interval_text((0.061, 0.115), 20) == "(95 % CI +6.1 to +11.5 %, 20 paired runs)"
