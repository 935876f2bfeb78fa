"""Scenario mutation operators for the search baselines (Decictor Algorithm 2).

A :class:`Mutant` is a seed scenario plus the participants added to it (a
:class:`~deft_gym.search.feasible.Layout`). :class:`NonInvasiveMutator` implements Decictor's
non-invasive operators - *adding* a static obstacle or a vehicle inside the feasible areas (a
vehicle's waypoint for every window is sampled from the area reachable from its previous one,
minus every motion area of that window), *removing* an added participant, and *changing* one
(remove, then add) - and :class:`RandomMutator` the unconstrained ones of the Random baseline
(participants anywhere on the road near the ego's path, no feasibility check).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
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
    VState,
    complete,
    sample_window,
    vehicle_spec,
)
from deft_gym.world.participants import SIZES


@dataclass
class Mutant:
    """A scenario of the search: the seed plus added participants, and its fitness."""

    layout: Layout
    fitness: float = 0.0
    n_ids: int = 0
    history: list[str] = field(default_factory=list)

    def copy(self) -> Mutant:
        lay = Layout(self.layout.areas)
        for p in self.layout.placed:
            lay.add(p)
        return Mutant(lay, self.fitness, self.n_ids, list(self.history))

    @property
    def specs(self) -> list[dict[str, Any]]:
        return [p.spec for p in self.layout.placed]

    def new_id(self, kind: str) -> str:
        self.n_ids += 1
        return f"mut_{kind}_{self.n_ids}"


class NonInvasiveMutator:
    """Decictor's non-invasive mutation delta: add / remove / change, one per call."""

    constrained = True

    def __init__(self, ctx: SeedContext, rng: np.random.Generator, max_added: int = 8, max_tries: int = 30,
                 p_static: float = 0.5) -> None:
        self.ctx, self.rng = ctx, rng
        self.max_added, self.max_tries, self.p_static = max_added, max_tries, p_static
        self.driver = LaneDriver(ctx.roadmap, ctx.feasible.dt, ctx.feasible.sample_dt)
        self.roi = ctx.areas.roi
        self.bounds = self.roi.bounds
        self.t_end = float(ctx.ref.t[-1])

    # -- Algorithm 2 ------------------------------------------------------------------------
    def mutate(self, m: Mutant) -> Mutant | None:
        """One random operation on a copy of ``m`` (None when the operation found no room)."""
        child = m.copy()
        ops = []
        if len(child.layout.placed) < self.max_added:
            ops.append("add")
        if child.layout.placed:
            ops += ["remove", "change"]
        op = ops[int(self.rng.integers(len(ops)))]
        if op == "remove":
            self.remove(child)
        elif op == "change":
            self.remove(child)
            if not self.add(child):
                return None
        elif not self.add(child):
            return None
        child.history.append(op)
        return child

    def remove(self, m: Mutant) -> None:
        placed = m.layout.placed
        m.layout.remove(placed[int(self.rng.integers(len(placed)))].id)

    def add(self, m: Mutant) -> bool:
        if self.rng.random() < self.p_static:
            obstacle = "CONE" if self.rng.random() < 0.5 else "STATIC_VEHICLE"
            return self.add_static(m, obstacle)
        return self.add_vehicle(m)

    # -- sampling ---------------------------------------------------------------------------
    def _point(self) -> tuple[float, float]:
        """A uniform random point of the region of interest (drivable area near the path)."""
        import shapely

        x0, y0, x1, y1 = self.bounds
        for _ in range(200):
            x, y = self.rng.uniform(x0, x1), self.rng.uniform(y0, y1)
            if shapely.contains_xy(self.roi, x, y):
                return float(x), float(y)
        c = self.roi.representative_point()
        return float(c.x), float(c.y)

    def _lane_pose(self) -> tuple[VState, float, float, float] | None:
        x, y = self._point()
        loc = self.ctx.roadmap.locate(np.array([x, y]))
        if loc is None:
            return None
        lane, s, d = loc
        g = self.ctx.roadmap.geom(lane)
        if not 0.0 <= s <= g.length:
            return None
        d = float(np.clip(d, -g.width / 2, g.width / 2))
        xy = g.xy(np.array(s), d)
        return VState(lane, float(s), d, 0.0), float(xy[0]), float(xy[1]), float(g.heading_point(s))

    def _ego_at(self, t: float) -> np.ndarray:
        ref = self.ctx.ref
        i = int(np.clip(round(t / ref.world_dt), 0, len(ref.ticks) - 1))
        return ref.xy[i]

    def add_static(self, m: Mutant, obstacle: str) -> bool:
        length, width = SIZES[obstacle]
        start = self._ego_at(0.0)
        for _ in range(self.max_tries):
            pose = self._lane_pose()
            if pose is None:
                continue
            _, x, y, h = pose
            if self.constrained:
                if math.hypot(x - start[0], y - start[1]) < self.ctx.feasible.spawn_distance:
                    continue
                if not m.layout.static_ok(np.array([x]), np.array([y]), np.array([h]), length, width)[0]:
                    continue
            pid = m.new_id("cone" if obstacle == "CONE" else "static")
            spec = {"id": pid, "type": "static", "obstacle": obstacle, "x": x, "y": y, "heading": h}
            m.layout.add(Placed(pid, "static", spec, area=m.layout.static_footprint(x, y, h, length, width)))
            return True
        return False

    def add_vehicle(self, m: Mutant) -> bool:
        dt = self.ctx.feasible.dt
        n_win = max(1, int(self.t_end / dt))
        for _ in range(self.max_tries):
            pose = self._lane_pose()
            if pose is None:
                continue
            st, x, y, _ = pose
            t0 = float(self.rng.integers(0, n_win)) * dt
            if self.constrained:
                ego = self._ego_at(t0)
                if math.hypot(x - ego[0], y - ego[1]) < self.ctx.feasible.spawn_distance:
                    continue
            v0 = float(self.rng.uniform(0.0, self.driver.v_max(st.lane)))
            st = VState(st.lane, st.s, st.d, v0)
            turn = str(self.rng.choice(["straight", "straight", "left", "right"]))
            traj = self._drive(m, st, t0, turn)
            if traj is None:
                continue
            pid = m.new_id("veh")
            m.layout.add(Placed(pid, "scripted", vehicle_spec(pid, traj), m.layout.window_areas(
                traj.t, traj.x, traj.y, traj.h, LENGTH, WIDTH), traj=traj))
            return True
        return False

    def _drive(self, m: Mutant, st: VState, t0: float, turn: str) -> Trajectory | None:
        ctx = self.ctx
        first = sample_window(self.driver, m.layout, st, t0, turn, ctx.path.xy, None, self.rng)
        if first is None:
            return None
        return complete(self.driver, m.layout, first, ctx.scenario.duration, ctx.path.xy, rng=self.rng)


class RandomMutator(NonInvasiveMutator):
    """The Random baseline: add / remove participants anywhere on the road near the ego's path,
    with no feasibility constraint."""

    constrained = False

    def mutate(self, m: Mutant) -> Mutant | None:
        child = m.copy()
        add = len(child.layout.placed) < self.max_added and (not child.layout.placed or self.rng.random() < 0.7)
        if add:
            if not self.add(child):
                return None
        else:
            self.remove(child)
        child.history.append("add" if add else "remove")
        return child

    def _drive(self, m: Mutant, st: VState, t0: float, turn: str) -> Trajectory | None:
        traj: Trajectory | None = None
        t, horizon = t0, self.ctx.scenario.duration
        while t < horizon - 1e-9:
            c = Controls(float(self.rng.uniform(0.0, self.driver.v_max(st.lane))),
                         int(self.rng.choice([0, 0, 0, -1, 1])), float(self.rng.uniform(-0.6, 0.6)), turn)
            w = self.driver.window(st, t, c) or self.driver.window(st, t, Controls(c.v_end, 0, st.d, turn))
            if w is None:
                return None
            traj = w if traj is None else traj.extend(w)
            st, t = w.states[-1], float(w.t[-1])
        return traj
