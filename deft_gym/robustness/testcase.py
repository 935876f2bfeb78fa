"""Interception policies and replayable test cases.

A policy is ASTAA's rule (section 3.2.2): *for all messages on topic X between t_i and t_j, set
field f to v* - here with several fields at once (``set``), an optional cap on how many messages
it touches (``max_count``) and two modes: ``intercept`` (the message is replaced by the modified
one) and ``inject`` (interleaving, 3.4.2: a modified copy is put on the bus ``inject_delay_ms``
after the original, which flows unmodified).

Running policies yields *instances*: the concrete messages they touched, named by topic role and
sequence number. With the same jitter seed a list of instances replays deterministically, which
is what delta debugging works on. A :class:`TestCase` holds either policies or instances, plus
everything needed to replay it (scenario, ADS configuration, jitter seed) and what it is expected
to produce (``expect``). Test cases are JSON files.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from deft_gym.bus.messages import ROLES
from deft_gym.config import ConfigError, validate
from deft_gym.files import write_atomic
from deft_gym.robustness.dictionary import lookup
from deft_gym.robustness.paths import parse

CASE_FORMAT = "deft_gym.astaa.case/1"


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", populate_by_name=True)


class Assignment(Strict):
    """Set the field(s) at ``path`` to the dictionary entry ``value``."""

    path: str
    value: str

    @field_validator("path")
    @classmethod
    def _path(cls, v: str) -> str:
        parse(v)  # PathError is a ValueError
        return v

    @field_validator("value")
    @classmethod
    def _value(cls, v: str) -> str:
        lookup(v)  # UnknownEntry is a ValueError
        return v


class _Targets(Strict):
    topic: str = Field(description="topic role, e.g. localization")
    mode: Literal["intercept", "inject"] = "intercept"
    set: list[Assignment] = Field(default_factory=list)
    delay_ms: float = Field(default=20.0, ge=0.0, description="inject: delay after the original")

    @field_validator("topic")
    @classmethod
    def _role(cls, v: str) -> str:
        if v not in ROLES:
            raise ValueError(f"unknown topic role {v!r}; expected one of {list(ROLES)}")
        return v


class Policy(_Targets):
    """For the messages on ``topic`` published in [``start``, ``end``] s (at most ``max_count``
    of them), set every assignment."""

    start: float = Field(ge=0.0)
    end: float = Field(ge=0.0)
    max_count: int | None = Field(default=None, ge=1)


class Instance(_Targets):
    """One message the test touches: the ``seq``-th message of ``topic`` (for ``inject``, the
    message the injected copy follows)."""

    seq: int = Field(ge=0)


class Expect(Strict):
    """What replaying the case should produce."""

    signature: str
    time: float | None = None
    fingerprint: str | None = None
    foundation: str | None = Field(default=None, description="digest of the simulation source it was recorded on")


class TestCase(Strict):
    """A replayable robustness test."""

    __test__ = False  # not a pytest class

    format: str = CASE_FORMAT
    id: str = "case"
    scenario: str = Field(description="scenario YAML path (relative to the repository root or absolute)")
    ads_config: str | None = Field(default=None, description="ADS config YAML (default configs/ads/default.yaml)")
    ads_overrides: dict[str, Any] = Field(default_factory=dict)
    hardening: bool = False
    jitter_seed: int
    policies: list[Policy] = Field(default_factory=list)
    instances: list[Instance] | None = None
    invariants: str | None = Field(default=None, description="invariants YAML (default configs/invariants/default.yaml)")
    deadline_s: float = Field(default=1.0, gt=0.0, description="CPU-time budget of one module computation [s]")
    hang_periods: int = Field(default=10, ge=1, description="silent for this many periods = hang")
    grace_s: float = Field(default=2.0, ge=0.0, description="sim time the run goes on after a crash or hang")
    stop_at: float | None = Field(default=None, gt=0.0, description="end the run at this sim time")
    expect: Expect | None = None
    note: str = ""

    @property
    def targets(self) -> list[_Targets]:
        """The instances when given, else the policies."""
        return list(self.instances) if self.instances is not None else list(self.policies)

    def with_instances(self, instances: list[Instance], **changes: Any) -> TestCase:
        """A copy of this case that replays exactly ``instances``."""
        return self.model_copy(update={"instances": instances, "policies": [], **changes}, deep=True)


def load_case(path: Path | str) -> TestCase:
    """Read and validate a test case; errors name the file and the field."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: invalid JSON (line {exc.lineno}): {exc.msg}") from None
    return validate(TestCase, data, path)


def save_case(case: TestCase, path: Path | str) -> Path:
    """Write a test case atomically (JSON, stable key order)."""
    data = case.model_dump(mode="json", exclude_none=True)
    return write_atomic(path, json.dumps(data, indent=1, sort_keys=False) + "\n")
