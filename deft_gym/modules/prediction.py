"""Prediction: a deliberately simple predictor, triggered by every perception message.

Static obstacles stay where they are, and so does any obstacle slower than ``static_speed``
[m/s] (a stationary classifier with a speed threshold: a slow mover is taken for a parked one);
an obstacle once taken for stationary stays so until it has been faster than the threshold for
``static_hold`` [s] (the classifier's hysteresis, against flicker).
A moving obstacle keeps its speed and its lateral offset along its lane, and at the end of the
lane continues on the successor with the least turning - so it misses turns and stops at red
lights, like the constant-velocity predictors real stacks fall back to. An obstacle offset from
its lane centre by more than ``intent_offset`` [m] towards a neighbour lane it may change to is
predicted to change into it over ``intent_time`` [s] (a lane-change intent classifier on the
lateral offset: a vehicle that merely drives off-centre is taken for one about to cut in).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from deft_gym.bus.ads import ModuleConfig
from deft_gym.bus.bus import Node, header
from deft_gym.bus.messages import NS_PER_S
from deft_gym.world.geometry import wrap_angle
from deft_gym.world.roadmap import RoadMap

STATIC_TYPES = ("CONE", "STATIC_VEHICLE")


class PredictionNode(Node):
    """Predicted trajectories over ``params.horizon`` [s] at ``params.dt`` [s]."""

    def __init__(self, roadmap: RoadMap, cfg: ModuleConfig, in_topic: str, out_topic: str) -> None:
        super().__init__("prediction", [in_topic], trigger=in_topic, processing=cfg.processing)
        self.roadmap, self.in_topic, self.out_topic = roadmap, in_topic, out_topic
        self.horizon = float(cfg.params.get("horizon", 6.0))
        self.dt = float(cfg.params.get("dt", 0.2))
        self.static_speed = float(cfg.params.get("static_speed", 1.0))
        self.static_hold = float(cfg.params.get("static_hold", 1.0))
        self.intent_offset = float(cfg.params.get("intent_offset", 0.6))
        self.intent_time = float(cfg.params.get("intent_time", 3.0))
        self.t = np.arange(round(self.horizon / self.dt) + 1) * self.dt
        self._t_list: list[float] = self.t.tolist()  # the same times as floats, for scalar math
        self._t_last = self._t_list[-1]
        # (lane, length bucket) -> (reference line, its wrapped heading if it is one straight lane)
        self._chains: dict[Any, tuple[Any, float | None]] = {}
        self._lane_of: dict[int, Any] = {}  # obstacle id -> its lane last cycle (tracking)
        self._still: dict[int, float | None] = {}  # obstacle id -> since when it has been fast again (None: still)

    def compute(self, now_ns: int) -> list[tuple[str, dict[str, Any]]]:
        msg = self.latest[self.in_topic]
        stamp = msg.payload["header"]["stamp"]
        out = []
        for ob in msg.payload["obstacles"]:
            out.append(self._predict(ob, stamp))
        payload = {"header": header(now_ns / NS_PER_S, self.name), "perception_stamp": stamp,
                   "obstacles": out}
        return [(self.out_topic, payload)]

    def _predict(self, ob: dict[str, Any], t0: float) -> dict[str, Any]:
        base = {"id": ob["id"], "type": ob["type"], "length": ob["length"], "width": ob["width"],
                "t0": t0, "dt": self.dt, "v": ob["v"]}
        v = float(ob["v"])
        if ob["type"] in STATIC_TYPES or self._stationary(ob["id"], v, t0):
            return {**base, "is_static": True, "x": [ob["x"]], "y": [ob["y"]], "heading": [ob["heading"]]}
        loc = self._locate(ob)
        if loc is not None:
            lane, s, d = loc
            shift = self._intent(lane, d)
            if shift:
                ref, _ = self._chain(lane, s + self._t_last * v + 5.0)
                w = float(self.roadmap.geom(lane).width)
                u = np.minimum(self.t / self.intent_time, 1.0)
                dd = d + (shift * w - d) * (3 * u**2 - 2 * u**3)  # smooth move to the neighbour's centre
                ss = s + self.t * v
                pts = ref.xy(ss, dd)
                hs = ref.heading(ss) + np.arctan2(np.gradient(dd, self.t), max(v, 0.5))
                return {**base, "is_static": False, "x": pts[:, 0].tolist(), "y": pts[:, 1].tolist(),
                        "heading": wrap_angle(hs).tolist(), "intent": "left" if shift < 0 else "right"}
            # the chain covers the horizon: t[-1] * v is dist[-1] below (the same product)
            ref, const = self._chain(lane, s + self._t_last * v + 5.0)
            if const is not None:  # one straight lane: the heading is the same everywhere
                xs, ys = ref.geoms[0].xy_list([s + t * v for t in self._t_list], d)
                return {**base, "is_static": False, "x": xs, "y": ys, "heading": [const] * len(xs)}
        dist = self.t * v
        if loc is None:
            h = ob["heading"]
            xs = ob["x"] + dist * np.cos(h)
            ys = ob["y"] + dist * np.sin(h)
            hs = np.full(self.t.shape, h)
        else:
            ss = s + dist
            pts = ref.xy(ss, d)
            xs, ys = pts[:, 0], pts[:, 1]
            hs = ref.heading(ss)
        return {**base, "is_static": False, "x": xs.tolist(), "y": ys.tolist(), "heading": wrap_angle(hs).tolist()}

    def _stationary(self, oid: int, v: float, t: float) -> bool:
        """The stationary classifier with hysteresis (see the module docstring)."""
        if v < self.static_speed:
            self._still[oid] = None
            return True
        if oid not in self._still:
            return False  # never seen still
        since = self._still[oid]
        if since is None:
            self._still[oid] = since = t
        if t - since >= self.static_hold:
            del self._still[oid]
            return False
        return True

    def _intent(self, lane: Any, d: float) -> int:
        """-1 / +1 when the offset ``d`` [m] (right +) says a change to the left / right
        neighbour is coming, else 0."""
        if abs(d) <= self.intent_offset:
            return 0
        shift = 1 if d > 0 else -1
        nb = (lane[0], lane[1], lane[2] + shift)
        return shift if nb in self.roadmap.changeable_neighbours(lane) else 0

    def _locate(self, ob: dict[str, Any]) -> tuple[Any, float, float] | None:
        """The obstacle's lane: the one it was on, or a successor/neighbour of it, while it fits;
        else a search of the whole map (like a tracker keeping obstacle history)."""
        rm = self.roadmap
        x, y, h = ob["x"], ob["y"], ob["heading"]
        prev = self._lane_of.get(ob["id"])
        if prev is not None:
            for lane in rm.around(prev):
                g = rm.geoms[lane]
                s, d = g.frenet_point(x, y)
                if (0.0 <= s <= g.length and abs(d) <= g.width / 2
                        and abs((h - g.heading_point(s) + np.pi) % (2 * np.pi) - np.pi) < 0.5):
                    self._lane_of[ob["id"]] = lane
                    return lane, s, d
        loc = rm.locate(np.array([x, y]), h, radius=3.0)
        if loc is not None:
            self._lane_of[ob["id"]] = loc[0]
        return loc

    def _chain(self, lane: Any, length: float) -> tuple[Any, float | None]:
        """The reference line along ``lane`` and its straight successors covering ``length`` [m],
        with its constant (wrapped) heading when it is a single straight lane."""
        key = (lane, int(length // 25))
        out = self._chains.get(key)
        if out is None:
            ref = self.roadmap.reference_line(self.roadmap.default_chain(lane, length))
            g = ref.geoms[0]
            const = (float(wrap_angle(np.full(1, g.heading0))[0])
                     if len(ref.geoms) == 1 and g.kind == "straight" else None)
            out = self._chains[key] = (ref, const)
        return out
