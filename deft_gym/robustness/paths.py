"""Field paths inside message payloads.

A path is dotted keys with list indices: ``x``, ``header.stamp``, ``trajectory.v`` (the whole
array), ``trajectory.v[*]`` (every element), ``obstacles[*].heading`` (the heading of every
obstacle), ``obstacles[2].heading`` (one of them), ``destination.lane[2]``. ``[*]`` is the
wildcard of a policy; :func:`expand` turns it into the concrete paths a message actually has,
which is what minimisation works on.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from functools import lru_cache
from typing import Any

_TOKEN = re.compile(r"([^.\[\]]+)|\[(\*|\d+)\]")

Token = tuple[str, Any]  # ("key", name) | ("idx", int) | ("all", None)


class PathError(ValueError):
    """A path that does not parse."""


@lru_cache(maxsize=4096)
def parse(path: str) -> tuple[Token, ...]:
    """Tokens of ``path``; raises :class:`PathError` on a malformed one."""
    tokens: list[Token] = []
    pos = 0
    while pos < len(path):
        if path[pos] == "." and tokens:
            pos += 1
        m = _TOKEN.match(path, pos)
        if m is None:
            raise PathError(f"bad field path {path!r} at position {pos}")
        if m.group(1) is not None:
            tokens.append(("key", m.group(1)))
        elif m.group(2) == "*":
            tokens.append(("all", None))
        else:
            tokens.append(("idx", int(m.group(2))))
        pos = m.end()
    if not tokens:
        raise PathError("empty field path")
    return tuple(tokens)


def _fmt(tokens: list[Token] | tuple[Token, ...]) -> str:
    out = ""
    for kind, v in tokens:
        if kind == "key":
            out += ("." if out else "") + v
        elif kind == "idx":
            out += f"[{v}]"
        else:
            out += "[*]"
    return out


def _locations(obj: Any, tokens: tuple[Token, ...], i: int, done: list[Token]) -> Iterator[tuple[Any, Any, list[Token]]]:
    """Yield ``(container, key, concrete tokens)`` of every location the path reaches."""
    kind, v = tokens[i]
    last = i == len(tokens) - 1
    if kind == "key":
        if not isinstance(obj, dict) or v not in obj:
            return
        keys: list[Any] = [v]
    else:
        if not isinstance(obj, list):
            return
        if kind == "idx":
            if v >= len(obj):
                return
            keys = [v]
        else:
            keys = list(range(len(obj)))
    for k in keys:
        here = [*done, ("key", k) if kind == "key" else ("idx", k)]
        if last:
            yield obj, k, here
        else:
            yield from _locations(obj[k], tokens, i + 1, here)


def expand(payload: Any, path: str) -> list[str]:
    """The concrete paths (no wildcard) that ``path`` reaches in ``payload``."""
    return [_fmt(t) for _, _, t in _locations(payload, parse(path), 0, [])]


def get(payload: Any, path: str) -> Any:
    """The value at the first location of ``path``; ``KeyError`` when there is none."""
    for container, key, _ in _locations(payload, parse(path), 0, []):
        return container[key]
    raise KeyError(path)


def apply(payload: Any, path: str, fn: Callable[[Any, str], Any]) -> int:
    """Replace the value at every location of ``path`` by ``fn(old, concrete_path)``.

    Returns how many locations were changed. Missing paths are skipped (a policy on
    ``obstacles[*].x`` does nothing to a message without obstacles)."""
    n = 0
    for container, key, tokens in list(_locations(payload, parse(path), 0, [])):
        container[key] = fn(container[key], _fmt(tokens))
        n += 1
    return n


def schema_field(path: str) -> str:
    """The schema-level name of a concrete path: indices become ``[*]``."""
    return _fmt([("all", None) if k == "idx" else (k, v) for k, v in parse(path)])
