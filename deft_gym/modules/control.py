"""Control: tracks the latest planned trajectory at a high rate.

Longitudinal: feed-forward acceleration of the time-matched trajectory point plus feedback on
speed and station error. Lateral: the planned path's curvature with feedback on offset and
heading (``lateral: curvature``, the default) or pure pursuit (``pure_pursuit``, which cuts tight
turns), converted to a steering angle for highway-env's bicycle model. A trajectory that has run out (no fresh plan) is
answered with braking.
"""

from __future__ import annotations

import bisect
import itertools
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.bus.ads import ModuleConfig
from deft_gym.bus.bus import Node, header
from deft_gym.bus.messages import NS_PER_S
from deft_gym.files import checked_kernel
from deft_gym.world.interp import interp1

try:  # the plan conversion compiled (setup.py): _trajectory_lists' result for the usual case, None
    # otherwise; not used without it or when DEFT_GYM_PURE_PYTHON is set
    from deft_gym.modules import _control_c
except ImportError:  # pragma: no cover - the build is optional
    _control_c = None
if os.environ.get("DEFT_GYM_PURE_PYTHON"):
    _control_c = None
_control_c = checked_kernel(_control_c, Path(__file__).with_name("_control_c.c"), Path(__file__))

WHEELBASE_HALF = 2.4  # [m] highway-env's bicycle: half the vehicle length


class ControlNode(Node):
    """Trajectory tracking (``params``: ``kp_speed``, ``kp_station``, ``lookahead_min`` [m],
    ``lookahead_gain`` [s], ``max_accel``, ``max_decel`` [m/s^2], ``max_steering`` [rad],
    ``lateral``: ``curvature``, the default - the path's curvature at the matched point plus
    feedback on the offset and on the heading less the bicycle's slip, over the look-ahead length
    (:func:`_curvature_law`) - or ``pure_pursuit``, which cuts tight turns: it takes the heading
    for the course, and a 7 m U-turn's slip is 0.35 rad)."""

    def __init__(self, cfg: ModuleConfig, topics: dict[str, str]) -> None:
        self.t_plan, self.t_loc = topics["planning"], topics["localization"]
        super().__init__("control", [self.t_plan, self.t_loc],
                         period_ns=round(NS_PER_S / cfg.rate_hz), processing=cfg.processing)
        self.out_topic = topics["control"]
        p = cfg.params
        self.kp_v = float(p.get("kp_speed", 0.8))
        self.kp_s = float(p.get("kp_station", 0.3))
        self.la_min = float(p.get("lookahead_min", 3.0))
        self.la_gain = float(p.get("lookahead_gain", 0.5))
        self.max_acc = float(p.get("max_accel", 3.0))
        self.max_dec = float(p.get("max_decel", 8.0))
        self.max_steer = float(p.get("max_steering", math.pi / 3))
        self.lateral = str(p.get("lateral", "curvature"))
        if self.lateral not in LATERAL_LAWS:
            raise ValueError(f"control.params.lateral: {self.lateral!r}; expected one of {', '.join(LATERAL_LAWS)}")
        self._cache_seq = -1
        self._tr: dict[str, Any] = {}
        self._fast = False
        self.kernel = _control_c  # None: the Python conversion only (tests compare the two)

    def _traj(self, msg: Any) -> dict[str, Any]:
        """The planned trajectory as arrays (unwrapped heading, arc length ``s``), converted once
        per plan. A well-formed one (equal lengths, finite ascending times) is kept as plain lists
        for the scalar look-ups; anything else takes numpy's path, with numpy's errors."""
        if msg.seq != self._cache_seq:
            tr = msg.payload["trajectory"]
            # the usual case, in plain floats (the same operations); compiled when built, which
            # leaves everything else to the Python version
            lists = self.kernel.float_lists(tr) if self.kernel is not None else None
            if lists is None:
                lists = _trajectory_lists(tr)
            if lists is not None:
                self._tr, self._fast = lists, True
            else:
                self._tr, self._fast = _numpy_trajectory(tr)
            self._cache_seq = msg.seq
        return self._tr

    def compute(self, now_ns: int) -> list[tuple[str, dict[str, Any]]]:
        t = now_ns / NS_PER_S
        plan, loc = self.latest.get(self.t_plan), self.latest.get(self.t_loc)
        steer, acc, seq = 0.0, -2.0, -1
        if plan is not None and loc is not None and plan.payload["trajectory"]["t"]:
            tr = self._traj(plan)
            interp = interp1 if self._fast else _np_interp
            seq = plan.seq
            pose = loc.payload
            x, y, h, v = pose["x"], pose["y"], pose["heading"], pose["v"]
            ts, xs, ys, ss = tr["t"], tr["x"], tr["y"], tr["s"]
            if t > ts[-1]:
                acc = -3.0
            else:
                # longitudinal
                v_ref = interp(t, ts, tr["v"])
                a_ref = interp(t, ts, tr["a"])
                s_ref = interp(t, ts, ss)
                if self._fast:
                    i = self.kernel.nearest(xs, ys, x, y) if self.kernel is not None else None
                    if i is None:  # no kernel, or values it leaves to Python
                        i = _nearest(xs, ys, x, y)
                else:
                    i = int(np.argmin((xs - x) ** 2 + (ys - y) ** 2))
                hi = tr["heading"][i]
                s_match = ss[i] + (x - xs[i]) * math.cos(hi) + (y - ys[i]) * math.sin(hi)
                acc = a_ref + self.kp_v * (v_ref - v) + self.kp_s * (s_ref - s_match)
                if v_ref < 0.05 and v < 0.3:
                    acc = min(acc, -1.0)
                acc = max(-self.max_dec, min(self.max_acc, acc))
                la = self.la_min + self.la_gain * v
                if self.lateral == "curvature":
                    kappa = _curvature_law(tr, s_match, x, y, h, la, interp)
                else:
                    kappa = _pure_pursuit(tr, s_match, x, y, h, la, interp)
                beta = math.asin(max(-1.0, min(1.0, kappa * WHEELBASE_HALF)))
                steer = math.atan(2.0 * math.tan(beta))
                steer = max(-self.max_steer, min(self.max_steer, steer))
        payload = {"header": header(t, self.name), "steering": steer, "acceleration": acc,
                   "trajectory_seq": seq}
        return [(self.out_topic, payload)]


LATERAL_LAWS = ("pure_pursuit", "curvature")


def _pure_pursuit(tr: dict[str, Any], s_match: float, x: float, y: float, h: float, la: float,
                  interp: Any) -> float:
    """Curvature [1/m] of the arc from the pose ``(x, y, h)`` to the plan's point ``la`` m past
    arc length ``s_match`` (straight on past its end): pure pursuit."""
    xs, ys, ss = tr["x"], tr["y"], tr["s"]
    s_t = s_match + la
    if s_t <= ss[-1]:
        tx = interp(s_t, ss, xs)
        ty = interp(s_t, ss, ys)
    else:
        extra = s_t - ss[-1]
        tx = xs[-1] + extra * math.cos(tr["heading"][-1])
        ty = ys[-1] + extra * math.sin(tr["heading"][-1])
    alpha = math.atan2(ty - y, tx - x) - h
    alpha = (alpha + math.pi) % (2 * math.pi) - math.pi
    return 2.0 * math.sin(alpha) / max(math.hypot(tx - x, ty - y), 1e-3)


def _curvature_law(tr: dict[str, Any], s_match: float, x: float, y: float, h: float, length: float,
                   interp: Any) -> float:
    """Curvature [1/m] of the ``curvature`` law: the plan path's at arc length ``s_match`` minus
    ``e / length**2`` plus ``2 sin(dh) / length``, with ``e`` [m] the pose ``(x, y)``'s offset to
    the left of the path and ``dh`` the heading the ego has on the path minus its own ``h``. The
    path's course and curvature come from its points (the chords' directions and their change per
    metre), not from the plan's ``heading``, which a planner may give as the body's heading or as
    the course. The heading on the path is its course less the slip angle of highway-env's bicycle
    at that curvature, ``asin(kappa L / 2)`` - 0.35 rad on a 7 m radius, which a law taking the
    course for the heading turns into steering the turn too tight. The offset then decays
    critically damped over ``length`` m of travel, at any speed; past the plan's end, straight on."""
    ss, xs, ys = tr["s"], tr["x"], tr["y"]
    n = len(ss)

    def course(k: int) -> float | None:
        dx, dy = xs[k + 1] - xs[k], ys[k + 1] - ys[k]
        return math.atan2(dy, dx) if ss[k + 1] - ss[k] > 1e-6 else None

    s_c = max(s_match, ss[0])
    k = max(0, min(n - 2, bisect.bisect_right(ss, s_c) - 1)) if n > 1 else 0
    c_k = course(k) if n > 1 else None
    past_end = s_match >= ss[-1]
    if past_end or c_k is None:  # straight on past the end; a chord of standing points: its heading
        h_ref, k_ref = c_k if c_k is not None else float(tr["heading"][-1 if past_end else k]), 0.0
        if past_end:
            x_ref = xs[-1] + (s_match - ss[-1]) * math.cos(h_ref)
            y_ref = ys[-1] + (s_match - ss[-1]) * math.sin(h_ref)
        else:
            x_ref, y_ref = interp(s_c, ss, xs), interp(s_c, ss, ys)
    else:
        m = k + 1 if k + 2 < n else k - 1  # the neighbouring chord
        c_m = course(m) if m >= 0 else None
        k_ref = 0.0
        if c_m is not None:
            turn = (c_m - c_k + math.pi) % (2 * math.pi) - math.pi
            k_ref = turn / (0.5 * (ss[m + 1] - ss[m] + ss[k + 1] - ss[k])) * (1 if m > k else -1)
        h_ref = c_k + k_ref * (s_c - 0.5 * (ss[k] + ss[k + 1]))
        x_ref, y_ref = interp(s_c, ss, xs), interp(s_c, ss, ys)
    e = -(x - x_ref) * math.sin(h_ref) + (y - y_ref) * math.cos(h_ref)
    slip = math.asin(max(-1.0, min(1.0, k_ref * WHEELBASE_HALF)))
    dh = (h_ref - slip - h + math.pi) % (2 * math.pi) - math.pi
    return k_ref - e / (length * length) + 2.0 * math.sin(dh) / length


def _unwrap(h: np.ndarray) -> np.ndarray:
    """``np.unwrap(h)`` (period 2 pi), without its work when no step reaches pi (then its
    result is ``h`` with ``+ 0.0`` added after the first element)."""
    if h.ndim == 1 and (np.abs(np.diff(h)) < math.pi).all():
        up = h.copy()
        up[1:] += 0.0
        return up
    return np.unwrap(h)


def _numpy_trajectory(tr: dict[str, Any]) -> tuple[dict[str, Any], bool]:
    """The trajectory's columns as arrays, heading unwrapped, plus ``s`` (arc length); as plain
    lists, and True, when they are well formed (see :func:`_well_formed`)."""
    arr = {k: np.asarray(tr[k], dtype=float) for k in ("t", "x", "y", "v", "a")}
    arr["heading"] = _unwrap(np.asarray(tr["heading"], dtype=float))
    seg = np.hypot(np.diff(arr["x"]), np.diff(arr["y"]))
    arr["s"] = np.concatenate([[0.0], np.cumsum(seg)])
    n = arr["t"].shape
    if all(a.ndim == 1 and a.shape == n for a in arr.values()):
        lists = {k: a.tolist() for k, a in arr.items()}
        if _well_formed(lists):
            return lists, True
    return arr, False


def _float_lists(tr: dict[str, Any]) -> dict[str, list[float]] | None:
    """The trajectory's columns as :func:`_numpy_trajectory` makes them, when every
    column is a list of the same number of plain floats (else None): heading unwrapped, ``s`` the
    running sum of ``np.hypot`` of the steps (``np.cumsum`` adds in order)."""
    cols = {k: tr[k] for k in ("t", "x", "y", "v", "a", "heading")}
    n = len(cols["t"]) if type(cols["t"]) is list else -1
    if n < 1 or any(type(c) is not list or len(c) != n or set(map(type, c)) != {float} for c in cols.values()):
        return None
    cols["heading"] = _unwrap(np.array(cols["heading"])).tolist()
    seg = np.hypot(np.diff(cols["x"]), np.diff(cols["y"])).tolist()
    cols["s"] = [0.0, *itertools.accumulate(seg)]
    return cols


def _trajectory_lists(tr: dict[str, Any]) -> dict[str, list[float]] | None:
    """:func:`_float_lists` when it applies and the result is :func:`_well_formed`, else None
    (what ``_control_c.float_lists`` computes for the usual case)."""
    lists = _float_lists(tr)
    return lists if lists is not None and _well_formed(lists) else None


def _well_formed(tr: dict[str, list[float]]) -> bool:
    """Finite, non-decreasing times and finite arc lengths (what the scalar look-ups need)."""
    t = tr["t"]
    return (all(map(math.isfinite, t)) and all(map(math.isfinite, tr["s"]))
            and all(b - a >= 0.0 for a, b in itertools.pairwise(t)))


def _np_interp(x: float, xp: np.ndarray, fp: np.ndarray) -> float:
    return float(np.interp(x, xp, fp))


def _nearest(xs: list[float], ys: list[float], x: float, y: float) -> int:
    """Index of the point nearest to ``(x, y)``, as ``np.argmin`` of the squared distances
    picks it (the first of equals; the first NaN if there is one)."""
    i, best = 0, math.inf
    for k in range(len(xs)):
        dx, dy = xs[k] - x, ys[k] - y
        d2 = dx * dx + dy * dy
        if d2 < best:
            i, best = k, d2
        elif d2 != d2:
            return k
    return i
