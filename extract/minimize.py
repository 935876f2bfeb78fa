"""Failure-test minimisation: the fewest frames that still reproduce P_faulty.

A planner that can be seeded (:meth:`deft_gym.planner.base.Planner.export_state`) gives the
shortest test of all: :func:`seeded_start` records its state just before the P_faulty frame (a
fresh planner fed the frames before it), and the failure test loads that state into a fresh
planner and plans the one frame. It is used only when a second fresh planner, loaded with the
state as the test will read it (after a JSON round trip), reproduces P_faulty's whole output bit
for bit. Otherwise the shortest replayed suffix is searched as follows.

The failure test of an episode replays frames through a fresh planner up to P_faulty, so that
the planner's state (trajectory stitching, hysteresis) is what it was live. A fresh planner
often needs only the last few of them: wherever the live planner had re-planned from scratch
(e.g. from its localization instead of stitching to its previous plan), a fresh planner given
that frame produces the very same output, and from then on it follows the live run exactly.

The search scans start frames ``s = index, index - 1, ...``: a reset planner plans frame ``s``
alone (one call); only when that output equals the recorded one bit for bit is the start
verified by replaying ``s..index`` through a new planner and checking P_faulty exactly (the
validator). The first verified start is the latest one of this kind; the failure test then
replays ``index - s + 1`` frames instead of ``index + 1``. Without any, it replays them all.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from deft_gym.bus.codec import decode, encode
from deft_gym.planner.base import Frame, Planner
from extract.validator import distance, same_output


@dataclass
class Minimised:
    """Where the failure test starts replaying, and what finding it cost."""

    replay_from: int
    candidates: int  #: starts whose first output matched and were verified
    plan_calls: int
    seconds: float


def shortest_replay(make_planner: Callable[[], Planner], frame: Callable[[int], Frame], index: int,
                    expected: Callable[[int], dict[str, Any]], measure: str = "lsed",
                    max_calls: int | None = None) -> Minimised:
    """The latest start ``s`` from which a fresh planner fed frames ``s..index`` reproduces
    ``expected(index)`` exactly (0 when none is found within ``max_calls`` planner calls)."""
    t0 = time.perf_counter()
    budget = max_calls if max_calls is not None else 2 * (index + 1)
    calls = candidates = 0
    probe = make_planner()
    target = expected(index)
    for s in range(index, 0, -1):
        if calls >= budget:
            break
        probe.reset()
        out = probe.plan(frame(s))
        calls += 1
        if out is None or distance(expected(s), out, measure) != 0.0:
            continue
        candidates += 1
        planner = make_planner()
        for j in range(s, index + 1):
            out = planner.plan(frame(j))
        calls += index + 1 - s
        if out is not None and distance(target, out, measure) == 0.0:
            return Minimised(s, candidates, calls, time.perf_counter() - t0)
    return Minimised(0, candidates, calls, time.perf_counter() - t0)


@dataclass
class Seed:
    """A recorded planner state for the failure test (``state`` None: not usable, see ``note``)."""

    frame: int
    state: dict[str, Any] | None
    plan_calls: int
    seconds: float
    note: str | None = None


def seeded_start(make_planner: Callable[[], Planner], frame: Callable[[int], Frame], index: int,
                 expected: Callable[[int], dict[str, Any]]) -> Seed:
    """The state a fresh planner has after frames ``0..index-1``, when loading it into another
    fresh planner makes that one reproduce ``expected(index)`` exactly (the whole output)."""
    t0 = time.perf_counter()
    probe = make_planner()
    if probe.export_state() is None:
        return Seed(index, None, 0, time.perf_counter() - t0, f"{type(probe).__name__} cannot be seeded")
    for j in range(index):
        probe.plan(frame(j))
    try:
        state = decode(encode(probe.export_state()))  # as the test reads it from the frames file
        seeded = make_planner()
        seeded.load_state(state)
        out = seeded.plan(frame(index))
    except (TypeError, ValueError, KeyError) as exc:
        return Seed(index, None, index + 1, time.perf_counter() - t0, f"seeding failed: {exc}")
    if not same_output(expected(index), out):
        return Seed(index, None, index + 1, time.perf_counter() - t0,
                    "the seeded planner does not reproduce P_faulty exactly")
    return Seed(index, state, index + 1, time.perf_counter() - t0)


def frame_getter(times: Sequence[float], inputs: Callable[[int], dict[str, Any]]) -> Callable[[int], Frame]:
    """Frame ``j`` from the chosen frame times and a decoder of the chosen inputs."""
    return lambda j: Frame(times[j], inputs(j))
