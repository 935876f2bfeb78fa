"""Running and judging hand-built mutations of a seed scenario (shared by test_nods_patterns.py
and test_seed_failures.py).

A mutation is a list of participant specs added to the seed, simulated as the search baselines
do and judged by the seed's :class:`~deft_gym.search.nods.DecisionOracle`: validity (every added
object at least 0.5 m from the optimal path), the task check, and the paper's consistency check
(2 m lane-aligned grid, IoU <= 0.6: a NoDS). :func:`place_static` asks for a static object at a
point of the optimal path's frame and has it granted by the search's own
:class:`~deft_gym.search.placement.Placer`, and :func:`assert_placeable` checks that objects lie
inside the seed's feasible areas - where the search methods may put them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import shapely

from deft_gym.scenarios.scenario import scenario_from_dict, with_participants
from deft_gym.search.context import SeedContext
from deft_gym.search.feasible import Layout, Placed
from deft_gym.search.nods import Verdict
from deft_gym.search.placement import Placer
from deft_gym.search.trace import Trace, TraceRecorder
from deft_gym.sim.simulation import Simulation
from deft_gym.world.participants import SIZES

SEEDS = (0, 1)  # the jitter seeds a mutation must fail on


@dataclass
class Run:
    verdict: Verdict
    decisions: list[tuple[float, dict[str, Any]]] = field(default_factory=list)
    predictions: list[tuple[float, dict[str, Any]]] = field(default_factory=list)
    perceptions: list[tuple[float, dict[str, Any]]] = field(default_factory=list)
    xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # the ego's path [m]
    trace: Trace | None = None

    def reasons(self) -> set[str]:
        return {d["reason"] for _, d in self.decisions}


def run(ctx: SeedContext, added: list[dict[str, Any]], jitter_seed: int) -> Run:
    """Simulate the seed plus ``added`` (as the search baselines do) and judge it, keeping what
    planning, prediction and perception published."""
    sc = scenario_from_dict(with_participants(ctx.scenario, "mutated", added))
    sim = Simulation(sc, ctx.ads, jitter_seed=jitter_seed, keep_planning=False)
    rec = TraceRecorder(sim, {a["id"] for a in added})
    out = Run(verdict=None)  # type: ignore[arg-type]
    topics = {ctx.ads.topic("planning"): out.decisions, ctx.ads.topic("prediction"): out.predictions,
              ctx.ads.topic("perception_obstacles"): out.perceptions}

    def tap(m: Any) -> None:
        if m.topic in topics:
            body = m.payload["decision"] if m.topic == ctx.ads.topic("planning") else m.payload
            topics[m.topic].append((m.payload["header"]["stamp"], body))

    sim.bus.taps.append(tap)
    res = sim.run()
    o = res.outcome
    trace = rec.trace(o.outcome, o.sim_time)
    out.verdict = ctx.oracle.judge(trace, o.collision.as_dict() if o.collision else None)
    out.xy = trace.xy
    out.trace = trace
    return out


def assert_nods(ctx: SeedContext, added: list[dict[str, Any]], mechanism: str | None = None) -> list[Run]:
    """``added`` is valid and gives a NoDS under the paper's oracle for every jitter seed of
    :data:`SEEDS` - with the root-cause ``mechanism`` the oracle names, when given; returns the
    runs."""
    runs = [run(ctx, added, js) for js in SEEDS]
    for js, r in zip(SEEDS, runs):
        v = r.verdict
        assert v.valid, f"jitter seed {js}: mutation invades the optimal path: {v.invasive_why}"
        assert v.outcome == "completed", f"jitter seed {js}: {v.outcome}"
        assert v.iou <= ctx.oracle.threshold and v.failure == "nods", f"jitter seed {js}: IoU {v.iou:.2f}"
        if mechanism is not None:
            assert v.finding is not None and v.finding.mechanism == mechanism, f"jitter seed {js}: {v.signature}"
            assert set(v.finding.trigger_ids) <= {a["id"] for a in added}, v.finding
    return runs


def assert_no_nods(ctx: SeedContext, added: list[dict[str, Any]]) -> Run:
    r = run(ctx, added, SEEDS[0])
    assert r.verdict.valid and r.verdict.outcome == "completed", r.verdict
    assert not r.verdict.nods, f"control: IoU {r.verdict.iou:.2f}"
    return r


# -- building blocks ------------------------------------------------------------------------------
def cone(pid: str, x: float, y: float) -> dict[str, Any]:
    return {"id": pid, "type": "static", "obstacle": "CONE", "x": x, "y": y, "heading": 0.0}


def parked(pid: str, x: float, y: float, heading: float = 0.0) -> dict[str, Any]:
    return {"id": pid, "type": "static", "obstacle": "STATIC_VEHICLE", "x": x, "y": y, "heading": heading}


def vehicle(pid: str, t: np.ndarray, x: np.ndarray, y: np.ndarray) -> dict[str, Any]:
    return {"id": pid, "type": "scripted",
            "waypoints": [{"t": float(a), "x": float(b), "y": float(c)} for a, b, c in zip(t, x, y)]}


# -- where the search may put objects ---------------------------------------------------------------
def place_static(ctx: SeedContext, layout: Layout, obstacle: str, sigma: float, lateral: float,
                 pid: str) -> dict[str, Any]:
    """A static ``obstacle`` (CONE | STATIC_VEHICLE) asked for at ``(sigma, lateral)`` of the
    optimal path's frame (arc length [m], offset to the right [m]) and granted under the
    ``closest`` rule by the search's own placer - the feasible pose nearest to the request, away
    from the path - as the search baselines and the RL env get their objects. Added to
    ``layout``; returns the participant spec."""
    placer = Placer(ctx, "closest", np.random.default_rng(0))
    pose = placer.static(layout, obstacle, sigma, lateral, ego_xy=ctx.ref.xy[0])
    assert pose is not None, f"no room for a {obstacle} at sigma {sigma} m, lateral {lateral} m"
    return placer.add_static(layout, pid, obstacle, pose)


def assert_placeable(ctx: SeedContext, specs: list[dict[str, Any]]) -> None:
    """Every static object in ``specs`` is inside the seed's feasible areas (``ctx.areas``): its
    box stays out of every window's motion areas of the reference run (the ego's, inflated by
    the margin, and the seed participants'), out of the other objects, and its centre lies in
    the region of interest (the drivable area and shoulder near the optimal path)."""
    for i, s in enumerate(specs):
        assert s["type"] == "static", s
        layout = Layout(ctx.areas)
        for other in specs[:i] + specs[i + 1:]:
            length, width = SIZES[other["obstacle"]]
            area = layout.static_footprint(other["x"], other["y"], other["heading"], length, width)
            layout.add(Placed(other["id"], "static", other, area=area))
        length, width = SIZES[s["obstacle"]]
        ok = layout.static_ok(np.array([s["x"]]), np.array([s["y"]]), np.array([s["heading"]]), length, width)
        assert bool(ok[0]), f"{s['id']} at ({s['x']:.2f}, {s['y']:.2f}) is outside the feasible area"
        assert shapely.contains_xy(ctx.areas.roi, s["x"], s["y"]), f"{s['id']} is outside the region of interest"
