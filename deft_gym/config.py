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

MAX_YAML_BYTES = 16 * 1024 * 1024  #: the largest configuration file read (scenarios have their own, lower bound)
MAX_YAML_VALUES = 1_000_000  #: values a document may expand to through aliases (``*name``)


class StrictLoader(_SAFE_LOADER):  # type: ignore[misc, valid-type]
    """The safe loader, refusing a mapping that names one key twice (YAML says keys are unique;
    PyYAML silently keeps the last). Merge keys (``<<: *base``) may still be overridden."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, Any] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.setdefault(key, key_node)
                except TypeError:  # an unhashable key: the constructor says so
                    continue
                if first is not key_node:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"duplicate key {str(key)[:80]!r} (first at line {first.start_mark.line + 1})",
                        key_node.start_mark)
        return super().construct_mapping(node, deep=deep)


StrictLoader.add_constructor("tag:yaml.org,2002:map", StrictLoader.construct_yaml_map)


def _expanded_size(data: Any, limit: int) -> int | None:
    """How many values ``data`` holds once every alias is expanded (each shared object counted as
    often as it is referenced), or None when that passes ``limit`` or an alias refers to its own
    ancestor (a recursive document); memoised, so a YAML bomb is measured without expanding it."""
    sizes: dict[int, int] = {}
    active: set[int] = set()

    def size(x: Any) -> int:
        if not isinstance(x, dict | list):
            return 1
        key = id(x)
        if key in sizes:
            return sizes[key]
        if key in active:
            raise RecursionError
        active.add(key)
        items = [*x.keys(), *x.values()] if isinstance(x, dict) else x
        n = 1
        for v in items:
            n += size(v)
            if n > limit:
                raise OverflowError
        active.discard(key)
        sizes[key] = n
        return n

    try:
        return size(data)
    except (OverflowError, RecursionError):
        return None


def read_config_text(path: Path, max_bytes: int = MAX_YAML_BYTES) -> str:
    """The text of a configuration file: ConfigError (one line) when it cannot be read, is not a
    regular file (a FIFO or a device would block or never end) or is larger than ``max_bytes``."""
    import os
    import stat

    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            kind = "a folder" if stat.S_ISDIR(st.st_mode) else "not a regular file (a FIFO, socket or device)"
            raise ConfigError(f"{path}: cannot read: {kind}")
        if st.st_size > max_bytes:
            raise ConfigError(f"{path}: {st.st_size / 1e6:.1f} MB; expected a file of at most {max_bytes / 1e6:g} MB")
        with open(path, "rb") as fh:
            data = fh.read(max_bytes + 1)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if len(data) > max_bytes:
        raise ConfigError(f"{path}: expected a file of at most {max_bytes / 1e6:g} MB")
    if b"\x00" in data:
        raise ConfigError(f"{path}: not a text file (it holds a NUL byte)")
    try:
        return data.decode()
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start})") from None


def load_yaml(path: Path | str, max_bytes: int = MAX_YAML_BYTES) -> Any:
    """Read a YAML file (``configs/...`` paths found in the shipped configs too), turning I/O
    and syntax errors into :class:`ConfigError`. Strict: a regular file of at most ``max_bytes``
    (:func:`read_config_text`), no key twice in a mapping, and aliases that expand the document
    to at most :data:`MAX_YAML_VALUES` values (a "billion laughs" bomb is refused before anything
    expands it, and its values are never printed)."""
    path = resolve_config_path(path)
    text = read_config_text(path, max_bytes)
    try:
        data = yaml.load(text, Loader=StrictLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark else ""
        raise ConfigError(f"{path}: invalid YAML{where}: {getattr(exc, 'problem', exc)}") from None
    except RecursionError:
        raise ConfigError(f"{path}: invalid YAML: nested too deeply") from None
    if "*" in text and _expanded_size(data, MAX_YAML_VALUES) is None:
        raise ConfigError(f"{path}: its aliases (*name) expand it to more than {MAX_YAML_VALUES:,} values or refer "
                          "to themselves; refused (a YAML bomb?)")
    return data


def load_mapping(path: Path | str) -> dict[str, Any]:
    """A YAML file holding a mapping (an empty file is an empty mapping)."""
    data = load_yaml(path)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    return data


def load_mapping_with_base(path: Path | str, what: str = "config") -> dict[str, Any]:
    """:func:`load_mapping` of ``path``; a file with ``base: other.yaml`` (relative to it) is that
    file, recursively, with its own keys deep-merged on top (``what``: the kind of file errors name)."""
    return _with_base(Path(path), load_mapping(path), [], what)


def _with_base(path: Path, data: dict[str, Any], seen: list[Path], what: str) -> dict[str, Any]:
    """``data`` (the mapping of ``path``) deep-merged on top of its ``base:`` file, recursively."""
    base = data.pop("base", None)
    if base is None:
        return data
    if not isinstance(base, str) or not base.strip():
        raise ConfigError(f"{path}: base: {base!r}; expected the path of {what}, relative to this file")
    base_path = (path.parent / base).resolve()
    if base_path in seen or base_path == path.resolve():
        raise ConfigError(f"{path}: base: {base!r} leads back to itself; expected a chain of configs without a loop")
    if not base_path.is_file():
        raise ConfigError(f"{path}: base: {base!r}: no such file {base_path}")
    parent = _with_base(base_path, load_mapping(base_path), [*seen, path.resolve()], what)
    return deep_merge(parent, data)


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


def validate_with_flags(model: type[M], data: dict[str, Any], source: Path | str,
                        flags: dict[str, tuple[str, Any]]) -> M:
    """``model`` validated from a file's ``data`` (named ``source`` in errors) with command-line
    values on top: ``flags`` maps a field to ``(flag, value)`` (a value of None: the flag was not
    given). A problem with a field a flag set names the flag (``--budget: ...``), not the file."""
    given = {field: (flag, value) for field, (flag, value) in flags.items() if value is not None}
    merged = {**data, **{field: value for field, (_, value) in given.items()}}
    try:
        return model.model_validate(merged)
    except ValidationError as err:
        lines = []
        for e in err.errors():
            loc = [str(p) for p in e["loc"]]
            msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"]
            if loc and loc[0] in given:
                rest = ".".join(loc[1:])
                lines.append(f"{given[loc[0]][0]}: {rest + ': ' if rest else ''}{msg}")
            else:
                lines.append(f"{source}: {'.'.join(loc) or '<root>'}: {msg}")
        raise ConfigError("\n".join(lines)) from None


def deep_merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    """Recursively merge ``extra`` into a copy of ``base``."""
    out = dict(base)
    for k, v in extra.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = v
    return out
