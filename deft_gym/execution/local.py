"""The local backend: a pool of worker processes on this machine.

Workers are forks of a forkserver that imported the item function's module (and ``preload``)
once, so a worker starts in milliseconds instead of importing torch and highway-env again;
items are submitted one at a time (no chunks: a slow item never holds others back) and at most
two per worker wait in the queue. A worker ends when the process that started it is gone (killed,
``kill -9`` included): it does not go on simulating, or writing into the run folder, beside the
run that resumes it.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue as queue_mod
import sys
import threading
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from deft_gym.execution import Progress, WorkerLost
from deft_gym.execution.watchdog import apply_env, carried_env

_QUEUE: Any = None  # this worker's progress queue (set by _init)


def _exit_with_parent() -> None:
    """End this worker as soon as the process that started it is gone (a daemon thread waits on
    the parent's sentinel, which closes when it exits, however it exits)."""
    parent = mp.parent_process()
    if parent is None:
        return

    def watch() -> None:
        parent.join()
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def _init(q: Any, initializer: Callable[..., None] | None, initargs: tuple[Any, ...],
          env: dict[str, str | None] | None = None) -> None:
    global _QUEUE
    _exit_with_parent()
    _QUEUE = q
    apply_env(env)  # the forkserver may be older than the setting (e.g. --watchdog-s)
    if initializer is not None:
        initializer(*initargs)


def _call(fn: Callable[..., Any], item: Any, with_progress: bool) -> Any:
    return fn(item, Progress(_QUEUE.put)) if with_progress else fn(item)


class LocalPool:
    """``workers`` processes, started on first use and reused until :meth:`close`."""

    def __init__(self, workers: int, initializer: Callable[..., None] | None, initargs: tuple[Any, ...],
                 preload: Sequence[str]) -> None:
        ctx = mp.get_context("forkserver")
        # not the module run as ``python -m MOD``: each worker runs it as ``__mp_main__`` anyway,
        # and finding it already imported makes runpy warn in every worker
        main_spec = getattr(sys.modules.get("__main__"), "__spec__", None)
        skip = {"", "__main__", getattr(main_spec, "name", None)}
        ctx.set_forkserver_preload([m for m in preload if m not in skip])
        self.concurrency = workers
        self.queue = ctx.Queue()
        self.pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init,
                                        initargs=(self.queue, initializer, initargs, carried_env()))

    def submit(self, fn: Callable[..., Any], item: Any, with_progress: bool, artifacts: Sequence[str],
               inputs: Sequence[str]) -> Future[Any]:
        try:
            return self.pool.submit(_call, fn, item, with_progress)
        except BrokenProcessPool as err:
            raise WorkerLost(_LOST) from err

    def wait(self, handles: list[Future[Any]], timeout: float) -> set[Future[Any]]:
        return wait(handles, timeout, return_when=FIRST_COMPLETED).done

    def result(self, handle: Future[Any]) -> Any:
        try:
            return handle.result()
        except BrokenProcessPool as err:
            raise WorkerLost(_LOST) from err

    def cancel(self, handles: Iterable[Future[Any]]) -> None:
        for h in handles:
            h.cancel()

    def drain(self) -> int:
        n = 0
        while True:
            try:
                n += int(self.queue.get_nowait())
            except queue_mod.Empty:
                return n

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)
        self.queue.close()


_LOST = ("a worker process died (killed, or out of memory); the record keeps every finished item: "
         "run the same command again to resume (on Ray, with --ray, lost items are retried)")
