"""The planner interface: a stateful, deterministic function from frames to trajectories.

A :class:`Frame` is what the planning module consumed in one cycle: the payload of the latest
message received on each role the planner reads (:attr:`Planner.inputs`; ``None`` when nothing
arrived yet) and the frame time. The payloads are plain JSON values whose fields, units and
frames are documented in their schemas (:data:`deft_gym.bus.messages.SCHEMAS`); the ``map`` role
carries the road map as data, so a planner needs nothing of deft_gym's internals.

**Output contract** (:func:`validate_output`): :meth:`Planner.plan` returns ``None`` when it
cannot plan yet, and then must leave its state unchanged; otherwise a dict with

- ``trajectory``: equally long lists (at least 2 points) of finite numbers ``t`` (absolute sim
  time [s], strictly increasing, ``t[0]`` = the frame time), ``x``, ``y`` (world frame [m], the
  vehicle centre), ``v`` (speed [m/s]), ``heading`` (world frame [rad], from +x towards +y),
  ``a`` (acceleration along the path [m/s^2]); other number series may follow (compared too);
- ``decision`` (optional): a JSON object describing the choice, in the planner's own terms;
- ``debug`` (optional): anything; never compared.

Any number of points and any spacing: nothing outside a planner assumes another's shape.

**State contract** (what DeFT relies on): same construction arguments + same sequence of frames
-> bit-identical outputs; everything time-dependent comes from ``frame.time``, never a clock, and
no global random generator is used; everything that changes from cycle to cycle lives in
``self.state``, so that :meth:`Planner.snapshot`/:meth:`Planner.restore` return to a state
exactly (the input search tries several candidate frames from one state). ``python -m
extract.contract`` checks all of it on a log's frames. A planner may also declare that it can
be *seeded* (:meth:`Planner.export_state`/:meth:`Planner.load_state`): a failure test then
starts from the state at its frame instead of replaying every frame before it.
"""

from __future__ import annotations

import copy
import functools
import importlib
import itertools
import math
import os
import sys
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

#: the trajectory series every output must carry (see the module docstring)
TRAJECTORY_FIELDS = ("t", "x", "y", "v", "heading", "a")
#: how far ``trajectory.t[0]`` may be from the frame time [s]
T0_TOLERANCE = 1e-6


@dataclass(frozen=True)
class Frame:
    """One planning input: frame creation time [s] and the payload per topic role."""

    time: float
    inputs: Mapping[str, dict[str, Any] | None]

    def get(self, role: str) -> dict[str, Any] | None:
        return self.inputs.get(role)


class Planner(ABC):
    """Base class of planners that plug into the planning module and into extracted tests.

    Subclasses keep everything that changes from cycle to cycle in ``self.state`` so that
    :meth:`snapshot`/:meth:`restore` are cheap and exact (the DeFT input search uses them to try
    several candidate frames from the same planner state).
    """

    #: topic roles the planner reads, its frame: the single source for the planning module's
    #: subscriptions (``planning.subscribe`` in the ADS config) and the extractor's mapping
    inputs: tuple[str, ...] = ("routing", "localization", "traffic_light", "prediction")
    #: attributes that ``plan()`` may change without them being state: memo caches keyed by what
    #: they hold and scratch buffers rewritten before every use. ``python -m extract.contract``
    #: reports a change to any other attribute than ``state`` as hidden state (check
    #: ``hidden_state``), whether or not the frames at hand make it change an output
    caches: tuple[str, ...] = ()

    def __init__(self, map_spec: Mapping[str, Any], **params: Any) -> None:
        self.map_spec = dict(map_spec)
        self.params = params
        self.state: Any = None

    @abstractmethod
    def reset(self) -> None:
        """Forget everything learned from earlier frames."""

    @abstractmethod
    def plan(self, frame: Frame) -> dict[str, Any] | None:
        """Plan one cycle; return ``{"trajectory": {...}, "decision": {...}}`` or None."""

    @classmethod
    def hard_clearance(cls, params: Mapping[str, Any]) -> float:
        """The lateral clearance [m] this planner (with ``params``) always keeps from obstacles.
        Search tools never place objects closer than this to the optimal path: a planner may
        rightly refuse a path that violates its own hard constraint. 0 when it declares none."""
        return 0.0

    def snapshot(self) -> Any:
        """A copy of the mutable state."""
        return copy.deepcopy(self.state)

    def restore(self, snapshot: Any) -> None:
        """Return to a state taken with :meth:`snapshot`."""
        self.state = copy.deepcopy(snapshot)

    def export_state(self) -> dict[str, Any] | None:
        """The state as plain JSON values, to seed a fresh planner with (:meth:`load_state`), or
        None: this planner cannot be seeded (the default). Apollo's planner is seeded this way
        by its previous trajectory (the trajectory stitcher)."""
        return None

    def load_state(self, state: Mapping[str, Any]) -> None:
        """Continue from a state :meth:`export_state` gave; ValueError when it cannot."""
        raise ValueError(f"{type(self).__name__} cannot be seeded (its export_state() gives None)")


def import_object(path: str) -> Any:
    """Import ``package.module:Name``."""
    if ":" not in path:
        raise ValueError(f"expected 'module:Class', got {path!r}")
    mod, _, name = path.partition(":")
    try:
        return getattr(importlib.import_module(mod), name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"cannot import {path!r}: {exc}") from None


def planner_fingerprint(cls_path: str) -> str:
    """SHA-256 of every source a planner class runs (:func:`source_digest`): a log records it, so
    a test can tell that the planner it was extracted for has changed."""
    return source_digest(import_object(cls_path)) or ""


def hosted_class(cls: type) -> type:
    """The planner class itself, also when ``cls`` is its :class:`HostedPlanner` stand-in."""
    return getattr(cls, "hosted_class", None) or cls


def planner_sources(cls: type) -> list[Path]:
    """(See :func:`_planner_sources`; the list is computed once per class.)"""
    return list(_planner_sources(hosted_class(cls)))


@functools.cache
def _planner_sources(cls: type) -> tuple[Path, ...]:
    """The source files a planner class runs: the file that defines it and, transitively, every
    module it imports (statically, ``import``/``from ... import`` anywhere in the file) that lives
    in its own package tree or in ``deft_gym`` - not the standard library or installed
    third-party packages, whose versions the provenance records - and, for a compiled extension
    among them (``_lattice_c``), its C source beside it (``_lattice_c.c``). Sorted."""
    import ast
    import importlib.util
    import inspect

    try:
        first = inspect.getsourcefile(cls)
    except (OSError, TypeError):
        return ()
    if not first:
        return ()
    top = cls.__module__.split(".")[0]
    first_path = Path(first).resolve()
    roots = {Path(__file__).resolve().parents[1]}  # deft_gym/
    root = _root_of(first_path, cls.__module__)
    if root is not None:
        roots.add((root / top) if (root / top).is_dir() else first_path.parent)
    venv = Path(sys.prefix).resolve()

    def ours(path: Path) -> bool:
        return any(path.is_relative_to(r) for r in roots) and not path.is_relative_to(venv) \
            and "site-packages" not in path.parts

    def origin(name: str) -> Path | None:
        mod = sys.modules.get(name)
        file = getattr(mod, "__file__", None) if mod is not None else None
        if file is None:
            try:
                spec = importlib.util.find_spec(name)
            except (ImportError, ValueError, AttributeError):
                return None
            file = spec.origin if spec is not None and spec.has_location else None
        return Path(file).resolve() if file else None

    def imported(path: Path, package: str) -> set[Path]:
        try:
            tree = ast.parse(path.read_bytes())
        except (OSError, SyntaxError, ValueError):
            return set()
        names: list[str] = []
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names += [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
                names += [base] + [f"{base}.{a.name}" for a in node.names]
        found = set()
        for name in names:
            if not name or name.split(".")[0] not in {top, "deft_gym"}:
                continue
            f = origin(name)
            if f is None or not ours(f):
                continue
            if f.suffix in (".so", ".pyd"):  # a compiled kernel: its C source (what it was built from)
                c = f.with_name(f.name.split(".")[0] + ".c")
                if c.exists():
                    found.add(c)
                continue
            if f.suffix == ".py":
                found.add(f)
        return found

    seen: set[Path] = set()
    todo = [(first_path, cls.__module__.rpartition(".")[0] if first_path.name != "__init__.py" else cls.__module__)]
    if first_path.suffix != ".py":
        return ()
    while todo:
        path, package = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        if path.suffix != ".py":
            continue
        for f in imported(path, package):
            if f not in seen:
                pkg = _module_of(f, roots)
                todo.append((f, pkg))
    return tuple(sorted(seen))


def _module_of(path: Path, roots: set[Path]) -> str:
    """The package a source file is in (dotted), for its relative imports."""
    for r in roots:
        if path.is_relative_to(r.parent):
            parts = list(path.relative_to(r.parent).with_suffix("").parts)
            if parts[-1] == "__init__":
                return ".".join(parts[:-1])
            return ".".join(parts[:-1])
    return ""


@functools.cache
def _digest_of(paths: tuple[tuple[str, int, int], ...]) -> str:
    import hashlib

    h = hashlib.sha256()
    for p, _, _ in paths:
        h.update(Path(p).name.encode() + b"\0")
        h.update(Path(p).read_bytes())
    return h.hexdigest()


def source_digest(cls: type) -> str | None:
    """SHA-256 of every source a planner class runs (:func:`planner_sources`: its file, the
    modules of its package and of ``deft_gym`` it imports, the C sources of its compiled kernels);
    None when it has no source file. A change to any of them - ``decision.py`` of the lattice
    planner, its kernel ``_lattice_c.c`` - changes it."""
    try:
        files = planner_sources(cls)
        if not files:
            return None
        return _digest_of(tuple((str(f), f.stat().st_mtime_ns, f.stat().st_size) for f in files))
    except OSError:
        return None


@functools.cache
def planner_provenance(cls: type) -> dict[str, Any]:
    """How to import a planner class anywhere and what it was built from: ``class``
    (``module:Name``), ``root`` (the ``sys.path`` folder its top-level package is in),
    ``source`` (its file relative to ``root``), ``source_sha256``, ``package`` (the installed
    distribution providing it, with version, or None), ``dependencies`` (versions of the
    distributions its module and its package import or require) and ``python``."""
    import inspect
    from importlib import metadata

    from packaging.requirements import Requirement

    cls = hosted_class(cls)
    module = sys.modules.get(cls.__module__) or importlib.import_module(cls.__module__)
    try:
        src = inspect.getsourcefile(cls)
    except TypeError:
        src = None
    path = Path(src).resolve() if src else None
    top = cls.__module__.split(".")[0]
    root = _root_of(path, cls.__module__) if path else None
    dists = metadata.packages_distributions()
    own = (dists.get(top) or [None])[0]
    deps: dict[str, str] = {}
    names = {v.__name__.split(".")[0] for v in vars(module).values() if isinstance(v, type(sys))}
    names |= {getattr(v, "__module__", "").split(".")[0] for v in vars(module).values()
              if isinstance(v, type) or callable(v)}
    wanted = {d for n in names if n and n != top for d in dists.get(n, [])}
    if own:
        for text in metadata.requires(own) or []:
            req = Requirement(text)
            if req.marker is None or "extra" not in str(req.marker):
                wanted.add(req.name)
    for d in sorted(wanted):
        try:
            deps[d] = metadata.version(d)
        except metadata.PackageNotFoundError:
            continue
    return {
        "class": f"{cls.__module__}:{cls.__qualname__}",
        "root": str(root) if root else None,
        "source": str(path.relative_to(root)) if path and root else (str(path) if path else None),
        "source_sha256": source_digest(cls),
        "package": {"name": own, "version": metadata.version(own)} if own else None,
        "dependencies": deps,
        "python": ".".join(map(str, sys.version_info[:3])),
    }


def _root_of(path: Path, module: str) -> Path | None:
    """The folder that holds a module's top-level package (what goes on ``sys.path``)."""
    parts = module.split(".")
    up = len(parts) - (1 if path.name != "__init__.py" else 0)
    root = path.parent
    for _ in range(up):
        root = root.parent
    return root if root.exists() else None


ISOLATION_ENV = "DEFT_GYM_PLANNER_ISOLATION"
ISOLATION_MODES = ("auto", "process", "inline")


def isolation_mode(value: str | None = None) -> str:
    """How planners run: ``value``, else ``DEFT_GYM_PLANNER_ISOLATION``, else ``auto``
    (ValueError naming the variable when it is not one of :data:`ISOLATION_MODES`)."""
    mode = value if value is not None else (os.environ.get(ISOLATION_ENV, "").strip() or "auto")
    if mode not in ISOLATION_MODES:
        raise ValueError(f"{ISOLATION_ENV}={mode!r}: expected one of {', '.join(ISOLATION_MODES)}")
    return mode


def runs_isolated(cls: type, mode: str | None = None) -> bool:
    """Whether a planner class runs in a process of its own (:class:`HostedPlanner`):
    ``process`` - every planner; ``inline`` - none; ``auto`` (the default) - every planner but
    those shipped in ``deft_gym.planner`` (the reference lattice planner keeps the fast path:
    calls in the simulation's process, nothing pickled)."""
    mode = isolation_mode(mode)
    if mode == "auto":
        return not hosted_class(cls).__module__.startswith("deft_gym.planner.")
    return mode == "process"


def load_planner(cls_path: str, map_spec: Mapping[str, Any], params: Mapping[str, Any] | None = None,
                 isolation: str | None = None) -> Planner:
    """Instantiate a planner from its class path, the map spec and its parameters; in a process
    of its own (:class:`HostedPlanner`) when :func:`runs_isolated` says so (``isolation``: a mode
    of :func:`isolation_mode`, e.g. ``inline`` for a checker that must see the planner's calls)."""
    cls = planner_class(cls_path)
    if runs_isolated(cls, isolation):
        return hosted(cls)(map_spec, **dict(params or {}))
    return cls(map_spec, **dict(params or {}))


class HostedPlanner(Planner):
    """A planner that runs in a child process of its own (:class:`deft_gym.execution.isolation.Hosted`)
    behind the same interface, so that nothing it does ends the program that calls it: whatever
    it raises (``SystemExit`` and ``KeyboardInterrupt`` included) comes back as an exception of
    type :class:`~deft_gym.execution.isolation.HostedError` naming what it raised; ending its
    process (``os._exit``, a segmentation fault, a signal) is a
    :class:`~deft_gym.execution.isolation.HostDied`; blocking is the caller's watchdog's hang (the
    child is then killed). Its outputs are the planner's, bit for bit (pickled). Built with
    :func:`hosted` (one subclass per planner class, carrying its ``inputs``); construction errors
    are ValueErrors. :meth:`close` ends the process (also when the object is collected)."""

    hosted_class: type[Planner] = Planner

    def __init__(self, map_spec: Mapping[str, Any], **params: Any) -> None:
        from deft_gym.execution.isolation import HostDied, Hosted, HostedError

        self.map_spec = dict(map_spec)
        self.params = params
        cls = self.hosted_class
        name = f"{cls.__module__}:{cls.__qualname__}"
        try:
            import inspect

            try:
                source = inspect.getsourcefile(cls) or ""
            except TypeError:
                source = ""
            self._host = Hosted(lambda: cls(map_spec, **params), f"the planner {name}", source)
        except (HostedError, HostDied) as exc:
            describe = getattr(exc, "describe", None)
            raise ValueError(describe() if callable(describe) else str(exc)) from None

    @property
    def state(self) -> Any:  # type: ignore[override]
        """A copy of the hosted planner's state (:meth:`snapshot`)."""
        return self.snapshot()

    def reset(self) -> None:
        self._host.call("reset")

    def plan(self, frame: Frame) -> dict[str, Any] | None:
        return self._host.call("plan", Frame(frame.time, dict(frame.inputs)))

    def snapshot(self) -> Any:
        return self._host.call("snapshot")

    def restore(self, snapshot: Any) -> None:
        self._host.call("restore", snapshot)

    def export_state(self) -> dict[str, Any] | None:
        return self._host.call("export_state")

    def load_state(self, state: Mapping[str, Any]) -> None:
        from deft_gym.execution.isolation import HostedError

        try:
            self._host.call("load_state", dict(state))
        except HostedError as exc:
            if exc.type_name in ("ValueError", "TypeError", "KeyError"):
                raise ValueError(exc.describe()) from None
            raise

    @classmethod
    def hard_clearance(cls, params: Mapping[str, Any]) -> float:
        return cls.hosted_class.hard_clearance(params)

    def close(self) -> None:
        """End the planner's process."""
        host = getattr(self, "_host", None)
        if host is not None:
            host.close()


@functools.cache
def hosted(cls: type[Planner]) -> type[HostedPlanner]:
    """The :class:`HostedPlanner` subclass standing for planner class ``cls`` (same ``inputs``)."""
    return type(f"Hosted{cls.__name__}", (HostedPlanner,),
                {"hosted_class": cls, "inputs": tuple(cls.inputs), "__doc__": cls.__doc__,
                 "__module__": HostedPlanner.__module__})


def planner_class(cls_path: str) -> type[Planner]:
    """The :class:`Planner` subclass ``module:Class`` names (ValueError otherwise)."""
    cls = import_object(cls_path)
    if not (isinstance(cls, type) and issubclass(cls, Planner)):
        raise ValueError(f"{cls_path} is not a deft_gym.planner.base.Planner subclass")
    return cls


def resolve_inputs(cls: type[Planner], configured: Sequence[str] | None, where: str = "planning.subscribe") -> list[str]:
    """The roles a planner reads: its class's :attr:`Planner.inputs`; a configured list must name
    the same roles (in any order), else ValueError saying what differs."""
    declared = list(cls.inputs)
    if configured is None or sorted(configured) == sorted(declared):
        return declared
    extra, missing = sorted(set(configured) - set(declared)), sorted(set(declared) - set(configured))
    what = "; ".join(filter(None, [f"{extra} not read by the planner" if extra else "",
                                   f"{missing} missing" if missing else ""]))
    raise ValueError(f"{where} {list(configured)} does not match {cls.__module__}:{cls.__qualname__}.inputs "
                     f"{declared} ({what}); leave it out to use the planner's")


# -- the output contract --------------------------------------------------------------------------
def validate_output(out: Any, frame_time: float) -> list[str]:
    """What is wrong with a planner output under the output contract (the module docstring),
    one short phrase each; empty when it is valid. ``None`` (no plan) is valid."""
    if out is None:
        return []
    if not isinstance(out, Mapping):
        return [f"output is a {type(out).__name__}, expected a dict with 'trajectory'"]
    tr = out.get("trajectory")
    if not isinstance(tr, Mapping):
        return ["output has no 'trajectory' object"]
    problems = []
    n = None
    numbers = {float, int}
    for key in [*TRAJECTORY_FIELDS, *(k for k in tr if k not in TRAJECTORY_FIELDS)]:
        col = tr.get(key)
        if col is None:
            problems.append(f"trajectory.{key} missing")
            continue
        if not isinstance(col, list | tuple) or not set(map(type, col)) <= numbers:
            problems.append(f"trajectory.{key} is not a list of numbers")
            continue
        if not all(map(math.isfinite, col)):
            problems.append(f"trajectory.{key} has a non-finite value")
        if n is None:
            n = len(col)
        elif len(col) != n:
            problems.append(f"trajectory.{key} has {len(col)} points, trajectory.t {n}")
    t = tr.get("t")
    if isinstance(t, list | tuple) and set(map(type, t)) <= numbers:
        if len(t) < 2:
            problems.append(f"trajectory has {len(t)} point(s), expected at least 2")
        elif not all(b > a for a, b in itertools.pairwise(t)):
            problems.append("trajectory.t is not strictly increasing")
        if t and not abs(t[0] - frame_time) <= T0_TOLERANCE:
            problems.append(f"trajectory.t[0] = {t[0]!r} s, expected the frame time {frame_time!r} s (absolute times)")
    dec = out.get("decision")
    if dec is not None and not isinstance(dec, Mapping):
        problems.append(f"decision is a {type(dec).__name__}, expected an object")
    return problems


# -- seeding: plain values of a state --------------------------------------------------------------
def to_plain(value: Any) -> Any:
    """A state value as plain JSON values that :func:`from_plain` turns back into the same value
    (numpy arrays keep dtype, shape and every bit; tuples stay tuples)."""
    if isinstance(value, np.ndarray):
        return {"__ndarray__": value.tolist(), "dtype": value.dtype.str, "shape": list(value.shape)}
    if isinstance(value, tuple):
        return {"__tuple__": [to_plain(v) for v in value]}
    if isinstance(value, list):
        return [to_plain(v) for v in value]
    if isinstance(value, Mapping):
        if not all(isinstance(k, str) for k in value):
            raise TypeError("state dicts must have string keys to be exported")
        return {k: to_plain(v) for k, v in value.items()}
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, bool | int | float | str):
        return value
    raise TypeError(f"cannot export a {type(value).__name__} as plain state")


def from_plain(value: Any) -> Any:
    """Inverse of :func:`to_plain`."""
    if isinstance(value, list):
        return [from_plain(v) for v in value]
    if isinstance(value, Mapping):
        if "__ndarray__" in value:
            return np.array(value["__ndarray__"], dtype=np.dtype(value["dtype"])).reshape(value["shape"])
        if "__tuple__" in value:
            return tuple(from_plain(v) for v in value["__tuple__"])
        return {k: from_plain(v) for k, v in value.items()}
    return value
