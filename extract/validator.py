"""The Trajectory Validator: whether a reproduced planning output is the recorded one.

*Reproduced means the whole output*: every trajectory field the planner publishes (``t``,
``x``, ``y``, ``v``, ``heading``, ``a`` and any other) and the decision. Positions are judged by
the paper's lock-step Euclidean distance (eq. 2) against the threshold theta [m]: the
reproduced trajectory is interpolated at the recorded one's timestamps and the point distances
are combined as sqrt(sum of squares) (:func:`deft_gym.planner.trajectory.lsed`; discrete
Frechet and Hausdorff can be selected instead). Every other field has a tolerance of its own
(:class:`Tolerances`; 0 by default: equal numbers), compared point by point (headings as
wrapped angle differences); the decision's numbers have the ``decision`` tolerance and its other
values must be equal. Bit-identical outputs short-cut without numpy, which is what almost every
check of the input search is.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from deft_gym.bus.messages import non_finite_field
from deft_gym.planner.trajectory import MEASURES

#: thresholds every summary reports [m]
SUMMARY_THETAS = (0.0, 0.1, 1.0, 7.0)
#: the trajectory fields judged together by the position measure (theta)
POSITION = ("x", "y")
#: fields whose deviation is an angle difference (wrapped to [-pi, pi))
ANGLES = ("heading",)

Measure = Callable[[Mapping[str, Any], Mapping[str, Any]], float]


def measure_fn(name: str) -> Measure:
    """The distance function called ``name`` (lsed, frechet, hausdorff)."""
    try:
        return MEASURES[name]
    except KeyError:
        raise ValueError(f"unknown measure {name!r}; expected one of {sorted(MEASURES)}") from None


def _traj(payload: Mapping[str, Any]) -> Mapping[str, Any] | None:
    tr = payload.get("trajectory") if isinstance(payload, Mapping) else None
    return tr if isinstance(tr, Mapping) else None


def nan_equal(a: Any, b: Any) -> bool:
    """``a == b`` for plain JSON-like values, except that NaN equals NaN (a planner that gives
    the recorded NaN again reproduces it; a NaN output is a finding, not a miss)."""
    if a == b:
        return True
    if isinstance(a, float) and isinstance(b, float):
        return a != a and b != b
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(nan_equal(x, y) for x, y in zip(a, b))
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return a.keys() == b.keys() and all(nan_equal(a[k], b[k]) for k in a)
    return False


def non_finite(payload: Any) -> bool:
    """Whether a planning output's trajectory holds a NaN or an infinity."""
    tr = _traj(payload)
    if tr is None:
        return False
    return any(non_finite_field(vals) is not None for vals in tr.values() if isinstance(vals, list))


def identical(expected: Mapping[str, Any], actual: Mapping[str, Any] | None) -> bool:
    """Same timestamps and positions, bit for bit (what the position measure short-cuts on;
    NaN equals NaN)."""
    if actual is None:
        return False
    a, b = _traj(expected), _traj(actual)
    return (a is not None and b is not None and nan_equal(a["x"], b["x"]) and nan_equal(a["y"], b["y"])
            and nan_equal(a["t"], b["t"]))


def same_output(expected: Mapping[str, Any], actual: Mapping[str, Any] | None) -> bool:
    """The whole output equal: every trajectory field and the decision (numbers compared as
    numbers; NaN equals NaN, as in :func:`compare`)."""
    if actual is None:
        return False
    a, b = _traj(expected), _traj(actual)
    return a is not None and nan_equal(a, b) and nan_equal(expected.get("decision"), actual.get("decision"))


def distance(expected: Mapping[str, Any], actual: Mapping[str, Any] | None, measure: Measure | str = "lsed") -> float:
    """Position distance [m] of ``actual`` from ``expected`` (inf when there is no usable output)."""
    if actual is None:
        return math.inf
    if identical(expected, actual):
        return 0.0
    fn = measure_fn(measure) if isinstance(measure, str) else measure
    try:
        d = float(fn(expected, actual))
    except (KeyError, TypeError, ValueError):
        return math.inf
    return d if math.isfinite(d) else math.inf


# -- whole-output comparison ---------------------------------------------------------------------
@dataclass(frozen=True)
class Tolerances:
    """How far each output field may be from the recorded one: ``theta`` [m] for positions
    (the measure), ``fields`` per trajectory field in its own unit (``v``: m/s, ``heading``:
    rad, ``t``: s, ...), ``decision`` for the decision's numbers. Unlisted fields: ``default``
    (0 = equal numbers)."""

    theta: float = 0.0
    fields: Mapping[str, float] = field(default_factory=dict)
    decision: float = 0.0
    default: float = 0.0

    def of(self, name: str) -> float:
        """Tolerance of trajectory field ``name``."""
        return float(self.fields.get(name, self.default))

    def as_dict(self) -> dict[str, Any]:
        """Plain form (frames file header, summary)."""
        return {"theta": self.theta, "fields": dict(self.fields), "decision": self.decision, "default": self.default}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, theta: float | None = None) -> Tolerances:
        """Inverse of :meth:`as_dict` (``theta`` given separately wins; missing keys: defaults)."""
        d = dict(d or {})
        return cls(float(theta if theta is not None else d.get("theta", 0.0)), dict(d.get("fields") or {}),
                   float(d.get("decision", 0.0)), float(d.get("default", 0.0)))

    def __post_init__(self) -> None:
        for name, v in [("theta", self.theta), ("decision", self.decision), ("default", self.default),
                        *((f"fields.{k}", v) for k, v in self.fields.items())]:
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"tolerance {name} must be a finite number >= 0, got {v!r}")


def parse_tolerances(items: list[str] | None, theta: float = 0.0) -> Tolerances:
    """Tolerances from ``FIELD=VALUE`` strings (``v=0.01``, ``heading=1e-6``, ``decision=0.5``,
    ``default=1e-9``), as the CLI takes them; ValueError names the bad item."""
    fields: dict[str, float] = {}
    decision = default = 0.0
    for item in items or []:
        name, sep, value = item.partition("=")
        try:
            v = float(value)
        except ValueError:
            v = math.nan
        if not sep or not name or not math.isfinite(v) or v < 0:
            raise ValueError(f"tolerance {item!r}: expected FIELD=VALUE with a number >= 0 (e.g. v=0.01)")
        if name in POSITION:
            raise ValueError(f"tolerance {item!r}: positions are judged by theta (--theta), not per field")
        if name == "decision":
            decision = v
        elif name == "default":
            default = v
        else:
            fields[name] = v
    return Tolerances(theta, fields, decision, default)


@dataclass
class FieldDiff:
    """One output field beyond its tolerance.

    ``field``: ``position`` (x, y by the measure), a trajectory field (``v``) or a decision
    entry (``decision.behavior``); ``deviation``: its largest deviation (inf: missing, another
    length or type); ``point``: where it is largest, with the recorded and replayed values
    there at full precision (whole values for decision entries)."""

    field: str
    deviation: float
    tolerance: float
    point: int | None = None
    time: float | None = None
    recorded: Any = None
    replayed: Any = None
    note: str = ""

    def text(self) -> str:
        """One line: field, deviation, where, recorded vs replayed (``repr``: every digit)."""
        if self.field == "position":
            head = f"position: {self.note} {self.deviation!r} m > theta {self.tolerance!r} m"
        elif self.field.startswith("decision"):
            head = self.field
        else:
            head = f"{self.field}: largest deviation {self.deviation!r} > tolerance {self.tolerance!r}"
        if self.note and self.field != "position":
            head += f" ({self.note})"
        if self.point is not None:
            when = f" (t={self.time!r} s)" if self.time is not None else ""
            head += f" at point {self.point}{when}"
        return head + f": recorded {self.recorded!r}, replayed {self.replayed!r}"


@dataclass
class Comparison:
    """A replayed output against the recorded one: the position distance [m] by the measure,
    the largest deviation of every compared field, and the fields beyond their tolerance."""

    distance: float
    deviations: dict[str, float]
    diffs: list[FieldDiff]

    @property
    def reproduced(self) -> bool:
        """Every field within its tolerance (positions within theta)."""
        return not self.diffs

    def text(self) -> str:
        """The differing fields, one per line."""
        return "\n".join(d.text() for d in self.diffs)


def compare(expected: Mapping[str, Any], actual: Mapping[str, Any] | None, tol: Tolerances | None = None,
            measure: Measure | str = "lsed") -> Comparison:
    """Compare the whole replayed output with the recorded one (see the module docstring)."""
    tol = tol or Tolerances()
    if actual is None:
        return Comparison(math.inf, {"output": math.inf},
                          [FieldDiff("output", math.inf, 0.0, note="the planner returned no output",
                                     recorded="an output", replayed=None)])
    exp_tr, act_tr = _traj(expected) or {}, _traj(actual) or {}
    if same_output(expected, actual):
        keys = [*exp_tr, *(f"decision.{k}" for k, _ in _leaves(expected.get("decision")))]
        return Comparison(0.0, dict.fromkeys(["position", *(k for k in keys if k not in POSITION)], 0.0), [])
    d = distance(expected, actual, measure)
    deviations: dict[str, float] = {"position": d}
    diffs: list[FieldDiff] = []
    if d > tol.theta:
        diffs.append(_position_diff(exp_tr, act_tr, d, tol.theta, measure))
    t_rec = exp_tr.get("t")
    for name in [*exp_tr, *(k for k in act_tr if k not in exp_tr)]:
        if name in POSITION:
            continue
        fd = _series_diff(name, exp_tr.get(name), act_tr.get(name), tol.of(name), t_rec)
        deviations[name] = fd.deviation
        if fd.deviation > fd.tolerance:
            diffs.append(fd)
    for fd in _decision_diffs(expected.get("decision"), actual.get("decision"), tol.decision):
        deviations[fd.field] = fd.deviation
        if fd.deviation > fd.tolerance:
            diffs.append(fd)
    return Comparison(d, deviations, diffs)


def _floats(values: Any) -> np.ndarray | None:
    if not isinstance(values, list | tuple):
        return None
    try:
        a = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        return None
    return a if a.ndim == 1 else None


def _deviation(rec: np.ndarray, rep: np.ndarray, angle: bool) -> np.ndarray:
    """|recorded - replayed| per point: 0 where equal (NaN == NaN, inf == inf), inf where only
    one is NaN or the difference is not finite, and never 0 where they differ (headings 2 pi
    apart are the same direction but not the same number)."""
    with np.errstate(invalid="ignore", over="ignore"):
        diff = rec - rep
        if angle:
            diff = (diff + math.pi) % (2 * math.pi) - math.pi
        dev = np.abs(diff)
    same = (rec == rep) | (np.isnan(rec) & np.isnan(rep))
    dev = np.where(np.isfinite(dev), np.maximum(dev, _TINY), math.inf)
    return np.where(same, 0.0, dev)


_TINY = float(np.finfo(float).tiny)


def _series_diff(name: str, rec: Any, rep: Any, tol: float, t_rec: Any) -> FieldDiff:
    if rec == rep and rec is not None:
        return FieldDiff(name, 0.0, tol)
    if rec is None or rep is None:
        where = "replayed" if rep is None else "recorded"
        return FieldDiff(name, math.inf, tol, note=f"missing in the {where} output",
                         recorded=rec if rec is None else f"{_kind(rec)}", replayed=rep if rep is None else _kind(rep))
    a, b = _floats(rec), _floats(rep)
    if a is None or b is None:
        return FieldDiff(name, math.inf, tol, note="not number series", recorded=rec, replayed=rep)
    if len(a) != len(b):
        return FieldDiff(name, math.inf, tol, note=f"{len(a)} recorded points, {len(b)} replayed",
                         recorded=_kind(rec), replayed=_kind(rep))
    dev = _deviation(a, b, name in ANGLES)
    k = int(dev.argmax()) if dev.size else 0
    if not dev.size or dev[k] == 0.0:
        return FieldDiff(name, 0.0, tol)
    return FieldDiff(name, float(dev[k]), tol, k, _at(t_rec, k), rec[k], rep[k])


def _position_diff(exp_tr: Mapping[str, Any], act_tr: Mapping[str, Any], d: float, theta: float,
                   measure: Measure | str) -> FieldDiff:
    """Where the positions differ most (point by point; the replayed track interpolated at the
    recorded timestamps when they differ)."""
    name = measure if isinstance(measure, str) else getattr(measure, "__name__", "distance")
    try:
        t, x, y = (np.asarray(exp_tr[k], dtype=float) for k in ("t", "x", "y"))
        t2, x2, y2 = (np.asarray(act_tr[k], dtype=float) for k in ("t", "x", "y"))
        if len(t) == len(t2) and np.array_equal(t, t2):
            k_x, k_y = x2, y2
            rep = lambda k: (act_tr["x"][k], act_tr["y"][k])  # noqa: E731 - the exact replayed values
        else:
            k_x, k_y = np.interp(t, t2, x2), np.interp(t, t2, y2)
            rep = lambda k: (float(k_x[k]), float(k_y[k]))  # noqa: E731
        dev = np.hypot(_deviation(x, k_x, False), _deviation(y, k_y, False))
        k = int(np.nan_to_num(dev, nan=math.inf).argmax())
        return FieldDiff("position", d, theta, k, float(t[k]), (exp_tr["x"][k], exp_tr["y"][k]), rep(k),
                         note=name)
    except (KeyError, TypeError, ValueError, IndexError):
        return FieldDiff("position", d, theta, note=name, recorded="x/y series", replayed="no usable x/y series")


def _leaves(value: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """``(dotted key, value)`` of a decision's leaves (lists are leaves)."""
    if isinstance(value, Mapping):
        for k, v in value.items():
            yield from _leaves(v, f"{prefix}.{k}" if prefix else str(k))
    elif prefix:
        yield prefix, value


def _decision_diffs(rec: Any, rep: Any, tol: float) -> list[FieldDiff]:
    if rec == rep:
        return []
    if not isinstance(rec, Mapping) or not isinstance(rep, Mapping):
        return [FieldDiff("decision", math.inf, tol, recorded=rec, replayed=rep)]
    a, b = dict(_leaves(rec)), dict(_leaves(rep))
    out = []
    for key in [*a, *(k for k in b if k not in a)]:
        va, vb = a.get(key, _MISSING), b.get(key, _MISSING)
        if va == vb and va is not _MISSING:
            out.append(FieldDiff(f"decision.{key}", 0.0, tol))
            continue
        if _number(va) and _number(vb):
            dev = float(_deviation(np.array([va], dtype=float), np.array([vb], dtype=float), False)[0])
        else:
            dev = math.inf
        out.append(FieldDiff(f"decision.{key}", dev, tol, recorded=va, replayed=vb))
    return out


class _Missing:
    def __repr__(self) -> str:
        return "<missing>"


_MISSING = _Missing()


def _number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _kind(v: Any) -> str:
    return f"{type(v).__name__} of {len(v)}" if isinstance(v, list | tuple) else type(v).__name__


def _at(series: Any, k: int) -> float | None:
    try:
        return float(series[k])
    except (TypeError, ValueError, IndexError, KeyError):
        return None


def field_summary(comparisons: list[Comparison], tol: Tolerances) -> dict[str, dict[str, Any]]:
    """Per field: its tolerance, how many frames have it within tolerance, its largest
    deviation and the first frame beyond tolerance (the ``fields`` entry of ``summary.json``)."""
    out: dict[str, dict[str, Any]] = {}
    for i, c in enumerate(comparisons):
        beyond = {fd.field for fd in c.diffs}
        for name, dev in c.deviations.items():
            row = out.setdefault(name, {"tolerance": _tol_of(name, tol), "frames": 0, "reproduced": 0,
                                        "max_deviation": 0.0, "first_beyond": None})
            row["frames"] += 1
            row["reproduced"] += name not in beyond
            row["max_deviation"] = max(row["max_deviation"], dev)
            if name in beyond and row["first_beyond"] is None:
                row["first_beyond"] = i
    for row in out.values():
        if not math.isfinite(row["max_deviation"]):
            row["max_deviation"] = None  # JSON: inf is "missing or another shape"
    return out


def _tol_of(name: str, tol: Tolerances) -> float:
    if name == "position":
        return tol.theta
    if name.startswith("decision"):
        return tol.decision
    return 0.0 if name == "output" else tol.of(name)


def reproduced_counts(distances: list[float], thetas: tuple[float, ...] = SUMMARY_THETAS) -> dict[str, int]:
    """How many distances are within each threshold, keyed ``"0"``, ``"0.1"``, ``"1"``, ``"7"``."""
    return {theta_key(t): sum(1 for d in distances if d <= t) for t in thetas}


def theta_key(theta: float) -> str:
    """``0.0 -> "0"``, ``0.1 -> "0.1"``: compact JSON keys for thresholds."""
    return f"{theta:g}"
