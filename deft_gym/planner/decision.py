"""The lane-level decision layer of the reference planner (modelled on Apollo's deciders).

Every cycle, before the lattice is evaluated, :class:`LaneDecider` looks at the lanes the ego may
drive in - its own and the changeable neighbours - and turns what it sees into constraints and
costs per lateral option of the lattice:

- **Path bounds (blocking).** Obstacles predicted static are taken by their SL boundary (the box
  of the obstacle in the reference line's (s, d) frame, so an angled object covers more of the
  lane than its footprint), in the ego's home lane grown laterally by an *impact buffer*
  (``impact_buffer``, or ``parked_impact_buffer`` for parked vehicles and vehicles predicted
  static; a lane it borrows is judged without them). Objects whose s
  ranges lie within ``parallel_gap`` of each other form one cluster; a lane is *blocked* at the
  first cluster that leaves no free interval of the lane at least ``ego_width + 2
  corridor_clearance`` wide within ``block_lookahead`` metres. Options staying in a blocked lane
  get a wall in front of the cluster (stop behind it), so the ego passes only by changing lanes.
- **Comfort.** A lane whose centred ego would pass static objects closer than ``comfort_gap``
  over at least ``tight_length`` metres of the lookahead is *tight* (cost ``w_tight``).
- **Gap acceptance.** A lane change needs a gap in the target lane (vehicles in it now or
  predicted to be in it at the end of their prediction): no vehicle alongside, the
  follower at least ``max(rear_gap_min, rear_time_gap x its speed)`` behind, the leader at least
  ``front_gap_min`` ahead; otherwise the change costs ``w_reject``. No change starts within
  ``junction_no_change`` metres of a junction.
- **Home lane and commitment.** The *home* lane is the lane the route wants (the current one
  while every lane continues along the route). Leaving home to pass a blocked or tight lane is a
  *lane borrow*; while home is free the ego is drawn back to it (``w_home`` per lane away). A
  lane change in progress costs ``w_abort`` to abandon. Through junctions the home lane keeps
  its index.

All of it is configuration of the planner (``LatticeParams``), so each of Decictor's root
causes of non-optimal decisions (Table II) is the consequence of a parameter choice, not a
planted bug: a large impact buffer enlarges the effect of obstacles on lane bounds; the corridor
clearance underestimates the room between parallel obstacles; the comfort gap keeps excessive
distance from static obstacles; the rear gap acceptance is over-cautious about trailing vehicles;
the prediction module's stationary classifier and lane-change intent (``static_speed``,
``intent_offset``) mistake slow movers for parked ones and over-weight other vehicles' intent.
The decision state lives in the planner's :class:`~deft_gym.planner.lattice.LatticeState`
(``home``, ``changing_to``, ``change_kind``) and is published in the planning ``decision``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

LaneId = tuple[str, str, int]
REJECTED = "rejected"


@dataclass
class LaneView:
    """What the decider sees of one lane the ego may drive in (s, d in the current reference
    line's frame [m])."""

    lane: LaneId
    centre: float
    blocked_at: float = math.inf  # s where the first impassable cluster starts
    blocked_by: list[int] = field(default_factory=list)  # obstacle indices of that cluster
    tight: float = 0.0  # metres of the lookahead with static objects closer than comfort_gap
    tight_by: list[int] = field(default_factory=list)  # obstacle indices closer than comfort_gap
    gap: str = ""  # why a change into this lane is refused ("" = accepted)
    gap_by: int = -1  # obstacle index of the vehicle that refused it (-1: none, e.g. a junction)
    gap_predicted: bool = False  # that vehicle is in the lane only by its prediction (an intent)


@dataclass
class Decision:
    """Per lateral option: extra cost and wall (largest allowed centre s), plus the lane views."""

    cost: np.ndarray
    walls: np.ndarray
    views: dict[LaneId, LaneView]
    home: LaneId


class LaneDecider:
    """Lane-level decisions for :class:`~deft_gym.planner.lattice.LatticePlanner` (see the
    module docstring). ``planner`` gives the map, the parameters and route helpers."""

    def __init__(self, planner: Any) -> None:
        self.pl = planner
        self.p = planner.p
        self.map = planner.map

    # -- per cycle ------------------------------------------------------------------------------
    def decide(self, lane: LaneId, route: Any, ref: Any, lat: Any, obs: dict[str, Any] | None,
               s0: float, v0: float) -> Decision:
        """Costs and walls of every lateral option of ``lat`` for the ego at ``s0`` [m] with
        speed ``v0`` [m/s] on ``lane``."""
        p, st = self.p, self.pl.state
        home = self._home(lane, route)
        n = len(lat.target)
        views: dict[LaneId, LaneView] = {}
        for j in range(n):
            tgt = lat.target[j]
            if tgt not in views:
                views[tgt] = self._view(tgt, float(lat.centre[j]), obs, s0, own=tgt == home)
        for tgt, view in views.items():
            if tgt != lane:
                view.gap = self._gap(view, obs, s0, v0) or self._junction_gap(ref, s0)
        half = p.ego_length / 2
        hv = views.get(home)  # home may be farther than a neighbour (then it counts as free)
        home_free = hv is None or (not math.isfinite(hv.blocked_at) and hv.tight < p.tight_length)
        cost = np.zeros(n)
        walls = np.full(n, math.inf)
        for j in range(n):
            tgt = lat.target[j]
            view = views[tgt]
            if math.isfinite(view.blocked_at):
                walls[j] = view.blocked_at - half - p.static_gap
            if view.tight >= p.tight_length:
                cost[j] += p.w_tight
            if tgt != lane and view.gap:
                cost[j] += p.w_reject
            if home_free:
                cost[j] += p.w_home * abs(tgt[2] - home[2]) if tgt[:2] == home[:2] else 0.0
            if st.changing_to is not None and st.changing_to != lane and tgt != st.changing_to:
                cost[j] += p.w_abort
        return Decision(cost, walls, views, home)

    def commit(self, dec: Decision, lane: LaneId | None, target: LaneId | None) -> str:
        """Update the decision state after the lattice chose an option with ``target`` lane
        (None: no feasible option, emergency stop); returns the reason published with the plan:
        ``keep`` (home lane), ``blocked`` (the current lane is blocked ahead), ``borrow`` /
        ``return`` (a lane change away from / towards home), ``away`` (keeping a lane other than
        home), ``estop``."""
        st = self.pl.state
        home = dec.home
        if lane is None or target is None:
            st.changing_to, st.change_kind = None, ""
            return "estop"
        if target != lane:
            if st.changing_to != target:  # a new lane change
                st.changing_to = target
                st.change_kind = "return" if _closer(target, lane, home) else "borrow"
            return st.change_kind
        st.changing_to, st.change_kind = None, ""
        view = dec.views.get(lane)
        if view is not None and math.isfinite(view.blocked_at):
            return "blocked"
        return "keep" if lane == st.home else "away"

    def published(self, dec: Decision, reason: str, obs: dict[str, Any] | None) -> dict[str, Any]:
        """What the plan publishes of the decision (lane ids as ``road-from-to-index`` strings):
        its ``reason``, the ``home`` lane, the ``blocked`` and ``tight`` lanes, the lane changes
        ``refused`` (lane -> why), and ``causes``: per lane, the perception ids of the objects
        behind each of those (``blocked``, ``tight``: ids; ``refused``: ``[id, "now" |
        "predicted"]``, predicted when the vehicle is in the lane only by its predicted lane
        change), so that a finding can name its trigger."""
        views = dec.views.values()
        home = self.pl.state.home
        ids = obs["id"] if obs is not None else []
        causes: dict[str, dict[str, Any]] = {}
        for v in views:
            c: dict[str, Any] = {}
            if math.isfinite(v.blocked_at):
                c["blocked"] = [ids[o] for o in v.blocked_by]
            if v.tight >= self.p.tight_length:
                c["tight"] = [ids[o] for o in v.tight_by]
            if v.gap and v.gap_by >= 0:
                c["refused"] = [ids[v.gap_by], "predicted" if v.gap_predicted else "now"]
            if c:
                causes[_name(v.lane)] = c
        return {"reason": reason, "home": list(home) if home else [],
                "blocked": sorted(_name(v.lane) for v in views if math.isfinite(v.blocked_at)),
                "tight": sorted(_name(v.lane) for v in views if v.tight >= self.p.tight_length),
                "refused": {_name(v.lane): v.gap for v in views if v.gap}, "causes": causes}

    # -- lanes ----------------------------------------------------------------------------------
    def _home(self, lane: LaneId, route: Any) -> LaneId:
        """The lane the route wants the ego in (see the module docstring); updates the state."""
        st = self.pl.state
        home = st.home
        road = lane[:2]
        if home is None:
            home = lane
        elif home[:2] != road:  # a new road: keep the lane index where it exists
            k = home[2]
            home = (road[0], road[1], k) if self.map.has_lane((road[0], road[1], k)) else lane
        ok = [lid for lid in self.map.road_lanes(road) if self.pl._continues(lid, route)]
        if ok and home not in ok:
            home = min(ok, key=lambda lid: (abs(lid[2] - lane[2]), lid[2]))
        st.home = home
        return home

    def _view(self, lane: LaneId, centre: float, obs: dict[str, Any] | None, s0: float, own: bool = True) -> LaneView:
        """Blocking and comfort of one lane (centre ``centre`` [m] in the current frame). The
        impact buffers grow objects in the ego's ``own`` lane only - its home lane, whose bounds
        it keeps - while a lane it borrows is judged by the objects' SL boundaries alone."""
        p = self.p
        view = LaneView(lane, centre)
        if obs is None:
            return view
        w = self.map.spec.lane_width
        lo_band, hi_band = centre - w / 2, centre + w / 2
        need = p.ego_width + 2 * p.corridor_clearance
        half = p.ego_length / 2
        front0 = s0 - half  # objects alongside the ego count too
        horizon = s0 + half + p.block_lookahead
        items = []  # (s_lo, s_hi, d_lo, d_hi, index)
        fs, fes, fd, fed = obs["fs"], obs["fes"], obs["fd"], obs["fed"]
        for o in range(obs["n"]):
            if not obs["still"][o]:
                continue
            s_lo, s_hi = fs[o][0] - fes[o][0], fs[o][0] + fes[o][0]
            if s_hi < front0 or s_lo > horizon:
                continue
            buf = 0.0 if not own else p.parked_impact_buffer if obs["kind"][o] != "CONE" else p.impact_buffer
            d_lo, d_hi = fd[o] - fed[o] - buf, fd[o] + fed[o] + buf
            if d_hi <= lo_band or d_lo >= hi_band:
                continue
            items.append((s_lo, s_hi, d_lo, d_hi, o))
            # comfort: the lateral gap of a lane-centred ego to the object (without buffers)
            gap = max(abs(fd[o] - centre) - fed[o] - p.ego_width / 2, -1.0)
            if gap < p.comfort_gap:
                view.tight += s_hi - s_lo + p.ego_length
                view.tight_by.append(o)
        if not items:
            return view
        items.sort()
        clusters: list[list[tuple[float, float, float, float, int]]] = []
        end = -math.inf
        for it in items:
            if clusters and it[0] <= end + p.parallel_gap:
                clusters[-1].append(it)
                end = max(end, it[1])
            else:
                clusters.append([it])
                end = it[1]
        for cl in clusters:
            if _widest_gap(lo_band, hi_band, [(a[2], a[3]) for a in cl]) < need:
                view.blocked_at = cl[0][0]
                view.blocked_by = [a[4] for a in cl]
                break
        return view

    def _gap(self, view: LaneView, obs: dict[str, Any] | None, s0: float, v0: float) -> str:
        """Why a lane change into ``view``'s lane is refused now ("" when the gap is accepted);
        the refusing vehicle goes to ``view.gap_by`` (and ``view.gap_predicted``)."""
        if obs is None:
            return ""
        p = self.p
        half_w = self.map.spec.lane_width / 2
        rear, front = s0 - p.ego_length / 2, s0 + p.ego_length / 2
        fs, fes, fd, fd_end, v = obs["fs"], obs["fes"], obs["fd"], obs["fd_end"], obs["v"]
        for o in range(obs["n"]):  # vehicles in the target lane now or by the end of their prediction
            if obs["still"][o] or min(abs(fd[o] - view.centre), abs(fd_end[o] - view.centre)) >= half_w:
                continue
            o_lo, o_hi = fs[o][0] - fes[o][0], fs[o][0] + fes[o][0]
            why = ""
            if o_hi >= rear - 1.0 and o_lo <= front + 1.0:
                why = "alongside"
            elif o_hi < rear and rear - o_hi < max(p.rear_gap_min, p.rear_time_gap * v[o]):
                why = "rear_gap"
            elif o_lo > front and o_lo - front < p.front_gap_min:
                why = "front_gap"
            if why:
                view.gap_by, view.gap_predicted = o, abs(fd[o] - view.centre) >= half_w
                return why
        return ""

    def _junction_gap(self, ref: Any, s0: float) -> str:
        """A lane change must not start within ``junction_no_change`` metres of a junction."""
        line = ref.line
        if len(line.lane_ids) < 2 or line.lane_ids[1][:2] not in self.map.junction_roads:
            return ""
        return "junction" if float(line.geoms[0].length) - s0 < self.p.junction_no_change else ""


def _name(lane: LaneId) -> str:
    return "-".join(map(str, lane))


def _closer(target: LaneId, lane: LaneId, home: LaneId) -> bool:
    """Does moving from ``lane`` to ``target`` bring the ego closer to ``home`` (same road)?"""
    if target[:2] != home[:2]:
        return False
    return abs(target[2] - home[2]) < abs(lane[2] - home[2])


def _widest_gap(lo: float, hi: float, blocks: list[tuple[float, float]]) -> float:
    """Widest free interval of ``[lo, hi]`` outside the union of ``blocks`` [m]."""
    best, x = 0.0, lo
    for a, b in sorted(blocks):
        if a > x:
            best = max(best, min(a, hi) - x)
        x = max(x, b)
        if x >= hi:
            break
    return max(best, hi - x)
