"""Configuration files, shared by every package: where configs live, YAML loading and pydantic
validation whose errors name the file and the field (:class:`ConfigError`), and deep merges of
overrides.

The ADS configuration itself (module rates, timing noise, topics, planner) is
:mod:`deft_gym.bus.ads`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar, overload

import yaml
from pydantic import BaseModel, ConfigDict, TypeAdapter, ValidationError

ROOT = Path(__file__).resolve().parent.parent


def _config_dir() -> Path:
    """The configs shipped with the package (``deft_gym/configs``, put there by the build) or,
    in a source checkout, the repository's ``configs/``."""
    from importlib.resources import files

    shipped = Path(str(files("deft_gym").joinpath("configs")))
    return shipped if shipped.is_dir() else ROOT / "configs"


CONFIG_DIR = _config_dir()


def resolve_config_path(path: str | Path) -> Path:
    """``path`` as given when it exists or is absolute; a ``configs/...`` path otherwise names a
    file in :data:`CONFIG_DIR` (so the shipped configs can name each other in an installed
    package, from any directory)."""
    p = Path(path)
    if p.is_absolute() or p.exists():
        return p
    if p.parts and p.parts[0] == "configs" and (CONFIG_DIR.joinpath(*p.parts[1:])).exists():
        return CONFIG_DIR.joinpath(*p.parts[1:])
    return p


def cache_dir() -> Path:
    """Where cached reference runs go: ``DEFT_GYM_CACHE``, else ``runs/cache`` of a source
    checkout, else ``~/.cache/deft-gym`` (an installed package never writes beside itself)."""
    import os

    if os.environ.get("DEFT_GYM_CACHE"):
        return Path(os.environ["DEFT_GYM_CACHE"])
    if (ROOT / "pyproject.toml").exists() and (ROOT / "configs").is_dir():
        return ROOT / "runs" / "cache"
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "deft-gym"


class ConfigError(ValueError):
    """A configuration file is invalid. The message names the file and the field."""


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # NaN/inf: never a setting


def format_validation_error(path: Path | str, err: ValidationError) -> str:
    """One line per problem: ``file: field.path: message``."""
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"]) or "<root>"
        msg = e["msg"]
        if e["type"] == "extra_forbidden":
            msg = "unknown key"
        lines.append(f"{path}: {loc}: {msg}")
    return "\n".join(lines)


# libyaml's parser when PyYAML has it (the same documents, parsed about 3x faster), else PyYAML's
_SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def load_yaml(path: Path | str) -> Any:
    """Read a YAML file (``configs/...`` paths found in the shipped configs too), turning I/O
    and syntax errors into :class:`ConfigError`."""
    path = resolve_config_path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        return yaml.load(text, Loader=_SAFE_LOADER)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark else ""
        raise ConfigError(f"{path}: invalid YAML{where}: {getattr(exc, 'problem', exc)}") from None


def load_mapping(path: Path | str) -> dict[str, Any]:
    """A YAML file holding a mapping (an empty file is an empty mapping)."""
    data = load_yaml(path)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    return data


M = TypeVar("M", bound=BaseModel)


@overload
def validate(model: type[M], data: Any, source: Path | str) -> M: ...
@overload
def validate(model: TypeAdapter[Any], data: Any, source: Path | str) -> Any: ...
def validate(model: type[M] | TypeAdapter[Any], data: Any, source: Path | str) -> Any:
    """``model.model_validate(data)`` (or a type adapter's ``validate_python``), with a
    validation error turned into a :class:`ConfigError` of one line per problem naming
    ``source`` and the field."""
    try:
        if isinstance(model, TypeAdapter):
            return model.validate_python(data)
        return model.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_validation_error(source, err)) from None


def deep_merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    """Recursively merge ``extra`` into a copy of ``base``."""
    out = dict(base)
    for k, v in extra.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = v
    return out
