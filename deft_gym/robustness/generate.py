"""Random test cases from the specification and the dictionary (ASTAA section 3.2).

Test ``i`` of a campaign is drawn from its own RNG seeded with ``"<seed>:<i>"``, so it does not
depend on any earlier result: a campaign can be resumed, run in parallel, or rerun with
hardening on and get exactly the same tests. Each test has 1-3 policies; a policy picks a topic
role, one or more fields of it (mixing exceptional and likely-valid values), a window
``[t_i, t_j]`` (log-uniform length, or a single message), and intercepts or, sometimes,
interleaves modified copies (or stale duplicates) of the messages.
"""

from __future__ import annotations

import math
import random
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from deft_gym.robustness.dictionary import candidates
from deft_gym.robustness.spec import CONSUMED_ROLES, FieldSpec, TestSpecification
from deft_gym.robustness.testcase import Assignment, Policy

ONE_SHOT_ROLES = ("routing",)  # published once at start-up: windows start at 0
MAX_PER_TEST = 100  # policies per test, fields per policy


class Range(BaseModel):
    """``[min, max]``, finite, 0 <= min <= max."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    min: float = Field(ge=0.0)
    max: float = Field(ge=0.0)

    @model_validator(mode="after")
    def _ordered(self) -> Range:
        if self.min > self.max:
            raise ValueError(f"min {self.min:g} is above max {self.max:g}; expected min <= max")
        return self


class GenerationConfig(BaseModel):
    """How tests are drawn."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    roles: list[str] = Field(default_factory=lambda: list(CONSUMED_ROLES))
    brittle: bool = Field(default=False, description="also target brittle fields (stamps, sequence numbers)")
    policies: Range = Range(min=1, max=3)
    fields_per_policy: Range = Range(min=1, max=2)
    exceptional_share: float = Field(default=0.8, ge=0.0, le=1.0)
    inject_share: float = Field(default=0.15, ge=0.0, le=1.0)
    duplicate_share: float = Field(default=0.5, ge=0.0, le=1.0, description="inject: share of stale duplicates")
    single_share: float = Field(default=0.4, ge=0.0, le=1.0, description="share of one-message policies")
    window_s: Range = Range(min=0.1, max=5.0)
    start_s: Range = Range(min=1.0, max=15.0)
    inject_delay_ms: Range = Range(min=0.0, max=150.0)
    order: Literal["random", "covering"] = Field(
        default="covering", description="covering: test i's first policy sets one field to one exceptional value, "
        "the fields taken in turn (roles interleaved) and each field's values in the dictionary's order, so every "
        "field meets its first exceptional value within the first (number of fields) tests")

    @field_validator("policies", "fields_per_policy")
    @classmethod
    def _counts(cls, v: Range) -> Range:
        if v.min < 1 or v.max > MAX_PER_TEST:
            raise ValueError(f"min {v.min:g}, max {v.max:g}; expected 1 <= min <= max <= {MAX_PER_TEST} "
                             "(a test has at least one policy, a policy at least one field)")
        return v

    @field_validator("window_s")
    @classmethod
    def _window(cls, v: Range) -> Range:
        if v.min <= 0:
            raise ValueError(f"min {v.min:g} s; expected a window longer than 0 s (one-message policies are "
                             "single_share's)")
        return v

    @field_validator("roles")
    @classmethod
    def _known_roles(cls, roles: list[str]) -> list[str]:
        unknown = [r for r in roles if r not in CONSUMED_ROLES]
        if unknown or not roles:
            raise ValueError(f"unknown role(s) {unknown}; expected some of {list(CONSUMED_ROLES)}")
        return roles


STALE = "stale duplicate"  # a covering entry: inject a stale duplicate of the role's messages


def covering_fields(spec: TestSpecification, cfg: GenerationConfig) -> list[tuple[str, FieldSpec | None]]:
    """The entries a ``covering`` campaign takes in turn: (role, field) - the first field of every
    role, then the second of every role, and so on (roles and fields in the specification's
    order) - and after each role's fields (role, None): a stale duplicate of its messages."""
    by_role: dict[str, list[FieldSpec]] = {}
    for f in spec.select(cfg.roles, brittle=cfg.brittle):
        by_role.setdefault(f.role, []).append(f)
    rows: list[list[tuple[str, FieldSpec | None]]] = [[(r, f) for f in by_role[r]] + [(r, None)] for r in sorted(by_role)]
    return [row[i] for i in range(max(map(len, rows), default=0)) for row in rows if i < len(row)]


def covered(spec: TestSpecification, cfg: GenerationConfig, index: int) -> tuple[str, FieldSpec | None, str]:
    """The role, field and exceptional value that test ``index`` of a ``covering`` campaign sets
    (field None, value :data:`STALE`: a stale duplicate injected instead)."""
    entries = covering_fields(spec, cfg)
    role, f = entries[index % len(entries)]
    if f is None:
        return role, None, STALE
    values = candidates(f, True) or candidates(f)
    return role, f, values[(index // len(entries)) % len(values)]


def generate_policies(spec: TestSpecification, cfg: GenerationConfig, rng: random.Random,
                      index: int | None = None) -> list[Policy]:
    """One test's policies (``index``: the test's number, which a ``covering`` order needs)."""
    fields = spec.select(cfg.roles, brittle=cfg.brittle)
    by_role: dict[str, list[FieldSpec]] = {}
    for f in fields:
        by_role.setdefault(f.role, []).append(f)
    roles = sorted(by_role)
    out = []
    count = rng.randint(int(cfg.policies.min), int(cfg.policies.max))
    if cfg.order == "covering" and index is not None:
        count = 1  # one field, one value: nothing else in the test can end it first or take the blame
    for n in range(count):
        role = rng.choice(roles)
        mode = "inject" if rng.random() < cfg.inject_share else "intercept"
        k = rng.randint(int(cfg.fields_per_policy.min), int(cfg.fields_per_policy.max))
        chosen = rng.sample(by_role[role], min(k, len(by_role[role])))
        sets = [] if mode == "inject" and rng.random() < cfg.duplicate_share else \
            [Assignment(path=f.path, value=_value(f, cfg, rng)) for f in chosen]
        if n == 0 and cfg.order == "covering" and index is not None:  # this test's field and value
            role, f, value = covered(spec, cfg, index)
            mode, sets = ("inject", []) if f is None else ("intercept", [Assignment(path=f.path, value=value)])
        if role in ONE_SHOT_ROLES:
            start, end = 0.0, 1.0
        else:
            start = rng.uniform(cfg.start_s.min, cfg.start_s.max)
            lo, hi = math.log(cfg.window_s.min), math.log(cfg.window_s.max)
            end = start + math.exp(rng.uniform(lo, hi))
        single = rng.random() < cfg.single_share
        out.append(Policy(topic=role, mode=mode, start=round(start, 3), end=round(end, 3),
                          max_count=1 if single else None, set=sets,
                          delay_ms=round(rng.uniform(cfg.inject_delay_ms.min, cfg.inject_delay_ms.max), 1)))
    return out


def _value(f: FieldSpec, cfg: GenerationConfig, rng: random.Random) -> str:
    exceptional = rng.random() < cfg.exceptional_share
    names = candidates(f, exceptional) or candidates(f)
    return rng.choice(names)


def case_rng(seed: int, index: int) -> random.Random:
    """The RNG of test ``index`` of a campaign with ``seed`` (independent of every other test)."""
    return random.Random(f"{seed}:{index}")


def describe(policies: list[Policy]) -> str:
    """A one-line summary of a test's policies."""
    parts: list[str] = []
    for p in policies:
        what = ",".join(f"{a.path}={a.value}" for a in p.set) or "duplicate"
        n = "x1" if p.max_count == 1 else f"{p.start:.1f}-{p.end:.1f}s"
        parts.append(f"{p.mode[:3]} {p.topic}[{n}] {what}")
    return "; ".join(parts)


__all__: list[Any] = ["GenerationConfig", "Range", "case_rng", "describe", "generate_policies"]
