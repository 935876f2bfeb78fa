"""CommonRoad's kinematic check, vectorised over samples and time steps, bit for bit the library's.

``ReactivePlanner._check_kinematics`` (commonroad-reactive-planner 2025.1) spends ~85 % of a plan
in a Python loop over every sample's time steps (a few hundred samples x 21 steps per cycle: ~90 ms
per plan; ~30 ms with this module, simulation included: ``deft-gym bench --commonroad``).
:func:`check_kinematics` computes the same quantities with numpy over all samples of one length
at once (rows) and their time steps (columns), in the same order of operations, so every float is
the library's:

- ``+ - * /`` element-wise are the same IEEE operations as on numpy scalars;
- ``x ** 2`` of a numpy or Python scalar is C ``pow`` (not ``x * x``), so it stays ``pow`` here
  (Python floats, one per step); ``math.cos`` stays ``math.cos``; ``np.tan`` / ``np.arctan2`` /
  ``np.round`` run the same ufunc loop on arrays as on scalars;
- a step at standstill in high-velocity mode keeps the previous step's orientation (a carry,
  filled in step order); ``np.argmax(ref_pos > s) - 1`` is ``searchsorted`` with the same -1
  when no reference point lies ahead;
- the first step that violates a constraint (velocity, kappa, yaw rate, kappa rate, acceleration,
  in the library's order) ends the sample and counts that constraint once.

:class:`FastKinematicsMixin` puts it in place of the library's method when neither the library's
multiprocessing nor its drawing of infeasible samples is on (those keep the library's loop).
tests/planner/test_commonroad_kinematics.py runs both on every bundle of whole episodes and
compares every array bit for bit and the rejection counts.

:class:`SharedLateralMixin` builds each lateral polynomial of a bundle once (the library builds it
again for every longitudinal sample of its duration); the test builds every bundle both ways and
compares every coefficient.

:class:`VectorCostMixin` computes the library's ``DefaultCostFunction`` for all feasible samples
of a bundle at once when it sorts them: each sum over a sample's time steps is numpy's sum of that
row (the same pairwise sum as of the sample's own array) and the scalar terms are the library's
expressions on the same numpy scalars, added in its order, so every cost and the order are the
library's (the test sorts every bundle of whole episodes both ways).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

try:  # the extra: pip install -e ".[commonroad]"
    from commonroad.common.util import TWO_PI
    from commonroad_rp.cost_function import DefaultCostFunction
    from commonroad_rp.reactive_planner import _EPS
    from commonroad_rp.trajectories import (
        CartesianSample,
        CurviLinearSample,
        FeasibilityStatus,
        TrajectoryBundle,
    )
except ImportError:  # pragma: no cover - the adapter reports the missing extra
    _EPS, TWO_PI = 1e-5, 2.0 * np.pi
    DefaultCostFunction = TrajectoryBundle = None

#: the library's constraint names in the order ``_check_constraints`` tries them
CONSTRAINTS = ("velocity", "kappa", "yaw_rate", "kappa_dot", "acceleration")


def _pow2(values: np.ndarray) -> np.ndarray:
    """``x ** 2`` as numpy and Python scalars compute it (C ``pow``), element by element."""
    return np.array([x ** 2 for x in values.ravel().tolist()], dtype=float).reshape(values.shape)


def _cos(values: np.ndarray) -> np.ndarray:
    """``math.cos`` element by element (the library's scalar cosine)."""
    return np.array([math.cos(x) for x in values.ravel().tolist()], dtype=float).reshape(values.shape)


def _valid_orientation(angle: np.ndarray) -> np.ndarray:
    """``make_valid_orientation`` element-wise: 2 pi subtracted / added until within +-2 pi."""
    two_pi = TWO_PI
    angle = angle.copy()
    while True:
        over = angle > two_pi
        if not over.any():
            break
        angle[over] = angle[over] - two_pi
    while True:
        under = angle < -two_pi
        if not under.any():
            break
        angle[under] = angle[under] + two_pi
    return angle


def _interpolate_angle(s: np.ndarray, idx: np.ndarray, co: Any) -> np.ndarray:
    """``interpolate_angle(s, ref_pos[i], ref_pos[i + 1], ref_theta[i], ref_theta[i + 1])``."""
    x1, x2 = co.ref_pos[idx], co.ref_pos[idx + 1]
    y1, y2 = co.ref_theta[idx], co.ref_theta[idx + 1]
    return _valid_orientation((y2 - y1) * (s - x1) / (x2 - x1) + y1)


def _first(hit: np.ndarray) -> np.ndarray:
    """Per row, the first column where ``hit`` is true, else the row length."""
    return np.where(hit.any(axis=1), np.argmax(hit, axis=1), hit.shape[1])


def first_violation(planner: Any, v: np.ndarray, kappa_gl: np.ndarray, theta_gl: np.ndarray,
                    a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per sample (rows: samples, columns: time steps): the first step ``_check_constraints``
    rejects and the index in :data:`CONSTRAINTS` of the constraint it counts; ``(n, -1)`` when none."""
    vp, checked, dt = planner.vehicle_params, planner.config.planning.constraints_to_check, planner.dt
    rows, n = v.shape
    kappa_max = np.tan(vp.delta_max) / vp.wheelbase
    step, which = np.full(rows, n), np.full(rows, -1)
    for k, name in enumerate(CONSTRAINTS):  # the library's order: at one step the earlier one counts
        if name not in checked:
            continue
        if name == "velocity":
            hit = v < -_EPS
        elif name == "kappa":
            hit = np.abs(kappa_gl) > kappa_max
        elif name == "yaw_rate":
            yaw_rate = np.zeros((rows, n))
            yaw_rate[:, 1:] = (theta_gl[:, 1:] - theta_gl[:, :-1]) / dt
            hit = np.abs(np.round(yaw_rate, 5)) > kappa_max * v
        elif name == "kappa_dot":
            steering = np.arctan2(vp.wheelbase * kappa_gl, 1.0)
            kappa_dot_max = vp.v_delta_max / (vp.wheelbase * _pow2(_cos(steering)))
            kappa_dot = np.zeros((rows, n))
            kappa_dot[:, 1:] = (kappa_gl[:, 1:] - kappa_gl[:, :-1]) / dt
            hit = np.abs(kappa_dot) > kappa_dot_max
        else:
            a_max = np.where(v > vp.v_switch, vp.a_max * vp.v_switch / v, vp.a_max)
            hit = ~((-vp.a_max <= a) & (a <= a_max))
        first = _first(hit)
        earlier = first < step
        step[earlier], which[earlier] = first[earlier], k
    return step, which


def _polynomials(polys: list[Any], x: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``calc_position``, ``calc_velocity``, ``calc_acceleration`` of the polynomials (rows) at the
    powers ``x = [tau, tau^2, .., tau^5]`` (rows, or one row for all), in the library's order of
    operations."""
    c = np.array([p.coeffs for p in polys])
    c0, c1, c2, c3, c4, c5 = (c[:, i:i + 1] for i in range(6))
    t, t2, t3, t4, t5 = x
    pos = c0 + c1 * t + c2 * t2 + c3 * t3 + c4 * t4 + c5 * t5
    vel = c1 + 2. * c2 * t + 3. * c3 * t2 + 4. * c4 * t3 + 5. * c5 * t4
    acc = 2 * c2 + 6 * c3 * t + 12 * c4 * t2 + 20 * c5 * t3
    return pos, vel, acc


def _powers(t: np.ndarray) -> list[np.ndarray]:
    t2 = np.square(t)
    t3 = t2 * t
    t4 = np.square(t2)
    return [t, t2, t3, t4, t4 * t]


def check_kinematics(planner: Any, trajectories: list[Any]) -> tuple[list[Any], list[Any]]:
    """The library's ``_check_kinematics(trajectories)`` (no multiprocessing, no drawing of
    infeasible samples): ``(feasible, [])`` in the bundle's order, each feasible sample's Cartesian
    and curvilinear states set (and enlarged to the horizon), the planner's rejection counts updated.
    Samples of one length are computed together (rows of 2-d arrays)."""
    dt = planner.dt
    times: dict[float, np.ndarray] = {}
    groups: dict[int, list[int]] = {}
    for j, trajectory in enumerate(trajectories):
        tau = trajectory.trajectory_long.delta_tau
        if tau not in times:
            times[tau] = np.arange(0, np.round(tau + dt, 5), dt)
        groups.setdefault(len(times[tau]), []).append(j)
    done: dict[int, Any] = {}
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for traj_len, members in groups.items():
            t = next(v for v in times.values() if len(v) == traj_len)
            done.update(_check_group(planner, [trajectories[j] for j in members], members, t))
    return [done[j] for j in sorted(done)], []


def _check_group(planner: Any, group: list[Any], members: list[int], t: np.ndarray) -> dict[int, Any]:
    """:func:`check_kinematics` for samples of one length (``t``: their time steps [s])."""
    co, dt, n_steps = planner._co, planner.dt, planner.N + 1
    reasons = planner._infeasible_reason_dict
    rows, n = len(group), len(t)
    s, s_velocity, s_acceleration = np.zeros((rows, n_steps)), np.zeros((rows, n_steps)), np.zeros((rows, n_steps))
    d, d_velocity, d_acceleration = np.zeros((rows, n_steps)), np.zeros((rows, n_steps)), np.zeros((rows, n_steps))
    s[:, :n], s_velocity[:, :n], s_acceleration[:, :n] = _polynomials([g.trajectory_long for g in group], _powers(t))
    if not planner._low_vel_mode:
        lat_x = _powers(t)
    else:
        s1 = s[:, :n] - s[:, :1]
        s2 = np.square(s1)
        s3 = s2 * s1
        s4 = np.square(s2)
        lat_x = [s1, s2, s3, s4, s4 * s1]
    d[:, :n], d_velocity[:, :n], d_acceleration[:, :n] = _polynomials([g.trajectory_lat for g in group], lat_x)
    s_velocity[np.abs(s_velocity) < _EPS] = 0.0
    d_velocity[np.abs(d_velocity) < _EPS] = 0.0
    # the library's quick pre-filter
    fast_acc = np.any(np.abs(s_acceleration) > planner.vehicle_params.a_max, axis=1)
    backwards = ~fast_acc & np.any(s_velocity < -_EPS, axis=1)
    reasons["acceleration"] += int(fast_acc.sum())
    reasons["velocity"] += int(backwards.sum())
    keep = np.flatnonzero(~(fast_acc | backwards))
    if not len(keep):
        return {}
    s, s_velocity, s_acceleration = s[keep], s_velocity[keep], s_acceleration[keep]
    d, d_velocity, d_acceleration = d[keep], d_velocity[keep], d_acceleration[keep]
    sv, sa, dv, da, ss, dd = (s_velocity[:, :n], s_acceleration[:, :n], d_velocity[:, :n], d_acceleration[:, :n],
                              s[:, :n], d[:, :n])
    moving = sv > 0.001
    if not planner._low_vel_mode:
        dp = np.where(moving, dv / sv, 0.0)
        ddot = da - dp * sa
        dpp = np.where(moving, ddot / _pow2(sv), 0.0)
        along = moving
    else:
        dp, dpp = dv, da
        along = np.ones_like(moving)
    # np.argmax(ref_pos > s) - 1: -1 when no reference point lies ahead
    k = np.searchsorted(co.ref_pos, ss, side="right")
    idx = np.where(k < len(co.ref_pos), k - 1, -1)
    s_lambda = (ss - co.ref_pos[idx]) / (co.ref_pos[idx + 1] - co.ref_pos[idx])
    ref_angle = _interpolate_angle(ss, idx, co)
    theta_cl = np.where(along, np.arctan2(dp, 1.0), 0.0)
    theta_gl = np.where(along, theta_cl + ref_angle, 0.0)
    if not along.all():  # standstill in high-velocity mode: the orientation is carried, step by step
        for i in range(n):
            still = ~along[:, i]
            if still.any():
                theta_gl[still, i] = planner.x_0.orientation if i == 0 else theta_gl[still, i - 1]
                theta_cl[still, i] = theta_gl[still, i] - ref_angle[still, i]
    k_r = (co.ref_curv[idx + 1] - co.ref_curv[idx]) * s_lambda + co.ref_curv[idx]
    k_r_d = (co.ref_curv_d[idx + 1] - co.ref_curv_d[idx]) * s_lambda + co.ref_curv_d[idx]
    one_kr_d = 1 - k_r * dd
    cos_theta = _cos(theta_cl)
    tan_theta = np.tan(theta_cl)
    ratio = cos_theta / one_kr_d
    kappa = (dpp + (k_r * dp + k_r_d * dd) * tan_theta) * cos_theta * _pow2(ratio) + ratio * k_r
    vel = sv * (one_kr_d / cos_theta)
    acc = sa * one_kr_d / cos_theta + (_pow2(sv) / cos_theta) * (
        one_kr_d * tan_theta * (kappa * one_kr_d / cos_theta - k_r) - (k_r_d * dd + k_r * dp))
    _, which = first_violation(planner, vel, kappa, theta_gl, acc)
    for r in np.flatnonzero(which >= 0).tolist():
        reasons[CONSTRAINTS[which[r]]] += 1
        group[keep[r]].feasibility_label = FeasibilityStatus.INFEASIBLE_KINEMATIC
    ok = np.flatnonzero(which < 0)
    x, y, inside = to_cartesian(co, ss[ok], dd[ok], n_steps)
    ok, x, y = ok[inside], x[inside], y[inside]
    full = {}
    for name, part in (("theta_gl", theta_gl), ("theta_cl", theta_cl), ("kappa", kappa), ("v", vel), ("a", acc)):
        full[name] = np.zeros((len(ok), n_steps))
        full[name][:, :n] = part[ok]
    cart = {"x": x, "y": y, "theta": full["theta_gl"], "v": full["v"], "a": full["a"], "kappa": full["kappa"]}
    cart["kappa_dot"] = np.concatenate([np.zeros((len(ok), 1)), np.diff(full["kappa"], axis=1)], axis=1)
    curv = {"s": s[ok], "d": d[ok], "theta": full["theta_cl"], "ss": s_velocity[ok], "sss": s_acceleration[ok],
            "dd": d_velocity[ok], "ddd": d_acceleration[ok]}
    if n_steps > n:
        _enlarge(cart, curv, n, dt)
    out: dict[int, Any] = {}
    for r, row in enumerate(ok.tolist()):
        trajectory = group[keep[row]]
        trajectory.feasibility_label = FeasibilityStatus.FEASIBLE
        trajectory.cartesian = CartesianSample(*(cart[k][r] for k in ("x", "y", "theta", "v", "a", "kappa")),
                                               kappa_dot=cart["kappa_dot"][r], current_time_step=n_steps)
        trajectory.curvilinear = CurviLinearSample(curv["s"][r], curv["d"][r], curv["theta"][r],
                                                   ss=curv["ss"][r], sss=curv["sss"][r], dd=curv["dd"][r],
                                                   ddd=curv["ddd"][r], current_time_step=n_steps)
        out[members[keep[row]]] = trajectory
    return out


def to_cartesian(co: Any, s: np.ndarray, d: np.ndarray, columns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``co.convert_to_cartesian_coords(s, d)`` of each row's points in step order: ``(x, y,
    inside)``, ``x`` and ``y`` [m] with ``columns`` columns (zero beyond the row's points);
    ``inside`` is False for a row with a point outside the projection domain (the call gave None),
    whose points after that one are not converted (the library's loop stops the sample there)."""
    rows, n = s.shape
    x, y = np.zeros((rows, columns)), np.zeros((rows, columns))
    inside = np.ones(rows, bool)
    convert = co.convert_to_cartesian_coords
    for r, (s_row, d_row) in enumerate(zip(s.tolist(), d.tolist())):
        points = []
        for s_i, d_i in zip(s_row, d_row):
            pos = convert(s_i, d_i)
            if pos is None:
                inside[r] = False
                break
            points.append(pos)
        else:
            if points:
                xy = np.array(points)
                x[r, :n], y[r, :n] = xy[:, 0], xy[:, 1]
    return x, y, inside


def _enlarge(cart: dict[str, np.ndarray], curv: dict[str, np.ndarray], n: int, dt: float) -> None:
    """``CartesianSample.enlarge`` and ``CurviLinearSample.enlarge`` of rows of ``n`` computed steps
    (in place, the library's order of operations): constant acceleration from the last step, no
    negative speeds, constant orientation and curvature."""
    last = n - 1
    t = np.arange(1, cart["x"].shape[1] - n + 1, 1) * dt
    a, v = cart["a"], cart["v"]
    a[:, n:] = a[:, last:last + 1]
    v_temp = v[:, last:last + 1] + t * a[:, -1:]
    v_temp = v_temp * np.greater_equal(v_temp, 0)
    v[:, n:] = v_temp
    for name in ("theta", "kappa", "kappa_dot"):
        cart[name][:, n:] = cart[name][:, last:last + 1]
    theta_last = cart["theta"][:, last].tolist()
    cos_last = np.array([math.cos(h) for h in theta_last])[:, None]
    sin_last = np.array([math.sin(h) for h in theta_last])[:, None]
    cart["x"][:, n:] = cart["x"][:, last:last + 1] + np.cumsum(dt * v_temp * cos_last, axis=1)
    cart["y"][:, n:] = cart["y"][:, last:last + 1] + np.cumsum(dt * v_temp * sin_last, axis=1)
    s_dot_temp = curv["ss"][:, last:last + 1] + t * curv["sss"][:, -1:]
    s_dot_temp = s_dot_temp * np.greater_equal(s_dot_temp, 0)
    curv["ss"][:, n:] = s_dot_temp
    curv["dd"][:, n:] = curv["dd"][:, last:last + 1] + t * curv["ddd"][:, -1:]
    for name in ("sss", "ddd", "theta"):
        curv[name][:, n:] = curv[name][:, last:last + 1]
    curv["s"][:, n:] = curv["s"][:, last:last + 1] + t * curv["ss"][:, last:last + 1]
    curv["d"][:, n:] = curv["d"][:, last:last + 1] + t * curv["dd"][:, last:last + 1]


class FastKinematicsMixin:
    """A ``ReactivePlanner`` whose ``_check_kinematics`` is :func:`check_kinematics` (same results;
    plans take 3.4x less CPU) unless the library's multiprocessing or its drawing of infeasible
    samples is on."""

    def _check_kinematics(self, trajectories: list[Any], queue_1: Any = None, queue_2: Any = None) -> Any:
        if self.config.debug.multiproc or self._draw_traj_set:  # type: ignore[attr-defined]
            return super()._check_kinematics(trajectories, queue_1, queue_2)  # type: ignore[misc]
        return check_kinematics(self, trajectories)


class SharedLateralMixin:
    """A ``ReactivePlanner`` whose trajectory bundle builds each lateral polynomial once.

    The library's ``generate_trajectories_at_level`` builds the lateral trajectory of a
    (duration, initial lateral state, end offset) again for every longitudinal sample of that
    duration - about 6 times per plan in high-velocity mode (a plan takes 1-10 % less CPU with
    them shared: docs/planner.md). Here the samples of one bundle share it: nothing writes to a
    sample's lateral trajectory (the library's evaluation cache inside it holds the same values for
    every sample), so the bundle has the same samples with the same numbers in the same order. Keys
    are the arguments' bytes (0.0 and -0.0 stay apart)."""

    def _create_trajectory_bundle(self, x_0_lon: Any, x_0_lat: Any, samp_level: int) -> Any:
        space = self.sampling_space  # type: ignore[attr-defined]
        build = space._generate_lat_trajectory
        built: dict[tuple[Any, ...], Any] = {}

        def lateral(delta_tau: Any, x_0: np.ndarray, x_d: np.ndarray) -> Any:
            key = (type(delta_tau), float(delta_tau).hex(), x_0.dtype.str, x_0.shape, x_0.tobytes(),
                   x_d.dtype.str, x_d.shape, x_d.tobytes())
            trajectory = built.get(key)
            if trajectory is None:
                trajectory = built[key] = build(delta_tau=delta_tau, x_0=x_0, x_d=x_d)
            return trajectory

        space._generate_lat_trajectory = lateral  # the instance's, in front of the class's static method
        try:
            return super()._create_trajectory_bundle(x_0_lon, x_0_lat, samp_level)  # type: ignore[misc]
        finally:
            del space._generate_lat_trajectory


def default_costs(cost_function: Any, trajectories: list[Any]) -> list[Any] | None:
    """``DefaultCostFunction.evaluate`` of each sample (numpy float64, the library's floats), or
    None when the samples' arrays are not all of one length (then the library evaluates them)."""
    cart = [t.cartesian for t in trajectories]
    curv = [t.curvilinear for t in trajectories]
    try:
        a, v = np.array([c.a for c in cart], dtype=float), np.array([c.v for c in cart], dtype=float)
        s, d = np.array([c.s for c in curv], dtype=float), np.array([c.d for c in curv], dtype=float)
        theta = np.array([c.theta for c in curv], dtype=float)
    except ValueError:  # ragged
        return None
    if not (a.ndim == v.ndim == s.ndim == d.ndim == theta.ndim == 2) or a.shape[1] == 0:
        return None
    cf = cost_function
    ds, dd, dsp = cf.desired_s, cf.desired_d, cf.desired_speed
    # the sums over time steps, one row per sample; the scalar terms per sample below
    acc = np.sum((cf.w_a * a) ** 2, axis=1)
    speed = np.sum((5 * (v - dsp)) ** 2, axis=1) if dsp is not None else None
    along = np.sum((0.25 * (ds - s)) ** 2, axis=1) if ds is not None else None
    lat = np.sum((0.25 * (dd - d)) ** 2, axis=1)
    orient = np.sum((0.25 * np.abs(theta)) ** 2, axis=1)
    mid = int(v.shape[1] / 2)
    out = []
    for r in range(len(trajectories)):
        costs = 0.0
        costs += acc[r]
        if dsp is not None:
            vr = v[r]
            costs += speed[r] + (50 * (vr[-1] - dsp) ** 2) + (100 * (vr[mid] - dsp) ** 2)
        if ds is not None:
            costs += along[r] + (20 * (ds - s[r][-1])) ** 2
        costs += lat[r] + (20 * (dd - d[r][-1])) ** 2
        costs += orient[r] + (5 * (np.abs(theta[r][-1]))) ** 2
        out.append(costs)
    return out


def sort_bundle(bundle: Any) -> None:
    """``TrajectoryBundle.sort`` with :func:`default_costs` when the bundle's cost function is the
    library's ``DefaultCostFunction`` itself (another one: the library's loop)."""
    if bundle._is_sorted:
        return
    trajectories, cost_function = bundle._trajectory_bundle, bundle._cost_function
    costs = (default_costs(cost_function, trajectories)
             if trajectories and type(cost_function) is DefaultCostFunction else None)
    if costs is None:
        TrajectoryBundle.sort(bundle)
        return
    for trajectory, cost in zip(trajectories, costs):  # what the ``cost`` setter stores
        trajectory._cost, trajectory._cost_function = cost, cost_function
    trajectories.sort(key=lambda x: x.cost)
    bundle._is_sorted = True


class VectorCostMixin:
    """A ``ReactivePlanner`` whose bundles sort by :func:`default_costs` (the same costs and order;
    sorting took 17 % of a plan's CPU with the library's loop over samples)."""

    def _create_trajectory_bundle(self, x_0_lon: Any, x_0_lat: Any, samp_level: int) -> Any:
        bundle = super()._create_trajectory_bundle(x_0_lon, x_0_lat, samp_level)  # type: ignore[misc]
        bundle.sort = lambda: sort_bundle(bundle)  # the instance's, in front of the class's method
        return bundle
