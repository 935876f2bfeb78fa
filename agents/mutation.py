"""Scenario mutation operators for the search baselines (Decictor Algorithm 2).

A :class:`Mutant` is a seed scenario plus the participants added to it (a
:class:`~deft_gym.search.feasible.Layout`). :class:`NonInvasiveMutator` implements Decictor's
non-invasive operators - *adding* a static obstacle or a vehicle inside the feasible areas (a
vehicle's waypoint for every window sampled from the area reachable from its previous one, minus
every motion area of that window), *removing* an added participant, and *changing* one (remove,
then add) - and :class:`RandomMutator` the unconstrained ones of the Random baseline
(participants anywhere on the road near the ego's path, no feasibility check).

What is added and where is drawn from the request grid every adversary shares
(:func:`~deft_gym.search.placement.draw_request`: kind, distance ahead of the reference ego at a
window start, lateral offset, a vehicle's speed and first manoeuvre) - what uniform random actions
of the RL env ask - and granted by the shared :class:`~deft_gym.search.placement.Placer` under the
evaluation's placement rule, exactly as the RL env's requests are. Random takes the requested
point as it is.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from deft_gym.scenarios.scenario import MIN_GAP, pose_xyh
from deft_gym.search.context import SeedContext
from deft_gym.search.feasible import Layout, Placed
from deft_gym.search.placement import Placer, Request, draw_request
from deft_gym.search.vehicles import Controls, Trajectory, VState, start_state, vehicle_spec
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

    def key(self) -> frozenset[tuple[Any, ...]]:
        """What makes two mutants near-duplicates: the same kinds of objects at the same places
        (statics to 0.5 m, vehicles by where and when they appear to 1 m / 1 s)."""
        out = []
        for p in self.layout.placed:
            s = p.spec
            if p.kind == "static":
                out.append((s["obstacle"], round(s["x"] / 0.5), round(s["y"] / 0.5)))
            else:
                w0, w1 = s["waypoints"][0], s["waypoints"][-1]
                out.append(("vehicle", round(w0["t"]), round(w0["x"]), round(w0["y"]), round(w1["x"] / 5.0),
                            round(w1["y"] / 5.0)))
        return frozenset(out)

    def new_id(self, kind: str) -> str:
        self.n_ids += 1
        return f"mut_{kind}_{self.n_ids}"


class NonInvasiveMutator:
    """Decictor's non-invasive mutation delta: add / remove / change, one per call."""

    def __init__(self, ctx: SeedContext, rng: np.random.Generator, rule: str = "closest", max_added: int = 8,
                 max_tries: int = 30, p_static: float = 0.5) -> None:
        self.ctx, self.rng = ctx, rng
        self.max_added, self.max_tries, self.p_static = max_added, max_tries, p_static
        self.placer = Placer(ctx, rule, rng)
        self.driver = self.placer.driver
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
        """Add one object: its kind drawn from the request grid, then up to ``max_tries``
        requests for it (a third of that for a vehicle, whose trajectory costs more)."""
        kind = draw_request(self.rng).kind
        if kind == "vehicle":
            return self.add_vehicle(m)
        return self.add_static(m, "CONE" if kind == "cone" else "STATIC_VEHICLE")

    # -- requests ---------------------------------------------------------------------------
    def _request(self) -> tuple[Request, float, float]:
        """A request of the shared grid (:func:`~deft_gym.search.placement.draw_request`) made at
        a window start ``t0`` [s] drawn uniformly over the reference run, relative to where the
        reference ego is then: ``(request, t0, sigma)`` with ``sigma`` the requested arc length
        [m] - the same requests uniform random actions of the RL env make."""
        req = draw_request(self.rng)
        dt = self.ctx.feasible.dt
        t0 = float(self.rng.integers(0, max(1, int(self.t_end / dt)))) * dt
        return req, t0, self.ctx.path.sigma_at_time(t0) + req.along

    def _ego_at(self, t: float) -> np.ndarray:
        ref = self.ctx.ref
        i = int(np.clip(round(t / ref.world_dt), 0, len(ref.ticks) - 1))
        return ref.xy[i]

    def add_static(self, m: Mutant, obstacle: str) -> bool:
        start = self._ego_at(0.0)
        for _ in range(self.max_tries):
            req, _, sigma = self._request()
            pose = self.placer.static(m.layout, obstacle, sigma, req.lateral, ego_xy=start)
            if pose is not None:
                self.placer.add_static(m.layout, m.new_id("cone" if obstacle == "CONE" else "static"), obstacle, pose)
                return True
        return False

    def add_vehicle(self, m: Mutant) -> bool:
        for _ in range(self.max_tries // 3):
            req, t0, sigma = self._request()
            traj = self.placer.vehicle(m.layout, t0, sigma, req.lateral, req.speed, req.manoeuvre,
                                       ego_xy=self._ego_at(t0), rng=self.rng)
            if traj is not None:
                self.placer.add_vehicle(m.layout, m.new_id("veh"), traj)
                return True
        return False


class RandomMutator(NonInvasiveMutator):
    """The Random baseline: add / remove participants anywhere on the road near the ego's path,
    with no feasibility constraint (and so no placement rule)."""

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

    @cached_property
    def _ego_start(self) -> np.ndarray:
        return pose_xyh(self.ctx.roadmap, self.ctx.scenario.ego)[0]

    def _off_ego(self, x: float, y: float, t0: float = 0.0) -> bool:
        """Whether a participant appearing at ``(x, y)`` at ``t0`` [s] is a scenario at all: one
        that starts on the ego (centres closer than the scenario format's ``MIN_GAP``) is refused
        by the scenario check, so Random draws again."""
        exy = self._ego_start
        return t0 > 0.0 or float(np.hypot(x - exy[0], y - exy[1])) >= MIN_GAP

    def _point_at(self) -> tuple[float, float, float]:
        """A requested point of the shared grid taken as it is (no placement rule): ``(x, y, t0)``."""
        req, t0, sigma = self._request()
        xy, _ = self.ctx.path.offset(np.array([sigma]), np.array([req.lateral]))
        return float(xy[0, 0]), float(xy[0, 1]), t0

    def add_static(self, m: Mutant, obstacle: str) -> bool:
        for _ in range(self.max_tries):
            x, y, _ = self._point_at()
            if self._off_ego(x, y):
                break
        else:
            return False
        loc = self.ctx.roadmap.locate(np.array([x, y]))
        h = float(self.ctx.roadmap.geom(loc[0]).heading_point(loc[1])) if loc is not None else 0.0
        pid = m.new_id("cone" if obstacle == "CONE" else "static")
        spec = {"id": pid, "type": "static", "obstacle": obstacle, "x": x, "y": y, "heading": h}
        length, width = SIZES[obstacle]
        m.layout.add(Placed(pid, "static", spec, area=m.layout.static_footprint(x, y, h, length, width)))
        return True

    def add_vehicle(self, m: Mutant) -> bool:
        for _ in range(self.max_tries):
            x, y, t0 = self._point_at()
            st = start_state(self.ctx.roadmap, x, y, 0.0, 0.0) or self._on_lane(x, y)
            if st is None:
                continue
            if not self._off_ego(x, y, t0):
                continue
            turn = str(self.rng.choice(["straight", "straight", "left", "right"]))
            traj = self._drive(st, t0, turn)
            # the drawn point may lie off the lane: the vehicle starts where it is clamped onto it
            if traj is None or not self._off_ego(float(traj.x[0]), float(traj.y[0]), t0):
                continue
            pid = m.new_id("veh")
            spec = vehicle_spec(pid, traj)
            m.layout.add(Placed(pid, "scripted", spec, {}, traj=traj))
            return True
        return False

    def _on_lane(self, x: float, y: float) -> VState | None:
        loc = self.ctx.roadmap.locate(np.array([x, y]))
        if loc is None:
            return None
        lane, s, d = loc
        g = self.ctx.roadmap.geom(lane)
        if not 0.0 <= s <= g.length:
            return None
        return VState(lane, float(s), float(np.clip(d, -g.width / 2, g.width / 2)), 0.0)

    def _drive(self, st: VState, t0: float, turn: str) -> Trajectory | None:
        traj: Trajectory | None = None
        t, horizon = t0, self.ctx.scenario.duration
        st = VState(st.lane, st.s, st.d, float(self.rng.uniform(0.0, self.driver.v_max(st.lane))))
        while t < horizon - 1e-9:
            c = Controls(float(self.rng.uniform(0.0, self.driver.v_max(st.lane))),
                         int(self.rng.choice([0, 0, 0, -1, 1])), float(self.rng.uniform(-0.6, 0.6)), turn)
            w = self.driver.window(st, t, c) or self.driver.window(st, t, Controls(c.v_end, 0, st.d, turn))
            if w is None:
                return None
            traj = w if traj is None else traj.extend(w)
            st, t = w.states[-1], float(w.t[-1])
        return traj
