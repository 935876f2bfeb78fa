"""The reference planner: a lane-aware Frenet lattice planner (Werling-style) along the route.

One cycle:

1. **Start state.** Stitch from the previous plan at the frame time if the vehicle is close to
   it (Apollo's trajectory stitcher); otherwise re-plan from the localization pose.
2. **Reference line.** The lane the vehicle is on, continued along the route.
3. **Lattice.** Lateral quintics in time to the lane centre, nudges inside the lane, and lane
   changes where allowed; longitudinal quartics to several cruise speeds and quintics that stop
   at walls (red/yellow stop lines, the destination, dead ends), slow down for curves or keep a
   gap to a leader. Every lateral x longitudinal pair is one candidate.
4. **Evaluation, vectorised** over candidates x time x obstacles: hard constraints (collision
   with predicted obstacles plus a hard buffer, walls, road edges, lateral acceleration) and a
   cost (speed, lateral offset, lane changes, route preference, comfort, a soft safety buffer
   around obstacles, and hysteresis against the previous decision).
5. **Fallback.** No feasible candidate -> emergency stop in the current lane.

It sees only its frame: routing, localization, traffic lights and predicted obstacles. It is
deterministic: no clock, no randomness, stable argmin. It makes the mistakes a real planner
makes: obstacles are judged by their Frenet boxes plus buffers (over-cautious next to lane
boundaries), and predictions (constant velocity along the lane) miss cut-ins and turns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from deft_gym.geometry import ReferenceLine, wrap_angle
from deft_gym.planner.base import Frame, Planner
from deft_gym.roadmap import LaneId, shared_roadmap


class LatticeParams(BaseModel):
    """Tuning of :class:`LatticePlanner` (SI units: m, s, m/s, m/s^2)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    horizon: float = Field(6.0, gt=1.0, le=15.0)
    dt: float = Field(0.2, gt=0.02, le=1.0)
    nudges: tuple[float, ...] = (-0.8, -0.4, 0.4, 0.8)
    speed_factors: tuple[float, ...] = (1.0, 0.7, 0.4)
    speed_times: tuple[float, ...] = (2.5, 5.0)
    stop_time_factors: tuple[float, ...] = (1.0, 1.5)
    lane_change_time: float = 3.5
    nudge_time: float = 2.5
    recentre_time: float = 1.5  #: a quicker return to the lane centre (after a wide turn, a swerve)
    default_cruise: float = 10.0
    max_accel: float = 2.5
    emergency_decel: float = 7.0
    max_lat_accel: float = 2.5
    hard_lat_accel: float = 5.0
    yellow_decel: float = 3.0
    ego_length: float = 4.8
    ego_width: float = 2.0
    lat_buffer_hard: float = 0.5
    lon_buffer_hard: float = 1.0
    lat_buffer_soft: float = 1.0
    stop_gap: float = 1.0
    follow_gap: float = 4.0
    static_gap: float = 6.0
    time_gap: float = 1.5
    stitch_lat: float = 0.5
    stitch_lon: float = 1.5
    edge_margin: float = 0.3
    w_speed: float = 8.0
    w_lat: float = 0.5
    w_nudge: float = 1.0
    w_lane_change: float = 3.0
    w_route: float = 20.0
    w_route_far: float = 2.0
    route_fork_distance: float = 80.0
    route_dest_distance: float = 30.0
    w_brake: float = 5.0
    w_blocked: float = 5.0
    w_accel: float = 0.05
    w_jerk: float = 0.01
    w_lat_accel: float = 0.05
    w_obstacle: float = 1.0
    w_hysteresis: float = 1.0
    ref_step: float = 0.25
    publish_debug: bool = False


@dataclass
class LatticeState:
    """Everything the planner carries from one cycle to the next."""

    traj: dict[str, np.ndarray] | None = None
    target_lane: LaneId | None = None
    offset: float = 0.0
    lane: LaneId | None = None
    cycles: int = 0


@dataclass
class _Route:
    roads: list[tuple[str, str]]
    dest_lane: LaneId
    dest_s: float
    cruise: float


@dataclass
class _Ref:
    """A reference line sampled on a uniform grid (for fast interpolation)."""

    line: ReferenceLine
    s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    h: np.ndarray
    k: np.ndarray
    vlim: np.ndarray  # curvature speed limit [m/s] on a 1 m grid starting at s[0]
    continues: bool  # the chain reaches the destination road or follows the route to its end

    def at(self, s: float) -> tuple[float, float]:
        """Heading [rad] and curvature [1/m] at one ``s`` (linear interpolation)."""
        f = (s - float(self.s[0])) / (float(self.s[1]) - float(self.s[0]))
        i = min(max(int(f), 0), len(self.s) - 2)
        w = min(max(f - i, 0.0), 1.0)
        return (float(self.h[i]) * (1 - w) + float(self.h[i + 1]) * w,
                float(self.k[i]) * (1 - w) + float(self.k[i + 1]) * w)

    def min_vlim(self, s_a: float, s_b: float) -> float:
        """Lowest curvature speed limit between ``s_a`` and ``s_b``."""
        i = max(int(s_a - float(self.s[0])), 0)
        j = max(int(s_b - float(self.s[0])) + 1, i + 1)
        seg = self.vlim[i:j]
        return float(seg.min()) if seg.size else math.inf


@dataclass
class _Lateral:
    """Per (lane, route): the lateral options and everything about them that is static."""

    target: list[LaneId]
    centre: np.ndarray
    offset: np.ndarray
    T: np.ndarray
    compat: np.ndarray
    change: np.ndarray
    static_cost: np.ndarray
    band: tuple[float, float]
    basis: list[np.ndarray] = field(default_factory=list)  # (3, n, K) for d0, d0', d0'', targets
    needed: np.ndarray = field(default_factory=lambda: np.zeros(0))  # lane changes still needed
    centres: np.ndarray = field(default_factory=lambda: np.zeros(0))  # distinct target lane centres


class LatticePlanner(Planner):
    """Lane-aware lattice planner along the route; see the module docstring."""

    def __init__(self, map_spec: dict[str, Any], **params: Any) -> None:
        super().__init__(map_spec, **params)
        self.p = LatticeParams.model_validate(params)
        self.map = shared_roadmap(self.map_spec)
        self.K = round(self.p.horizon / self.p.dt) + 1
        self.tk = np.arange(self.K) * self.p.dt
        self._route_cache: dict[Any, _Route] = {}
        self._ref_cache: dict[Any, _Ref] = {}
        self._lat_cache: dict[Any, _Lateral] = {}
        reach = max(self.p.horizon * self.p.horizon, 30.0) + 20.0  # [m] obstacles farther never matter
        self._reach2 = reach * reach
        self._half_lane = self.map.spec.lane_width / 2
        self._inv_k = 1.0 / self.K
        # Profiles with a fixed duration are linear in their start/end values, so their shapes
        # are computed once: cruise rows (speed factor x duration) and lateral durations.
        t = self.tk[None, :]
        qT = np.array([[T for _ in self.p.speed_factors for T in self.p.speed_times]]).T
        qf = np.array([[f for f in self.p.speed_factors for _ in self.p.speed_times]]).T
        _one, zero = np.ones_like(qT), np.zeros_like(qT)
        self._cruise_basis = [np.stack(_quartic(0.0, *u, qT, t)) for u in
                              ((1.0, 0.0, zero), (0.0, 1.0, zero), (0.0, 0.0, qf))]
        # reach quintics (to s1, v1 at T, then constant speed): T on a 0.1 s grid; for one T the
        # profile is linear in (s0, v0, a0, s1, v1), so each grid T has a (5, 3, K) basis
        self._reach_T = np.round(np.arange(1.0, self.p.horizon + 4.0 + 1e-9, 0.1), 6)
        TT = self._reach_T[:, None]
        one, zero = np.ones_like(TT), np.zeros_like(TT)
        self._reach_basis = np.stack([np.stack(_quintic(*u, zero, TT, t)) for u in
                                      ((0.0, 1.0, 0.0, zero, zero), (0.0, 0.0, 1.0, zero, zero),
                                       (0.0, 0.0, 0.0, one, zero), (0.0, 0.0, 0.0, zero, one))],
                                     axis=1).transpose(2, 1, 0, 3)  # (T, coefficient, s/v/a, K)
        self._lat_basis: dict[float, list[np.ndarray]] = {}
        for T in sorted({self.p.nudge_time, self.p.lane_change_time, self.p.recentre_time}):
            TT = np.array([[T]])
            self._lat_basis[T] = [np.stack(_quintic(*u, TT, t))[:, 0] for u in
                                  ((1.0, 0.0, 0.0, np.zeros((1, 1)), 0.0, 0.0),
                                   (0.0, 1.0, 0.0, np.zeros((1, 1)), 0.0, 0.0),
                                   (0.0, 0.0, 1.0, np.zeros((1, 1)), 0.0, 0.0),
                                   (0.0, 0.0, 0.0, np.ones((1, 1)), 0.0, 0.0))]
        self.state = LatticeState()

    def reset(self) -> None:
        self.state = LatticeState()

    # =========================================================================================
    def plan(self, frame: Frame) -> dict[str, Any] | None:
        routing, loc = frame.get("routing"), frame.get("localization")
        if routing is None or loc is None:
            return None
        st = self.state
        route = self._route(routing)
        t0 = float(frame.time)
        x0, y0, h0, v0, a0, stitched = self._start_state(t0, loc)
        lane = self._locate(x0, y0, h0, route)
        if lane is None:
            out = self._straight_stop(t0, x0, y0, h0, v0)
            self._commit(out, None, 0.0, None)
            return self._payload(out, "ESTOP", None, None, stitched, math.inf)
        ref = self._reference(lane, route)
        s0, d0 = ref.line.frenet_point(x0, y0)
        href, kr = ref.at(s0)
        dh = (h0 - href + math.pi) % (2 * math.pi) - math.pi
        vs0 = v0 * math.cos(dh) / max(1.0 - kr * d0, 0.2)
        vd0 = v0 * math.sin(dh)
        as0, ad0 = a0 * math.cos(dh), a0 * math.sin(dh)
        # a (nearly) stopped car cannot brake harder than its speed allows: a stitched braking
        # acceleration would make every profile dip below zero speed
        as0 = max(as0, -max(vs0, 0.0) / 0.3)
        v_des = min(route.cruise, float(self.map.lanes[lane].speed_limit or route.cruise))

        obs = self._obstacles(frame.get("prediction"), t0, ref, s0, d0)
        lat = self._lateral(lane, route)
        b0, b1, b2, b3 = lat.basis
        d, dd, ddd = d0 * b0 + vd0 * b1 + ad0 * b2 + b3
        walls = self._walls(frame.get("traffic_light"), ref, route, lane, s0, vs0, lat)
        lon = self._longitudinal(s0, vs0, as0, v_des, ref, walls, obs, lat)
        c_route = self._route_cost(lat, ref, route, lane, s0)
        best, cost = self._evaluate(ref, lat, d, dd, ddd, lon, obs, walls, v_des, c_route)
        if best is None:
            s, v, acc = _brake(s0, vs0, self.p.emergency_decel, self.tk)
            out = self._to_xy(ref, t0, s, v, acc, np.full(self.K, d0), np.zeros(self.K), h0)
            behavior, target, off = "ESTOP", lane, st.offset
        else:
            li, pi = best
            out = self._to_xy(ref, t0, lon["s"][pi], lon["v"][pi], lon["a"][pi], d[li], dd[li], h0)
            target, off = lat.target[li], float(lat.offset[li])
            behavior = self._behavior(lane, target, off, lon["label"][pi])
        self._commit(out, target, off, lane)
        return self._payload(out, behavior, lane, target, stitched, cost)

    # -- frame parsing ------------------------------------------------------------------------
    def _route(self, routing: dict[str, Any]) -> _Route:
        dest = routing["destination"]
        key = (tuple(tuple(seg["road"]) for seg in routing["segments"]), tuple(dest["lane"]), dest["s"],
               routing.get("cruise_speed"))
        r = self._route_cache.get(key)
        if r is None:
            lane = tuple(dest["lane"])
            cruise = routing.get("cruise_speed") or self.p.default_cruise
            r = _Route([tuple(seg["road"]) for seg in routing["segments"]], (lane[0], lane[1], int(lane[2])),
                       float(dest["s"]), float(cruise))
            self._route_cache[key] = r
        return r

    def _start_state(self, t0: float, loc: dict[str, Any]) -> tuple[float, float, float, float, float, bool]:
        x, y, h, v, a = (float(loc["x"]), float(loc["y"]), float(loc["heading"]), float(loc["v"]),
                         float(loc.get("a", 0.0)))
        prev = self.state.traj
        if prev is not None:
            t = prev["t"]
            t_first, t_last = float(t[0]), float(t[-1])
            if t_first <= t0 <= t_last:
                f = (t0 - t_first) / self.p.dt
                i = min(int(f), self.K - 2)
                w = f - i

                def at(key: str) -> float:
                    arr = prev[key]
                    return float(arr[i]) * (1.0 - w) + float(arr[i + 1]) * w

                xp, yp, hp = at("x"), at("y"), at("hu")
                dx, dy = x - xp, y - yp
                ch, sh = math.cos(hp), math.sin(hp)
                if abs(-dx * sh + dy * ch) <= self.p.stitch_lat and abs(dx * ch + dy * sh) <= self.p.stitch_lon:
                    hw = (hp + math.pi) % (2 * math.pi) - math.pi
                    return xp, yp, hw, at("v"), at("a"), True
        return x, y, h, max(v, 0.0), a, False

    def _locate(self, x: float, y: float, h: float, route: _Route) -> LaneId | None:
        """The lane the vehicle is on: search around the previous lane first (its successors and
        neighbours), the whole map only when that finds nothing good."""
        prev = self.state.lane
        if prev is not None:
            cand = [prev, *self.map.successors[prev], *self.map.changeable_neighbours(prev)]
            best, score = self._best_lane(cand, x, y, h, route)
            if best is not None and score < 1.5:
                return best
        _, idx = self.map.candidate_lanes(np.array([x, y]), radius=4.0)
        best, score = self._best_lane([self.map.lane_ids[j] for j in sorted(idx.tolist())], x, y, h, route)
        return best if score < 6.0 else None

    def _best_lane(self, cand: list[LaneId], x: float, y: float, h: float, route: _Route) -> tuple[LaneId | None, float]:
        roads = route.roads
        best, best_score = None, math.inf
        for lid in cand:
            g = self.map.geoms[lid]
            s, d = g.frenet_point(x, y)
            hl = g.heading_point(min(max(s, 0.0), g.length))
            dh = abs((h - hl + math.pi) % (2 * math.pi) - math.pi)
            score = abs(d) + 2.0 * max(0.0, -s, s - g.length) + 4.0 * dh
            if lid[:2] not in roads:
                score += 3.0
            if lid == self.state.lane:
                score -= 0.3
            if score < best_score:
                best, best_score = lid, score
        return best, best_score

    # -- reference line -----------------------------------------------------------------------
    def _next_on_route(self, lid: LaneId, route: _Route) -> LaneId | None:
        road = lid[:2]
        if road not in route.roads:
            return self.map.straight_successor(lid)
        i = route.roads.index(road)
        if i + 1 >= len(route.roads):
            return None
        nxt = route.roads[i + 1]
        for succ in self.map.successors[lid]:
            if succ[:2] == nxt:
                return succ
        return None

    def _reference(self, lane: LaneId, route: _Route) -> _Ref:
        key = (lane, tuple(route.roads), route.dest_lane)
        ref = self._ref_cache.get(key)
        if ref is not None:
            return ref
        chain = [lane]
        total = self.map.geoms[lane].length
        reach = total + 150.0  # the horizon from anywhere on the lane, with margin
        while total < reach:
            nxt = self._next_on_route(chain[-1], route)
            if nxt is None or nxt in chain:
                break
            chain.append(nxt)
            total += self.map.geoms[nxt].length
        last = chain[-1]
        continues = last[:2] == route.dest_lane[:2] or self._next_on_route(last, route) is not None
        line = self.map.reference_line(chain)
        s = np.arange(-20.0, line.length + 60.0 + self.p.ref_step, self.p.ref_step)
        xy = line.xy(s)
        h = np.unwrap(line.heading(s))
        k = line.curvature(s)
        s1 = np.arange(float(s[0]), float(s[-1]), 1.0)
        k1 = np.abs(np.interp(s1, s, k))
        # speed limit along the chain: curvature (lateral acceleration) and each lane's limit
        lane_limit = np.array([float(self.map.lanes[lid].speed_limit or np.inf) for lid in chain])
        vlim = np.minimum(np.sqrt(self.p.max_lat_accel / np.maximum(k1, 1e-6)), lane_limit[line._piece(s1)])
        ref = _Ref(line, s, xy[:, 0].copy(), xy[:, 1].copy(), h, k, vlim, continues)
        self._ref_cache[key] = ref
        return ref

    # -- obstacles ----------------------------------------------------------------------------
    def _obstacles(self, pred: dict[str, Any] | None, t0: float, ref: _Ref, s0: float,
                   d0: float) -> dict[str, np.ndarray] | None:
        """Predicted obstacle boxes at the planning times ``t0 + k dt`` (held at their last
        prediction point): centre, heading and half-size in world coordinates for the collision
        check, plus their Frenet coordinates now and at the horizon for choosing leaders.
        Obstacles that stay out of the ego's reach over the horizon are dropped."""
        if not pred or not pred.get("obstacles"):
            return None
        K, tq = self.K, t0 + self.tk
        statics = []
        groups: dict[tuple[float, float, int], list[dict[str, Any]]] = {}
        for ob in pred["obstacles"]:
            if len(ob["x"]) == 1:  # static: one point, constant over the horizon
                statics.append((ob["x"][0], ob["y"][0], ob["heading"][0], 0.5 * ob["length"], 0.5 * ob["width"], 0.0))
            else:  # moving: grouped by time base, resampled together
                groups.setdefault((float(ob["t0"]), float(ob["dt"]), len(ob["x"])), []).append(ob)
        blocks_x, blocks_y, blocks_h, dims = [], [], [], []
        if statics:
            st = np.array(statics)
            blocks_x.append(np.repeat(st[:, :1], K, axis=1))
            blocks_y.append(np.repeat(st[:, 1:2], K, axis=1))
            blocks_h.append(np.repeat(st[:, 2:3], K, axis=1))
            dims.append(st[:, 3:])
        for (ot0, odt, n), obs_g in groups.items():
            f = np.clip((tq - ot0) * (1.0 / odt), 0.0, n - 1.0)
            i = np.minimum(f.astype(np.int64), n - 2)
            w = f - i
            X = np.array([ob["x"] for ob in obs_g])
            Y = np.array([ob["y"] for ob in obs_g])
            x0, y0 = X[:, i], Y[:, i]
            blocks_x.append(x0 + (X[:, i + 1] - x0) * w)
            blocks_y.append(y0 + (Y[:, i + 1] - y0) * w)
            blocks_h.append(np.array([ob["heading"] for ob in obs_g])[:, np.rint(f).astype(np.int64)])
            dims.append(np.array([(0.5 * ob["length"], 0.5 * ob["width"], ob.get("v", 0.0)) for ob in obs_g]))
        if len(blocks_x) == 1:
            ox, oy, oh, dims_a = blocks_x[0], blocks_y[0], blocks_h[0], dims[0]
        else:
            ox, oy, oh = np.concatenate(blocks_x), np.concatenate(blocks_y), np.concatenate(blocks_h)
            dims_a = np.concatenate(dims)
        # relevance: within reach of the ego over the horizon
        ex, ey = float(np.interp(s0, ref.s, ref.x)), float(np.interp(s0, ref.s, ref.y))
        gx, gy = ox - ex, oy - ey
        near = (gx * gx + gy * gy).min(axis=1) < self._reach2
        # Frenet now and at the horizon (leaders, gaps, followers)
        ends = np.stack([ox[:, ::K - 1], oy[:, ::K - 1]], axis=-1)
        sf, df = ref.line.frenet(ends)
        phi = oh[:, ::K - 1] - np.interp(sf, ref.s, ref.h)
        c, sn = np.abs(np.cos(phi)), np.abs(np.sin(phi))
        hl, hw = dims_a[:, :1], dims_a[:, 1:2]
        fes = hl * c + hw * sn
        # a follower in the ego's own lane is responsible for keeping its distance
        follower = (sf[:, 0] + fes[:, 0] < s0 - self.p.ego_length / 2) & (np.abs(df[:, 0] - d0) < self._half_lane)
        keep = near & ~follower
        if not keep.any():
            return None
        if not keep.all():
            ox, oy, oh, dims_a, sf, df, fes = (a[keep] for a in (ox, oy, oh, dims_a, sf, df, fes))
            c, sn, hl, hw = c[keep], sn[keep], hl[keep], hw[keep]
        return {"x": ox, "y": oy, "c": np.cos(oh), "s": np.sin(oh), "hl": hl, "hw": hw,
                "r": np.hypot(hl, hw), "v": dims_a[:, 2], "fs": sf, "fd": df, "fes": fes,
                "fed": hl * sn + hw * c}

    # -- lateral options ----------------------------------------------------------------------
    def _continues(self, lid: LaneId, route: _Route) -> bool:
        if lid[:2] == route.dest_lane[:2]:
            return lid == route.dest_lane
        return self._next_on_route(lid, route) is not None or lid[:2] not in route.roads

    def _lateral(self, lane: LaneId, route: _Route) -> _Lateral:
        """Lateral targets from ``lane``: its centre, nudges, and lane changes where allowed."""
        key = (lane, tuple(route.roads), route.dest_lane)
        lat = self._lat_cache.get(key)
        if lat is not None:
            return lat
        p, w = self.p, self.map.spec.lane_width
        targets: list[tuple[LaneId, float, float, float]] = [(lane, 0.0, 0.0, p.nudge_time),
                                                             (lane, 0.0, 0.0, p.recentre_time)]
        targets += [(lane, 0.0, off, p.nudge_time) for off in p.nudges]
        nbs = self.map.changeable_neighbours(lane)
        for nb in nbs:
            targets.append((nb, w * (nb[2] - lane[2]), 0.0, p.lane_change_time))  # ids grow rightwards
        offset = np.array([t[2] for t in targets])
        change = np.array([t[0] != lane for t in targets])
        compat = np.array([self._continues(t[0], route) for t in targets])
        # route preference: lane changes still needed after this option to reach a lane that
        # continues along the route (so the planner moves towards it one lane at a time)
        road_ok = [j for a, b, j in self.map.road_lanes(lane[:2]) if self._continues((a, b, j), route)]
        n_lanes = len(self.map.road_lanes(lane[:2]))
        needed = np.array([min((abs(t[0][2] - j) for j in road_ok), default=n_lanes) for t in targets])
        static_cost = p.w_nudge * np.abs(offset) + p.w_lane_change * change
        band = (-w / 2 - w * sum(1 for b in nbs if b[2] < lane[2]),
                w / 2 + w * sum(1 for b in nbs if b[2] > lane[2]))
        lat = _Lateral([t[0] for t in targets], np.array([t[1] for t in targets]), offset,
                       np.array([t[3] for t in targets]), compat, change, static_cost, band)
        lat.needed = needed
        lat.centres = np.unique(lat.centre)
        rows = [[self._lat_basis[t[3]][c] for t in targets] for c in range(4)]
        lat.basis = [np.stack(r, axis=1) for r in rows[:3]]
        lat.basis.append(np.stack(rows[3], axis=1) * (lat.centre + lat.offset)[None, :, None])
        self._lat_cache[key] = lat
        return lat

    def _route_cost(self, lat: _Lateral, ref: _Ref, route: _Route, lane: LaneId, s0: float) -> np.ndarray:
        """Cost of the lane changes each option still leaves to do: mild while the point where
        the lane must be right (the end of the road before a fork, or the destination) is far,
        strong once fewer than ``route_*_distance`` metres per needed change remain."""
        p = self.p
        if lane[:2] == route.dest_lane[:2]:
            dist, per_lane = route.dest_s - s0, p.route_dest_distance
        else:
            dist, per_lane = float(ref.line.geoms[0].length) - s0, p.route_fork_distance
        urgent = dist < lat.needed * per_lane
        return lat.needed * np.where(urgent, p.w_route, p.w_route_far)

    # -- walls --------------------------------------------------------------------------------
    def _walls(self, tl: dict[str, Any] | None, ref: _Ref, route: _Route, lane: LaneId, s0: float,
               v0: float, lat: _Lateral) -> np.ndarray:
        """Per lateral option, the largest allowed centre ``s`` over the horizon: red (or
        stoppable yellow, or unknown) lights, the destination, and the end of a lane that leaves
        the route."""
        p = self.p
        half = p.ego_length / 2
        colors = {lt["id"]: lt["color"] for lt in (tl or {}).get("lights", [])}
        limit_all = math.inf
        line = ref.line
        for j, lid in enumerate(line.lane_ids):
            off = float(line.offsets[j])
            sl = self.map.stop_line_of.get(lid)
            if sl is not None:
                s_line = off + sl.s
                gap = s_line - (s0 + half)
                if gap > -0.5:
                    color = colors.get(sl.light_id, "UNKNOWN")
                    need = v0 * v0 / (2 * max(gap - p.stop_gap, 0.1))
                    stop = (color in ("RED", "UNKNOWN") and need <= p.emergency_decel) or (
                        color == "YELLOW" and need <= p.yellow_decel)
                    if stop:
                        limit_all = min(limit_all, s_line - half - p.stop_gap)
            if lid[:2] == route.dest_lane[:2]:
                limit_all = min(limit_all, off + route.dest_s)
        limits = np.full(len(lat.target), limit_all)
        if not ref.continues:
            dead_end = float(line.offsets[-1] + line.geoms[-1].length) - half - p.stop_gap
            for i, tgt in enumerate(lat.target):
                if tgt == lane or not lat.compat[i]:
                    limits[i] = min(limits[i], dead_end)
        return limits

    # -- longitudinal profiles ----------------------------------------------------------------
    def _longitudinal(self, s0: float, v0: float, a0: float, v_des: float, ref: _Ref,
                      walls: np.ndarray, obs: dict[str, np.ndarray] | None, lat: _Lateral) -> dict[str, Any]:
        """Speed profiles: cruise quartics, and quintics reaching (s, v) targets - stops at walls,
        slowing for curves, keeping a gap behind leaders - plus an emergency brake."""
        p, tk = self.p, self.tk
        labels: list[str] = []
        v_des = min(v_des, ref.min_vlim(s0, s0 + 8.0))
        labels = ["CRUISE"] * (len(p.speed_factors) * len(p.speed_times))
        bv, ba, bf = self._cruise_basis
        cruise = v0 * bv + a0 * ba + v_des * bf
        cruise[0] += s0
        targets: list[tuple[float, float, str]] = []
        for lim in sorted(set(walls[np.isfinite(walls)].tolist())):
            targets.append((lim, 0.0, "STOP"))
        s_c, v_c = self._curve_target(ref, s0, v0)
        if s_c is not None:
            targets.append((s_c, v_c, "CRUISE"))
        if obs is not None:  # leaders: nearest obstacle ahead in each lateral target's band
            half = p.ego_length / 2
            centres = lat.centres
            s_first, e_first = obs["fs"][:, 0], obs["fes"][:, 0]
            band = np.abs(obs["fd"][None, :, 0] - centres[:, None]) < obs["fed"][None, :, 0] + (p.ego_width / 2 + 0.3)
            ahead = band & (s_first - e_first > s0 + half - 0.5)[None, :]
            lead = np.where(ahead, s_first[None, :], np.inf).argmin(axis=1)
            for ci in np.flatnonzero(ahead.any(axis=1)).tolist():
                m = int(lead[ci])
                vl = float(obs["v"][m])
                if vl < 0.5:
                    targets.append((float(s_first[m] - e_first[m]) - half - p.static_gap, 0.0, "BLOCKED"))
                else:
                    rear_end = float(obs["fs"][m, -1] - obs["fes"][m, -1]) - half
                    targets.append((rear_end - max(p.follow_gap, p.time_gap * vl), vl, "FOLLOW"))
        rs, rv, rT = [], [], []
        for s_e, v_e, label in targets:
            dist = s_e - s0
            if dist <= 0.05:
                continue
            for f in p.stop_time_factors:
                rs.append(s_e)
                rv.append(v_e)
                rT.append(f * 2.0 * dist / max(v0 + v_e, 0.5))
                labels.append(label)
        brake = np.stack(_brake(s0, v0, p.emergency_decel, tk))[:, None, :]
        labels.append("BRAKE")
        if rs:
            ti = np.clip(np.rint((np.array(rT) - 1.0) * 10.0).astype(np.int64), 0, len(self._reach_T) - 1)
            B = self._reach_basis[ti]  # (R, 4, 3, K): v0, a0, s1, v1 shapes
            # positions are shift-invariant: plan from 0 to (s1 - s0), then add s0
            reach = (v0 * B[:, 0] + a0 * B[:, 1] + (np.array(rs) - s0)[:, None, None] * B[:, 2]
                     + np.array(rv)[:, None, None] * B[:, 3])  # (R, 3, K)
            reach[:, 0] += s0
            sva = np.concatenate([cruise, reach.transpose(1, 0, 2), brake], axis=1)
        else:
            sva = np.concatenate([cruise, brake], axis=1)
        penalty = np.array([{"BRAKE": p.w_brake, "BLOCKED": p.w_blocked}.get(x, 0.0) for x in labels])
        labels = [{"BRAKE": "STOP", "BLOCKED": "STOP"}.get(x, x) for x in labels]
        return {"s": sva[0], "v": sva[1], "a": sva[2], "label": labels, "n": len(labels), "penalty": penalty}

    def _curve_target(self, ref: _Ref, s0: float, v0: float) -> tuple[float | None, float]:
        """Where a curve ahead needs a lower speed than ``v0``, and that speed."""
        i0 = max(int(s0 - float(ref.s[0])), 0)
        ahead = ref.vlim[i0:i0 + int(max(30.0, v0 * self.p.horizon)) + 1]
        slow = np.flatnonzero(ahead < v0 - 0.2)
        if slow.size == 0:
            return None, 0.0
        i = int(slow[0])
        return float(ref.s[0]) + i0 + i - self.p.ego_length / 2, float(ahead[i:].min())

    # -- evaluation ---------------------------------------------------------------------------
    BATCH = 8

    def _evaluate(self, ref: _Ref, lat: _Lateral, d: np.ndarray, dd: np.ndarray, ddd: np.ndarray,
                  lon: dict[str, Any], obs: dict[str, np.ndarray] | None, walls: np.ndarray,
                  v_des: float, c_route: np.ndarray) -> tuple[tuple[int, int] | None, float]:
        """Cheapest feasible (lateral, longitudinal) pair.

        Costs and constraints that do not involve obstacles are separable and evaluated for all
        pairs at once; the obstacle check (hard buffer -> infeasible, soft buffer -> extra cost)
        runs lazily on pairs in order of their obstacle-free cost, stopping as soon as no
        unchecked pair can beat the best one (exact, as the obstacle cost is never negative)."""
        p, st = self.p, self.state
        nP = lon["n"]
        ls, lv, la = lon["s"], lon["v"], lon["a"]
        w = self.map.spec.lane_width
        # longitudinal-only
        kr = np.interp(ls, ref.s, ref.k)
        vref = max(v_des, 1.0)
        inv_k = self._inv_k
        dv = lv - v_des
        jerk = la[:, 1:] - la[:, :-1]
        c_lon = ((p.w_speed * inv_k / vref**2) * (dv * dv).sum(axis=-1) + (p.w_accel * inv_k) * (la * la).sum(axis=-1)
                 + (p.w_jerk / p.dt**2 / (self.K - 1)) * (jerk * jerk).sum(axis=-1) + lon["penalty"])
        # speed limits (lanes and curvature) ahead; only a start that is already above the limit
        # where the ego is may take time to come down (3 m/s^2)
        idx = np.clip((ls - float(ref.s[0])).astype(np.int64), 0, len(ref.vlim) - 1)
        limit = ref.vlim[idx] + 0.3
        if lv[0, 0] > limit[0, 0]:
            limit = np.maximum(limit, lv[:, :1] - 3.0 * self.tk)
        ok_lon = (lv.min(axis=-1) > -0.1) & (lv <= limit).all(axis=-1)
        # lateral-only: stay inside the drivable band (the current road's lanes while on it, the
        # lane itself beyond); a start outside the band is allowed but must not get worse
        left, right = lat.band
        half_w = p.ego_width / 2
        out = np.maximum(left - p.edge_margin + half_w - d, 0.0) + np.maximum(d + half_w - right - p.edge_margin, 0.0)
        ok_lat = (out <= out[:, :1] + 0.05).all(axis=-1)
        dl = d - (lat.centre + lat.offset)[:, None]
        c_lat = (p.w_lat * inv_k / (w * w)) * (dl * dl).sum(axis=-1) + lat.static_cost + c_route
        if st.target_lane is not None:
            same = np.fromiter((t == st.target_lane for t in lat.target), bool, len(lat.target))
            c_lat = c_lat + p.w_hysteresis * (~same + np.abs(lat.offset - st.offset))
        # pairs: walls and lateral acceleration (Frenet: kappa v^2 + d'')
        cent = kr * lv * lv
        pair = cent[None] + ddd[:, None]
        a_lat = np.maximum(pair.max(axis=-1), -pair.min(axis=-1))
        feasible = ((ls.max(axis=-1)[None, :] <= walls[:, None] + 0.05) & (a_lat <= p.hard_lat_accel)
                    & ok_lon[None, :] & ok_lat[:, None])
        base = c_lat[:, None] + c_lon[None, :] + p.w_lat_accel * a_lat
        base = np.where(feasible, base, np.inf).ravel()
        order = np.argsort(base, kind="stable")
        n_ok = int(np.isfinite(base).sum())
        if n_ok == 0:
            return None, math.inf
        if obs is None:
            i = int(order[0])
            return (i // nP, i % nP), float(base[i])
        best_i, best_cost = -1, math.inf
        for start in range(0, n_ok, self.BATCH):
            idx = order[start:min(start + self.BATCH, n_ok)]
            if base[idx[0]] >= best_cost:
                break
            li, pi = idx // nP, idx % nP
            total = base[idx] + self._obstacle_cost(ref, d[li], dd[li], ls[pi], lv[pi], kr[pi], obs)
            j = int(np.argmin(total))
            if total[j] < best_cost:
                best_i, best_cost = int(idx[j]), float(total[j])
        if best_i < 0:
            return None, math.inf
        return (best_i // nP, best_i % nP), best_cost

    def _obstacle_cost(self, ref: _Ref, d: np.ndarray, dd: np.ndarray, s: np.ndarray, v: np.ndarray,
                       kr: np.ndarray, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Soft-buffer cost of candidate rows, ``inf`` where the hard buffer is violated.

        Exact oriented-box separation (separating-axis test, :func:`_box_separation`) between
        the ego at each planned pose and each predicted obstacle box, in world coordinates. Hard:
        the boxes overlap, or the ego box grown by the hard buffers (longitudinal, lateral)
        overlaps the obstacle more than it does at the start (a buffer the ego is already inside
        may be kept or left, not worsened); soft: separation below the soft buffer. Only
        (candidate, obstacle, time) triples whose bounding circles come within the soft buffer
        are tested; all others cannot contribute."""
        p = self.p
        n = len(s)
        hr = np.interp(s, ref.s, ref.h)
        sh, ch = np.sin(hr), np.cos(hr)
        ex = np.interp(s, ref.s, ref.x) - d * sh
        ey = np.interp(s, ref.s, ref.y) + d * ch
        dx = obs["x"] - ex[:, None, :]
        dy = obs["y"] - ey[:, None, :]
        la, wa = p.ego_length / 2, p.ego_width / 2
        reach = math.hypot(la + p.lon_buffer_hard, wa + p.lat_buffer_hard) + p.lat_buffer_soft + obs["r"]
        close = dx * dx + dy * dy < reach * reach
        if not close.any():
            return np.zeros(n)
        eh = hr + np.arctan2(dd, np.maximum(v * (1.0 - kr * d), 1e-3))
        # the start pose (the same for every candidate) against every obstacle
        _, sep_h0 = _box_separation(dx[0, :, 0], dy[0, :, 0], math.cos(eh[0, 0]), math.sin(eh[0, 0]),
                                       obs["c"][:, 0], obs["s"][:, 0], obs["hl"][:, 0], obs["hw"][:, 0],
                                       la, wa, p.lon_buffer_hard, p.lat_buffer_hard)
        ci, oi, ki = np.nonzero(close)
        eh = eh[ci, ki]
        sep, sep_h = _box_separation(dx[ci, oi, ki], dy[ci, oi, ki], np.cos(eh), np.sin(eh),
                                     obs["c"][oi, ki], obs["s"][oi, ki], obs["hl"][oi, 0], obs["hw"][oi, 0],
                                     la, wa, p.lon_buffer_hard, p.lat_buffer_hard)
        bad = (sep < 0.0) | (sep_h < np.minimum(0.0, sep_h0[oi] - 0.05))
        pen = np.maximum(p.lat_buffer_soft - np.maximum(sep, 0.0), 0.0)
        cost = (p.w_obstacle * p.dt / p.lat_buffer_soft) * np.bincount(ci, weights=pen, minlength=n)
        hard = np.bincount(ci, weights=bad, minlength=n) > 0
        return np.where(hard, np.inf, cost)

    # -- outputs ------------------------------------------------------------------------------
    def _to_xy(self, ref: _Ref, t0: float, s: np.ndarray, v: np.ndarray, a: np.ndarray,
               d: np.ndarray, dd: np.ndarray, h0: float) -> dict[str, np.ndarray]:
        xr = np.interp(s, ref.s, ref.x)
        yr = np.interp(s, ref.s, ref.y)
        hr = np.interp(s, ref.s, ref.h)
        kr = np.interp(s, ref.s, ref.k)
        sh, ch = np.sin(hr), np.cos(hr)
        vs = v * (1.0 - kr * d)
        moving = (np.abs(vs) > 1e-3) | (np.abs(dd) > 1e-3)
        h_rel0 = (h0 - float(hr[0]) + math.pi) % (2 * math.pi) - math.pi
        phi = np.where(moving, np.arctan2(dd, np.maximum(vs, 1e-3)), h_rel0)
        return {"t": t0 + self.tk, "x": xr - d * sh, "y": yr + d * ch, "v": np.hypot(vs, dd),
                "hu": hr + phi, "a": np.asarray(a, dtype=float)}

    def _straight_stop(self, t0: float, x0: float, y0: float, h0: float, v0: float) -> dict[str, np.ndarray]:
        s, v, a = _brake(0.0, v0, self.p.emergency_decel, self.tk)
        return {"t": t0 + self.tk, "x": x0 + s * math.cos(h0), "y": y0 + s * math.sin(h0), "v": v,
                "hu": np.full(self.K, h0), "a": a}

    def _behavior(self, lane: LaneId, target: LaneId, off: float, label: str) -> str:
        if target != lane:
            return "CHANGE_LANE"
        if off != 0.0:
            return "NUDGE"
        return label

    def _commit(self, out: dict[str, np.ndarray], target: LaneId | None, off: float, lane: LaneId | None) -> None:
        st = self.state
        st.traj = out
        st.target_lane = target
        st.offset = off
        st.lane = lane
        st.cycles += 1

    def _payload(self, out: dict[str, np.ndarray], behavior: str, lane: LaneId | None,
                 target: LaneId | None, stitched: bool, cost: float) -> dict[str, Any]:
        traj = {"t": out["t"].tolist(), "x": out["x"].tolist(), "y": out["y"].tolist(),
                "v": out["v"].tolist(), "heading": wrap_angle(out["hu"]).tolist(), "a": out["a"].tolist()}
        decision = {"behavior": behavior, "lane": list(lane) if lane else [],
                    "target_lane": list(target) if target else [], "stitched": stitched,
                    "cost": cost if math.isfinite(cost) else -1.0}
        return {"trajectory": traj, "decision": decision}


def _box_separation(dx: np.ndarray, dy: np.ndarray, ec: np.ndarray | float, es: np.ndarray | float,
                    oc: np.ndarray, os_: np.ndarray, lb: np.ndarray, wb: np.ndarray, la: float, wa: float,
                    lh: float, wh: float) -> tuple[np.ndarray, np.ndarray]:
    """Separating-axis test of two oriented boxes, element-wise.

    The ego box (half length ``la``, half width ``wa``, heading cos/sin ``ec, es``) and an
    obstacle box (``lb, wb``, heading ``oc, os_``) whose centre is ``(dx, dy)`` from the ego's.
    Returns the separation [m] (the largest gap along the four box axes; negative = overlap)
    and the same for the ego box grown by ``lh`` (longitudinally) and ``wh`` (laterally)."""
    crel = np.abs(oc * ec + os_ * es)
    srel = np.abs(os_ * ec - oc * es)
    p1 = np.abs(dx * ec + dy * es) - (lb * crel + wb * srel)  # along the ego's axes
    p2 = np.abs(dy * ec - dx * es) - (lb * srel + wb * crel)
    p3 = np.abs(dx * oc + dy * os_) - lb  # along the obstacle's axes
    p4 = np.abs(dy * oc - dx * os_) - wb
    r_a_u = la * crel + wa * srel
    r_a_v = la * srel + wa * crel
    sep = np.maximum(np.maximum(p1 - la, p2 - wa), np.maximum(p3 - r_a_u, p4 - r_a_v))
    sep_h = np.maximum(np.maximum(p1 - la - lh, p2 - wa - wh),
                       np.maximum(p3 - r_a_u - (lh * crel + wh * srel), p4 - r_a_v - (lh * srel + wh * crel)))
    return sep, sep_h


# -- polynomial profiles (vectorised over rows, Horner form) -------------------------------------
def _quintic(x0: float | np.ndarray, v0: float | np.ndarray, a0: float | np.ndarray, x1: np.ndarray,
             v1: np.ndarray, a1: np.ndarray, T: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quintics from (x0, v0, a0) to (x1, v1, a1) at T, then constant velocity.

    ``x1, v1, a1, T`` have shape ``(rows, 1)``, ``t`` shape ``(1, K)``; returns ``(rows, K)``."""
    T2 = T * T
    b0 = x1 - (x0 + v0 * T + 0.5 * a0 * T2)
    b1 = v1 - (v0 + a0 * T)
    b2 = a1 - a0
    T3 = T2 * T
    c3 = (10 * b0 - 4 * b1 * T + 0.5 * b2 * T2) / T3
    c4 = (-15 * b0 + 7 * b1 * T - b2 * T2) / (T3 * T)
    c5 = (6 * b0 - 3 * b1 * T + 0.5 * b2 * T2) / (T3 * T2)
    tt = np.minimum(t, T)
    h2 = 0.5 * a0
    x = x0 + tt * (v0 + tt * (h2 + tt * (c3 + tt * (c4 + tt * c5))))
    v = v0 + tt * (a0 + tt * (3 * c3 + tt * (4 * c4 + tt * 5 * c5)))
    a = a0 + tt * (6 * c3 + tt * (12 * c4 + tt * 20 * c5))
    over = t - tt
    x = x + v1 * over
    after = over > 0
    v = np.where(after, v1, v)
    a = np.where(after, a1, a)
    return x, v, a


def _quartic(s0: float, v0: float, a0: float, v1: np.ndarray, T: np.ndarray,
             t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Velocity keeping: quartics from (s0, v0, a0) to speed v1 and zero acceleration at T,
    then constant speed. ``v1, T`` have shape ``(rows, 1)``."""
    b0 = v1 - v0 - a0 * T
    b1 = -a0
    c3 = (3 * b0 - b1 * T) / (3 * T * T)
    c4 = (-2 * b0 + b1 * T) / (4 * T * T * T)
    tt = np.minimum(t, T)
    s = s0 + tt * (v0 + tt * (0.5 * a0 + tt * (c3 + tt * c4)))
    v = v0 + tt * (a0 + tt * (3 * c3 + tt * 4 * c4))
    a = a0 + tt * (6 * c3 + tt * 12 * c4)
    over = t - tt
    s = s + v1 * over
    after = over > 0
    v = np.where(after, v1, v)
    a = np.where(after, 0.0, a)
    return s, v, a


def _brake(s0: float, v0: float, decel: float, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Constant deceleration to standstill."""
    t_stop = max(v0, 0.0) / decel
    tt = np.minimum(t, t_stop)
    s = s0 + v0 * tt - 0.5 * decel * tt**2
    v = np.maximum(v0 - decel * tt, 0.0)
    a = np.where(t < t_stop, -decel, 0.0)
    return s, v, a
