"""Motion of the vehicles an adversary adds: lane-bound, window by window.

A vehicle's state is ``(lane, s, d, v)`` (lane coordinates, highway-env conventions: ``d``
positive to the right). Over one window of ``dt`` seconds it follows :class:`Controls`: a
constant acceleration towards ``v_end`` (bounded by ``a_max`` / ``d_max``), an optional change
to the next lane on either side (a smooth lateral move over the window) and an in-lane offset;
at the end of a lane it continues on a successor (straight by default, or the left/right turn);
at a dead end it stops. The result is sampled every ``sample_dt`` seconds and becomes the
waypoints of a ``scripted`` participant, which the world replays exactly.

:func:`complete` extends a trajectory window by window until the horizon with the first option
(keep going, faster, slower, move away from the ego's path, stop) that keeps the vehicle
non-invasive in that window - Decictor's Algorithm 2 ("Adding"), with the waypoint of each window
chosen from the feasible set in a fixed order of preference (or at random for the search
baselines), backtracking when a window has no feasible continuation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from deft_gym.search.feasible import Layout
from deft_gym.world.participants import SIZES, motion_headings
from deft_gym.world.roadmap import LaneId, RoadMap

LENGTH, WIDTH = SIZES["VEHICLE"]


@dataclass(frozen=True)
class VState:
    """Lane-bound vehicle state: lane, arc length s [m], offset d [m] (right +), speed v [m/s]."""

    lane: LaneId
    s: float
    d: float
    v: float


@dataclass(frozen=True)
class Controls:
    """What a vehicle does during one window."""

    v_end: float
    shift: int = 0  # -1: lane to the left, +1: lane to the right
    d_end: float = 0.0  # in-lane offset at the end of the window [m]
    turn: str = "straight"  # successor choice at the end of a lane: straight | left | right


@dataclass
class Trajectory:
    """Sampled motion: times [s], poses and the lane state at every sample."""

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    h: np.ndarray
    states: list[VState]
    turn: str = "straight"

    def index(self, t: float) -> int:
        return int(np.clip(np.searchsorted(self.t, t - 1e-9), 0, len(self.t) - 1))

    def state_at(self, t: float) -> VState:
        return self.states[self.index(t)]

    def until(self, t: float) -> Trajectory:
        """The part up to time ``t`` (inclusive)."""
        n = int(np.searchsorted(self.t, t + 1e-9))
        n = max(n, 1)
        return Trajectory(self.t[:n], self.x[:n], self.y[:n], self.h[:n], self.states[:n], self.turn)

    def extend(self, other: Trajectory) -> Trajectory:
        """This trajectory followed by ``other`` (whose first sample repeats our last; its
        heading - the direction of the next segment - wins)."""
        k = 1 if len(self.t) and len(other.t) and abs(other.t[0] - self.t[-1]) < 1e-9 else 0
        h = np.concatenate([self.h[:len(self.h) - k], other.h])
        return Trajectory(np.concatenate([self.t, other.t[k:]]), np.concatenate([self.x, other.x[k:]]),
                          np.concatenate([self.y, other.y[k:]]), h, self.states + other.states[k:], other.turn)

    def waypoints(self) -> list[dict[str, float]]:
        """Scripted-participant waypoints ``{t, x, y}`` (collinear interior points dropped; the
        first also carries the initial heading)."""
        t, x, y = self.t, self.x, self.y
        keep = np.ones(len(t), dtype=bool)
        if len(t) > 2:
            vx, vy = np.diff(x) / np.diff(t), np.diff(y) / np.diff(t)
            same = (np.abs(vx[1:] - vx[:-1]) < 1e-6) & (np.abs(vy[1:] - vy[:-1]) < 1e-6)
            keep[1:-1] = ~same
        wps = [{"t": round(float(a), 6), "x": float(b), "y": float(c)} for a, b, c in zip(t[keep], x[keep], y[keep])]
        wps[0]["heading"] = float(self.h[0])  # the heading while it stands still before moving
        return wps


class LaneDriver:
    """Integrates :class:`Controls` over windows on a road map."""

    def __init__(self, roadmap: RoadMap, dt: float = 2.0, sample_dt: float = 0.25, a_max: float = 3.0,
                 d_max: float = 5.0, v_max_factor: float = 1.3) -> None:
        self.map, self.dt, self.sample_dt = roadmap, dt, sample_dt
        self.a_max, self.d_max = a_max, d_max
        self.n = max(1, round(dt / sample_dt))
        self.u = np.arange(self.n + 1) / self.n
        self.v_max_factor = v_max_factor
        self.min_lateral_speed = 3.0  # [m/s] below this a vehicle keeps its lateral offset

    def v_max(self, lane: LaneId) -> float:
        return self.v_max_factor * float(self.map.lanes[lane].speed_limit or 12.0)

    def neighbour(self, lane: LaneId, shift: int) -> LaneId | None:
        """The parallel lane ``shift`` (+-1) to the side on the same road that a lane change may
        reach (a striped line between them, not in a junction)."""
        if shift == 0:
            return lane
        a, b, k = lane
        nb = (a, b, k + shift)
        return nb if nb in self.map.changeable_neighbours(lane) else None

    def successor(self, lane: LaneId, turn: str) -> LaneId | None:
        succ = self.map.successors.get(lane, [])
        if not succ:
            return None
        straight = self.map.straight_successor(lane)
        if turn == "straight" or len(succ) == 1:
            return straight
        g = self.map.geoms[lane]
        h_end = float(g.heading_point(g.length))

        def dh(b: LaneId) -> float:
            gb = self.map.geoms[b]
            return float((gb.heading_point(gb.length) - h_end + math.pi) % (2 * math.pi) - math.pi)

        turns = [(dh(b), b) for b in succ]
        pick = min(turns) if turn == "left" else max(turns)  # heading grows turning right (y down)
        return pick[1] if abs(pick[0]) > 0.3 else straight

    def window(self, st: VState, t0: float, c: Controls) -> Trajectory | None:
        """One window of motion from ``st`` at ``t0``; None if the lane change is impossible."""
        dt, u = self.dt, self.u
        w = self.map.geoms[st.lane].width
        target = self.neighbour(st.lane, c.shift)
        if target is None:
            return None
        v_end = float(np.clip(c.v_end, 0.0, self.v_max(st.lane)))
        a = float(np.clip((v_end - st.v) / dt, -self.d_max, self.a_max))
        tau = u * dt
        v = np.maximum(st.v + a * tau, 0.0)
        if a < 0 and st.v + a * dt < 0:  # stops inside the window
            t_stop = st.v / -a
            s_rel = np.where(tau < t_stop, st.v * tau + 0.5 * a * tau**2, st.v * t_stop + 0.5 * a * t_stop**2)
        else:
            s_rel = st.v * tau + 0.5 * a * tau**2
        d_goal = c.shift * w + float(np.clip(c.d_end, -0.9, 0.9))
        if c.shift and st.s + s_rel[-1] + 5.0 > self.map.geoms[st.lane].length:
            return None  # lane changes only well before the end of the lane
        if abs(d_goal - st.d) > 0.05 and min(st.v, v_end) < self.min_lateral_speed:
            return None  # no sideways moves at a crawl
        ss = 3 * u**2 - 2 * u**3
        d = st.d + (d_goal - st.d) * ss
        dd = (d_goal - st.d) * (6 * u - 6 * u**2) / dt
        # walk along lanes
        lanes = [st.lane] * len(u)
        s_abs = st.s + s_rel
        s_loc = s_abs.copy()
        lane, off, start = st.lane, 0.0, 0
        xs, ys, hs = np.empty(len(u)), np.empty(len(u)), np.empty(len(u))
        while True:
            g = self.map.geoms[lane]
            local = s_abs - off
            over = np.flatnonzero(local[start:] > g.length) + start
            end = int(over[0]) if len(over) else len(u)
            if end > start:
                seg = slice(start, end)
                xy = g.xy(local[seg], d[seg])
                xs[seg], ys[seg] = xy[:, 0], xy[:, 1]
                hs[seg] = g.heading(local[seg]) + np.arctan2(dd[seg], np.maximum(v[seg], 0.5))
                s_loc[seg] = local[seg]
                lanes[start:end] = [lane] * (end - start)
            if end == len(u):
                break
            nxt = self.successor(lane, c.turn)
            if nxt is None:  # dead end: stop at the end of the lane
                xy = g.xy(np.full(len(u) - end, g.length), d[end:])
                xs[end:], ys[end:] = xy[:, 0], xy[:, 1]
                hs[end:] = g.heading_point(g.length)
                v[end:] = 0.0
                s_loc[end:] = g.length
                lanes[end:] = [lane] * (len(u) - end)
                break
            off += g.length
            lane, start = nxt, end
        hs = motion_headings(xs, ys, hs)
        states = [VState(lanes[i], float(s_loc[i]), float(d[i]), float(v[i])) for i in range(len(u))]
        last = states[-1]
        if c.shift:
            nb = self.neighbour(last.lane, c.shift)
            if nb is not None:
                last = VState(nb, last.s, last.d - c.shift * w, last.v)
                states[-1] = last
        return Trajectory(t0 + tau, xs, ys, hs, states, c.turn)


def start_state(roadmap: RoadMap, x: float, y: float, heading: float, v: float) -> VState | None:
    """The lane state of a pose on the road (None when it is off every lane)."""
    loc = roadmap.locate(np.array([x, y]), heading)
    if loc is None:
        return None
    lane, s, d = loc
    g = roadmap.geoms[lane]
    if not (0.0 <= s <= g.length) or abs(d) > g.width / 2:
        return None
    return VState(lane, float(s), float(d), float(v))


def lateral_shifts(driver: LaneDriver, st: VState, ref_xy: np.ndarray) -> tuple[list[int], list[int]]:
    """Possible lane shifts that take the vehicle away from / towards the reference path
    (farthest / closest first)."""
    here = driver.map.geoms[st.lane].xy(np.array(st.s), st.d)
    d0 = float(np.min(np.hypot(*(ref_xy - here).T)))
    away, toward = [], []
    for sh in (-1, 1):
        nb = driver.neighbour(st.lane, sh)
        if nb is None:
            continue
        g = driver.map.geoms[nb]
        p = g.xy(np.array(min(st.s, g.length)), st.d)
        dist = float(np.min(np.hypot(*(ref_xy - p).T)))
        (away if dist > d0 else toward).append((dist, sh))
    return [sh for _, sh in sorted(away, reverse=True)], [sh for _, sh in sorted(toward)]


def options(driver: LaneDriver, st: VState, turn: str, ref_xy: np.ndarray,
            rng: np.random.Generator | None = None) -> list[Controls]:
    """Continuation options for one window: in order of preference (keep going, faster, slower,
    away from the ego's path, towards it, nudge, stop), or shuffled with ``rng``."""
    vm = driver.v_max(st.lane)
    away, toward = lateral_shifts(driver, st, ref_xy)
    opts = [Controls(st.v, 0, st.d, turn), Controls(min(st.v + 4.0, vm), 0, st.d, turn),
            Controls(max(st.v - 4.0, 0.0), 0, st.d, turn)]
    opts += [Controls(st.v, sh, 0.0, turn) for sh in away + toward]
    opts += [Controls(st.v, 0, d, turn) for d in (-0.8, 0.8) if abs(d - st.d) > 0.3]
    opts.append(Controls(0.0, 0, st.d, turn))
    if rng is not None:
        opts = [opts[int(i)] for i in rng.permutation(len(opts))]
        opts.insert(int(rng.integers(len(opts) + 1)), Controls(float(rng.uniform(0.0, vm)), 0,
                                                              float(rng.uniform(-0.6, 0.6)), turn))
    return opts


def window_feasible(layout: Layout, w: Trajectory, skip: str | None = None) -> bool:
    """One window of motion (starting at ``w.t[0]``) invades no motion area of its time window
    (``skip``: an added participant to ignore, the one being changed)."""
    k = layout.areas.window(float(w.t[0]) + 1e-6)
    return layout.first_conflict(w.t, w.x, w.y, w.h, LENGTH, WIDTH, skip, k, k + 1) < 0


def complete(driver: LaneDriver, layout: Layout, traj: Trajectory, horizon: float, ref_xy: np.ndarray,
             skip: str | None = None, rng: np.random.Generator | None = None,
             budget: int = 60) -> Trajectory | None:
    """Extend ``traj`` (whose own feasibility is the caller's business) window by window up to
    ``horizon`` [s] so that every new window is feasible - Algorithm 2's loop, as a depth-first
    search that backtracks when a window has no feasible continuation (at most ``budget``
    window checks). None when there is none. Options are tried in order of preference, or in
    random order with ``rng`` (the search baselines)."""
    stack: list[tuple[Trajectory, list[Controls]]] = []
    cur: Trajectory = traj
    checks = 0
    while cur.t[-1] < horizon - 1e-9:
        st = cur.states[-1]
        stack.append((cur, options(driver, st, cur.turn, ref_xy, rng)))
        nxt = None
        while stack and nxt is None:
            base, opts = stack[-1]
            t0 = float(base.t[-1])
            while opts:
                w = driver.window(base.states[-1], t0, opts.pop(0))
                if w is None:
                    continue
                checks += 1
                if window_feasible(layout, w, skip):
                    nxt = base.extend(w)
                    break
                if checks >= budget:
                    return None
            if nxt is None:
                stack.pop()  # dead end: back to the previous window's next option
        if nxt is None:
            return None
        cur = nxt
    return cur


def sample_window(driver: LaneDriver, layout: Layout, st: VState, t0: float, turn: str, ref_xy: np.ndarray,
                  skip: str | None, rng: np.random.Generator, tries: int = 12) -> Trajectory | None:
    """A random feasible first window from ``st`` (Algorithm 2, line 9: y_{t+dt} sampled in the
    non-invasive area reachable from y_t), or None after ``tries`` refusals."""
    opts = options(driver, st, turn, ref_xy, rng)[:tries]
    for c in opts:
        w = driver.window(st, t0, c)
        if w is not None and window_feasible(layout, w, skip):
            return w
    return None


def vehicle_spec(pid: str, traj: Trajectory) -> dict[str, Any]:
    """The scripted-participant spec of a trajectory."""
    return {"id": pid, "type": "scripted", "waypoints": traj.waypoints(), "length": LENGTH, "width": WIDTH}

