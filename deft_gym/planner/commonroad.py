"""CommonRoad's reactive planner behind the planner interface: a third-party planner as a target.

:class:`CommonRoadPlanner` wraps ``commonroad_rp.reactive_planner.ReactivePlanner`` from
``commonroad-reactive-planner`` 2025.1 (TUM's sampling-based planner in Frenet coordinates:
quartic / quintic polynomials sampled in end time, end speed or stop position and lateral offset
around a reference path, checked for kinematic feasibility, sorted by cost and checked lazily for
collisions with CommonRoad's collision checker). Install it with ``pip install -e ".[commonroad]"``
(``make test`` does); select it with ``configs/ads/commonroad.yaml``. Nothing of deft_gym is used
but the planner interface; everything comes from the frame (docs/planner.md has the table):

- ``map``: every lane becomes a CommonRoad lanelet (centre line, bounds at half its width,
  successors, adjacent lanes), from which CommonRoad's drivability checker builds the road
  boundary the collision checker holds (leaving the lanes is a collision); the reference path is
  the centre line of the ego's route lane continued lane by lane along the route, in a CommonRoad
  curvilinear coordinate system (spline-smoothed and resampled as CommonRoad's
  ``create_coordinate_system`` does);
- ``routing``: the route lanes (the reference switches to a route lane when the ego is in another
  lane of the road, which makes the lane change; it stays while the ego swerves), the destination
  (a desired stop position once it is near: the planner's ``stopping`` mode) and the cruise speed;
- ``localization``: the initial state (the pose moved to the rear axle, CommonRoad's reference
  point; the speed; acceleration and steering angle from the previous plan at the frame time while
  the ego is near it, else the measured acceleration and the yaw rate's steering angle);
- ``prediction``: static obstacles as boxes, moving ones as time-variant boxes along their
  predicted paths resampled at the planner's time steps (both grown by ``margin``);
- ``traffic_light``: a red light (or a yellow one it can stop for) at a stop line on the
  reference is a desired stop position before the line, or behind the vehicles queued there;
  a red one is approached as a standing leader (the desired speed falls to reach 0 there); an ego
  all but stopped at or past a light's or the destination's stop position holds (a braking plan,
  ``HOLD``).

What the library leaves to its user, the adapter sets as a user would: the desired velocity (the
cruise speed capped by the speed limits, the reference's curvature, a moving leader ahead in
the ego's corridor, a light to stop for and a destination with a standing obstacle at or past it,
each reached ``lag`` seconds early because the planner follows it with a lag), where to stop for
the destination (before such an obstacle, as before a red light's queue),
when to switch to stopping mode, and what to do when the planner finds no trajectory (the rest of
the previous plan while the collision checker finds it free and the ego could still brake short
of every lane's end after following it - the library's road boundary leaves lane ends open - else
braking at ``fallback_decel``).
Two mismatches inside the library are bridged: commonroad-clcs 2025 raises where the planner
expects None outside the projection domain (the adapter's coordinate system returns None, so the
sample is dropped as the planner intends instead of ending the cycle), and the lanelets of lanes
that continue each other overlap by ``joint_overlap`` so that a kink at a lane joint leaves no
notch in the road boundary. Failures of the library are not hidden: they are the decision's
``result`` (``NO_TRAJECTORY``, ``ERROR`` with its ``error``) and its ``fallback``.

The output is the planner's optimal trajectory (the vehicle centre, ``dt`` apart, absolute times
from the frame time) and a decision in the planner's own terms: ``result`` (``OPTIMAL``,
``STANDSTILL``: the library's standstill trajectory, ``NO_TRAJECTORY``, ``ERROR``), ``fallback``
(``PREVIOUS``, ``BRAKE`` or empty), the longitudinal ``mode`` and what it stops for (``stop``,
``stop_s``), ``desired_speed``, ``leader``, the sampling statistics, ``low_vel_mode``, the lane,
the reference's first lane (``target_lane``), the final lateral offset ``d_end``.

**State.** The library object keeps values across cycles that change its plans. The one that
matters is ``_low_vel_mode``: ``reset()`` turns the Cartesian initial state into the curvilinear
one with the *previous* cycle's mode (lateral derivatives per metre in low-velocity mode, per
second otherwise), and only then does ``plan()`` set the mode from the new speed. The adapter
keeps it in ``self.state`` and puts it back before every cycle, and sets every other per-cycle
value of the library object (initial state, coordinate system, collision checker, desired speed
or stop position, sampling intervals, cost-function targets, statistics) before planning, so the
library object is a pure function of the frame and ``self.state``. The state is plain values
(``low_vel_mode``, the located ``lane``, the reference's first lane ``target``, the previous plan
``prev``, ``cycles``), so the planner can also be seeded (:meth:`export_state`/:meth:`load_state`).
Caches (per map message: lanelet network, road boundary, library object; per lane chain:
coordinate system) are functions of the map alone.

**Clock.** ``ReactivePlanner.plan()`` times itself with ``time.perf_counter`` for its statistics
(``planning_times``, ``journal``), which no output depends on. While it plans, the adapter points
the library module's ``time`` at :class:`_StepClock`, a counter that advances by one per call, so
``plan()`` calls no wall clock (the contract checker sees none) and the statistics count calls
instead of seconds; the library's module is restored afterwards. Its logger is silenced (a log
record reads the clock) and its multiprocessing is off.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import hashlib
import json
import math
import weakref
from collections.abc import Iterator, Mapping
from typing import Any, NamedTuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from deft_gym.planner.base import Frame, Planner

try:  # the extra: pip install -e ".[commonroad]"
    import commonroad_rp.reactive_planner as _rp_module
    from commonroad.scenario.lanelet import Lanelet, LaneletNetwork
    from commonroad.scenario.scenario import Scenario
    from commonroad_clcs.config import CLCSParams, ProcessingOption, ResamplingOption
    from commonroad_clcs.pycrccosy import (
        CurvilinearProjectionDomainLateralError,
        CurvilinearProjectionDomainLongitudinalError,
    )
    from commonroad_dc import pycrcc
    from commonroad_rp.reactive_planner import ReactivePlanner
    from commonroad_rp.state import ReactivePlannerState
    from commonroad_rp.utility.config import ReactivePlannerConfiguration
    from commonroad_rp.utility.utils_coordinate_system import CoordinateSystem

    from deft_gym.planner.commonroad_kinematics import (
        FastKinematicsMixin,
        SharedLateralMixin,
        VectorCostMixin,
    )
except ImportError as _exc:  # pragma: no cover - depends on the installation
    IMPORT_ERROR: ImportError | None = _exc
else:
    IMPORT_ERROR = None

LaneKey = tuple[Any, ...]

#: a level above CRITICAL: the library's logger creates no records (a record reads the clock)
_SILENT = 100


class CommonRoadParams(BaseModel):
    """Tuning of :class:`CommonRoadPlanner` (SI units). The library's own settings are named as in
    ``ReactivePlannerConfiguration`` (``planning.*``, ``sampling.*``, ``vehicle.*``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # planning.*
    dt: float = Field(0.2, gt=0.0, description="[s] planner time step (planning.dt)")
    time_steps: int = Field(20, ge=5, le=100, description="steps of a plan (planning.time_steps_computation): "
                            "the horizon is dt x time_steps")
    low_vel_mode_threshold: float = Field(4.0, ge=0.0, description="[m/s] below it lateral motion is "
                                          "planned over distance, not time (planning.low_vel_mode_threshold)")
    # sampling.*
    num_sampling_levels: int = Field(3, ge=2, le=6, description="sampling levels; plan() tries levels 1 .. n-1 "
                                     "(the library's 4 adds a level of 5814 samples: seconds per plan)")
    t_min: float = Field(0.4, gt=0.0, description="[s] shortest sampled end time (sampling.t_min)")
    max_deceleration_ratio: float = Field(0.125, gt=0.0, le=1.0, description="share of a_max x horizon the "
                                          "sampled end speeds reach below the current speed")
    d_min: float = Field(-3.0, description="[m] lateral samples around the reference (sampling.d_min)")
    d_max: float = Field(3.0, description="[m] (sampling.d_max)")
    s_min: float = Field(-1.0, description="[m] stop-position samples around a desired stop (sampling.s_min)")
    s_max: float = Field(1.0, description="[m] (sampling.s_max)")
    # vehicle.* (the ego's box; axle positions and steering limits: CommonRoad's vehicle 2, a BMW 320i)
    ego_length: float = Field(4.8, gt=0.0)
    ego_width: float = Field(2.0, gt=0.0)
    wb_front_axle: float = Field(1.1561957064, gt=0.0)
    wb_rear_axle: float = Field(1.4227170936, gt=0.0)
    a_max: float = Field(6.0, gt=0.0, description="[m/s^2] |acceleration| bound of the plans (vehicle.a_max)")
    delta_max: float = Field(1.066, gt=0.0, lt=1.5, description="[rad] steering angle bound (vehicle.delta_max)")
    v_delta_max: float = Field(0.4, gt=0.0, description="[rad/s] steering rate bound (vehicle.v_delta_max): "
                               "with the curvature rate of the path it bounds the speed into a tight turn")
    # the adapter
    margin: float = Field(0.3, ge=0.0, description="[m] obstacles' boxes grown by this on every side")
    default_cruise: float = Field(10.0, gt=0.0, description="[m/s] desired speed when the route names none")
    stop_gap: float = Field(1.0, ge=0.0, description="[m] from the ego's front to a stop line when stopped")
    follow_gap: float = Field(4.0, ge=0.0, description="[m] the desired speed reaches a moving leader's speed "
                              "this far behind it (at comfort_decel)")
    stop_engage: float = Field(10.0, ge=0.0, description="[m] a stop point this near (or within half the "
                               "horizon at the current speed) switches to stopping mode")
    destination_room: float = Field(10.0, ge=0.0, description="[m] a standing obstacle in the ego's corridor that ends "
                                    "less than this before the ego's front at the destination's stop, or reaches past "
                                    "it, is stopped behind (the destination's stop is moved to its rear, as a queue "
                                    "moves a red light's): there is no room to pass it and return to the lane before "
                                    "the route ends")
    max_lat_accel: float = Field(2.0, gt=0.0, description="[m/s^2] the desired speed is capped ahead of curves "
                                 "of the reference so that lateral acceleration stays below this")
    comfort_decel: float = Field(1.0, gt=0.0, description="[m/s^2] how early the desired speed drops before a "
                                 "curve, a lower speed limit or a slower leader (the planner follows its desired "
                                 "speed with some lag)")
    lag: float = Field(2.5, ge=0.0, description="[s] the desired speed reaches a cap this long (at the current "
                       "speed) before the curve, speed limit or leader that sets it")
    yellow_decel: float = Field(3.0, gt=0.0, description="[m/s^2] a yellow light is stopped for when this "
                                "suffices")
    red_hold_speed: float = Field(1.0, ge=0.0, description="[m/s] an ego this slow at or past a red light's stop "
                                  "position (past the line by less than its length) or the destination's holds: a "
                                  "braking plan, not the library's, whose stop samples reach 1 m on (it crept over "
                                  "the line; it crept up to a car standing at the destination, each cycle's stop "
                                  "moved to where it stood)")
    fallback_decel: float = Field(6.0, gt=0.0, description="[m/s^2] braking of the fallback plan")
    stitch_distance: float = Field(1.0, ge=0.0, description="[m] the previous plan's acceleration and steering "
                                   "start the next one while the ego is this close to it")
    boundary_overlap: float = Field(0.05, ge=0.0, description="[m] lanelet bounds widened by this so that "
                                    "adjacent lanes overlap (no slivers in the road boundary)")
    joint_overlap: float = Field(1.0, ge=0.0, description="[m] lanelets prolonged by this where a lane continues "
                                 "another (kinks at lane joints leave no notch in the road boundary)")
    end_wall: float = Field(2.0, gt=0.0, description="[m] depth of the wall across the end of a lane that ends "
                            "(no successor): the fallback's check of the previous plan closes lane ends that the "
                            "library's road boundary leaves open")
    end_reaction: float = Field(0.5, ge=0.0, description="[s] a lane's end counts in the fallback's check once the "
                                "previous plan reaches it within the braking distance at fallback_decel plus this "
                                "long at the current speed")
    reference_back: float = Field(20.0, ge=0.0, description="[m] the reference path extended behind its first lane")
    reference_ahead: float = Field(50.0, ge=0.0, description="[m] ... and past its last lane")
    vectorised_kinematics: bool = Field(True, description="the library's kinematic check vectorised over samples "
                                        "and time steps, and each bundle's lateral polynomials built once, bit for bit "
                                        "its results (commonroad_kinematics.py); false: the library's own code (plans "
                                        "take ~3.5-3.8x the CPU)")


class _Ahead(NamedTuple):
    """An obstacle in the ego's corridor ahead (``CommonRoadPlanner._corridor``)."""

    gap: float  #: [m] from the ego's front to the obstacle's rear along the reference (0 where they overlap)
    id: int
    v: float  #: [m/s] its predicted speed
    moving: bool
    kind: str  #: its type ("VEHICLE", "STATIC_VEHICLE", ...)
    far: float  #: [m] from the ego's front to the obstacle's front along the reference


class _StepClock:
    """Stands in for the ``time`` module inside ``commonroad_rp.reactive_planner`` while it plans:
    ``perf_counter`` counts calls (the library only subtracts two readings for its statistics)."""

    def __init__(self) -> None:
        self.n = 0

    def perf_counter(self) -> float:
        self.n += 1
        return float(self.n)


@contextlib.contextmanager
def _library_clock() -> Iterator[_StepClock]:
    clock = _StepClock()
    real = _rp_module.time
    _rp_module.time = clock
    try:
        yield clock
    finally:
        _rp_module.time = real


if IMPORT_ERROR is None:

    class _CoordinateSystem(CoordinateSystem):
        """The planner's coordinate system as the planner expects it: ``convert_to_cartesian_coords``
        gives None outside the projection domain (the planner then drops the sample as "out of
        projection domain"), where commonroad-clcs 2025 raises, which would end the whole cycle."""

        _to_cartesian = CoordinateSystem.convert_to_cartesian_coords  # super()'s, looked up once

        def convert_to_cartesian_coords(self, s: float, d: float) -> Any:
            try:
                return self._to_cartesian(s, d)
            except (CurvilinearProjectionDomainLongitudinalError, CurvilinearProjectionDomainLateralError):
                return None


    class _FastReactivePlanner(VectorCostMixin, SharedLateralMixin, FastKinematicsMixin, ReactivePlanner):
        """The library's planner with its kinematic check and its default cost vectorised and each
        bundle's lateral polynomials built once (same results)."""


class _MapModel:
    """What the adapter derives from one map message (a cache: a function of the map alone)."""

    def __init__(self, mp: Mapping[str, Any], p: CommonRoadParams) -> None:
        self.lanes: dict[LaneKey, dict[str, Any]] = {}
        for ln in mp["lanes"]:
            key = tuple(ln["id"])
            self.lanes[key] = {
                "x": np.asarray(ln["x"], float), "y": np.asarray(ln["y"], float), "s": np.asarray(ln["s"], float),
                "width": float(ln["width"]), "speed_limit": float(ln["speed_limit"]),
                "succ": [tuple(s) for s in ln["successors"]], "left": tuple(ln["left"]), "right": tuple(ln["right"]),
                "junction": bool(ln.get("junction", False)),
            }
        self.stop_lines = [{"lane": tuple(sl["lane"]), "s": float(sl["s"]), "light": str(sl["light_id"])}
                           for sl in mp.get("stop_lines", [])]
        self.ids = {key: i + 1 for i, key in enumerate(self.lanes)}
        self.network = self._network(p)
        self.coords: dict[tuple[LaneKey, ...], Any] = {}
        self.planner = self._planner(p)
        self.boundary = self.planner.collision_checker  # holds the road boundary only
        self.ends = self._ends(p)

    def _network(self, p: CommonRoadParams) -> Any:
        """The lanes as CommonRoad lanelets. The world frame has y pointing down on screen, so the
        bound at +90 deg from the driving direction (CommonRoad's left) is the driver's right:
        CommonRoad sees the mirror image, consistently (its lateral d is positive to the right, as
        the map's)."""
        preds: dict[LaneKey, list[int]] = {k: [] for k in self.lanes}
        for k, ln in self.lanes.items():
            for s in ln["succ"]:
                if s in preds:
                    preds[s].append(self.ids[k])
        lanelets = []
        for k, ln in self.lanes.items():
            c = np.column_stack([ln["x"], ln["y"]])
            # lanes that continue each other overlap by joint_overlap: a kink between a lane's end
            # and its successor's start leaves no notch in the road boundary
            if ln["succ"]:
                c = np.vstack([c, c[-1] + p.joint_overlap * _unit(c[-1] - c[-2])])
            if preds[k]:
                c = np.vstack([c[0] - p.joint_overlap * _unit(c[1] - c[0]), c])
            n = _normals(c)
            half = 0.5 * ln["width"] + p.boundary_overlap
            right_nb, left_nb = ln["right"], ln["left"]  # the driver's
            lanelets.append(Lanelet(
                left_vertices=c + half * n, center_vertices=c, right_vertices=c - half * n, lanelet_id=self.ids[k],
                predecessor=preds[k], successor=[self.ids[s] for s in ln["succ"] if s in self.ids],
                adjacent_left=self.ids.get(right_nb), adjacent_left_same_direction=True if right_nb in self.ids else None,
                adjacent_right=self.ids.get(left_nb), adjacent_right_same_direction=True if left_nb in self.ids else None))
        return LaneletNetwork.create_from_lanelet_list(lanelets, cleanup_ids=False)

    def _ends(self, p: CommonRoadParams) -> Any:
        """A wall (``end_wall`` deep, as wide as the lanelet) across the end of every lane with no
        successor on the map: the library's road boundary closes the road's sides only, so a plan
        may run on past a road's end without colliding. Only the fallback checks against it: the
        library's own collision check stays the library's."""
        walls = pycrcc.CollisionChecker()
        for ln in self.lanes.values():
            if any(s in self.lanes for s in ln["succ"]):
                continue
            c = np.column_stack([ln["x"], ln["y"]])
            u = _unit(c[-1] - c[-2])
            mid = c[-1] + 0.5 * p.end_wall * u
            walls.add_collision_object(pycrcc.RectOBB(0.5 * p.end_wall, 0.5 * ln["width"] + p.boundary_overlap,
                                                      math.atan2(u[1], u[0]), float(mid[0]), float(mid[1])))
        return walls

    def _planner(self, p: CommonRoadParams) -> Any:
        cfg = ReactivePlannerConfiguration()
        cfg.planning.dt = p.dt
        cfg.planning.time_steps_computation = p.time_steps
        cfg.planning.planning_horizon = p.dt * p.time_steps
        cfg.planning.low_vel_mode_threshold = p.low_vel_mode_threshold
        cfg.sampling.num_sampling_levels = p.num_sampling_levels
        cfg.sampling.t_min = p.t_min
        cfg.sampling.max_deceleration_ratio = p.max_deceleration_ratio
        cfg.sampling.d_min, cfg.sampling.d_max = p.d_min, p.d_max
        cfg.sampling.s_min, cfg.sampling.s_max = p.s_min, p.s_max
        v = cfg.vehicle
        v.length, v.width = p.ego_length, p.ego_width
        v.wb_front_axle, v.wb_rear_axle = p.wb_front_axle, p.wb_rear_axle
        v.a_max = p.a_max
        v.delta_min, v.delta_max = -p.delta_max, p.delta_max
        v.v_delta_min, v.v_delta_max = -p.v_delta_max, p.v_delta_max
        v._update_computed_params()
        cfg.debug.multiproc = False
        cfg.debug.logging_level = _SILENT
        cfg.debug.draw_traj_set = False
        sc = Scenario(dt=p.dt)
        sc.add_objects(self.network)
        cfg.scenario = sc
        return (_FastReactivePlanner if p.vectorised_kinematics else ReactivePlanner)(cfg)

    def coordinate_system(self, chain: tuple[LaneKey, ...], p: CommonRoadParams) -> Any:
        co = self.coords.get(chain)
        if co is None:
            # CommonRoad's create_coordinate_system(): spline smoothing, adaptive resampling
            params = CLCSParams(processing_option=ProcessingOption.SPLINE_SMOOTHING)
            params.spline.degree_spline = 3
            params.spline.smoothing_factor = 2.0
            params.resampling.option = ResamplingOption.ADAPTIVE
            params.resampling.min_step, params.resampling.max_step = 0.5, 1.0
            with np.errstate(divide="ignore", invalid="ignore"):  # straight stretches: curvature 0
                co = self.coords[chain] = _CoordinateSystem(self.reference(chain, p), True, params)
        return co

    def reference(self, chain: tuple[LaneKey, ...], p: CommonRoadParams) -> np.ndarray:
        """The chain's centre lines joined, at most 1 m apart, extended straight at both ends."""
        pts: list[np.ndarray] = []
        for k in chain:
            ln = self.lanes[k]
            c = np.column_stack([ln["x"], ln["y"]])
            if pts and np.hypot(*(c[0] - pts[-1][-1])) < 1e-6:
                c = c[1:]
            pts.append(c)
        line = np.concatenate(pts)
        seg = np.hypot(*np.diff(line, axis=0).T)
        parts = [line[:1]]
        for i in range(len(seg)):
            n = max(1, math.ceil(float(seg[i])))
            parts.append(line[i] + (line[i + 1] - line[i]) * (np.arange(1, n + 1)[:, None] / n))
        line = np.concatenate(parts)
        back = np.arange(max(1, math.ceil(p.reference_back)), 0, -1)[:, None] * (p.reference_back / max(1, math.ceil(p.reference_back)))
        ahead = np.arange(1, max(1, math.ceil(p.reference_ahead)) + 1)[:, None] * (p.reference_ahead / max(1, math.ceil(p.reference_ahead)))
        return np.concatenate([line[0] - _unit(line[1] - line[0]) * back, line,
                               line[-1] + _unit(line[-1] - line[-2]) * ahead])


class CommonRoadPlanner(Planner):
    """CommonRoad's reactive planner on deft_gym's frames (see the module docstring)."""

    inputs = ("map", "routing", "localization", "traffic_light", "prediction")
    #: memo caches: the CommonRoad road model of each map (keyed by the map's digest) and the last
    #: map message with its digest (so an unchanged map is not hashed again)
    caches = ("_models", "_last_map")

    def __init__(self, map_spec: Mapping[str, Any], **params: Any) -> None:
        if IMPORT_ERROR is not None:
            raise ImportError(f"CommonRoadPlanner needs commonroad-reactive-planner: pip install -e '.[commonroad]' "
                              f"({IMPORT_ERROR})")
        super().__init__(map_spec, **params)
        self.p = CommonRoadParams(**params)
        self._models: dict[str, _MapModel] = {}
        self._last_map: tuple[Any, str] | None = None  # (the message, its digest)
        _LIVE.add(self)
        self.reset()

    @classmethod
    def hard_clearance(cls, params: Mapping[str, Any]) -> float:
        return CommonRoadParams(**dict(params)).margin

    def reset(self) -> None:
        self.state = {"low_vel_mode": False, "lane": None, "target": None, "prev": None, "cycles": 0}

    def export_state(self) -> dict[str, Any]:
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in self.state.items()}

    def load_state(self, state: Mapping[str, Any]) -> None:
        missing = {"low_vel_mode", "lane", "target", "prev", "cycles"} - set(state)
        if missing:
            raise ValueError(f"CommonRoadPlanner state lacks {sorted(missing)}")
        self.state = {"low_vel_mode": bool(state["low_vel_mode"]),
                      "lane": list(state["lane"]) if state["lane"] is not None else None,
                      "target": list(state["target"]) if state["target"] is not None else None,
                      "prev": {k: list(v) for k, v in state["prev"].items()} if state["prev"] else None,
                      "cycles": int(state["cycles"])}

    # -- one cycle -------------------------------------------------------------------------------
    def plan(self, frame: Frame) -> dict[str, Any] | None:
        mp, routing, loc = frame.get("map"), frame.get("routing"), frame.get("localization")
        if mp is None or routing is None or loc is None:
            return None
        p, st = self.p, self.state
        model = self._model(mp)
        x0, y0, h0 = float(loc["x"]), float(loc["y"]), float(loc["heading"])
        lane = self._locate(model, routing, x0, y0, h0)
        if lane is None:
            return None
        target = self._target(model, routing, lane)
        chain = self._chain(model, routing, target)
        rp = model.planner
        rp._low_vel_mode = bool(st["low_vel_mode"])  # the hidden state: it shapes reset()'s initial state
        decision: dict[str, Any] = {
            "result": "ERROR", "mode": "velocity_keeping", "stop": "", "stop_s": -1.0, "desired_speed": -1.0,
            "leader": -1, "lane": list(lane), "target_lane": list(target), "samples": -1,
            "infeasible_kinematics": -1, "infeasible_collision": -1, "low_vel_mode": False, "stitched": False,
            "d_end": 0.0, "fallback": "", "error": ""}
        v0 = max(float(loc["v"]), 0.0)
        acc, steer, stitched = self._dynamics(frame.time, loc, x0, y0, v0)
        state0 = ReactivePlannerState(
            time_step=0, position=np.array([x0 - p.wb_rear_axle * math.cos(h0), y0 - p.wb_rear_axle * math.sin(h0)]),
            orientation=h0, velocity=v0, acceleration=acc, yaw_rate=float(loc.get("yaw_rate", 0.0)),
            steering_angle=steer)
        result, cc = None, None
        try:
            co = model.coordinate_system(chain, p)
            cc = self._collision_checker(model, frame)
            rp._planning_times_list.clear()
            rp.reset(initial_state_cart=state0, collision_checker=cc, coordinate_system=co)
            mode, stop_for, s_stop, v_des, leader = self._longitudinal(frame, model, routing, chain, co, lane, v0)
            decision.update({"mode": mode, "stop": stop_for, "desired_speed": float(v_des), "leader": leader,
                             "stop_s": float(s_stop) if s_stop is not None else -1.0})
            if mode == "hold":
                decision["result"] = "HOLD"
            else:
                rp.config.sampling.longitudinal_mode = mode
                if mode == "stopping":
                    rp.set_desired_lon_position(s_stop)
                else:
                    # current_speed 0.0 would make the library read a planning problem we have none of
                    rp.set_desired_velocity(desired_velocity=v_des, current_speed=max(v0, 1e-6))
                with _library_clock():
                    result = rp.plan()
                decision.update({"result": "OPTIMAL" if result is not None else "NO_TRAJECTORY",
                                 "samples": int(rp.total_count_samples),
                                 "infeasible_kinematics": int(rp.infeasible_count_kinematics),
                                 "infeasible_collision": int(rp.infeasible_count_collision)})
        except Exception as exc:  # the library's failures (projection domain, its own bugs): fall back
            decision.update({"result": "ERROR", "error": f"{type(exc).__name__}: {exc}"[:200]})
        st["low_vel_mode"] = bool(rp._low_vel_mode)
        decision["low_vel_mode"] = st["low_vel_mode"]
        decision["stitched"] = stitched
        if result is not None:
            traj = self._output(result[0].state_list, frame.time)
            if len(traj["t"]) < p.time_steps + 1 and decision["result"] == "OPTIMAL":
                decision["result"] = "STANDSTILL"
            decision["d_end"] = float(result[2][-1][0]) if result[2] else 0.0
        else:  # none found (or the library failed): the previous plan while it stays collision-free, else braking
            traj = self._previous(frame.time, cc, model.ends) if cc is not None and decision["result"] != "HOLD" else None
            if traj is not None:
                decision["fallback"] = "PREVIOUS"
            else:
                traj = self._fallback(frame.time, x0, y0, h0, v0)
                decision["fallback"] = "BRAKE"
        st["lane"], st["target"] = list(lane), list(target)
        st["prev"] = {k: list(traj[k]) for k in ("t", "x", "y", "heading", "v", "a", "steering")}
        st["cycles"] += 1
        return {"trajectory": {k: traj[k] for k in ("t", "x", "y", "v", "heading", "a")}, "decision": decision}

    # -- the map and the route -------------------------------------------------------------------
    def _model(self, mp: Mapping[str, Any]) -> _MapModel:
        """The map's model, built once per map (the same message, or an equal one, is not
        digested again)."""
        last = self._last_map
        if last is not None and (last[0] is mp or last[0] == mp):
            key = last[1]
        else:
            body = json.dumps({k: v for k, v in mp.items() if k != "header"}, sort_keys=True, allow_nan=True)
            key = hashlib.sha256(body.encode()).hexdigest()
        self._last_map = (mp, key)
        model = self._models.get(key)
        if model is None:
            model = self._models[key] = _MapModel(mp, self.p)
        return model

    def _locate(self, model: _MapModel, routing: Mapping[str, Any], x: float, y: float, h: float) -> LaneKey | None:
        """The lane the ego is on: the previous one or its successors first, else the best of all
        (distance, heading, off the route)."""
        roads = {tuple(seg["road"]) for seg in routing["segments"]}
        prev = tuple(self.state["lane"]) if self.state["lane"] else None
        near: list[LaneKey] = []
        if prev in model.lanes:
            ln = model.lanes[prev]
            near = [prev, *ln["succ"], *(ln[side] for side in ("left", "right") if ln[side])]
        best, best_score = None, math.inf
        for cands, good in ((near, 3.0), (list(model.lanes), 6.0)):
            best, best_score = None, math.inf
            for k in cands:
                if k not in model.lanes:
                    continue
                dist, hl, over = _nearest_on(model.lanes[k], x, y)
                dh = abs((h - hl + math.pi) % (2 * math.pi) - math.pi)
                score = dist + 2.0 * over + 3.0 * dh + (0.0 if k[:2] in roads else 2.0)
                if score < best_score:
                    best, best_score = k, score
            if best is not None and best_score <= good:
                return best
        return None

    @staticmethod
    def _route_lanes(routing: Mapping[str, Any]) -> dict[tuple[Any, ...], list[int]]:
        return {tuple(seg["road"]): [int(i) for i in seg["lanes"]] for seg in routing["segments"]}

    def _target(self, model: _MapModel, routing: Mapping[str, Any], lane: LaneKey) -> LaneKey:
        """The first lane of the reference path. It stays the previous one (or its continuation
        along the route on the ego's road) while the ego swerves into a neighbour lane, as
        CommonRoad's fixed reference path along a route does; without one (or when the ego left
        it), the ego's lane; either way the route lane of that road nearest to it."""
        prev = tuple(self.state["target"]) if self.state["target"] else None
        if prev in model.lanes:
            on_road = [k for k in self._chain(model, routing, prev) if k[:2] == lane[:2]]
            if on_road:
                return self._route_lane(model, routing, on_road[0])
        return self._route_lane(model, routing, lane)

    def _route_lane(self, model: _MapModel, routing: Mapping[str, Any], lane: LaneKey) -> LaneKey:
        """The route lane of ``lane``'s road nearest to it (itself when it is one)."""
        allowed = self._route_lanes(routing).get(lane[:2])
        if not allowed or lane[2] in allowed:
            return lane
        best = min(allowed, key=lambda i: (abs(i - lane[2]), i))
        cand = (*lane[:2], best)
        return cand if cand in model.lanes else lane

    def _chain(self, model: _MapModel, routing: Mapping[str, Any], first: LaneKey) -> tuple[LaneKey, ...]:
        """``first`` continued lane by lane along the route to its end (successors on the next road
        of the route, its route lanes first)."""
        roads = [tuple(seg["road"]) for seg in routing["segments"]]
        allowed = self._route_lanes(routing)
        chain = [first]
        while len(chain) < 50:
            cur = chain[-1]
            if cur[:2] not in roads:
                break
            i = roads.index(cur[:2])
            if i + 1 >= len(roads):
                break
            nxt = roads[i + 1]
            succ = [s for s in model.lanes[cur]["succ"] if s[:2] == nxt and s in model.lanes]
            if not succ:
                break
            pick = [s for s in succ if s[2] in allowed.get(nxt, [])] or succ
            chain.append(pick[0])
        return tuple(chain)

    # -- inputs of the library -------------------------------------------------------------------
    def _dynamics(self, t: float, loc: Mapping[str, Any], x: float, y: float, v: float) -> tuple[float, float, bool]:
        """Acceleration and steering angle of the initial state: the previous plan's at ``t`` when
        the ego is within ``stitch_distance`` of it, else the measured acceleration and the steering
        angle of the measured yaw rate (bounded)."""
        prev = self.state["prev"]
        if prev is not None and prev["t"][0] <= t <= prev["t"][-1]:
            tt = prev["t"]
            px, py = float(np.interp(t, tt, prev["x"])), float(np.interp(t, tt, prev["y"]))
            if math.hypot(px - x, py - y) <= self.p.stitch_distance:
                return float(np.interp(t, tt, prev["a"])), float(np.interp(t, tt, prev["steering"])), True
        wb = self.p.wb_front_axle + self.p.wb_rear_axle
        kappa_max = math.tan(self.p.delta_max) / wb
        kappa = float(loc.get("yaw_rate", 0.0)) / v if v > 1.0 else 0.0
        kappa = max(-kappa_max, min(kappa_max, kappa))
        return float(loc.get("a", 0.0)), math.atan2(wb * kappa, 1.0), False

    def _collision_checker(self, model: _MapModel, frame: Frame) -> Any:
        """The road boundary plus the predicted obstacles at the planner's time steps."""
        p = self.p
        cc = model.boundary.clone()
        m = p.margin
        steps = np.arange(p.time_steps + 1) * p.dt + frame.time
        for ob in (frame.get("prediction") or {}).get("obstacles", []):
            hl, hw = 0.5 * float(ob["length"]) + m, 0.5 * float(ob["width"]) + m
            xs, ys, hs = ob["x"], ob["y"], ob["heading"]
            if len(xs) == 1 or ob.get("is_static"):
                cc.add_collision_object(pycrcc.RectOBB(hl, hw, float(hs[0]), float(xs[0]), float(ys[0])))
                continue
            f = np.clip((steps - float(ob["t0"])) / float(ob["dt"]), 0.0, len(xs) - 1.0)
            i = np.minimum(f.astype(int), len(xs) - 2)
            w = f - i
            xa, ya, ha = np.asarray(xs, float), np.asarray(ys, float), np.unwrap(np.asarray(hs, float))
            px = xa[i] + w * (xa[i + 1] - xa[i])
            py = ya[i] + w * (ya[i + 1] - ya[i])
            ph = ha[i] + w * (ha[i + 1] - ha[i])
            tvo = pycrcc.TimeVariantCollisionObject(0)
            for k in range(len(steps)):
                tvo.append_obstacle(pycrcc.RectOBB(hl, hw, float(ph[k]), float(px[k]), float(py[k])))
            cc.add_collision_object(tvo)
        return cc

    def _longitudinal(self, frame: Frame, model: _MapModel, routing: Mapping[str, Any], chain: tuple[LaneKey, ...],
                      co: Any, lane: LaneKey, v0: float) -> tuple[str, str, float | None, float, int]:
        """``(mode, what it stops for, desired stop position [s of the rear axle], desired speed,
        leader id or -1)``: stopping mode for the nearest stop point on the reference (a red light,
        or the rear of the queue before it; a yellow one it can still stop before at ``yellow_decel``;
        the destination, or the rear of a standing obstacle at or just before it) once it is within
        ``stop_engage`` or half the horizon at the current speed (past a light's stop position: where
        ``yellow_decel`` stops it; "hold" at or past any stop below ``red_hold_speed``), else velocity keeping at
        the cruise speed capped by the speed limits, the curves, a moving leader, the lights it
        stops for and the destination (each as a standing leader at its stop position; a
        destination a lane over at its position on the reference)."""
        p = self.p
        s_ego = self._s_of(co, *self._rear(frame))
        to_front = p.wb_rear_axle + 0.5 * p.ego_length
        ahead = self._corridor(frame, co, s_ego + to_front)
        v_des = self._desired_speed(model, routing, chain, co, s_ego, v0)
        leader = -1
        for ob in ahead:  # the nearest moving obstacle ahead in the corridor
            if ob.moving:
                cap = self._approach_cap(ob.gap - p.follow_gap, v0, ob.v)
                if cap < v_des:
                    v_des, leader = cap, ob.id
                break
        colours = {lt["id"]: lt["color"] for lt in (frame.get("traffic_light") or {}).get("lights", [])}
        stops: list[tuple[float, str]] = []
        for sl in model.stop_lines:
            if sl["lane"] not in chain:
                continue
            colour = colours.get(sl["light"])
            if colour not in ("RED", "YELLOW"):
                continue
            s_line = self._s_along(model, co, sl["lane"], sl["s"])
            if s_line is None:
                continue
            s_stop = s_line - to_front - p.stop_gap
            queue = [ob.gap for ob in ahead if ob.kind == "VEHICLE" and s_ego + to_front + ob.gap < s_line]
            if queue:
                s_stop = min(s_stop, s_ego + queue[0] - p.stop_gap)
            gap = s_stop - s_ego
            to_line = s_line - to_front - s_ego  # the front's distance to the line
            if colour == "YELLOW" and (to_line <= 0.0 or v0 * v0 > 2.0 * p.yellow_decel * to_line):
                continue  # on or over the line, or too late to stop before it: go
            if gap < -0.5 * p.stop_gap - 1.0 and colour == "RED":
                if v0 < p.red_hold_speed and s_ego + to_front < s_line + p.ego_length:
                    stops.append((s_ego, "RED_LIGHT"))  # overshot the line, all but stopped: stay
                continue  # past it
            stops.append((s_stop, "RED_LIGHT" if colour == "RED" else "YELLOW_LIGHT"))
            # approached as a standing leader: the desired speed falls to 0 at the stop (a yellow one too: it
            # was not skipped above, so it can still be stopped for)
            v_des = min(v_des, self._approach_cap(gap, v0))
        dest = routing["destination"]
        dkey = tuple(dest["lane"])
        # the route's end, approached as a standing leader; while the destination is a lane over, at its
        # position on the reference's lane of the same road (the stop itself waits for the ego in its lane)
        at = dkey if dkey in chain else next((ln for ln in chain if ln[:2] == dkey[:2]), None)
        s_dest = self._s_along(model, co, at, float(dest["s"])) if at is not None else None
        if s_dest is not None:
            s_stop = s_dest - p.wb_rear_axle
            if at == dkey:
                # what stands at or beyond it, within the plans' reach, is no reason to pull out (plans that
                # keep the cruise speed up to the stop run past it and swerve round it, and there is no room to
                # pass what stands at it and return to the lane before the end); the stop moves to the rear of
                # the first such obstacle, as a queue moves a red light's
                reach = max(v0, v_des) * p.dt * p.time_steps
                front_at_stop = s_stop - s_ego  # [m] from the ego's front now to its front at the stop
                standing = [ob.gap for ob in ahead
                            if not ob.moving and ob.gap <= reach and ob.far >= front_at_stop - p.destination_room]
                if standing:  # stop_gap behind its rear, less the library's stop samples' reach past the stop
                    s_stop = min(s_stop, s_ego + standing[0] - p.stop_gap - p.s_max)
                stops.append((s_stop, "DESTINATION"))
            v_des = min(v_des, self._approach_cap(s_stop - s_ego, v0))
        if stops:
            s_stop, what = min(stops)
            gap = s_stop - s_ego
            light = what in ("RED_LIGHT", "YELLOW_LIGHT")
            if gap <= 0.0 and v0 < p.red_hold_speed:  # a light's or the destination's
                return "hold", what, s_ego, 0.0, leader  # the library's stop samples reach 1 m on: it would creep
            if gap <= max(p.stop_engage, 0.5 * v0 * p.dt * p.time_steps):
                # past the stop position, still rolling: stop where yellow_decel brings it (the library
                # finds no stop at its own position and the previous, moving plan would run the light)
                reach = s_ego + v0 * v0 / (2.0 * p.yellow_decel) if light else s_ego
                return "stopping", what, max(s_stop, reach), 0.0, leader
        return "velocity_keeping", "", None, v_des, leader

    def _approach_cap(self, gap: float, v0: float, v_leader: float = 0.0) -> float:
        """[m/s] The desired speed that reaches ``v_leader`` [m/s] ``gap`` [m] ahead at
        ``comfort_decel``, ``lag`` seconds early at the current speed ``v0`` [m/s]: a leader, a red
        light or a stop approached as a standing leader (``v_leader`` 0)."""
        p = self.p
        return math.sqrt(max(v_leader * v_leader + 2.0 * p.comfort_decel * (gap - v0 * p.lag), 0.0))

    def _corridor(self, frame: Frame, co: Any, s_front: float) -> list[_Ahead]:
        """Predicted obstacles now in the ego's corridor along the reference ahead of its front,
        nearest first (vehicles waiting before a red light form its queue; parked ones and cones do
        not)."""
        p = self.p
        out = []
        for ob in (frame.get("prediction") or {}).get("obstacles", []):
            try:
                s_o, d_o = co.convert_to_curvilinear_coords(float(ob["x"][0]), float(ob["y"][0]))
            except Exception:  # outside the projection domain
                continue
            if abs(float(d_o)) > 0.5 * p.ego_width + 0.5 * float(ob["width"]) + p.margin:
                continue
            gap = float(s_o) - 0.5 * float(ob["length"]) - s_front
            if gap > -0.5 * float(ob["length"]):
                moving = not ob.get("is_static") and len(ob["x"]) > 1 and float(ob["v"]) > 1.0
                out.append(_Ahead(max(gap, 0.0), int(ob["id"]), float(ob["v"]), moving, str(ob.get("type", "")),
                                  gap + float(ob["length"])))
        return sorted(out)

    def _desired_speed(self, model: _MapModel, routing: Mapping[str, Any], chain: tuple[LaneKey, ...], co: Any,
                       s_ego: float, v0: float) -> float:
        """The route's cruise speed, capped by the speed limits and the curves of the reference
        ahead (lateral acceleration ``max_lat_accel``), each reached at ``comfort_decel`` after
        ``lag`` seconds at the current speed: what a user sets as the reactive planner's desired
        velocity (the planner follows it with a lag: its cost trades speed error for acceleration)."""
        p = self.p
        v = min(float(routing.get("cruise_speed") or p.default_cruise), model.lanes[chain[0]]["speed_limit"])
        lag = v0 * p.lag
        for k in chain[1:]:
            s0 = self._s_along(model, co, k, 0.0)
            if s0 is not None and s0 > s_ego:
                room = max(s0 - s_ego - lag, 0.0)
                v = min(v, math.sqrt(model.lanes[k]["speed_limit"] ** 2 + 2.0 * p.comfort_decel * room))
        pos, curv = np.asarray(co.ref_pos), np.abs(np.asarray(co.ref_curv))
        ahead = pos >= s_ego
        if ahead.any():
            v_curve = np.sqrt(p.max_lat_accel / np.maximum(curv[ahead], 1e-9))
            room = np.maximum(pos[ahead] - s_ego - lag, 0.0)
            v = min(v, float(np.sqrt(v_curve * v_curve + 2.0 * p.comfort_decel * room).min()))
        return v

    def _rear(self, frame: Frame) -> tuple[float, float]:
        loc = frame.get("localization")
        h = float(loc["heading"])
        return float(loc["x"]) - self.p.wb_rear_axle * math.cos(h), float(loc["y"]) - self.p.wb_rear_axle * math.sin(h)

    @staticmethod
    def _s_of(co: Any, x: float, y: float) -> float:
        return float(co.convert_to_curvilinear_coords(x, y)[0])

    def _s_along(self, model: _MapModel, co: Any, lane: LaneKey, s: float) -> float | None:
        """The reference's s of the point ``s`` along ``lane``'s centre line (None outside its domain)."""
        ln = model.lanes[lane]
        x, y = float(np.interp(s, ln["s"], ln["x"])), float(np.interp(s, ln["s"], ln["y"]))
        try:
            return self._s_of(co, x, y)
        except Exception:  # outside the projection domain (the library's own exception types)
            return None

    # -- outputs ---------------------------------------------------------------------------------
    def _output(self, states: list[Any], t0: float) -> dict[str, list[float]]:
        """The library's states (rear axle) as the trajectory of the vehicle centre."""
        p = self.p
        n = len(states)
        h = np.array([float(s.orientation) for s in states])
        rx = np.array([float(s.position[0]) for s in states])
        ry = np.array([float(s.position[1]) for s in states])
        return {"t": [t0 + k * p.dt for k in range(n)],
                "x": (rx + p.wb_rear_axle * np.cos(h)).tolist(), "y": (ry + p.wb_rear_axle * np.sin(h)).tolist(),
                "v": [float(s.velocity) for s in states], "heading": h.tolist(),
                "a": [float(s.acceleration) for s in states], "steering": [float(s.steering_angle) for s in states]}

    def _previous(self, t0: float, cc: Any, ends: Any) -> dict[str, list[float]] | None:
        """The rest of the previous plan from ``t0`` on (at the planner's steps; braking at
        ``fallback_decel`` past its end) when it collides with nothing the collision checker now
        holds and the ego could still stop short of every lane's end (``ends``:
        :meth:`_MapModel._ends`) after following it, else None: what a reactive planner's host
        does while replanning finds nothing. A lane's end counts where the plan reaches it within
        the braking distance at ``fallback_decel`` plus ``end_reaction`` s at the current speed: a
        plan whose far end runs past a lane's end is followed while there is room to brake (the
        next cycle may find a plan), and not once there is not."""
        prev, p = self.state["prev"], self.p
        if prev is None or not prev["t"][0] <= t0 <= prev["t"][-1]:
            return None
        n = p.time_steps + 1
        tk = t0 + np.arange(n) * p.dt
        tt = np.asarray(prev["t"])
        inside = np.minimum(tk, tt[-1])
        out = {k: np.interp(inside, tt, np.asarray(prev[k])) for k in ("x", "y", "v", "a", "steering")}
        out["heading"] = np.interp(inside, tt, np.unwrap(np.asarray(prev["heading"])))
        tau = np.maximum(tk - tt[-1], 0.0)  # past the previous plan's end: braking on along its last heading
        v_end, h_end = float(prev["v"][-1]), float(out["heading"][-1])
        stop = v_end / p.fallback_decel
        ds = np.where(tau < stop, v_end * tau - 0.5 * p.fallback_decel * tau * tau, 0.5 * v_end * stop)
        out["x"] = out["x"] + ds * math.cos(h_end)
        out["y"] = out["y"] + ds * math.sin(h_end)
        out["v"] = np.where(tau > 0, np.maximum(v_end - p.fallback_decel * tau, 0.0), out["v"])
        out["a"] = np.where(tau > 0, np.where(tau < stop, -p.fallback_decel, 0.0), out["a"])
        v0 = float(out["v"][0])
        reach = v0 * v0 / (2.0 * p.fallback_decel) + v0 * p.end_reaction
        along = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(out["x"]), np.diff(out["y"])))])
        hl, hw = 0.5 * p.ego_length, 0.5 * p.ego_width
        for k in range(n):
            box = pycrcc.RectOBB(hl, hw, float(out["heading"][k]), float(out["x"][k]), float(out["y"][k]))
            if cc.time_slice(k).collide(box) or (along[k] <= reach and ends.collide(box)):
                return None
        return {"t": tk.tolist(), **{k: [float(x) for x in v] for k, v in out.items()}}

    def _fallback(self, t0: float, x: float, y: float, h: float, v: float) -> dict[str, list[float]]:
        """Braking at ``fallback_decel`` along the previous plan's path (straight on without one)."""
        p = self.p
        n = p.time_steps + 1
        tk = np.arange(n) * p.dt
        vk = np.maximum(v - p.fallback_decel * tk, 0.0)
        stop_t = v / p.fallback_decel
        sk = np.where(tk < stop_t, v * tk - 0.5 * p.fallback_decel * tk * tk, 0.5 * v * stop_t)
        ak = np.where(tk < stop_t, -p.fallback_decel, 0.0)
        prev = self.state["prev"]
        px = py = None
        if prev is not None and len(prev["x"]) >= 2:
            px, py = np.asarray(prev["x"]), np.asarray(prev["y"])
            seg = np.hypot(np.diff(px), np.diff(py))
            ps = np.concatenate([[0.0], np.cumsum(seg)])
            if ps[-1] > 1e-3:
                s0 = _project_polyline(px, py, ps, x, y)
                q = s0 + sk
                xs = np.interp(q, ps, px)
                ys = np.interp(q, ps, py)
                j = np.clip(np.searchsorted(ps, q, side="right") - 1, 0, len(ps) - 2)
                hs = np.arctan2(py[j + 1] - py[j], px[j + 1] - px[j])
                hs = h + (hs - h + math.pi) % (2 * math.pi) - math.pi
                over = np.maximum(q - ps[-1], 0.0)
                xs, ys = xs + over * np.cos(hs), ys + over * np.sin(hs)
                xs[0], ys[0], hs[0] = x, y, h
            else:
                px = None
        if px is None:
            xs, ys, hs = x + sk * math.cos(h), y + sk * math.sin(h), np.full(n, h)
        return {"t": (t0 + tk).tolist(), "x": np.asarray(xs, float).tolist(), "y": np.asarray(ys, float).tolist(),
                "v": vk.tolist(), "heading": np.asarray(hs, float).tolist(), "a": ak.tolist(), "steering": [0.0] * n}


_LIVE: weakref.WeakSet[CommonRoadPlanner] = weakref.WeakSet()


@atexit.register
def _release() -> None:
    """Free the library's objects before the interpreter tears its extension modules down (their
    bindings report every object still alive then as leaked, a screenful at each exit)."""
    for planner in list(_LIVE):
        planner._models.clear()
        planner._last_map = None
    gc.collect()


# -- geometry -------------------------------------------------------------------------------------
def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.hypot(*v))
    return v / n if n > 0 else np.array([1.0, 0.0])


def _normals(c: np.ndarray) -> np.ndarray:
    """Unit normals (+90 deg from the direction) at the points of a polyline (mean of the
    adjacent segments' directions inside)."""
    d = np.diff(c, axis=0)
    d = d / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)[:, None]
    t = np.vstack([d[:1], d[:-1] + d[1:], d[-1:]])
    t = t / np.maximum(np.hypot(t[:, 0], t[:, 1]), 1e-12)[:, None]
    return np.column_stack([-t[:, 1], t[:, 0]])


def _nearest_on(ln: Mapping[str, np.ndarray], x: float, y: float) -> tuple[float, float, float]:
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


def _project_polyline(px: np.ndarray, py: np.ndarray, ps: np.ndarray, x: float, y: float) -> float:
    dx, dy = np.diff(px), np.diff(py)
    seg2 = np.maximum(dx * dx + dy * dy, 1e-12)
    u = np.clip(((x - px[:-1]) * dx + (y - py[:-1]) * dy) / seg2, 0.0, 1.0)
    k = int(np.argmin((px[:-1] + u * dx - x) ** 2 + (py[:-1] + u * dy - y) ** 2))
    return float(ps[k] + u[k] * (ps[k + 1] - ps[k]))
