"""Run a seed scenario with added participants once and judge it (the search baselines' unit of
budget, and the replay of an adversary episode from its equivalent scenario)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from deft_gym.scenarios.scenario import scenario_from_dict, with_participants
from deft_gym.search.context import SeedContext
from deft_gym.search.nods import Verdict
from deft_gym.search.trace import Trace, TraceRecorder
from deft_gym.sim.simulation import EpisodeResult, Simulation


@dataclass
class EpisodeRun:
    """A judged run."""

    verdict: Verdict
    trace: Trace
    result: EpisodeResult
    scenario: dict[str, Any]
    seconds: float  # wall time: building, simulating and judging
    cpu_seconds: float = 0.0  # process CPU time of the same


def run_scenario(ctx: SeedContext, specs: list[dict[str, Any]], jitter_seed: int,
                 out_dir: Path | str | None = None, added_at: dict[str, float] | None = None) -> EpisodeRun:
    """Simulate the seed plus ``specs`` with ``jitter_seed`` and judge it against the reference.

    ``added_at`` (participant id -> sim time [s]) adds those participants mid-run, in the order
    of ``specs``, as the adversary env did - so an env episode's equivalent scenario replays it
    exactly; the others are part of the scenario from the start (the search baselines)."""
    t0, c0 = time.perf_counter(), time.process_time()
    added_at = added_at or {}
    later = [s for s in specs if s["id"] in added_at]
    data = with_participants(ctx.scenario, f"{ctx.name}+mut", [s for s in specs if s["id"] not in added_at])
    sc = scenario_from_dict(data, source=f"{ctx.name} (mutated)")
    sim = Simulation(sc, ctx.ads, jitter_seed=jitter_seed, out_dir=out_dir, keep_planning=False)
    rec = TraceRecorder(sim, {s["id"] for s in specs})
    try:
        sim.start()
        for spec in later:
            t = added_at[spec["id"]]
            if t > 0.0 and sim.advance(t):
                break
            sim.add_participant(spec)
        sim.advance(sc.duration)
    finally:
        res = sim.finish()
    o = res.outcome
    trace = rec.trace(o.outcome, o.sim_time)
    verdict = ctx.oracle.judge(trace, o.collision.as_dict() if o.collision else None)
    return EpisodeRun(verdict, trace, res, data, time.perf_counter() - t0, time.process_time() - c0)
