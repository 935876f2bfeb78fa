"""The expression language of safety invariants: a safe subset of Python expressions.

Expressions are parsed with :mod:`ast`, checked against a whitelist (literals, names, attribute
and index access, arithmetic, comparisons, boolean logic, conditional expressions,
comprehensions and calls of the provided functions; no private attributes, no other callables)
and compiled once. Payloads are exposed through :class:`View`, so ``localization.v`` and
``prediction.obstacles[0].x`` read message fields.

The built-in functions are NaN-aware where it matters: ``finite`` is False for NaN, infinities,
non-numbers and ``None``; write bounds as ``lo <= x <= hi`` (False for NaN) rather than
``not x > hi`` (True for NaN - the very bug ASTAA's NaN lesson is about).
"""

from __future__ import annotations

import ast
import itertools
import math
from collections.abc import Callable, Iterable
from typing import Any

_ALLOWED = (
    ast.Expression, ast.BoolOp, ast.And, ast.Or, ast.BinOp, ast.Add, ast.Sub, ast.Mult, ast.Div,
    ast.Mod, ast.Pow, ast.FloorDiv, ast.UnaryOp, ast.Not, ast.USub, ast.UAdd, ast.Compare, ast.Eq,
    ast.NotEq, ast.Lt, ast.LtE, ast.Gt, ast.GtE, ast.Is, ast.IsNot, ast.In, ast.NotIn, ast.IfExp,
    ast.Call, ast.Name, ast.Load, ast.Store, ast.Attribute, ast.Subscript, ast.Slice, ast.Constant,
    ast.List, ast.Tuple, ast.GeneratorExp, ast.ListComp, ast.comprehension,
)


class ExprError(ValueError):
    """An expression that does not parse or uses something outside the language."""


class View:
    """Attribute and index access to a payload without copying it."""

    __slots__ = ("_v",)

    def __init__(self, value: Any) -> None:
        self._v = value

    def __getattr__(self, key: str) -> Any:
        v = self._v
        if isinstance(v, dict):
            try:
                return wrap(v[key])
            except KeyError:
                raise AttributeError(f"no field {key!r}") from None
        raise AttributeError(f"no field {key!r} in a {type(v).__name__}")

    def __getitem__(self, key: Any) -> Any:
        return wrap(self._v[key])

    def __len__(self) -> int:
        return len(self._v)

    def __iter__(self) -> Any:
        return (wrap(x) for x in self._v)

    def __contains__(self, item: Any) -> bool:
        return item in self._v

    def __eq__(self, other: Any) -> bool:
        return self._v == (other._v if isinstance(other, View) else other)

    def __hash__(self) -> int:
        return id(self._v)

    def __repr__(self) -> str:
        return f"View({self._v!r})"[:200]

    @property
    def raw(self) -> Any:
        return self._v


def wrap(value: Any) -> Any:
    """Dicts and lists as :class:`View`, other values as they are."""
    return View(value) if isinstance(value, dict | list) else value


def raw(value: Any) -> Any:
    """The plain value behind a :class:`View`."""
    return value.raw if isinstance(value, View) else value


def _is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def finite(x: Any) -> bool:
    """A real, finite number (False for NaN, infinities, booleans, None and non-numbers)."""
    return _is_number(x) and math.isfinite(x)


def all_finite(xs: Any) -> bool:
    """Every element is :func:`finite` (False for a non-list)."""
    xs = raw(xs)
    if not isinstance(xs, list):
        return False
    try:
        if math.isfinite(sum(xs)):  # fast path: one C loop (a non-number raises)
            return not any(isinstance(x, bool) for x in xs) if True in xs or False in xs else True
    except (TypeError, OverflowError):
        return False
    return all(finite(x) for x in xs)


def increasing(xs: Any) -> bool:
    """Strictly increasing finite numbers."""
    xs = raw(xs)
    return isinstance(xs, list) and all_finite(xs) and all(a < b for a, b in itertools.pairwise(xs))


def same_length(*seqs: Any) -> bool:
    """All arguments are lists of one length."""
    seqs = tuple(raw(s) for s in seqs)
    return all(isinstance(s, list) for s in seqs) and len({len(s) for s in seqs}) <= 1


def wrap_angle(a: float) -> float:
    """An angle wrapped to [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


def _len(x: Any) -> int:
    return len(raw(x))


def _num(fn: Callable[..., Any]) -> Callable[..., Any]:
    return lambda *a: fn(*(raw(x) for x in a))


BUILTINS: dict[str, Callable[..., Any]] = {
    "finite": finite, "all_finite": all_finite, "increasing": increasing, "same_length": same_length,
    "is_number": _is_number, "isnan": lambda x: _is_number(x) and math.isnan(x), "wrap_angle": wrap_angle,
    "len": _len, "abs": abs, "min": _num(min), "max": _num(max), "all": all, "any": any, "sum": _num(sum),
    "hypot": math.hypot, "sqrt": math.sqrt, "cos": math.cos, "sin": math.sin, "round": round,
}


class Expr:
    """A compiled expression; ``names`` are the free names it reads."""

    def __init__(self, source: str, allowed: Iterable[str], functions: Iterable[str]) -> None:
        self.source = source.strip()
        try:
            tree = ast.parse(f"(\n{self.source}\n)", mode="eval")  # parentheses: multi-line YAML
        except SyntaxError as exc:
            raise ExprError(f"syntax error in {self.source!r}: {exc.msg}") from None
        functions = set(functions) | set(BUILTINS)
        bound = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store)}
        allowed = set(allowed) | functions | bound | {"True", "False", "None"}
        self.names: set[str] = set()
        for node in ast.walk(tree):
            if not isinstance(node, _ALLOWED):
                raise ExprError(f"{type(node).__name__} is not allowed in {self.source!r}")
            if isinstance(node, ast.Attribute) and node.attr.startswith("_"):
                raise ExprError(f"private attribute {node.attr!r} in {self.source!r}")
            if isinstance(node, ast.Call) and not (isinstance(node.func, ast.Name) and node.func.id in functions):
                raise ExprError(f"only the provided functions can be called in {self.source!r}")
            if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Load):
                if node.id not in allowed:
                    raise ExprError(f"unknown name {node.id!r} in {self.source!r}")
                self.names.add(node.id)
        self._code = compile(tree, f"<invariant {self.source[:40]}>", "eval")

    def __call__(self, env: dict[str, Any]) -> Any:
        """Evaluate with ``env`` as the globals (so comprehensions see every name)."""
        env["__builtins__"] = {}
        return eval(self._code, env)
