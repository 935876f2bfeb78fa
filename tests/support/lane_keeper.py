"""A second planner, of another design than the reference lattice planner, to test generality.

``LaneKeeperPlanner`` follows the route lane by lane (no lane changes, no nudges) and plans its
speed with the Intelligent Driver Model integrated over the horizon, stopping for red and yellow
lights at stop lines, behind predicted obstacles on its path and at the destination. It reads
only its frame - the ``map`` message for all geometry - and imports nothing of deft_gym but the
planner interface. Its trajectory has another shape (21 points, 0.25 s apart) and its decision
another vocabulary (``mode``, ``leader``, ``gap``).

State of its own (``self.state``, a plain dict): the speed command it smooths towards the IDM's
(so every plan depends on the previous one), the lane it was on (lane search starts there) and a
hold flag - once stopped at a red light it waits for green before moving (hysteresis). The state
is plain values, so the planner can be seeded (:meth:`export_state`/:meth:`load_state`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from deft_gym.planner.base import Frame, Planner


class LaneKeeperPlanner(Planner):
    caches = ("_lanes", "_map_key")  # the lane index of the map message (a cache, not state)

    """Route-following lane keeper with an IDM speed profile (see the module docstring)."""

    inputs = ("map", "routing", "localization", "traffic_light", "prediction")

    N, DT = 21, 0.25  #: points and spacing [s] of a plan
    A_MAX, B_COMF, GAP0, HEADWAY = 1.5, 2.0, 4.0, 1.4  #: IDM [m/s^2, m/s^2, m, s]

    def __init__(self, map_spec: Mapping[str, Any], **params: Any) -> None:
        super().__init__(map_spec, **params)
        self.ego_length = float(params.get("ego_length", 4.8))  #: [m]
        self.smooth = float(params.get("smooth", 0.5))  #: share of the IDM's speed change adopted per cycle
        self._lanes: dict[tuple[Any, ...], dict[str, Any]] | None = None
        self._map_key: int | None = None
        self.reset()

    def reset(self) -> None:
        self.state = {"v_cmd": None, "lane": None, "hold": False, "cycles": 0}

    def export_state(self) -> dict[str, Any]:
        return dict(self.state)

    def load_state(self, state: Mapping[str, Any]) -> None:
        missing = {"v_cmd", "lane", "hold", "cycles"} - set(state)
        if missing:
            raise ValueError(f"LaneKeeperPlanner state lacks {sorted(missing)}")
        self.state = {k: state[k] for k in ("v_cmd", "lane", "hold", "cycles")}

    # -- one cycle -------------------------------------------------------------------------------
    def plan(self, frame: Frame) -> dict[str, Any] | None:
        mp, routing, loc = frame.get("map"), frame.get("routing"), frame.get("localization")
        if mp is None or routing is None or loc is None:
            return None
        lanes = self._index(mp)
        x0, y0, h0 = float(loc["x"]), float(loc["y"]), float(loc["heading"])
        lane = self._locate(lanes, routing, x0, y0, h0)
        if lane is None:
            return None
        path = self._path(lanes, routing, lane)
        s0 = _project(path, x0, y0)
        st = self.state
        v_meas = max(float(loc["v"]), 0.0)
        v0 = v_meas if st["v_cmd"] is None else 0.5 * (v_meas + st["v_cmd"])
        limit = min(float(routing.get("cruise_speed") or 10.0), lanes[lane]["speed_limit"])
        stop, mode, leader, lead_v = self._constraint(frame, mp, routing, path, s0, lanes, lane)
        hold = st["hold"] and mode == "STOP_LINE"
        t, s, v, a = self._profile(s0, v0, limit, stop, lead_v, hold)
        xs, ys, hs = _along(path, s)
        if hold or (mode == "STOP_LINE" and v0 < 0.2):
            mode = "HOLD"
        st["v_cmd"] = v0 + self.smooth * (float(v[1]) - v0)
        st["lane"] = list(lane)
        st["hold"] = mode == "HOLD"
        st["cycles"] += 1
        return {"trajectory": {"t": (frame.time + t).tolist(), "x": xs.tolist(), "y": ys.tolist(), "v": v.tolist(),
                               "heading": hs.tolist(), "a": a.tolist()},
                "decision": {"mode": mode, "leader": leader, "gap": (stop - s0) if math.isfinite(stop) else -1.0,
                             "lane": list(lane)}}

    # -- the map ---------------------------------------------------------------------------------
    def _index(self, mp: Mapping[str, Any]) -> dict[tuple[Any, ...], dict[str, Any]]:
        """Lane polylines as arrays, built once per map (a cache of the map message, not state)."""
        key = len(mp["lanes"]) * 7919 + len(mp.get("stop_lines", []))
        if self._lanes is None or key != self._map_key:
            self._lanes = {tuple(ln["id"]): {"x": np.asarray(ln["x"], float), "y": np.asarray(ln["y"], float),
                                             "s": np.asarray(ln["s"], float), "succ": [tuple(s) for s in ln["successors"]],
                                             "speed_limit": float(ln["speed_limit"]), "width": float(ln["width"])}
                           for ln in mp["lanes"]}
            self._map_key = key
        return self._lanes

    def _locate(self, lanes: dict[tuple[Any, ...], dict[str, Any]], routing: Mapping[str, Any], x: float, y: float,
                h: float) -> tuple[Any, ...] | None:
        roads = [tuple(seg["road"]) for seg in routing["segments"]]
        prev = tuple(self.state["lane"]) if self.state["lane"] else None
        cands = [prev, *lanes[prev]["succ"]] if prev in lanes else []
        best, best_score = None, math.inf
        for lid in cands or list(lanes):
            ln = lanes[lid]
            dist, hl, over = _nearest_on(ln, x, y)
            dh = abs((h - hl + math.pi) % (2 * math.pi) - math.pi)
            score = dist + 2.0 * over + 3.0 * dh + (0.0 if lid[:2] in roads else 2.0)
            if score < best_score:
                best, best_score = lid, score
        if cands and best_score > 3.0:  # lost: search the whole map
            self.state["lane"] = None
            return self._locate(lanes, routing, x, y, h)
        return best if best_score < 6.0 else None

    def _path(self, lanes: dict[tuple[Any, ...], dict[str, Any]], routing: Mapping[str, Any],
              lane: tuple[Any, ...]) -> dict[str, np.ndarray]:
        """The lane's centre line continued along the route (at least 120 m)."""
        roads = [tuple(seg["road"]) for seg in routing["segments"]]
        chain = [lane]
        total = lanes[lane]["s"][-1]
        while total < 120.0:
            cur = chain[-1]
            nxt_roads = roads[roads.index(cur[:2]) + 1:] if cur[:2] in roads else []
            succ = [s for s in lanes[cur]["succ"] if nxt_roads and s[:2] == nxt_roads[0]] or lanes[cur]["succ"][:1]
            if not succ or succ[0] in chain:
                break
            chain.append(succ[0])
            total += lanes[succ[0]]["s"][-1]
        xs, ys, ss, ids, offs = [], [], [], [], []
        off = 0.0
        for lid in chain:
            ln = lanes[lid]
            skip = 1 if xs else 0
            xs.append(ln["x"][skip:])
            ys.append(ln["y"][skip:])
            ss.append(ln["s"][skip:] + off)
            ids.append(lid)
            offs.append(off)
            off += float(ln["s"][-1])
        return {"x": np.concatenate(xs), "y": np.concatenate(ys), "s": np.concatenate(ss), "lanes": ids,
                "offsets": offs}

    # -- what stops the ego ------------------------------------------------------------------------
    def _constraint(self, frame: Frame, mp: Mapping[str, Any], routing: Mapping[str, Any], path: dict[str, Any],
                    s0: float, lanes: Any, lane: Any) -> tuple[float, str, int, float]:
        """The nearest stop point ahead on the path [m along it], the mode, the leader's id (-1)
        and its speed: a red/yellow stop line, a predicted obstacle on the path, the destination."""
        stop, mode, leader, lead_v = math.inf, "CRUISE", -1, 0.0
        colours = {lt["id"]: lt["color"] for lt in (frame.get("traffic_light") or {}).get("lights", [])}
        for sl in mp.get("stop_lines", []):
            lid = tuple(sl["lane"])
            if lid in path["lanes"] and colours.get(sl["light_id"]) in ("RED", "YELLOW"):
                at = path["offsets"][path["lanes"].index(lid)] + float(sl["s"]) - 1.0
                if s0 - 0.5 < at < stop:
                    stop, mode = at, "STOP_LINE"
        dest = routing["destination"]
        if tuple(dest["lane"]) in path["lanes"]:
            at = path["offsets"][path["lanes"].index(tuple(dest["lane"]))] + float(dest["s"])
            if at < stop:
                stop, mode = at, "ARRIVE"
        half = lanes[lane]["width"] / 2
        for ob in (frame.get("prediction") or {}).get("obstacles", []):
            ox, oy = float(ob["x"][0]), float(ob["y"][0])
            so = _project(path, ox, oy)
            px, py, _ = _along(path, np.array([so]))
            if math.hypot(px[0] - ox, py[0] - oy) > half + 0.5 * float(ob["width"]):
                continue
            at = so - 0.5 * float(ob["length"]) - 0.5 * self.ego_length
            if s0 < at < stop:
                stop, mode, leader, lead_v = at, "FOLLOW", int(ob["id"]), float(ob["v"])
        return stop, mode, leader, lead_v

    def _profile(self, s0: float, v0: float, limit: float, stop: float, lead_v: float,
                 hold: bool) -> tuple[np.ndarray, ...]:
        """IDM integrated over the horizon (semi-implicit Euler): times [s from the frame], s, v, a."""
        t = np.arange(self.N) * self.DT
        s, v, a = np.empty(self.N), np.empty(self.N), np.empty(self.N)
        s[0], v[0] = s0, v0
        for k in range(self.N):
            gap = stop - s[k]
            if hold:
                acc = -self.B_COMF if v[k] > 0.0 else 0.0
            else:
                free = 1.0 - (v[k] / max(limit, 0.1)) ** 4
                if math.isfinite(gap):
                    closing = v[k] - lead_v
                    want = self.GAP0 * 0.25 + v[k] * self.HEADWAY + v[k] * closing / (2 * math.sqrt(self.A_MAX * self.B_COMF))
                    acc = self.A_MAX * (free - (max(want, 0.0) / max(gap, 0.1)) ** 2)
                else:
                    acc = self.A_MAX * free
            acc = max(-6.0, min(self.A_MAX, acc))
            a[k] = acc
            if k + 1 < self.N:
                v[k + 1] = max(v[k] + acc * self.DT, 0.0)
                s[k + 1] = s[k] + 0.5 * (v[k] + v[k + 1]) * self.DT
        return t, s, v, a


def _nearest_on(ln: dict[str, np.ndarray], x: float, y: float) -> tuple[float, float, float]:
    """Distance [m] of (x, y) from a lane's centre line, the heading [rad] of the nearest
    segment, and how far [m] the point lies before its start or past its end."""
    px, py = ln["x"], ln["y"]
    dx, dy = np.diff(px), np.diff(py)
    seg2 = np.maximum(dx * dx + dy * dy, 1e-12)
    raw = ((x - px[:-1]) * dx + (y - py[:-1]) * dy) / seg2
    u = np.clip(raw, 0.0, 1.0)
    d2 = (px[:-1] + u * dx - x) ** 2 + (py[:-1] + u * dy - y) ** 2
    k = int(np.argmin(d2))
    seg = math.sqrt(float(seg2[k]))
    over = max(0.0, -float(raw[0]) * seg) if k == 0 else 0.0
    if k == len(dx) - 1:
        over = max(over, (float(raw[k]) - 1.0) * seg)
    return math.sqrt(float(d2[k])), math.atan2(float(dy[k]), float(dx[k])), over


def _project(path: dict[str, np.ndarray], x: float, y: float) -> float:
    """Arc length [m] of the point of the path nearest to (x, y) (on its segments)."""
    px, py, ps = path["x"], path["y"], path["s"]
    dx, dy = np.diff(px), np.diff(py)
    seg2 = np.maximum(dx * dx + dy * dy, 1e-12)
    u = np.clip(((x - px[:-1]) * dx + (y - py[:-1]) * dy) / seg2, 0.0, 1.0)
    cx, cy = px[:-1] + u * dx, py[:-1] + u * dy
    k = int(np.argmin((cx - x) ** 2 + (cy - y) ** 2))
    return float(ps[k] + u[k] * (ps[k + 1] - ps[k]))


def _along(path: dict[str, np.ndarray], s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions and headings at arc lengths ``s`` (extrapolated straight past the end)."""
    px, py, ps = path["x"], path["y"], path["s"]
    x, y = np.interp(s, ps, px), np.interp(s, ps, py)
    k = np.clip(np.searchsorted(ps, s, side="right") - 1, 0, len(ps) - 2)
    h = np.arctan2(py[k + 1] - py[k], px[k + 1] - px[k])
    over = np.maximum(s - ps[-1], 0.0)
    return x + over * np.cos(h), y + over * np.sin(h), h
