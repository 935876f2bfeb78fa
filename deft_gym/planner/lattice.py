"""The reference planner: a lane-aware Frenet lattice planner (Werling-style) along the route.

One cycle:

1. **Start state.** Stitch from the previous plan at the frame time if the vehicle is close to
   it (Apollo's trajectory stitcher); otherwise re-plan from the localization pose.
2. **Reference line.** The lane the vehicle is on, continued along the route.
3. **Lattice.** Lateral quintics in time to the lane centre, nudges inside the lane, and lane
   changes where allowed; longitudinal quartics to several cruise speeds and quintics that stop
   at walls (red/yellow stop lines, the destination, dead ends), slow down for curves or keep a
   gap to a leader (where it will be after 2, 4 and 6 s). Every lateral x longitudinal pair is one
   candidate.
4. **Evaluation, vectorised** over candidates x time x obstacles: hard constraints (collision
   with predicted obstacles plus a hard buffer, walls, road edges, lateral acceleration) and a
   cost (speed, lateral offset, lane changes, route preference, comfort, a soft safety buffer
   around obstacles, closing in on a leader below a 1 s time gap, and hysteresis against the
   previous decision).
5. **Fallback.** No feasible candidate -> emergency stop in the current lane.

It sees only its frame: routing, localization, traffic lights and predicted obstacles. It is
deterministic: no clock, no randomness, stable argmin. It makes the mistakes a real planner
makes: obstacles are judged by their Frenet boxes plus buffers (over-cautious next to lane
boundaries), and predictions (constant velocity along the lane) miss cut-ins and turns.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from deft_gym.files import checked_kernel
from deft_gym.planner.base import Frame, Planner, from_plain, to_plain
from deft_gym.planner.decision import LaneDecider
from deft_gym.world.geometry import ReferenceLine, wrap_angle
from deft_gym.world.roadmap import LaneId, shared_roadmap

try:  # the C function behind np.interp: the same results without the Python wrapper's overhead
    from numpy._core.multiarray import interp as _interp

    _interp(0.5, np.array([0.0, 1.0]), np.array([0.0, 1.0]))
except (ImportError, TypeError):  # pragma: no cover - other numpy layouts
    _interp = np.interp

try:  # the evaluation step, obstacle resampling and profiles compiled (setup.py); bit-identical to
    # _evaluate_numpy, _obstacles' numpy lines and _profiles_numpy, used without it or when
    # DEFT_GYM_PURE_PYTHON is set
    from deft_gym.planner import _lattice_c
except ImportError:  # pragma: no cover - the build is optional
    _lattice_c = None
if os.environ.get("DEFT_GYM_PURE_PYTHON"):
    _lattice_c = None
# a kernel built before lattice.py or _lattice_c.c was edited is not used (the edit must count)
_lattice_c = checked_kernel(_lattice_c, Path(__file__).with_name("_lattice_c.c"), Path(__file__))

_FLIP = np.array([[1.0], [-1.0]])  # see _perp


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
    change_offsets: tuple[float, ...] = (-0.4, 0.4)  #: offsets [m] in the target lane of a lane change
    nudge_time: float = 2.5
    recentre_time: float = 1.5  #: a quicker return to the lane centre (after a wide turn, a swerve)
    default_cruise: float = 10.0
    max_accel: float = 2.5
    emergency_decel: float = 7.0
    max_lat_accel: float = 2.5
    hard_lat_accel: float = 5.0
    max_rel_heading: float = Field(0.5, gt=0.0, lt=1.5, description="[rad] a car cannot move sideways "
                                   "faster than it moves on: lateral displacement <= tan(this) x distance + slack")
    lateral_slack: float = Field(0.15, ge=0.0, description="[m] the slack of that bound (small corrections "
                                 "while standing are allowed)")
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
    w_closing: float = Field(4.0, ge=0.0, description="cost of closing in on a moving leader ahead in the ego's "
                             "band below headway_time: the mean over the horizon of the growth of the gap's shortfall "
                             "from max(follow_gap, headway_time x speed), as a fraction of it (0: off, the planner before v38)")
    headway_time: float = Field(1.0, ge=0.0, description="[s] the time gap below which closing in costs w_closing "
                                "(ISO 15622's shortest ACC gap is 0.8 s)")
    follow_times: tuple[float, ...] = Field((2.0, 4.0, 6.0), description="[s] durations of the FOLLOW profiles: each "
                                            "reaches the gap behind a moving leader where the leader is predicted "
                                            "then, at its speed (empty: one target at the leader's position at the "
                                            "end of the horizon, reached after stop_time_factors, the planner before v38)")
    ref_step: float = 0.25
    publish_debug: bool = False
    # lane-level decisions (deft_gym.planner.decision): path bounds, comfort, gap acceptance, home lane
    decisions: bool = True
    block_lookahead: float = Field(50.0, ge=0.0, description="[m] static objects this far ahead of the ego's front can block its lane")
    impact_buffer: float = Field(0.35, ge=0.0, description="[m] lateral growth of a static object's SL boundary in the path bounds")
    parked_impact_buffer: float = Field(0.7, ge=0.0, description="[m] the same for parked vehicles and vehicles predicted static")
    corridor_clearance: float = Field(0.4, ge=0.0, description="[m] free width asked for each side of the ego between objects (the hard buffer then decides the exact path)")
    parallel_gap: float = Field(4.8, ge=0.0, description="[m] objects closer than this along s form one cluster (parallel obstacles)")
    comfort_gap: float = Field(1.0, ge=0.0, description="[m] lateral gap to static objects below which a lane is uncomfortable")
    tight_length: float = Field(12.0, gt=0.0, description="[m] uncomfortable length from which a lane is tight")
    w_tight: float = 6.0
    rear_gap_min: float = Field(8.0, ge=0.0, description="[m] smallest accepted gap to the follower in the target lane")
    rear_time_gap: float = Field(1.5, ge=0.0, description="[s] accepted gap to the follower: its speed times this")
    front_gap_min: float = Field(4.0, ge=0.0, description="[m] smallest accepted gap to the leader in the target lane")
    junction_no_change: float = Field(20.0, ge=0.0, description="[m] no lane change starts this close to a junction")
    w_home: float = 4.0
    w_reject: float = 1000.0
    w_abort: float = 10.0


@dataclass
class LatticeState:
    """Everything the planner carries from one cycle to the next."""

    traj: dict[str, np.ndarray] | None = None
    target_lane: LaneId | None = None
    offset: float = 0.0
    lane: LaneId | None = None
    cycles: int = 0
    home: LaneId | None = None  #: the lane the route wants the ego in (lane decisions)
    changing_to: LaneId | None = None  #: target of the lane change in progress
    change_kind: str = ""  #: "borrow" (leaving home) or "return"


@dataclass
class _Route:
    roads: list[tuple[str, str]]
    dest_lane: LaneId
    dest_s: float
    cruise: float


@dataclass
class _Ref:
    """A reference line sampled on a uniform grid (for fast interpolation), plus what the
    planner needs of it every cycle, precomputed (it is cached per lane and route)."""

    line: ReferenceLine
    s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    h: np.ndarray
    k: np.ndarray
    vlim: np.ndarray  # curvature speed limit [m/s] on a 1 m grid starting at s[0]
    continues: bool  # the chain reaches the destination road or follows the route to its end
    stops: list[tuple[float, str]]  # (s of the stop line, light id) along the chain
    dest_offsets: list[float]  # offsets of the chain's lanes on the destination road
    end: float  # s of the end of the chain

    def __post_init__(self) -> None:
        self.s_first = float(self.s[0])
        self.vlim_list: list[float] = self.vlim.tolist()
        self.vlim_min = min(self.vlim_list, default=math.inf)
        self.vlim_max = max(self.vlim_list, default=math.inf)

    def at(self, s: float) -> tuple[float, float]:
        """Heading [rad] and curvature [1/m] at one ``s`` (linear interpolation)."""
        f = (s - float(self.s[0])) / (float(self.s[1]) - float(self.s[0]))
        i = min(max(int(f), 0), len(self.s) - 2)
        w = min(max(f - i, 0.0), 1.0)
        return (float(self.h[i]) * (1 - w) + float(self.h[i + 1]) * w,
                float(self.k[i]) * (1 - w) + float(self.k[i + 1]) * w)

    def min_vlim(self, s_a: float, s_b: float) -> float:
        """Lowest curvature speed limit between ``s_a`` and ``s_b``."""
        i = max(int(s_a - self.s_first), 0)
        j = max(int(s_b - self.s_first) + 1, i + 1)
        seg = self.vlim_list[i:j]
        return min(seg) if seg else math.inf


@dataclass
class _Poses:
    """Ego poses along candidate rows (rows x time, or one row): the reference heading, the
    centre (x, y), the speed along the reference and the heading relative to it."""

    h: np.ndarray
    xy: np.ndarray  # (2, rows, time)
    vs: np.ndarray
    rel: np.ndarray

    @staticmethod
    def along(ref: _Ref, d: np.ndarray, dd: np.ndarray, s: np.ndarray, v: np.ndarray,
              kr: np.ndarray) -> _Poses:
        """Poses of profiles ``s`` (speed ``v``, curvature ``kr`` there), offset ``d`` (rate ``dd``)."""
        hr = _interp(s, ref.s, ref.h)
        sh, ch = np.sin(hr), np.cos(hr)
        xy = np.empty((2, *s.shape))
        np.subtract(_interp(s, ref.s, ref.x), d * sh, out=xy[0])
        np.add(_interp(s, ref.s, ref.y), d * ch, out=xy[1])
        vs = v * (1.0 - kr * d)
        return _Poses(hr, xy, vs, _atan2(dd, np.maximum(vs, 1e-3)))

    def row(self, j: int) -> _Poses:
        return _Poses(self.h[j], self.xy[:, j], self.vs[j], self.rel[j])


@dataclass
class _Lateral:
    """Per (lane, route): the lateral options and everything about them that is static."""

    target: list[LaneId]
    centre: np.ndarray
    offset: np.ndarray
    static_cost: np.ndarray
    band: tuple[float, float]
    basis: list[np.ndarray] = field(default_factory=list)  # (3, n, K) for d0, d0', d0'', targets
    centres: list[float] = field(default_factory=list)  # distinct target lane centres
    target_d: np.ndarray = field(default_factory=lambda: np.zeros(0))  # centre + offset
    band_lo: float = 0.0  # band[0] - edge margin + half the ego width
    w_lat: float = 0.0  # weight of the squared lateral offset (per sample, per lane width^2)
    route_cost: tuple[np.ndarray, ...] = ()  # lane changes still needed x (urgent, far) weight
    route_dist: tuple[np.ndarray, ...] = ()  # needed lane changes x (destination, fork) distance
    dead_end: list[int] = field(default_factory=list)  # options stopped by the end of a leaving lane
    _hyst: dict[tuple[LaneId, float], np.ndarray] = field(default_factory=dict)

    def hysteresis(self, target: LaneId, offset: float, weight: float) -> np.ndarray:
        """Cost of leaving the previous decision (target lane and offset); ``weight`` must be
        the same in every call (results are cached)."""
        c = self._hyst.get((target, offset))
        if c is None:
            same = np.fromiter((t == target for t in self.target), bool, len(self.target))
            c = self._hyst[(target, offset)] = weight * (~same + np.abs(self.offset - offset))
        return c


class LatticePlanner(Planner):
    """Lane-aware lattice planner along the route; see the module docstring."""

    #: the road map (its geometry caches), memo caches of routes, reference lines and lateral
    #: profiles, and the kernel's parameter block (rewritten per call): no state
    caches = ("map", "_route_cache", "_ref_cache", "_lat_cache", "_kernel_params")

    def __init__(self, map_spec: dict[str, Any], **params: Any) -> None:
        super().__init__(map_spec, **params)
        self.p = LatticeParams.model_validate(params)
        p = self.p
        self.map = shared_roadmap(self.map_spec)
        self.K = round(p.horizon / p.dt) + 1
        self.tk = np.arange(self.K) * p.dt
        self._route_cache: dict[Any, _Route] = {}
        self._ref_cache: dict[Any, _Ref] = {}
        self._lat_cache: dict[Any, _Lateral] = {}
        reach = max(p.horizon * p.horizon, 30.0) + 20.0  # [m] obstacles farther never matter
        self._reach2 = reach * reach
        self._half_lane = self.map.spec.lane_width / 2
        self._inv_k = 1.0 / self.K
        # constants of the cost and the collision check (the same float operations as inline)
        self._w_acc = p.w_accel * self._inv_k
        self._w_jerk = p.w_jerk / p.dt**2 / (self.K - 1)
        self._w_obs = p.w_obstacle * p.dt / p.lat_buffer_soft
        la, wa = p.ego_length / 2, p.ego_width / 2
        self._ego_half = np.array([[la], [wa]])
        self._hard_buf = np.array([[p.lon_buffer_hard], [p.lat_buffer_hard]])
        # bounding-circle radius of the ego grown by the hard buffers, plus the soft buffer
        self._reach_ego = math.hypot(la + p.lon_buffer_hard, wa + p.lat_buffer_hard) + p.lat_buffer_soft
        self._penalty = {"BRAKE": p.w_brake, "BLOCKED": p.w_blocked}
        self._tan_head = math.tan(p.max_rel_heading)
        #: the compiled evaluation step (None: numpy); its parameters, per call (7), constant, then
        #: the batch size (set per call), in the order of the P_* enum in _lattice_c.c
        self.kernel = _lattice_c
        self._kernel_params = np.array(
            [0.0] * 7 + [p.w_speed * self._inv_k, self._w_acc, self._w_jerk, p.ego_width / 2, p.edge_margin,
                         p.hard_lat_accel, p.w_lat_accel, self._w_obs, p.lat_buffer_soft, la, wa,
                         p.lon_buffer_hard, p.lat_buffer_hard, self._tan_head, p.lateral_slack,
                         self.BATCH])
        # Profiles with a fixed duration are linear in their start/end values, so their shapes
        # are computed once: cruise rows (speed factor x duration) and lateral durations.
        t = self.tk[None, :]
        qT = np.array([[T for _ in p.speed_factors for T in p.speed_times]]).T
        qf = np.array([[f for f in p.speed_factors for _ in p.speed_times]]).T
        _one, zero = np.ones_like(qT), np.zeros_like(qT)
        self._cruise_basis = [np.stack(_quartic(0.0, *u, qT, t)) for u in
                              ((1.0, 0.0, zero), (0.0, 1.0, zero), (0.0, 0.0, qf))]
        self._n_cruise = len(p.speed_factors) * len(p.speed_times)
        self._cruise_stack = np.ascontiguousarray(np.stack(self._cruise_basis))  # (3, 3, C, K), compiled path
        # reach quintics (to s1, v1 at T, then constant speed): T on a 0.1 s grid; for one T the
        # profile is linear in (s0, v0, a0, s1, v1), so each grid T has a (5, 3, K) basis
        self._reach_T = np.round(np.arange(1.0, p.horizon + 4.0 + 1e-9, 0.1), 6)
        TT = self._reach_T[:, None]
        one, zero = np.ones_like(TT), np.zeros_like(TT)
        self._reach_basis = np.ascontiguousarray(
            np.stack([np.stack(_quintic(*u, zero, TT, t)) for u in
                      ((0.0, 1.0, 0.0, zero, zero), (0.0, 0.0, 1.0, zero, zero),
                       (0.0, 0.0, 0.0, one, zero), (0.0, 0.0, 0.0, zero, one))],
                     axis=1).transpose(2, 1, 0, 3))  # (T, coefficient, s/v/a, K)
        self._lat_basis: dict[float, list[np.ndarray]] = {}
        for T in sorted({p.nudge_time, p.lane_change_time, p.recentre_time}):
            TT = np.array([[T]])
            self._lat_basis[T] = [np.stack(_quintic(*u, TT, t))[:, 0] for u in
                                  ((1.0, 0.0, 0.0, np.zeros((1, 1)), 0.0, 0.0),
                                   (0.0, 1.0, 0.0, np.zeros((1, 1)), 0.0, 0.0),
                                   (0.0, 0.0, 1.0, np.zeros((1, 1)), 0.0, 0.0),
                                   (0.0, 0.0, 0.0, np.ones((1, 1)), 0.0, 0.0))]
        self.state = LatticeState()
        self.decider = LaneDecider(self) if p.decisions else None

    def reset(self) -> None:
        self.state = LatticeState()

    @classmethod
    def hard_clearance(cls, params: Any) -> float:
        """The hard lateral buffer ``lat_buffer_hard`` [m]."""
        return LatticeParams.model_validate(dict(params)).lat_buffer_hard

    def export_state(self) -> dict[str, Any]:
        """Every :class:`LatticeState` field as plain values (seeds a failure test at its frame)."""
        return {f.name: to_plain(getattr(self.state, f.name)) for f in fields(LatticeState)}

    def load_state(self, state: Mapping[str, Any]) -> None:
        """Continue from :meth:`export_state`'s values; ValueError when a field is missing."""
        missing = [f.name for f in fields(LatticeState) if f.name not in state]
        if missing:
            raise ValueError(f"LatticePlanner state lacks {missing}")
        self.state = LatticeState(**{f.name: from_plain(state[f.name]) for f in fields(LatticeState)})

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
        lat_d = d0 * b0 + vd0 * b1 + ad0 * b2 + b3  # (d, d', d'') x option x time
        walls, wall_s = self._walls(frame.get("traffic_light"), ref, route, lane, s0, vs0, lat)
        c_route = self._route_cost(lat, ref, route, lane, s0)
        dec, blocked_s = None, set()
        if self.decider is not None:
            dec = self.decider.decide(lane, route, ref, lat, obs, s0, vs0)
            if np.isfinite(dec.walls).any():
                walls = np.minimum(walls, dec.walls)
                blocked_s = {x for x in dec.walls.tolist() if math.isfinite(x)} - set(wall_s)
                wall_s = sorted(set(wall_s) | blocked_s)
            c_route = c_route + dec.cost
        # a wall the ego is already past (it stopped a little late) holds it where it is, rather
        # than leaving no feasible plan
        walls = np.maximum(walls, s0) if isinstance(walls, np.ndarray) else max(walls, s0)
        lon = self._longitudinal(s0, vs0, as0, v_des, ref, wall_s, obs, lat, blocked_s, d0)
        best, cost, poses = self._evaluate(ref, lat, lat_d, lon, obs, walls, v_des, c_route)
        if best is None:
            s, v, acc = lon["sva"][:, -1]  # the emergency brake, the last profile
            dd = np.zeros(self.K)
            poses = _Poses.along(ref, np.full(self.K, d0), dd, s, v, _interp(s, ref.s, ref.k))
            out = self._to_xy(poses, t0, dd, acc, h0)
            behavior, target, off = "ESTOP", lane, st.offset
        else:
            li, pi = best
            out = self._to_xy(poses, t0, lat_d[1, li], lon["sva"][2, pi], h0)
            target, off = lat.target[li], float(lat.offset[li])
            behavior = self._behavior(lane, target, off, lon["label"][pi])
        reason = self.decider.commit(dec, lane, target if best is not None else None) if dec is not None else ""
        self._commit(out, target, off, lane)
        payload = self._payload(out, behavior, lane, target, stitched, cost)
        if dec is not None:
            st = self.state
            payload["decision"].update(self.decider.published(dec, reason, obs))
        return payload

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
            best, score = self._best_lane(self.map.around(prev), x, y, h, route)
            if best is not None and score < 1.5:
                return best
        _, idx = self.map.candidate_lanes(np.array([x, y]), radius=4.0)
        best, score = self._best_lane([self.map.lane_ids[j] for j in sorted(idx.tolist())], x, y, h, route)
        return best if score < 6.0 else None

    def _best_lane(self, cand: Sequence[LaneId], x: float, y: float, h: float, route: _Route) -> tuple[LaneId | None, float]:
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
        stops, dest_offsets = [], []
        for j, lid in enumerate(line.lane_ids):
            off = float(line.offsets[j])
            sl = self.map.stop_line_of.get(lid)
            if sl is not None:
                stops.append((off + sl.s, sl.light_id))
            if lid[:2] == route.dest_lane[:2]:
                dest_offsets.append(off)
        end = float(line.offsets[-1] + line.geoms[-1].length)
        ref = _Ref(line, s, xy[:, 0].copy(), xy[:, 1].copy(), h, k, vlim, continues, stops, dest_offsets, end)
        self._ref_cache[key] = ref
        return ref

    # -- obstacles ----------------------------------------------------------------------------
    def _obstacles(self, pred: dict[str, Any] | None, t0: float, ref: _Ref, s0: float,
                   d0: float) -> dict[str, Any] | None:
        """Predicted obstacle boxes at the planning times ``t0 + k dt`` (held at their last
        prediction point): centre, heading and half-size in world coordinates for the collision
        check, plus their Frenet coordinates now and at the horizon for choosing leaders.
        Obstacles that stay out of the ego's reach over the horizon are dropped.

        Per (obstacle, time) values are ``(2, n, K)`` (``xy``) or flat ``(2, n K)`` (``cs``:
        heading cos/sin, ``lw``: half length/width); per obstacle values for the leaders are
        lists."""
        if not pred or not pred.get("obstacles"):
            return None
        K = self.K
        statics, kinds, ids = [], [], []
        groups: dict[tuple[float, float, int], list[dict[str, Any]]] = {}
        for ob in pred["obstacles"]:
            if len(ob["x"]) == 1:  # static: one point, constant over the horizon
                statics.append((ob["x"][0], ob["y"][0], ob["heading"][0], 0.5 * ob["length"], 0.5 * ob["width"], 0.0))
                kinds.append(ob.get("type", ""))
                ids.append(ob.get("id"))
            else:  # moving: grouped by time base, resampled together
                groups.setdefault((float(ob["t0"]), float(ob["dt"]), len(ob["x"])), []).append(ob)
        still = [True] * len(statics)
        for obs_g in groups.values():
            kinds += [ob.get("type", "") for ob in obs_g]
            ids += [ob.get("id") for ob in obs_g]
            still += [False] * len(obs_g)
        n = len(statics) + sum(len(g) for g in groups.values())
        oxy = np.empty((2, n, K))  # centre (x, y) over time
        oh = np.empty((n, K))  # heading over time
        dims = np.empty((n, 3))  # half length, half width, speed
        j = len(statics)
        if statics:
            st = _numbers(statics, "x/y/heading/length/width")
            oxy[:, :j] = st[:, :2].T[:, :, None]
            oh[:j] = st[:, 2:3]
            dims[:j] = st[:, 3:]
        if groups:
            tq = t0 + self.tk
        kernel = self.kernel
        for (ot0, odt, m), obs_g in groups.items():
            j1 = j + len(obs_g)
            # the compiled lines below, when every value is a Python float (else they run)
            if kernel is not None and kernel.resample(obs_g, tq, ot0, 1.0 / odt, m, j, oxy, oh, dims):
                j = j1
                continue
            f = np.minimum(np.maximum((tq - ot0) * (1.0 / odt), 0.0), m - 1.0)
            i = np.minimum(f.astype(np.int64), m - 2)
            w = f - i
            # x, y and heading of the group's predictions (obstacle, point), each must be numbers
            X, Y, H = (_numbers([ob[key] for ob in obs_g], key) for key in ("x", "y", "heading"))
            x0, y0 = X[:, i], Y[:, i]
            oxy[0, j:j1] = x0 + (X[:, i + 1] - x0) * w
            oxy[1, j:j1] = y0 + (Y[:, i + 1] - y0) * w
            oh[j:j1] = H[:, np.rint(f).astype(np.int64)]
            dims[j:j1] = _numbers([(0.5 * ob["length"], 0.5 * ob["width"], ob.get("v", 0.0)) for ob in obs_g],
                                  "length/width/v")
            j = j1
        # relevance: within reach of the ego over the horizon
        ex, ey = float(_interp(s0, ref.s, ref.x)), float(_interp(s0, ref.s, ref.y))
        if kernel is not None:
            near = kernel.near(oxy, ex, ey, self._reach2)
        else:
            gx, gy = oxy[0] - ex, oxy[1] - ey
            near = ((gx * gx + gy * gy).min(axis=1) < self._reach2).tolist()
        if not any(near):
            return None
        # Frenet now and at the horizon (leaders, gaps, followers)
        ends = oxy[:, :, ::K - 1].transpose(1, 2, 0).reshape(-1, 2).tolist()  # (obstacle, now/end) x/y
        sf_l, df_l = ref.line.frenet_list(ends)
        sf = np.array(sf_l).reshape(n, 2)
        phi = oh[:, ::K - 1] - _interp(sf, ref.s, ref.h)
        c, sn = np.abs(np.cos(phi)), np.abs(np.sin(phi))
        hl, hw = dims[:, :1], dims[:, 1:2]
        fes = hl * c + hw * sn
        fed0 = hl[:, 0] * sn[:, 0] + hw[:, 0] * c[:, 0]
        fs_l, fes_l, fd0_l = sf.tolist(), fes.tolist(), df_l[0::2]  # d now: the even points
        fd1_l = df_l[1::2]  # d at the end of the horizon (lane decisions: predicted lane changes)
        # a follower in the ego's own lane is responsible for keeping its distance
        behind = s0 - self.p.ego_length / 2
        keep = [o for o in range(n) if near[o] and not (fs_l[o][0] + fes_l[o][0] < behind
                                                         and abs(fd0_l[o] - d0) < self._half_lane)]
        if not keep:
            return None
        if len(keep) < n:
            oxy, oh, dims = oxy.take(keep, axis=1), oh.take(keep, axis=0), dims.take(keep, axis=0)
            hl, hw, fed0 = dims[:, :1], dims[:, 1:2], fed0.take(keep)
            fs_l, fes_l, fd0_l = [fs_l[o] for o in keep], [fes_l[o] for o in keep], [fd0_l[o] for o in keep]
            kinds, still, fd1_l = [kinds[o] for o in keep], [still[o] for o in keep], [fd1_l[o] for o in keep]
            ids = [ids[o] for o in keep]
        n = len(keep)
        ocs = np.empty((2, n * K))  # cos, sin of the heading, flat (obstacle, time)
        np.cos(oh.ravel(), out=ocs[0])
        np.sin(oh.ravel(), out=ocs[1])
        reach = self._reach_ego + np.hypot(hl, hw)
        return {"n": n, "xy": oxy, "cs": ocs, "lw": np.repeat(dims[:, :2].T, K, axis=1), "reach2": reach * reach,
                "start": np.arange(n) * K,  # flat (obstacle, time) index of time 0
                # per obstacle, for choosing leaders: Frenet s (now, end), extent along s (now,
                # end), d now, extent along d now, speed
                "fs": fs_l, "fes": fes_l, "fd": fd0_l, "fed": fed0.tolist(), "v": dims[:, 2].tolist(),
                # per obstacle, for lane decisions: perceived type, whether it is predicted static,
                # and its perception id (published with the decisions it causes)
                "kind": kinds, "still": still, "fd_end": fd1_l, "id": ids}

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
        for nb in nbs:  # ids grow rightwards; the target lane's centre and offsets in it
            targets += [(nb, w * (nb[2] - lane[2]), off, p.lane_change_time) for off in (0.0, *p.change_offsets)]
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
        lat = _Lateral([t[0] for t in targets], np.array([t[1] for t in targets]), offset, static_cost, band)
        lat.centres = np.unique(lat.centre).tolist()
        lat.target_d = lat.centre + lat.offset
        lat.band_lo = band[0] - p.edge_margin + p.ego_width / 2
        lat.w_lat = p.w_lat * self._inv_k / (w * w)
        lat.route_cost = (needed * p.w_route, needed * p.w_route_far)
        lat.route_dist = (needed * p.route_dest_distance, needed * p.route_fork_distance)
        lat.dead_end = [i for i, tgt in enumerate(lat.target) if tgt == lane or not compat[i]]
        rows = [[self._lat_basis[t[3]][c] for t in targets] for c in range(4)]
        lat.basis = [np.stack(r, axis=1) for r in rows[:3]]
        lat.basis.append(np.stack(rows[3], axis=1) * lat.target_d[None, :, None])
        self._lat_cache[key] = lat
        return lat

    def _route_cost(self, lat: _Lateral, ref: _Ref, route: _Route, lane: LaneId, s0: float) -> np.ndarray:
        """Cost of the lane changes each option still leaves to do: mild while the point where
        the lane must be right (the end of the road before a fork, or the destination) is far,
        strong once fewer than ``route_*_distance`` metres per needed change remain."""
        if lane[:2] == route.dest_lane[:2]:
            dist, limit = route.dest_s - s0, lat.route_dist[0]
        else:
            dist, limit = float(ref.line.geoms[0].length) - s0, lat.route_dist[1]
        return np.where(dist < limit, *lat.route_cost)

    # -- walls --------------------------------------------------------------------------------
    def _walls(self, tl: dict[str, Any] | None, ref: _Ref, route: _Route, lane: LaneId, s0: float,
               v0: float, lat: _Lateral) -> tuple[np.ndarray | float, list[float]]:
        """Per lateral option (one value when the same for all), the largest allowed centre
        ``s`` over the horizon: red (or stoppable yellow, or unknown) lights, the destination,
        and the end of a lane that leaves the route. Also the distinct finite values, ascending."""
        p = self.p
        half = p.ego_length / 2
        colors = {lt["id"]: lt["color"] for lt in (tl or {}).get("lights", [])}
        limit_all = math.inf
        for s_line, light in ref.stops:
            gap = s_line - (s0 + half)
            if gap > -0.5:
                color = colors.get(light, "UNKNOWN")
                need = v0 * v0 / (2 * max(gap - p.stop_gap, 0.1))
                stop = (color in ("RED", "UNKNOWN") and need <= p.emergency_decel) or (
                    color == "YELLOW" and need <= p.yellow_decel)
                if stop:
                    limit_all = min(limit_all, s_line - half - p.stop_gap)
        for off in ref.dest_offsets:
            limit_all = min(limit_all, off + route.dest_s)
        if ref.continues:  # the same for every option
            return limit_all, [limit_all] if math.isfinite(limit_all) else []
        limits = np.full(len(lat.target), limit_all)
        dead_end = ref.end - half - p.stop_gap
        for i in lat.dead_end:
            limits[i] = min(limits[i], dead_end)
        return limits, sorted({x for x in limits.tolist() if math.isfinite(x)})

    # -- longitudinal profiles ----------------------------------------------------------------
    def _longitudinal(self, s0: float, v0: float, a0: float, v_des: float, ref: _Ref,
                      wall_s: list[float], obs: dict[str, Any] | None, lat: _Lateral,
                      blocked_s: set[float] = frozenset(), d0: float = 0.0) -> dict[str, Any]:  # type: ignore[assignment]
        """Speed profiles: cruise quartics, and quintics reaching (s, v) targets - stops at walls
        (``wall_s``; those in ``blocked_s`` are in front of a blocked lane's obstacles and cost
        like stopping behind a static leader), slowing for curves, keeping a gap behind leaders -
        plus an emergency brake."""
        p = self.p
        v_des = min(v_des, ref.min_vlim(s0, s0 + 8.0))
        targets: list[tuple[float, float, str, float | None]] = [
            (lim, 0.0, "BLOCKED" if lim in blocked_s else "STOP", None) for lim in wall_s]
        s_c, v_c = self._curve_target(ref, s0, v0)
        if s_c is not None:
            targets.append((s_c, v_c, "CRUISE", None))
        if obs is not None:
            targets += self._leaders(obs, lat, s0)
        labels = ["CRUISE"] * self._n_cruise
        ds, rv, ti = [], [], []
        last_T = len(self._reach_T) - 1
        for s_e, v_e, label, T_fixed in targets:
            dist = s_e - s0
            if dist <= 0.05:
                continue
            durations = [f * 2.0 * dist / max(v0 + v_e, 0.5) for f in p.stop_time_factors] if T_fixed is None \
                else [T_fixed]
            for T in durations:
                ti.append(_grid_index((T - 1.0) * 10.0, last_T))  # nearest grid T
                ds.append(dist)
                rv.append(v_e)
                labels.append(label)
        labels.append("BRAKE")
        sva = np.empty((3, len(labels), self.K))  # (s, v, a) x profile x time: cruise, reach, brake
        kernel = self.kernel
        if kernel is None or not kernel.profiles(sva, self._cruise_stack, self._reach_basis, ti, ds, rv, s0, v0,
                                                 a0, v_des, p.emergency_decel, self.tk):
            self._profiles_numpy(sva, ti, ds, rv, s0, v0, a0, v_des)
        penalty = np.array([self._penalty.get(x, 0.0) for x in labels])
        if obs is not None and p.w_closing > 0.0:
            penalty += self._closing_cost(obs, s0, d0, v0, sva)
        labels = ["STOP" if x in self._penalty else x for x in labels]
        return {"sva": sva, "label": labels, "n": len(labels),
                "penalty": penalty}

    def _profiles_numpy(self, sva: np.ndarray, ti: list[int], ds: list[float], rv: list[float], s0: float,
                        v0: float, a0: float, v_des: float) -> None:
        """Fill ``sva`` (3, P, K): cruise rows, reach rows (grid duration index ``ti``, distance
        ``ds``, end speed ``rv``), then the brake. The compiled ``profiles`` does the same
        operations in the same order, and refuses (so these lines run) what is not plain
        ints and floats."""
        n_c = self._n_cruise
        bv, ba, bf = self._cruise_basis
        np.add(v0 * bv + a0 * ba, v_des * bf, out=sva[:, :n_c])
        sva[0, :n_c] += s0
        if ds:
            B = self._reach_basis.take(ti, axis=0)  # (R, 4, 3, K): v0, a0, s1, v1 shapes
            # positions are shift-invariant: plan from 0 to (s1 - s0), then add s0
            coef = np.array((ds, rv))[:, :, None, None]
            np.add(v0 * B[:, 0] + a0 * B[:, 1] + coef[0] * B[:, 2], coef[1] * B[:, 3],
                   out=sva[:, n_c:-1].transpose(1, 0, 2))
            sva[0, n_c:-1] += s0
        sva[0, -1], sva[1, -1], sva[2, -1] = _brake(s0, v0, self.p.emergency_decel, self.tk)

    def _leaders(self, obs: dict[str, Any], lat: _Lateral, s0: float) -> list[tuple[float, float, str, float | None]]:
        """Per distinct lateral target centre, targets ``(s, v, label, duration or None)`` behind the
        nearest obstacle ahead in its band: a standstill gap behind a static one; behind a moving one
        its gap (``max(follow_gap, time_gap x v)``) at its predicted position after each of
        ``follow_times``, at its speed (its rear moving linearly from now to the end of the
        horizon and on)."""
        p = self.p
        half = p.ego_length / 2
        margin = p.ego_width / 2 + 0.3
        front = s0 + half - 0.5
        fs, fes, fd, fed, vs = obs["fs"], obs["fes"], obs["fd"], obs["fed"], obs["v"]
        ahead = [o for o in range(obs["n"]) if fs[o][0] - fes[o][0] > front]
        targets = []
        for c in lat.centres:
            m, best = -1, math.inf
            for o in ahead:
                if abs(fd[o] - c) < fed[o] + margin and fs[o][0] < best:
                    m, best = o, fs[o][0]
            if m < 0:
                continue
            vl = vs[m]
            if vl < 0.5:
                targets.append((fs[m][0] - fes[m][0] - half - p.static_gap, 0.0, "BLOCKED", None))
                continue
            gap = max(p.follow_gap, p.time_gap * vl)
            rear_end = fs[m][1] - fes[m][1] - half
            if not p.follow_times:
                targets.append((rear_end - gap, vl, "FOLLOW", None))
                continue
            rear_now = fs[m][0] - fes[m][0] - half
            rate = (rear_end - rear_now) / float(self.tk[-1])  # [m/s] along the reference
            targets += [(rear_now + rate * T - gap, vl, "FOLLOW", T) for T in p.follow_times]
        return targets

    def _closing_cost(self, obs: dict[str, Any], s0: float, d0: float, v0: float,
                      sva: np.ndarray) -> np.ndarray | float:
        """Per speed profile: ``w_closing`` x the mean over the horizon of how much the gap to the
        nearest moving leader ahead in the ego's own band (its rear moving linearly from now to its
        predicted end) falls further short of ``max(follow_gap, headway_time x v(t))`` than it does
        now, as a fraction of that (0 for a profile that keeps the gap or does not close in). Without
        it the speed term pulled the ego in to the hard buffer behind a slow leader (1 m behind a
        6 m/s truck for a minute, docs/metrics.md ``headway``); a gap already short (a cut-in, a
        lane change behind a car) costs nothing, so the ego is not made to brake to open it. Zero
        for an obstacle not moving on ahead of the ego (oncoming, crossing)."""
        p = self.p
        half = p.ego_length / 2
        margin = p.ego_width / 2 + 0.3
        fs, fes, fd, fed, vs = obs["fs"], obs["fes"], obs["fd"], obs["fed"], obs["v"]
        m, rear_now = -1, math.inf
        for o in range(obs["n"]):
            rear = fs[o][0] - fes[o][0]
            if rear > s0 + half - 0.5 and vs[o] >= 0.5 and abs(fd[o] - d0) < fed[o] + margin and rear < rear_now:
                m, rear_now = o, rear
        if m < 0:
            return 0.0
        t_end = float(self.tk[-1])
        rear_end = fs[m][1] - fes[m][1]
        if rear_end - rear_now < 0.5 * t_end:  # slower than 0.5 m/s along the ego's reference
            return 0.0
        rear_t = rear_now + (rear_end - rear_now) / t_end * self.tk  # (K,)
        need = np.maximum(p.follow_gap, p.headway_time * sva[1])
        short = np.maximum(need - (rear_t - sva[0] - half), 0.0) / need
        need_now = max(p.follow_gap, p.headway_time * v0)
        short_now = max(need_now - (rear_now - s0 - half), 0.0) / need_now
        return p.w_closing * (np.maximum(short - short_now, 0.0).sum(axis=-1) / self.K)  # = .mean(-1), bit for bit

    def _curve_target(self, ref: _Ref, s0: float, v0: float) -> tuple[float | None, float]:
        """Where a curve ahead needs a lower speed than ``v0``, and that speed."""
        if not v0 - 0.2 > ref.vlim_min:  # nothing anywhere on the line is slow enough
            return None, 0.0
        i0 = max(int(s0 - ref.s_first), 0)
        ahead = ref.vlim[i0:i0 + int(max(30.0, v0 * self.p.horizon)) + 1]
        slow = np.flatnonzero(ahead < v0 - 0.2)
        if slow.size == 0:
            return None, 0.0
        i = int(slow[0])
        return ref.s_first + i0 + i - self.p.ego_length / 2, float(ahead[i:].min())

    # -- evaluation ---------------------------------------------------------------------------
    BATCH = 8

    def _evaluate(self, ref: _Ref, lat: _Lateral, lat_d: np.ndarray, lon: dict[str, Any],
                  obs: dict[str, Any] | None, walls: np.ndarray | float, v_des: float,
                  c_route: np.ndarray) -> tuple[tuple[int, int] | None, float, _Poses | None]:
        """Cheapest feasible (lateral, longitudinal) pair, its cost, and the ego poses along it:
        the compiled step when it is built, :meth:`_evaluate_numpy` otherwise (the same results,
        bit for bit)."""
        kernel = self.kernel
        if kernel is None:
            return self._evaluate_numpy(ref, lat, lat_d, lon, obs, walls, v_des, c_route)
        p, st = self.p, self.state
        hyst = None if st.target_lane is None else lat.hysteresis(st.target_lane, st.offset, p.w_hysteresis)
        prm = self._kernel_params
        prm[:7] = v_des, ref.s_first, ref.vlim_min, ref.vlim_max, lat.band_lo, lat.band[1], lat.w_lat
        prm[-1] = self.BATCH  # read per call, as the numpy path does
        li, pi, cost = kernel.evaluate(
            ref.s, ref.x, ref.y, ref.h, ref.k, ref.vlim, lon["sva"], lon["penalty"], lat_d, lat.target_d,
            lat.static_cost, c_route, hyst, walls if isinstance(walls, np.ndarray) else float(walls),
            *((obs["xy"], obs["cs"], obs["lw"], obs["reach2"]) if obs is not None else (None,) * 4),
            self.tk, prm)
        if li < 0:
            return None, math.inf, None
        s, v = lon["sva"][0, pi], lon["sva"][1, pi]
        return (li, pi), cost, _Poses.along(ref, lat_d[0, li], lat_d[1, li], s, v, _interp(s, ref.s, ref.k))

    def _evaluate_numpy(self, ref: _Ref, lat: _Lateral, lat_d: np.ndarray, lon: dict[str, Any],
                        obs: dict[str, Any] | None, walls: np.ndarray | float, v_des: float,
                        c_route: np.ndarray) -> tuple[tuple[int, int] | None, float, _Poses | None]:
        """:meth:`_evaluate` in numpy: the specification of the compiled step.

        Costs and constraints that do not involve obstacles are separable and evaluated for all
        pairs at once; the obstacle check (hard buffer -> infeasible, soft buffer -> extra cost)
        runs lazily on pairs in order of their obstacle-free cost, stopping as soon as no
        unchecked pair can beat the best one (exact, as the obstacle cost is never negative).
        A pair's obstacle cost does not depend on the pairs checked with it, so the batch sizes
        change the speed only, never the result."""
        p, st = self.p, self.state
        nP = lon["n"]
        sva = lon["sva"]
        ls, lv, la = sva[0], sva[1], sva[2]
        d, ddd = lat_d[0], lat_d[2]
        # longitudinal-only
        kr = _interp(ls, ref.s, ref.k)
        vref = max(v_des, 1.0)
        dv = lv - v_des
        jerk = la[:, 1:] - la[:, :-1]
        c_lon = ((p.w_speed * self._inv_k / vref**2) * (dv * dv).sum(axis=-1) + self._w_acc * (la * la).sum(axis=-1)
                 + self._w_jerk * (jerk * jerk).sum(axis=-1) + lon["penalty"])
        # speed limits (lanes and curvature) ahead; only a start that is already above the limit
        # where the ego is may take time to come down (3 m/s^2)
        if ref.vlim_min == ref.vlim_max:  # the same limit everywhere
            limit = ref.vlim_min + 0.3
            high = lv[0, 0] > limit
        else:
            idx = np.minimum(np.maximum((ls - ref.s_first).astype(np.int64), 0), len(ref.vlim) - 1)
            limit = ref.vlim.take(idx) + 0.3
            high = lv[0, 0] > limit[0, 0]
        if high:
            limit = np.maximum(limit, lv[:, :1] - 3.0 * self.tk)
        ok_lon = ((lv > -0.1) & (lv <= limit)).all(axis=-1)  # min(v) > -0.1 and v <= limit
        # lateral-only: stay inside the drivable band (the current road's lanes while on it, the
        # lane itself beyond); a start outside the band is allowed but must not get worse
        out = (np.maximum(lat.band_lo - d, 0.0)
               + np.maximum(d + p.ego_width / 2 - lat.band[1] - p.edge_margin, 0.0))
        ok_lat = (out <= out[:, :1] + 0.05).all(axis=-1)
        dl = d - lat.target_d[:, None]
        c_lat = lat.w_lat * (dl * dl).sum(axis=-1) + lat.static_cost + c_route
        if st.target_lane is not None:
            c_lat = c_lat + lat.hysteresis(st.target_lane, st.offset, p.w_hysteresis)
        # pairs: walls and lateral acceleration (Frenet: kappa v^2 + d''); the largest |a| is
        # exactly max(max a, -min a)
        a_lat = np.abs((kr * lv * lv)[None] + ddd[:, None]).max(axis=-1)
        # no sideways motion without forward motion: lateral displacement within tan(max heading)
        # x distance travelled + slack
        ok_head = (np.abs(d - d[:, :1])[:, None, :]
                   <= self._tan_head * (ls - ls[:, :1])[None] + p.lateral_slack).all(axis=-1)
        wall = walls[:, None] + 0.05 if isinstance(walls, np.ndarray) else walls + 0.05
        feasible = ((ls.max(axis=-1)[None, :] <= wall) & (a_lat <= p.hard_lat_accel)
                    & ok_lon[None, :] & ok_lat[:, None] & ok_head)
        base = c_lat[:, None] + c_lon[None, :] + p.w_lat_accel * a_lat
        base = np.where(feasible, base, np.inf).ravel()
        order = base.argsort(kind="stable")
        n_ok = int(np.count_nonzero(np.isfinite(base)))
        if n_ok == 0:
            return None, math.inf, None
        if obs is None:
            i = int(order[0])
            li, pi = i // nP, i % nP
            return (li, pi), float(base[i]), _Poses.along(ref, d[li], lat_d[1, li], ls[pi], lv[pi], kr[pi])
        # Pairs are judged in batches of BATCH in cost order (a batch's pick is its argmin,
        # which is its first NaN if there is one); the obstacle cost is computed for several
        # batches at once when more than the first is needed, then judged batch by batch.
        best_i, best_cost, best_poses = -1, math.inf, None
        start, size, B = 0, self.BATCH, self.BATCH
        while start < n_ok and base[order[start]] < best_cost:
            idx = order[start:min(start + size, n_ok)]
            li, pi = np.divmod(idx, nP)
            c_obs, poses = self._obstacle_cost(ref, lat_d[:2].take(li, axis=1), sva[:2].take(pi, axis=1),
                                               kr.take(pi, axis=0), obs)
            total = base.take(idx) + c_obs
            for b in range(0, len(idx), B):
                if b and base[idx[b]] >= best_cost:
                    start = n_ok  # no later pair can beat the best
                    break
                j = b + int(total[b:b + B].argmin())
                if total[j] < best_cost:
                    best_i, best_cost, best_poses = int(idx[j]), float(total[j]), poses.row(j)
            else:
                start, size = start + size, 4 * size  # rarely needed: check the rest in bigger chunks
        if best_i < 0:
            return None, math.inf, None
        return (best_i // nP, best_i % nP), best_cost, best_poses

    def _obstacle_cost(self, ref: _Ref, d_dd: np.ndarray, s_v: np.ndarray, kr: np.ndarray,
                       obs: dict[str, Any]) -> tuple[np.ndarray, _Poses]:
        """Soft-buffer cost of candidate rows, ``inf`` where the hard buffer is violated.

        Exact oriented-box separation (separating-axis test, :func:`_box_separation`) between
        the ego at each planned pose and each predicted obstacle box, in world coordinates. Hard:
        the boxes overlap, or the ego box grown by the hard buffers (longitudinal, lateral)
        overlaps the obstacle more than it does at the start (a buffer the ego is already inside
        may be kept or left, not worsened); soft: separation below the soft buffer. Only
        (candidate, obstacle, time) triples whose bounding circles come within the soft buffer
        are tested; all others cannot contribute. x/y pairs are stacked on a leading axis.
        Also returns the ego poses of the rows."""
        p = self.p
        n = d_dd.shape[1]
        poses = _Poses.along(ref, d_dd[0], d_dd[1], s_v[0], s_v[1], kr)
        dxy = obs["xy"][:, None] - poses.xy[:, :, None]  # (2, candidate, obstacle, time)
        sq = dxy * dxy
        f = np.flatnonzero(sq[0] + sq[1] < obs["reach2"])  # close: flat indices (c m + o) K + k
        if not f.size:
            return np.zeros(n), poses
        eh = poses.h + poses.rel
        # the start pose (the same for every candidate) against every obstacle, and the close
        # triples, in one call: entries [:m] are the start, [m:] the triples
        m, K = obs["n"], self.K
        f_all = np.concatenate((obs["start"], f))
        ok_all = f_all % (m * K)  # (o K + k)
        ecs = np.empty((2, len(f_all)))
        eh_all = np.repeat(eh, m, axis=0).ravel().take(f_all)
        np.cos(eh_all, out=ecs[0])
        np.sin(eh_all, out=ecs[1])
        eh0 = eh[0, 0]
        ecs[0, :m], ecs[1, :m] = math.cos(eh0), math.sin(eh0)
        sep, sep_h = _box_separation(dxy.reshape(2, -1).take(f_all, axis=1), ecs, obs["cs"].take(ok_all, axis=1),
                                     obs["lw"].take(ok_all, axis=1), self._ego_half, self._hard_buf)
        sep_h0 = sep_h[:m]
        sep, sep_h = sep[m:], sep_h[m:]
        ci, oi = f // (m * K), ok_all[m:] // K
        bad = (sep < 0.0) | (sep_h < np.minimum(0.0, sep_h0.take(oi) - 0.05))
        pen = np.maximum(p.lat_buffer_soft - np.maximum(sep, 0.0), 0.0)
        cost = self._w_obs * np.bincount(ci, weights=pen, minlength=n)
        cost[ci[bad]] = np.inf
        return cost, poses

    # -- outputs ------------------------------------------------------------------------------
    def _to_xy(self, poses: _Poses, t0: float, dd: np.ndarray, a: np.ndarray,
               h0: float) -> dict[str, np.ndarray]:
        """The trajectory in world coordinates from the ego poses along it (a standstill keeps
        the start heading)."""
        hr, vs = poses.h, poses.vs
        moving = (np.abs(vs) > 1e-3) | (np.abs(dd) > 1e-3)
        h_rel0 = (h0 - float(hr[0]) + math.pi) % (2 * math.pi) - math.pi
        # the heading never turns further from the reference than a car can (a sideways step at a
        # crawl would otherwise publish a heading of up to +-90 degrees)
        lim = self.p.max_rel_heading
        phi = np.where(moving, np.minimum(np.maximum(poses.rel, -lim), lim), h_rel0)
        return {"t": t0 + self.tk, "x": poses.xy[0], "y": poses.xy[1], "v": np.hypot(vs, dd),
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


def _atan2(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``np.arctan2`` computed by the C library's ``atan2``, as the compiled step does: numpy's
    own SIMD ``arctan2`` (AVX-512 machines) differs from it in the last bit for about 1 % of
    arguments, which made the compiled and the numpy evaluation disagree there."""
    y, x = np.broadcast_arrays(np.asarray(y, dtype=float), np.asarray(x, dtype=float))
    return np.array(list(map(math.atan2, y.ravel().tolist(), x.ravel().tolist())), dtype=float).reshape(y.shape)


def _perp(u: np.ndarray) -> np.ndarray:
    """``(u, v) -> (v, -u)`` along the leading axis of 2 (exact: a swap and sign flips)."""
    return u[::-1] * _FLIP


def _numbers(values: Any, what: str) -> np.ndarray:
    """``np.array(values)``, which must hold numbers: a null or a string (even one that reads as
    a number) in a prediction is an error here, never a NaN or a silently parsed value."""
    a = np.array(values)
    if a.dtype.kind not in "biuf":
        raise TypeError(f"prediction obstacle {what} must be numbers (got {a.dtype})")
    return a


def _grid_index(x: float, last: int) -> int:
    """``np.clip(np.rint(x).astype(np.int64), 0, last)`` for one value: round half to even;
    NaN, infinities and values beyond int64 give 0, as numpy's cast does on x86 (INT64_MIN)."""
    if not math.isfinite(x):
        return 0
    r = round(x)
    if not -(2**63) <= r < 2**63:
        return 0
    return min(max(r, 0), last)


def _box_separation(dxy: np.ndarray, ecs: np.ndarray, ocs: np.ndarray, lw: np.ndarray,
                    ego: np.ndarray, grow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Separating-axis test of two oriented boxes, element-wise.

    Every argument stacks an x/y-like pair on a leading axis of 2: the obstacle box centre
    relative to the ego's ``dxy = (dx, dy)``, the ego heading ``ecs = (cos, sin)``, the obstacle
    heading ``ocs`` and half size ``lw = (half length, half width)``; the ego's half size ``ego``
    and its growth ``grow`` (longitudinal, lateral) have shape ``(2, 1)``.
    Returns the separation [m] (the largest gap along the four box axes; negative = overlap)
    and the same for the ego box grown by ``grow``."""
    ec, es = ecs[0], ecs[1]
    rel = np.abs(ocs * ec + _perp(ocs) * es)  # |cos|, |sin| of the relative heading
    rel_t = rel[::-1]
    dxy_t = _perp(dxy)
    lb, wb = lw[0], lw[1]
    la, wa = ego[0, 0], ego[1, 0]
    lh, wh = grow[0, 0], grow[1, 0]
    # along the ego's axes, then along the obstacle's
    q12 = np.abs(dxy * ec + dxy_t * es) - (lb * rel + wb * rel_t) - ego
    q34 = np.abs(dxy * ocs[0] + dxy_t * ocs[1]) - lw - (la * rel + wa * rel_t)
    sep = np.maximum(np.maximum(q12[0], q12[1]), np.maximum(q34[0], q34[1]))
    h12 = q12 - grow
    h34 = q34 - (lh * rel + wh * rel_t)
    sep_h = np.maximum(np.maximum(h12[0], h12[1]), np.maximum(h34[0], h34[1]))
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
