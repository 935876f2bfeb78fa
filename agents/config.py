"""Training configuration (``configs/train/*.yaml``), validated with pydantic.

Any problem is reported as one line per field: ``<file>: <field.path>: <what was expected>``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from deft_gym.config import load_mapping_with_base, validate_with_flags

if TYPE_CHECKING:  # imported on first use (it loads the whole simulation): ``--help`` stays fast
    from deft_gym.envs.adversary import AdversaryConfig

ALGOS = ("ppo", "a2c")  # SB3 algorithms that take MultiDiscrete actions


class TrainConfig(BaseModel):
    """One training run of the adversary."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field("adversary", pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$",
                      description="the run's name: its default folder runs/adversary/<name> (one folder name)")
    algo: Literal["ppo", "a2c"] = "ppo"
    policy: Literal["MlpPolicy"] = "MlpPolicy"
    timesteps: int = Field(100_000, ge=1, le=10**10)
    seed: int = 0
    n_envs: int = Field(2, ge=1, le=64)
    vec_env: Literal["subproc", "dummy"] = "subproc"
    checkpoint_every: int = Field(10_000, ge=1, description="env steps between checkpoints")
    algo_kwargs: dict[str, Any] = Field(default_factory=dict)
    policy_kwargs: dict[str, Any] = Field(default_factory=lambda: {"net_arch": [128, 128]})
    generated: int = Field(0, ge=0, le=10_000, description="robust generated scenarios gen:<seed> (seeds from 0 on) "
                           "added to env.scenarios for training; held-out evaluation seeds start at 1000000")
    env: AdversaryConfig = Field(default_factory=lambda: _env_config()())
    log_episodes: bool = Field(True, description="record every episode's MCAP log (failures -> extractor)")
    init_model: str | None = Field(None, description="start from this trained model's policy and optimiser "
                                   "(a model.zip of the same algo and network, or default: the shipped adversary), "
                                   "e.g. to aim it at another oracle; none: a fresh policy")

    @field_validator("policy_kwargs")
    @classmethod
    def _net_arch(cls, v: dict[str, Any]) -> dict[str, Any]:
        """``net_arch``: layer widths 1..4096 (at most 16 layers), a list or ``{pi: [...], vf: [...]}``
        (torch would raise deep in the model's construction on a width of -5)."""
        arch = v.get("net_arch")
        if arch is None:
            return v
        lists = {"": arch} if isinstance(arch, list) else arch if isinstance(arch, dict) else None
        if lists is None or (isinstance(arch, dict) and (set(arch) - {"pi", "vf"} or not arch)):
            raise ValueError("net_arch: expected a list of layer widths or {pi: [...], vf: [...]}")
        for key, widths in lists.items():
            ok = isinstance(widths, list) and len(widths) <= 16 and all(
                isinstance(w, int) and not isinstance(w, bool) and 1 <= w <= 4096 for w in widths)
            if not ok:
                raise ValueError(f"net_arch{'.' + key if key else ''}: {widths!r}; expected at most 16 layer widths, "
                                 "each an integer in 1..4096")
        return v


def _env_config() -> type:
    from deft_gym.envs.adversary import AdversaryConfig

    return AdversaryConfig


def complete() -> None:
    """Resolve :class:`TrainConfig`'s env field (the adversary env's config class)."""
    if not TrainConfig.__pydantic_complete__:
        TrainConfig.model_rebuild(_types_namespace={"AdversaryConfig": _env_config()})


def load_train_config(path: Path | str | None = None, overrides: dict[str, Any] | None = None) -> TrainConfig:
    """Load ``path`` (or the defaults; a file with ``base: other.yaml`` builds on that file) with
    ``overrides`` on top; errors name file and field, or
    the flag of an override (``--timesteps``, ``--n-envs``: a field name ``n_envs`` is ``--n-envs``)."""
    complete()
    data = load_mapping_with_base(path, "a training config") if path is not None else {}
    flags = {key: ("--" + key.replace("_", "-"), value) for key, value in (overrides or {}).items()}
    return validate_with_flags(TrainConfig, data, path if path is not None else "<defaults>", flags)


# bounds of the SB3 hyper-parameters a config commonly sets: (low, low inclusive, high)
_ALGO_BOUNDS: dict[str, tuple[float, bool, float]] = {
    "learning_rate": (0.0, False, 1.0), "n_steps": (1, True, 1e7), "batch_size": (2, True, 1e7),
    "n_epochs": (1, True, 1e4), "gamma": (0.0, False, 1.0), "gae_lambda": (0.0, True, 1.0),
    "clip_range": (0.0, False, 10.0), "ent_coef": (0.0, True, 10.0), "vf_coef": (0.0, True, 100.0),
    "max_grad_norm": (0.0, False, 1e6)}


def check_train_settings(cfg: TrainConfig, source: Path | str | None) -> None:
    """ConfigError (one line naming the file and field) for an ``algo_kwargs`` key the SB3
    algorithm does not take, a value out of range, a rollout of one sample, or an env scenario
    that does not resolve - before any env starts."""
    import inspect
    import math

    from stable_baselines3 import A2C, PPO

    from deft_gym.config import ConfigError

    name = str(source) if source is not None else "<defaults>"
    algo = {"ppo": PPO, "a2c": A2C}[cfg.algo]
    params = inspect.signature(algo.__init__).parameters
    taken = set(params) - {"self", "policy", "env", "policy_kwargs"}
    for key, value in cfg.algo_kwargs.items():
        if key not in taken:
            raise ConfigError(f"{name}: algo_kwargs.{key}: not a parameter of SB3 {algo.__name__}; "
                              f"expected one of {sorted(taken)}")
        if key in _ALGO_BOUNDS and not callable(value):
            low, inclusive, high = _ALGO_BOUNDS[key]
            ok = (isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
                  and (value >= low if inclusive else value > low) and value <= high)
            if not ok:
                raise ConfigError(f"{name}: algo_kwargs.{key}: expected a number {'>=' if inclusive else '>'} {low:g} "
                                  f"and <= {high:g}, got {value!r}")
    from stable_baselines3.common.policies import ActorCriticPolicy

    policy_params = set(inspect.signature(ActorCriticPolicy.__init__).parameters) - {
        "self", "observation_space", "action_space", "lr_schedule"}
    for key in cfg.policy_kwargs:
        if key not in policy_params:
            raise ConfigError(f"{name}: policy_kwargs.{key}: not a parameter of SB3's MlpPolicy; expected one of "
                              f"{sorted(policy_params)}")
    if cfg.init_model:
        from deft_gym.models import resolve_model

        if not Path(resolve_model(cfg.init_model)).is_file():
            raise ConfigError(f"{name}: init_model: {cfg.init_model}: no such file; expected a model.zip written by "
                              "agents.train, or default (the shipped adversary)")
    if cfg.algo_kwargs.get("n_steps", params["n_steps"].default) * cfg.n_envs < 2:
        raise ConfigError(f"{name}: algo_kwargs.n_steps: n_steps x n_envs must be at least 2")
    from deft_gym.scenarios.scenario import SCENARIO_GROUPS, is_group_scenario
    from deft_gym.search.context import (  # names, paths, gen:<seed>, <name>~v<seed>
        ads_config,
        resolve_scenario,
    )

    if cfg.env.ads is not None:
        try:
            ads_config(cfg.env.ads)
        except ConfigError as err:
            raise ConfigError(f"{name}: env.ads: {err}") from None

    seen: set[str] = set()
    for i, scenario in enumerate(cfg.env.scenarios):
        if scenario in seen:
            continue
        seen.add(scenario)
        if scenario in SCENARIO_GROUPS or is_group_scenario(scenario.split("~v")[0]):
            raise ConfigError(f"{name}: env.scenarios.{i}: {scenario!r} is an evaluation-only scenario "
                              f"(groups {list(SCENARIO_GROUPS)}, configs/scenarios/<group>/); training never uses them")
        try:
            resolve_scenario(scenario)
        except (ConfigError, ValueError, OSError) as err:
            raise ConfigError(f"{name}: env.scenarios.{i}: {scenario!r} does not resolve ({err})") from None
