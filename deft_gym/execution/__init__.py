"""The execution layer every campaign runs on: work items in, results out in item order, with
progress and resume from an append-only record, on a backend chosen at run time.

- ``local`` (default, no Ray needed): worker processes of this machine (forkserver, started once
  per :class:`Executor` and reused by all its maps; one worker runs in this process);
- ``ray``: tasks on a Ray instance - a local one (``--ray``) or a cluster (``--ray-address ADDR``
  or ``RAY_ADDRESS``). A task whose worker process or node dies is retried by Ray
  (``max_retries``); an item's result is taken once, so the record holds no duplicates.

Results do not depend on the backend or the number of workers: an item carries its own seeds,
and :meth:`Executor.map` yields results in item order whatever order they finish in, so records
appended as results arrive are the same file on one worker, sixteen, or a cluster. Artifacts that
remote items write (logs, extracted tests, renders) reach the run folder: see
:mod:`deft_gym.execution.transfer` and docs/distributed.md.

Layer 0 (docs/architecture.md): imports nothing of deft_gym but :mod:`deft_gym.config` and
:mod:`deft_gym.files`, so ``extract`` uses it too.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
import sys
from collections.abc import Callable, Hashable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar

from deft_gym.config import ConfigError
from deft_gym.files import append_jsonl, read_jsonl

T = TypeVar("T")
R = TypeVar("R")

RAY_MISSING = "Ray is not installed; install it with: pip install 'deft-gym[ray]'"
DEFAULT_RETRIES = 3  # Ray task retries when a worker process or node dies


class BackendError(ConfigError):
    """A backend that cannot be used (Ray missing, a cluster that does not answer); one line
    naming the flag. A :class:`~deft_gym.config.ConfigError`, so the programs exit 2 on it."""


class WorkerLost(RuntimeError):
    """A local worker process died; what the record holds is kept (run the command again)."""


@dataclass(frozen=True)
class Backend:
    """Where work items run: ``local`` processes or ``ray`` (a local instance when ``address``
    is None, else the cluster at ``address``); ``workers`` [processes] is the local pool's size
    and a local Ray instance's CPUs (a cluster runs as many items at once as it has CPUs)."""

    kind: Literal["local", "ray"] = "local"
    workers: int = 1
    address: str | None = None
    max_retries: int = DEFAULT_RETRIES

    def describe(self) -> str:
        if self.kind == "local":
            return f"{self.workers} local worker process{'es' if self.workers != 1 else ''}"
        return f"Ray cluster at {self.address}" if self.address else f"local Ray instance ({self.workers} CPUs)"


def add_backend_arguments(parser: argparse.ArgumentParser) -> None:
    """``--ray`` and ``--ray-address`` (see :func:`backend_from_args`)."""
    parser.add_argument("--ray", action="store_true",
                        help="run on Ray: a local instance of --workers CPUs, or the cluster in RAY_ADDRESS")
    parser.add_argument("--ray-address", default=None, metavar="ADDR",
                        help="run on the Ray cluster at ADDR (e.g. ray://head:10001 or head:6379); implies --ray")


def backend_from_args(args: argparse.Namespace, workers: int) -> Backend:
    """The backend the flags ask for: ``--ray-address ADDR`` > ``--ray`` with ``RAY_ADDRESS`` set
    > ``--ray`` (a local Ray instance) > local processes. Ray is connected here, so a missing
    Ray or a cluster that does not answer is a :class:`BackendError` before any work starts."""
    if workers < 1:
        raise BackendError(f"--workers: must be at least 1, got {workers}")
    address = getattr(args, "ray_address", None)
    if address is None and getattr(args, "ray", False):
        address = os.environ.get("RAY_ADDRESS") or None
    if not (getattr(args, "ray", False) or address):
        return Backend("local", workers)
    backend = Backend("ray", workers, address)
    from deft_gym.execution.ray_backend import connect

    connect(backend, "--ray-address" if getattr(args, "ray_address", None) else "--ray")
    return backend


def ray_installed() -> bool:
    """Is Ray importable here (``pip install 'deft-gym[ray]'``)?"""
    return importlib.util.find_spec("ray") is not None


# -- resume -----------------------------------------------------------------------------------------
class Record:
    """An append-only JSON-lines record of finished work (:mod:`deft_gym.files`): read on start
    (a line cut by a kill is skipped), appended as results arrive; what it holds is not run again."""

    def __init__(self, path: Path | str, fsync: bool = False) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fsync = fsync
        self.rows: list[dict[str, Any]] = read_jsonl(self.path)

    def add(self, row: dict[str, Any]) -> None:
        self.rows.append(row)
        append_jsonl(self.path, row, fsync=self.fsync)

    def keys(self, *fields: str) -> set[tuple[Any, ...]]:
        """The ``fields`` of every row, as tuples (what is done)."""
        return {tuple(r.get(f) for f in fields) for r in self.rows}

    def todo(self, items: Iterable[T], key: Callable[[T], Hashable], *fields: str) -> list[T]:
        """The ``items`` whose ``key`` is not among the rows' ``fields``, in item order."""
        done = self.keys(*fields)
        return [i for i in items if key(i) not in done]


# measured durations: the only fields of a record that differ between runs of the same items
TIMING_KEYS = frozenset({"seconds", "cpu_seconds", "wall_time", "wall_s", "wall", "process_cpu", "max_compute_s",
                         "cpu_s", "metric_cpu_s"})  # cpu_s, metric_cpu_s: what the driving-quality metrics cost


def without_timings(value: Any) -> Any:
    """``value`` (records: dicts, lists) without its :data:`TIMING_KEYS`: what must be identical
    whatever the backend and the number of workers."""
    if isinstance(value, dict):
        return {k: without_timings(v) for k, v in value.items() if k not in TIMING_KEYS}
    if isinstance(value, list):
        return [without_timings(v) for v in value]
    return value


# -- running ----------------------------------------------------------------------------------------
class Progress:
    """What an item function that reports its own progress gets: ``put(n)`` adds ``n`` units."""

    def __init__(self, sink: Callable[[int], None]) -> None:
        self._sink = sink

    def put(self, n: int = 1) -> None:
        self._sink(n)


def importable(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` as its module's attribute when it was defined in ``__main__`` of ``python -m MOD``,
    so worker processes and Ray workers import it by name instead of copying it."""
    if getattr(fn, "__module__", None) != "__main__":
        return fn
    spec = getattr(sys.modules["__main__"], "__spec__", None)
    if spec is None or not spec.name:
        return fn
    return getattr(importlib.import_module(spec.name), fn.__qualname__, fn)


class _Pool:
    """What :meth:`Executor.map` needs of a backend."""

    concurrency: int

    def submit(self, fn: Callable[..., Any], item: Any, with_progress: bool,
               artifacts: Sequence[str], inputs: Sequence[str]) -> Any: ...

    def wait(self, handles: list[Any], timeout: float) -> set[Any]: ...

    def result(self, handle: Any) -> Any: ...

    def cancel(self, handles: Iterable[Any]) -> None: ...

    def drain(self) -> int: ...

    def close(self) -> None: ...


class Executor:
    """Maps work items to results on one backend; start it once per campaign (a context
    manager) and call :meth:`map` for each phase: the worker processes (or the Ray connection)
    are reused. ``initializer(*initargs)`` runs once in every worker process. ``preload``:
    modules the local forkserver imports once, so that each worker starts as a fork of a warm
    process. ``run_dir``: the run folder that artifacts must reach (Ray)."""

    def __init__(self, backend: Backend | None = None, *, initializer: Callable[..., None] | None = None,
                 initargs: tuple[Any, ...] = (), preload: Sequence[str] = (), run_dir: Path | str | None = None,
                 artifacts_mode: str | None = None) -> None:
        self.backend = backend or Backend()
        self.initializer, self.initargs = initializer, initargs
        self.preload = tuple(preload)
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.artifacts_mode = artifacts_mode
        self._pool: _Pool | None = None

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def serial(self) -> bool:
        """One local worker: items run in this process."""
        return self.backend.kind == "local" and self.backend.workers <= 1

    def _start(self, fn: Callable[..., Any]) -> _Pool:
        if self._pool is None:
            if self.backend.kind == "ray":
                from deft_gym.execution.ray_backend import RayPool

                self._pool = RayPool(self.backend, self.initializer, self.initargs, self.run_dir,
                                     self.artifacts_mode)
            else:
                from deft_gym.execution.local import LocalPool

                self._pool = LocalPool(self.backend.workers, self.initializer, self.initargs,
                                       (*self.preload, getattr(fn, "__module__", "")))
        return self._pool

    def map(self, fn: Callable[..., R], items: Iterable[Any], *, progress: Callable[[int], None] | None = None,
            item_progress: bool = False, artifacts: Callable[[Any], Sequence[Path | str]] | None = None,
            inputs: Callable[[Any], Sequence[Path | str]] | None = None) -> Iterator[R]:
        """``fn(item)`` for every item, yielded in item order (results that finish early wait for
        the ones before them). ``progress(n)`` is called as work is done: one per item, or, with
        ``item_progress``, the units ``fn(item, progress)`` reports through
        :class:`Progress`. ``artifacts(item)``: files and folders the item writes that must reach
        the run folder; ``inputs(item)``: files it reads that must reach its node (Ray, see
        :mod:`deft_gym.execution.transfer`). Closing the iterator early cancels what has not run."""
        items = list(items)
        if not items:
            return
        if self.serial:
            direct = Progress(progress or (lambda n: None))
            for item in items:
                res = fn(item, direct) if item_progress else fn(item)
                if progress is not None and not item_progress:
                    progress(1)
                yield res
            return
        fn = importable(fn)
        pool = self._start(fn)
        running_cap = 2 * pool.concurrency  # queued or running at once: keeps every worker busy
        ahead_cap = max(8 * pool.concurrency, 64)  # finished results waiting for an earlier one
        pending: dict[int, Any] = {}
        finished: dict[int, R] = {}
        submitted = nxt = 0
        try:
            while nxt < len(items):
                while submitted < len(items) and len(pending) < running_cap and \
                        len(pending) + len(finished) < ahead_cap:
                    item = items[submitted]
                    pending[submitted] = pool.submit(
                        fn, item, item_progress, [str(p) for p in artifacts(item)] if artifacts else [],
                        [str(p) for p in inputs(item)] if inputs else [])
                    submitted += 1
                done = pool.wait(list(pending.values()), 0.2)
                for i in sorted(i for i, h in pending.items() if h in done):
                    finished[i] = pool.result(pending.pop(i))
                    if progress is not None and not item_progress:
                        progress(1)
                ticks = pool.drain()
                if ticks and progress is not None and item_progress:
                    progress(ticks)
                while nxt in finished:
                    yield finished.pop(nxt)
                    nxt += 1
        finally:
            if pending:
                pool.cancel(pending.values())

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None


def executor_for(args: argparse.Namespace, workers: int, **kwargs: Any) -> Executor:
    """An :class:`Executor` on the backend the flags ask for (:func:`backend_from_args`)."""
    return Executor(backend_from_args(args, workers), **kwargs)
