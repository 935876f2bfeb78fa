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


def test_recording_only_pairs_each_encoding_with_an_unrecorded_run() -> None:
    """`deft-gym bench --recording-only`: per repeat one unrecorded, one binary, one all-JSON and
    one inline-written run of the same jitter seed (short runs here); ratios over the unrecorded CPU."""
    from deft_gym.cli.bench import recording_overhead
    from tests.support.extract_support import short_scenario

    res = recording_overhead(short_scenario("lane_follow_static", 3.0), repeats=3)
    assert [len(res["cpu_s"][k]) for k in ("unrecorded", "binary", "json", "inline")] == [3, 3, 3, 3]
    for name in ("binary", "json", "inline"):
        lo, hi = res[name]["ci95"]
        assert -0.5 < lo <= res[name]["median"] <= hi < 2.0
    assert 0 <= res["binary_lower_in"] <= 3
