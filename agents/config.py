"""Training configuration (``configs/train/*.yaml``), validated with pydantic.

Any problem is reported as one line per field: ``<file>: <field.path>: <what was expected>``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from deft_gym.config import load_mapping, validate

if TYPE_CHECKING:  # imported on first use (it loads the whole simulation): ``--help`` stays fast
    from deft_gym.envs.adversary import AdversaryConfig

ALGOS = ("ppo", "a2c")  # SB3 algorithms that take MultiDiscrete actions


class TrainConfig(BaseModel):
    """One training run of the adversary."""

    model_config = ConfigDict(extra="forbid")

    name: str = "adversary"
    algo: Literal["ppo", "a2c"] = "ppo"
    policy: str = "MlpPolicy"
    timesteps: int = Field(100_000, ge=1)
    seed: int = 0
    n_envs: int = Field(2, ge=1, le=64)
    vec_env: Literal["subproc", "dummy"] = "subproc"
    checkpoint_every: int = Field(10_000, ge=1, description="env steps between checkpoints")
    algo_kwargs: dict[str, Any] = Field(default_factory=dict)
    policy_kwargs: dict[str, Any] = Field(default_factory=lambda: {"net_arch": [128, 128]})
    generated: int = Field(0, ge=0, description="robust generated scenarios gen:<seed> (seeds from 0 on) "
                           "added to env.scenarios for training; held-out evaluation seeds start at 1000000")
    env: AdversaryConfig = Field(default_factory=lambda: _env_config()())
    log_episodes: bool = Field(True, description="record every episode's MCAP log (failures -> extractor)")


def _env_config() -> type:
    from deft_gym.envs.adversary import AdversaryConfig

    return AdversaryConfig


def complete() -> None:
    """Resolve :class:`TrainConfig`'s env field (the adversary env's config class)."""
    if not TrainConfig.__pydantic_complete__:
        TrainConfig.model_rebuild(_types_namespace={"AdversaryConfig": _env_config()})


def load_train_config(path: Path | str | None = None, overrides: dict[str, Any] | None = None) -> TrainConfig:
    """Load ``path`` (or the defaults) with ``overrides`` on top; errors name file and field."""
    complete()
    data = load_mapping(path) if path is not None else {}
    for key, value in (overrides or {}).items():
        if value is not None:
            data[key] = value
    return validate(TrainConfig, data, path if path is not None else "<defaults>")
