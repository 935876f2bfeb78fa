"""Safety invariants written in YAML, evaluated online (on the bus) and offline (on a log).

An invariant is evaluated at every message of its ``on`` role (or once at the end for
``on: outcome``) with the latest *original* payload of every role in scope - what each module
said, before any interception - so injecting NaN into localization does not trivially "violate"
a localization check, while the planner's and the controller's reactions to it are judged.

.. code-block:: yaml

    params: {max_decel: 8.0}
    invariants:
      - name: control_accel_bounds          # simple: a bound on one output
        kind: simple
        on: control
        assert: -params.max_decel <= control.acceleration <= 3.0
      - name: speed_limit                   # complex: multi-variable and temporal
        kind: complex
        on: chassis
        requires: [localization]
        never: not (chassis.speed <= lane_speed_limit(localization.x, localization.y, localization.heading) + 2.0)
        for: 1.0

Keys: ``assert`` (must hold at every evaluation) or ``never`` (must not hold for longer than
``for`` seconds, 0 = at all); ``let`` names sub-expressions, and ``prev.<name>`` is their value at
the previous evaluation (None at the first); ``where`` restricts evaluation; ``requires`` lists
roles that must have been seen. Names in scope: every topic role, ``msg`` (the evaluated
message), ``t`` (its publish time [s]), ``prev``, ``params``, ``outcome`` and the functions of
:mod:`.expr` plus ``lane_speed_limit``, ``stop_line``, ``on_road`` (:mod:`.mapquery`) and
``light_color(light_id)``. An expression that raises counts as a violation (the output could
not be judged valid).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from deft_gym.bus.messages import NS_PER_S, ROLES
from deft_gym.config import CONFIG_DIR, ConfigError, load_yaml, validate
from deft_gym.robustness.expr import BUILTINS, Expr, ExprError, View, wrap
from deft_gym.robustness.mapquery import MapQuery

DEFAULT_INVARIANTS = CONFIG_DIR / "invariants" / "default.yaml"
SCOPE_ROLES = (*ROLES, "outcome")
MAP_FUNCTIONS = ("lane_speed_limit", "stop_line", "on_road", "light_color")


class InvariantSpec(BaseModel):
    """One invariant as written in YAML."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    name: str = Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")
    kind: Literal["simple", "complex"] = "simple"
    description: str = ""
    on: str
    requires: list[str] = Field(default_factory=list)
    where: str | None = None
    let: dict[str, str] = Field(default_factory=dict)
    assert_: str | None = Field(default=None, alias="assert")
    never: str | None = None
    for_: float = Field(default=0.0, ge=0.0, alias="for", description="seconds a `never` condition may last")

    @model_validator(mode="after")
    def _one_check(self) -> InvariantSpec:
        if (self.assert_ is None) == (self.never is None):
            raise ValueError("give exactly one of 'assert' and 'never'")
        for role in [self.on, *self.requires]:
            if role not in SCOPE_ROLES:
                raise ValueError(f"unknown role {role!r}; expected one of {list(SCOPE_ROLES)}")
        if self.for_ and self.assert_ is not None:
            raise ValueError("'for' applies to 'never' conditions only")
        return self


class InvariantFile(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    params: dict[str, Any] = Field(default_factory=dict)
    invariants: list[InvariantSpec]


@dataclass
class Invariant:
    """A compiled invariant."""

    spec: InvariantSpec
    lets: list[tuple[str, Expr]]
    where: Expr | None
    check: Expr

    @property
    def name(self) -> str:
        return self.spec.name


@dataclass
class InvariantSet:
    """The invariants of one YAML file, compiled."""

    invariants: list[Invariant]
    params: dict[str, Any] = field(default_factory=dict)
    source: str = ""

    @property
    def names(self) -> list[str]:
        return [i.name for i in self.invariants]


def load_invariants(path: Path | str | None = None) -> InvariantSet:
    """Read, validate and compile an invariants file; errors name the file and the field."""
    path = Path(path) if path else DEFAULT_INVARIANTS
    data = load_yaml(path)
    if isinstance(data, dict) and isinstance(data.get("invariants"), list):
        # YAML 1.1 reads the key `on` as the boolean True; take it back
        data["invariants"] = [{("on" if k is True else k): v for k, v in d.items()} if isinstance(d, dict) else d
                              for d in data["invariants"]]
    spec = validate(InvariantFile, data, path)
    out = []
    names = set()
    for i, inv in enumerate(spec.invariants):
        if inv.name in names:
            raise ConfigError(f"{path}: invariants.{i}.name: duplicate name {inv.name!r}")
        names.add(inv.name)
        scope = {*SCOPE_ROLES, "msg", "t", "prev", "params"}
        try:
            lets = []
            for key, src in inv.let.items():
                lets.append((key, Expr(src, scope, MAP_FUNCTIONS)))
                scope.add(key)
            where = Expr(inv.where, scope, MAP_FUNCTIONS) if inv.where else None
            check = Expr(inv.assert_ or inv.never or "", scope, MAP_FUNCTIONS)
        except ExprError as exc:
            raise ConfigError(f"{path}: invariants.{i} ({inv.name}): {exc}") from None
        out.append(Invariant(inv, lets, where, check))
    return InvariantSet(out, dict(spec.params), str(path))


@dataclass
class Violation:
    """An invariant that failed in a run."""

    name: str
    kind: str
    time: float  # first violation [s]
    count: int = 1  # evaluations (assert) or episodes (never) in violation
    detail: str = ""

    @property
    def signature(self) -> str:
        return f"violation:{self.name}"

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind, "time": self.time, "count": self.count,
                "detail": self.detail, "signature": self.signature}


def _short(v: Any) -> str:
    v = v.raw if isinstance(v, View) else v
    try:
        s = json.dumps(v, allow_nan=True, default=str)
    except (TypeError, ValueError):
        s = repr(v)
    return s if len(s) <= 120 else s[:117] + "..."


class InvariantMonitor:
    """Evaluates an :class:`InvariantSet` on a stream of (role, payload, time) observations."""

    def __init__(self, invariants: InvariantSet, map_spec: dict[str, Any] | Any,
                 on_violation: Any = None) -> None:
        self.set = invariants
        self.query = MapQuery(map_spec)
        self.latest: dict[str, Any] = {}
        self.violations: dict[str, Violation] = {}
        self.on_violation = on_violation
        self.errors: list[str] = []
        self._prev: dict[str, View | None] = {i.name: None for i in invariants.invariants}
        self._since: dict[str, float | None] = {i.name: None for i in invariants.invariants}
        self._by_role: dict[str, list[Invariant]] = {}
        for inv in invariants.invariants:
            self._by_role.setdefault(inv.spec.on, []).append(inv)
        q = self.query
        self._functions = {**BUILTINS, "lane_speed_limit": q.lane_speed_limit, "stop_line": lambda *a: wrap(q.stop_line(*a)),
                           "on_road": q.on_road, "light_color": self._light_color}
        self._params = wrap(invariants.params)

    def _light_color(self, light_id: Any) -> str | None:
        tl = self.latest.get("traffic_light")
        if tl is None:
            return None
        for light in tl.raw.get("lights", ()) if isinstance(tl.raw, dict) else ():
            if isinstance(light, dict) and light.get("id") == light_id:
                return light.get("color")
        return None

    def observe(self, role: str, payload: dict[str, Any], time_s: float) -> None:
        """One original message of ``role`` published at ``time_s``."""
        view = View(payload)
        self.latest[role] = view
        for inv in self._by_role.get(role, ()):
            self._evaluate(inv, view, time_s)

    def observe_message(self, role: str, msg: Any) -> None:
        """Observer signature of :class:`~.interception.Interceptor`."""
        if role in ROLES:
            self.observe(role, msg.payload, msg.publish_ns / NS_PER_S)

    def finish(self, outcome: dict[str, Any] | None, time_s: float) -> list[Violation]:
        """Evaluate the ``on: outcome`` invariants and return every violation."""
        if outcome is not None:
            self.observe("outcome", outcome, time_s)
        return sorted(self.violations.values(), key=lambda v: (v.time, v.name))

    def _evaluate(self, inv: Invariant, msg: View, t: float) -> None:
        spec = inv.spec
        for role in spec.requires:
            if role not in self.latest:
                return
        env: dict[str, Any] = {r: self.latest.get(r) for r in SCOPE_ROLES}
        env.update(self._functions)
        env.update(msg=msg, t=t, prev=self._prev[inv.name], params=self._params)
        lets: dict[str, Any] = {}
        try:
            for key, ex in inv.lets:
                lets[key] = env[key] = ex(env)
            self._prev[inv.name] = View(lets) if lets else View({})
            if inv.where is not None and not inv.where(env):
                self._since[inv.name] = None
                return
            value = bool(inv.check(env))
            bad = (not value) if spec.assert_ is not None else value
            detail = "" if not bad else self._detail(inv, env, lets)
        except Exception as exc:  # an output that cannot be judged is not valid
            self._prev[inv.name] = View(lets)
            bad, detail = True, f"cannot evaluate: {type(exc).__name__}: {exc}"[:200]
        self._update(inv, bad, t, detail)

    def _detail(self, inv: Invariant, env: dict[str, Any], lets: dict[str, Any]) -> str:
        parts = [f"{k}={_short(v)}" for k, v in lets.items()]
        for name in sorted(inv.check.names & set(SCOPE_ROLES)):
            if env.get(name) is not None and name != "outcome":
                parts.append(f"{name}.stamp={_short(getattr(env[name], 'header', View({})).raw.get('stamp'))}")
        return ", ".join(parts)[:300]

    def _update(self, inv: Invariant, bad: bool, t: float, detail: str) -> None:
        name = inv.name
        if not bad:
            self._since[name] = None
            return
        spec = inv.spec
        if spec.never is not None and spec.for_ > 0:
            since = self._since[name]
            if since is None:
                self._since[name] = t
                return
            if t - since <= spec.for_ + 1e-9:
                return
            if since < -1.0:  # this episode of the condition was already reported
                return
            self._since[name] = -math.inf
            self._report(inv, t, detail + f" (held {t - since:.2f} s)")
            return
        self._report(inv, t, detail)

    def _report(self, inv: Invariant, t: float, detail: str) -> None:
        v = self.violations.get(inv.name)
        if v is None:
            v = self.violations[inv.name] = Violation(inv.name, inv.spec.kind, t, 1, detail)
            if self.on_violation is not None:
                self.on_violation(v)
        else:
            v.count += 1
