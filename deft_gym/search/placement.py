"""Placement rules: where an object requested at a point of the path frame actually goes.

Every adversary - the RL env and the search baselines - asks for objects from one request grid
(:data:`KINDS`, :data:`ALONG` the path ahead of the ego, :data:`LATERAL` offsets, vehicle
:data:`SPEEDS` and :data:`MANOEUVRES`: the RL env's actions index it, the baselines draw from it
uniformly with :func:`draw_request`) at a point ``(sigma, lateral)`` of the reference path frame (:class:`~deft_gym.search.refpath.RefPath`: arc length
[m], offset to the right [m]) and hands the request to the same :class:`Placer`, so a comparison
between them is a comparison of where they ask, not of how requests are granted. Two rules:

- ``closest``: the feasible point nearest to the request, searching outwards from the path (away
  from the optimal path, in 5 cm steps) and then a few metres along it - "as close as allowed";
- ``uniform``: a point drawn uniformly among the feasible ones within ``window`` metres of the
  request (along and across the path) - the request only says roughly where.

Feasible means non-invasive (:class:`~deft_gym.search.feasible.Layout`): a static object never
enters the reference motion areas or another added object, a vehicle's every window stays out of
that window's areas; objects also keep ``spawn_distance`` from the ego where they appear.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from deft_gym.search.context import SeedContext
from deft_gym.search.feasible import Layout, Placed
from deft_gym.search.vehicles import (
    LENGTH,
    WIDTH,
    Controls,
    LaneDriver,
    Trajectory,
    complete,
    lateral_shifts,
    start_state,
    vehicle_spec,
    window_feasible,
)
from deft_gym.world.participants import SIZES

# -- what every adversary may ask for: the request grid ------------------------------------------
# The RL env's action indexes it; the search baselines (and uniform random actions) draw from it
# uniformly (:func:`draw_request`), so every method asks from the same distribution
KINDS = ("cone", "static_vehicle", "vehicle")  # what is added
ALONG = (-20.0, -10.0, 0.0, 10.0, 20.0, 30.0, 45.0, 60.0, 80.0)  # [m] along the path, ahead of the ego
LATERAL = (-3.5, -2.5, -2.0, -1.5, 0.0, 1.5, 2.0, 2.5, 3.5)  # [m] offset from the path, right +
SPEEDS = (0.0, 0.3, 0.6, 0.9, 1.2)  # x the lane's speed limit (vehicles)
MANOEUVRES = ("keep", "toward", "away", "left", "right")  # a vehicle's first window


@dataclass
class Request:
    """One placement request: ``kind`` (of :data:`KINDS`) at ``along`` metres ahead of the ego
    on the optimal path and ``lateral`` metres to its right; a vehicle with ``speed`` x the lane
    limit and a first-window ``manoeuvre``."""

    kind: str
    along: float
    lateral: float
    speed: float = 0.0
    manoeuvre: str = "keep"


def draw_request(rng: np.random.Generator) -> Request:
    """A request drawn uniformly from the grid (what uniform random actions of the RL env ask)."""
    return Request(KINDS[int(rng.integers(len(KINDS)))], ALONG[int(rng.integers(len(ALONG)))],
                   LATERAL[int(rng.integers(len(LATERAL)))], SPEEDS[int(rng.integers(len(SPEEDS)))],
                   MANOEUVRES[int(rng.integers(len(MANOEUVRES)))])


RULES = ("closest", "uniform")
STEP = 0.05  # [m] lateral grid of the closest rule
ALONG_TRIES = (0.0, 3.0, -3.0, 6.0, -6.0)  # [m] along-path offsets the closest rule tries


@dataclass
class StaticPose:
    """Where a static object went: world pose and path-frame position."""

    x: float
    y: float
    heading: float
    sigma: float
    lateral: float


class Placer:
    """Grants placement requests under one rule (see the module docstring)."""

    def __init__(self, ctx: SeedContext, rule: str, rng: np.random.Generator, window: float = 3.0,
                 samples: int = 96) -> None:
        if rule not in RULES:
            raise ValueError(f"placement rule {rule!r}: expected one of {RULES}")
        self.ctx, self.rule, self.rng = ctx, rule, rng
        self.window, self.samples = window, samples
        self.driver = LaneDriver(ctx.roadmap, ctx.feasible.dt, ctx.feasible.sample_dt)

    # -- statics --------------------------------------------------------------------------------
    def candidates(self, sigma: float, lateral: float) -> tuple[np.ndarray, np.ndarray]:
        """Candidate path-frame points for a request, in the order the rule tries them (closest) or
        drawn at random (uniform)."""
        if self.rule == "closest":
            side = math.copysign(1.0, lateral) if lateral else 0.0
            steps = np.arange(0, round(3.0 / STEP) + 1) * STEP
            lats = [lateral + side * steps] if side else [steps + 0.5, -(steps + 0.5)]
            sig = [sigma + ds for ds in ALONG_TRIES for ls in lats for _ in ls]
            lat = [v for _ in ALONG_TRIES for ls in lats for v in ls]
            return np.array(sig), np.array(lat)
        w, n = self.window, self.samples
        return sigma + self.rng.uniform(-w, w, n), lateral + self.rng.uniform(-w, w, n)

    def static(self, layout: Layout, obstacle: str, sigma: float, lateral: float,
               ego_xy: np.ndarray | None = None, extra_ok: Any = None) -> StaticPose | None:
        """A feasible pose for a static ``obstacle`` (CONE | STATIC_VEHICLE) requested at
        ``(sigma, lateral)``; ``ego_xy``: where the ego is now (kept ``spawn_distance`` away);
        ``extra_ok(x, y, h) -> bool array``: a further test of the caller's. None: no room."""
        length, width = SIZES[obstacle]
        sig, lat = self.candidates(sigma, lateral)
        # the closest rule takes the first feasible candidate: test them a block at a time
        block = len(sig) // len(ALONG_TRIES) if self.rule == "closest" else len(sig)
        for a in range(0, len(sig), block):
            sg, lt = sig[a:a + block], lat[a:a + block]
            xy, h = self.ctx.path.offset(sg, lt)
            ok = layout.static_ok(xy[:, 0], xy[:, 1], h, length, width)
            if ego_xy is not None:
                ok &= np.hypot(xy[:, 0] - ego_xy[0], xy[:, 1] - ego_xy[1]) >= self.ctx.feasible.spawn_distance
            if extra_ok is not None and ok.any():
                ok &= extra_ok(xy[:, 0], xy[:, 1], h)
            idx = np.flatnonzero(ok)
            if len(idx):
                i = int(idx[0]) if self.rule == "closest" else int(idx[int(self.rng.integers(len(idx)))])
                return StaticPose(float(xy[i, 0]), float(xy[i, 1]), float(h[i]), float(sg[i]), float(lt[i]))
        return None

    def add_static(self, layout: Layout, pid: str, obstacle: str, pose: StaticPose) -> dict[str, Any]:
        """Add a granted static object to ``layout``; returns its participant spec."""
        length, width = SIZES[obstacle]
        spec = {"id": pid, "type": "static", "obstacle": obstacle, "x": pose.x, "y": pose.y, "heading": pose.heading}
        layout.add(Placed(pid, "static", spec, area=layout.static_footprint(pose.x, pose.y, pose.heading,
                                                                            length, width)))
        return spec

    # -- vehicles -------------------------------------------------------------------------------
    def vehicle_starts(self, sigma: float, lateral: float) -> list[tuple[float, float]]:
        """Candidate start points for a vehicle, in the order tried."""
        if self.rule == "closest":
            side = math.copysign(1.0, lateral) if lateral else 0.0
            out = []
            for ds in (0.0, 5.0, -5.0, 10.0, -10.0):
                for dl in (0.0, 0.5, 1.0, 1.75, 2.5, 3.5):
                    if dl and not side:
                        continue
                    out.append((sigma + ds, lateral + side * dl))
            return out
        w = 2 * self.window
        return list(zip((sigma + self.rng.uniform(-w, w, 24)).tolist(), (lateral + self.rng.uniform(-w, w, 24)).tolist()))

    def vehicle(self, layout: Layout, t0: float, sigma: float, lateral: float, speed_factor: float,
                manoeuvre: str, ego_xy: np.ndarray | None = None, skip: str | None = None,
                trajectory_ok: Any = None, max_completions: int = 3,
                rng: np.random.Generator | None = None) -> Trajectory | None:
        """A feasible trajectory for a vehicle appearing at ``t0`` [s] near ``(sigma, lateral)``
        with ``speed_factor`` x its lane's speed limit and a first-window ``manoeuvre`` (keep |
        toward | away | left | right), completed window by window to the horizon (Decictor's
        Adding). ``trajectory_ok(traj) -> bool``: a further test of the caller's; ``rng``: draw each
        later window's continuation at random among the feasible ones (else in a fixed order of
        preference)."""
        ctx, driver = self.ctx, self.driver
        tries = 0
        for sig, lat in self.vehicle_starts(sigma, lateral):
            xy, h = ctx.path.offset(np.array([sig]), np.array([lat]))
            st = start_state(ctx.roadmap, float(xy[0, 0]), float(xy[0, 1]), float(h[0]), 0.0)
            if st is None:
                continue
            if ego_xy is not None and skip is None and \
                    math.hypot(xy[0, 0] - ego_xy[0], xy[0, 1] - ego_xy[1]) < ctx.feasible.spawn_distance:
                continue
            v = speed_factor * driver.v_max(st.lane) / driver.v_max_factor
            st = type(st)(st.lane, st.s, st.d, v)
            first = first_window(driver, ctx, st, t0, v, manoeuvre)
            if first is None or not window_feasible(layout, first, skip):
                continue
            if trajectory_ok is not None and not trajectory_ok(first):
                continue
            tries += 1
            traj = complete(driver, layout, first, ctx.scenario.duration, ctx.path.xy, skip=skip, rng=rng)
            if traj is not None and (trajectory_ok is None or trajectory_ok(traj)):
                return traj
            if tries >= max_completions:
                return None
        return None

    def add_vehicle(self, layout: Layout, pid: str, traj: Trajectory) -> dict[str, Any]:
        """Add (or replace) a vehicle in ``layout``; returns its participant spec."""
        spec = vehicle_spec(pid, traj)
        layout.replace(Placed(pid, "scripted", spec, layout.window_areas(traj.t, traj.x, traj.y, traj.h, LENGTH, WIDTH),
                              traj=traj))
        return spec


def first_window(driver: LaneDriver, ctx: SeedContext, st: Any, t0: float, v: float, manoeuvre: str) -> Trajectory | None:
    """The first window of a vehicle's motion for a manoeuvre: keep its lane, change towards or
    away from the optimal path, or take the left / right turn at the next junction."""
    turn = manoeuvre if manoeuvre in ("left", "right") else "straight"
    shift = 0
    if manoeuvre in ("toward", "away"):
        away, toward = lateral_shifts(driver, st, ctx.path.xy)
        choice = away if manoeuvre == "away" else toward
        if not choice:
            return None
        shift = choice[0]
    return driver.window(st, t0, Controls(v, shift, 0.0 if shift else st.d, turn))
