"""ADS configuration: module rates, timing-noise magnitudes, topics and the planner to load.

Loaded from YAML (``configs/ads/default.yaml``) and validated with pydantic; any error names the
file and the field. Everything that shapes timing lives here, so the jitter is configuration,
not code.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import ConfigDict, Field, PrivateAttr, field_validator

from deft_gym.bus.messages import DEFAULT_TOPICS, ROLES, VIEWER_TOPICS
from deft_gym.config import (
    CONFIG_DIR,
    Strict,
    deep_merge,
    load_mapping_with_base,
    validate,
)

DEFAULT_ADS_CONFIG = CONFIG_DIR / "ads" / "default.yaml"


def _known_roles(cls: type, v: list[str]) -> list[str]:
    """Validator of a list of topic roles."""
    bad = [r for r in v if r not in ROLES]
    if bad:
        raise ValueError(f"unknown topic role(s) {bad}; expected some of {list(ROLES)}")
    return v


MAX_HZ = 1000.0  #: highest rate of any timer [Hz] (a bound: 1e9 Hz would never finish)
MIN_HZ = 1.0  #: lowest rate of a module's timer and of the chassis [Hz]
MIN_WORLD_HZ = 5.0  #: lowest world rate [Hz]: a step longer than 0.2 s is not a simulation of driving
MAX_MS = 60_000.0  #: longest mean processing or delivery time [ms]

class Duration(Strict):
    """A processing-time distribution [ms]: lognormal with the given mean and std, clipped to
    ``min_ms``, and with probability ``spike_prob`` multiplied by ``spike_factor`` (a scheduling
    hiccup). With jitter disabled the duration is exactly ``mean_ms``."""

    mean_ms: float = Field(ge=0.0, le=MAX_MS)
    std_ms: float = Field(default=0.0, ge=0.0)
    min_ms: float = Field(default=0.0, ge=0.0)
    spike_prob: float = Field(default=0.0, ge=0.0, le=1.0)
    spike_factor: float = Field(default=1.0, ge=1.0)


class JitterConfig(Strict):
    """Magnitudes of the timing noise. All draws come from the jitter RNG (its own seed)."""

    enabled: bool = True
    delivery: Duration = Duration(mean_ms=1.0, std_ms=0.6)
    drop_prob: float = Field(default=0.001, ge=0.0, lt=1.0)
    reliable: list[str] = Field(default_factory=lambda: ["routing", "map"],
                                description="topic roles whose deliveries are never lost (a drawn loss is "
                                "redelivered), as Apollo's routing response is latched (transient local)")
    _roles = field_validator("reliable")(_known_roles)
    timer_ms: float = Field(default=0.5, ge=0.0, description="std of timer wake-up lateness")
    dispatch: Duration = Duration(mean_ms=0.3, std_ms=0.2)
    shuffle_simultaneous: bool = True


def _known_trigger(cls: type, v: str | None) -> str | None:
    if v is not None and v not in ROLES:
        raise ValueError(f"unknown trigger role {v!r}; expected one of {list(ROLES)}")
    return v


class ModuleConfig(Strict):
    """A bus node: either periodic (``rate_hz``) or triggered by a topic role (``trigger``)."""

    rate_hz: float | None = Field(default=None, ge=MIN_HZ, le=MAX_HZ)
    trigger: str | None = None
    processing: Duration = Duration(mean_ms=1.0)
    params: dict[str, Any] = Field(default_factory=dict)
    node: str | None = Field(default=None, description="'module:Class' replacing the built-in node "
                             "class (same constructor arguments), e.g. a fault-injecting or hardened variant")

    _trigger = field_validator("trigger")(_known_trigger)

    @field_validator("node")
    @classmethod
    def _a_node(cls, v: str | None) -> str | None:
        """A replacement node must be importable and a bus node (a planner class named here, or a
        module that does not import, is refused with the config, not a traceback at the run)."""
        if v is None:
            return v
        import importlib

        from deft_gym.bus.bus import Node

        mod, sep, name = v.partition(":")
        if not sep or not mod or not name:
            raise ValueError(f"expected 'module:Class', got {v!r}")
        try:
            obj = getattr(importlib.import_module(mod), name)
        except (ImportError, AttributeError) as exc:
            raise ValueError(f"cannot import {v!r}: {exc}") from None
        except Exception as exc:  # the module itself fails while it is imported
            raise ValueError(f"cannot import {v!r}: {type(exc).__name__}: {exc}") from None
        if not (isinstance(obj, type) and issubclass(obj, Node)):
            raise ValueError(f"{v} is not a deft_gym.bus.bus.Node subclass (a module of the bus; a planner goes in "
                             "planning.planner.class)")
        return v


class PlannerSpec(Strict):
    """Which planner class to load (``module:Class``) and its parameters."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    cls: str = Field(default="deft_gym.planner.lattice:LatticePlanner", alias="class")
    params: dict[str, Any] = Field(default_factory=dict)


class PlanningConfig(ModuleConfig):
    subscribe: list[str] | None = Field(default=None, description="roles of the planner's frame; None (default): "
                                        "the planner's Planner.inputs, which a list must match")
    trigger: str | None = "prediction"
    planner: PlannerSpec = PlannerSpec()
    publish_input_headers: bool = False

    _roles = field_validator("subscribe")(_known_roles)


class AdsConfig(Strict):
    """The whole ADS: world step, module timing, topic names, planner."""

    world_hz: float = Field(default=20.0, ge=MIN_WORLD_HZ, le=MAX_HZ)
    chassis_hz: float = Field(default=20.0, ge=MIN_HZ, le=MAX_HZ)
    #: [deg] the ego chassis' steering limit. highway-env's bicycle puts both axles half the car's
    #: 4.8 m length from its centre, so 50 deg turns its centre on 4.69 m, a car's turning circle;
    #: highway-env's own 35 deg gives 7.26 m, less than the generator's tightest turns need
    max_steering_deg: float = Field(default=50.0, gt=0.0, lt=90.0)
    topics: dict[str, str] = Field(default_factory=lambda: dict(DEFAULT_TOPICS))
    jitter: JitterConfig = JitterConfig()
    routing: ModuleConfig = ModuleConfig(processing=Duration(mean_ms=5.0))
    localization: ModuleConfig = ModuleConfig(rate_hz=20.0)
    perception: ModuleConfig = ModuleConfig(rate_hz=10.0)
    traffic_light: ModuleConfig = ModuleConfig(rate_hz=10.0)
    prediction: ModuleConfig = ModuleConfig(trigger="perception_obstacles")
    planning: PlanningConfig = PlanningConfig()
    control: ModuleConfig = ModuleConfig(rate_hz=20.0)
    _source: str = PrivateAttr(default="ADS config")  #: the file it was loaded from

    @field_validator("topics")
    @classmethod
    def _all_roles(cls, v: dict[str, str]) -> dict[str, str]:
        unknown = sorted(set(v) - set(ROLES))
        if unknown:
            raise ValueError(f"unknown topic role(s) {unknown}; expected {list(ROLES)}")
        topics = {**DEFAULT_TOPICS, **v}
        owner: dict[str, str] = {}
        for role, name in topics.items():
            if not isinstance(name, str) or not name.strip() or name != name.strip():
                raise ValueError(f"topics.{role}: {name!r} is not a topic name; expected a non-empty name such as "
                                 f"{DEFAULT_TOPICS[role]!r}")
            if name in VIEWER_TOPICS:
                raise ValueError(f"topics.{role}: {name!r} is reserved for the viewer channels of the log; "
                                 "expected another name")
            if name in owner:
                raise ValueError(f"topics.{owner[name]} and topics.{role} are both {name!r}; expected one topic per "
                                 "role (two modules publishing one topic would read each other's messages)")
            owner[name] = role
        return topics

    def topic(self, role: str) -> str:
        """Bus topic name of a role."""
        return self.topics[role]


def load_ads_config(path: Path | str | None = None, overrides: dict[str, Any] | None = None,
                    source: str | None = None) -> AdsConfig:
    """Load and validate an ADS config; ``overrides`` is deep-merged on top of the file. A file
    with ``base: other.yaml`` (relative to it) is that file with its own keys deep-merged on top.
    ``source``: what errors name (default: the file), e.g. the overlay that ``overrides`` came from."""
    path = Path(path) if path else DEFAULT_ADS_CONFIG
    data = load_mapping_with_base(path, "an ADS config")
    if overrides:
        data = deep_merge(data, overrides)
    ads = validate(AdsConfig, data, source or path)
    ads._source = str(path)  # names the file in errors found later (the planner)
    return ads
