"""The topic-role mapping: which log topic plays which role for the planner under test.

The extractor knows nothing about the simulator that wrote a log; a mapping (YAML, see
``configs/mappings/deft_gym.yaml``) says which topic carries the planning outputs, which ones the
planner subscribes to (its frame) and which of them triggers a planning cycle, where an output
states its frame time and its inputs' sequence numbers, and - for logs without deft_gym
metadata - which planner to load.
"""

from __future__ import annotations

from collections.abc import Mapping as AbcMapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from deft_gym.config import CONFIG_DIR, ConfigError, load_yaml
from deft_gym.planner.base import planner_class, resolve_inputs

MAPPING_DIR = CONFIG_DIR / "mappings"
DEFAULT_MAPPING = MAPPING_DIR / "deft_gym.yaml"


class MappingError(ValueError):
    """A mapping is invalid or does not fit the log. The message names the file and the field."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Delivery(_Strict):
    """Prior of the input search: lognormal delivery delay per subscriber, and its drop rate."""

    mean_ms: float = Field(1.0, gt=0.0)
    std_ms: float = Field(0.6, ge=0.0)
    drop_prob: float = Field(0.001, ge=0.0, lt=1.0)
    dispatch_ms: float = Field(0.3, ge=0.0)  #: trigger receipt -> frame creation (frame-time guesses)


class PlannerRef(_Strict):
    """A planner to load: ``module:Class``, its parameters and the map spec it is built with."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    cls: str = Field(alias="class")
    params: dict[str, Any] = Field(default_factory=dict)
    map: dict[str, Any]


class EgoBox(_Strict):
    length: float | None = Field(None, gt=0.0)
    width: float | None = Field(None, gt=0.0)


class TopicMapping(_Strict):
    """A validated mapping (see the module docstring and ``configs/mappings/deft_gym.yaml``)."""

    name: str = "custom"
    topics: dict[str, str]
    inputs: list[str] | None = Field(None, min_length=1)  #: None: the planner's Planner.inputs
    trigger: str | None = None
    frame_time_field: str | None = "header.stamp"
    frame_time_hint: str | None = None
    input_seqs_field: str | None = "debug.input_seqs"
    seq_field: str | None = None
    delivery: Delivery = Delivery()
    planner: PlannerRef | None = None
    ego: EgoBox = EgoBox()
    outcome_metadata: str | None = "deft_gym.outcome"
    #: metadata record with the optimal path a run was judged against (``x``, ``y``, ``limit`` [m]):
    #: the non-optimal decision's failure test (P_departure); None: no such test
    optimal_path_metadata: str | None = "deft_gym.optimal_path"
    source: str = Field("<dict>", exclude=True)

    @model_validator(mode="after")
    def _consistent(self) -> TopicMapping:
        if "planning" not in self.topics:
            raise ValueError("topics: needs a 'planning' entry (the outputs to reproduce)")
        if self.inputs is not None:
            missing = [r for r in self.inputs if r not in self.topics]
            if missing:
                raise ValueError(f"inputs: role(s) {missing} have no entry under topics")
            if "planning" in self.inputs:
                raise ValueError("inputs: 'planning' is the output, not an input")
            if self.trigger is not None and self.trigger not in self.inputs:
                raise ValueError(f"trigger: {self.trigger!r} is not one of inputs {self.inputs}")
        return self

    def topic(self, role: str) -> str | None:
        """Topic name of a role (None when the mapping has no such role)."""
        return self.topics.get(role)

    def as_dict(self) -> dict[str, Any]:
        """Plain form (recorded in frames files and summaries)."""
        return {"source": self.source, **self.model_dump(mode="json", by_alias=True)}


def load_mapping(spec: TopicMapping | AbcMapping[str, Any] | str | Path | None = None) -> TopicMapping:
    """A mapping from ``None`` (the deft_gym default), a YAML path or a dict."""
    if isinstance(spec, TopicMapping):
        return spec
    if spec is None:
        spec = DEFAULT_MAPPING
    if isinstance(spec, str | Path):
        path = Path(spec)
        try:
            data = load_yaml(path)
        except ConfigError as err:
            raise MappingError(str(err).replace(": cannot read:", ": cannot read mapping:")) from None
        if not isinstance(data, dict):
            raise MappingError(f"{path}: expected a mapping (role -> topic ...) at the top level")
        return _validate(data, str(path))
    return _validate(dict(spec), "<dict>")


def _validate(data: dict[str, Any], source: str) -> TopicMapping:
    try:
        return TopicMapping.model_validate({**data, "source": source})
    except ValidationError as err:
        problems = []
        for e in err.errors():
            loc = ".".join(str(p) for p in e["loc"]) or "<root>"
            msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"]
            problems.append(f"{source}: {loc}: {msg}")
        raise MappingError("; ".join(problems)) from None


def input_roles(mapping: TopicMapping, planner: str) -> list[str]:
    """The roles of the planner's frame: ``planner``'s :attr:`Planner.inputs` (the single source);
    a mapping that lists ``inputs`` must name the same roles. MappingError (one line) when they
    differ, when a role has no topic or the trigger is not among them."""
    try:
        roles = resolve_inputs(planner_class(planner), mapping.inputs, f"{mapping.source}: inputs")
    except ValueError as exc:
        raise MappingError(str(exc)) from None
    missing = [r for r in roles if r not in mapping.topics]
    if missing:
        raise MappingError(f"{mapping.source}: topics: no topic for role(s) {missing}, which {planner} reads "
                           "(Planner.inputs)")
    if mapping.trigger is not None and mapping.trigger not in roles:
        raise MappingError(f"{mapping.source}: trigger: {mapping.trigger!r} is not one of the planner's inputs {roles}")
    return roles


def get_field(payload: Any, path: str) -> Any:
    """The value at a dotted path (``header.stamp``, ``trajectory.t.0``) or None when absent."""
    cur = payload
    for part in path.split("."):
        if isinstance(cur, dict):
            cur = cur.get(part)
        elif isinstance(cur, list) and part.lstrip("-").isdigit():
            i = int(part)
            cur = cur[i] if -len(cur) <= i < len(cur) else None
        else:
            return None
        if cur is None:
            return None
    return cur
