"""The Ray backend: every work item is one Ray task (1 CPU) on a local Ray instance or a cluster.

Ray does the distributed parts: scheduling over the nodes, retrying a task whose worker process
or node died (``max_retries``), shipping items and results through its object store, waiting
(``ray.wait``), cancelling. This module only adds what a campaign needs on top: each worker
process runs the initializer once, progress units flow back through a :class:`ray.util.queue.Queue`,
and artifacts reach the run folder (:mod:`deft_gym.execution.transfer`).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

from deft_gym.execution import RAY_MISSING, Backend, BackendError, Progress, WorkerLost, transfer
from deft_gym.execution.watchdog import apply_env, carried_env
from deft_gym.files import first_line

LOCAL_OBJECT_STORE = 256 * 2**20  # [bytes] a local instance's object store: items and results are small


def code_paths() -> list[str]:
    """The driver's own code on ``sys.path`` (not the standard library or installed packages):
    a local Ray instance's workers import the same code as the driver (a checkout, a worktree,
    the tests' folder), not whatever copy is installed."""
    prefixes = {os.path.realpath(p) for p in (sys.prefix, sys.base_prefix, sys.exec_prefix)}
    out = []
    for p in sys.path:
        real = os.path.realpath(p or os.getcwd())
        if os.path.isdir(real) and not any(real.startswith(x + os.sep) or real == x for x in prefixes) \
                and "site-packages" not in real and real not in out:
            out.append(real)
    return out


def connect(backend: Backend, flag: str = "--ray") -> None:
    """Connect to the backend's Ray (start a local instance of ``backend.workers`` CPUs, or join
    the cluster at ``backend.address``); an existing connection is reused."""
    try:
        import ray
    except ImportError:
        raise BackendError(f"{flag}: {RAY_MISSING}") from None
    if ray.is_initialized():
        return
    path = os.pathsep.join([*code_paths(), *filter(None, [os.environ.get("PYTHONPATH")])])
    try:
        if backend.address:  # the cluster's workers get the path and the warm-up through the job's runtime env
            ray.init(address=backend.address, log_to_driver=True, runtime_env={
                "env_vars": {"PYTHONPATH": path}, "worker_process_setup_hook": f"{__name__}.warm_worker"})
        else:  # a local instance's workers inherit this environment: the workers Ray starts with it serve at once
            os.environ["PYTHONPATH"] = path
            # Ray runs its workers at nice 15; on a machine shared with other work that starves
            # a campaign the local backend would run at normal priority
            ray.init(num_cpus=backend.workers, object_store_memory=LOCAL_OBJECT_STORE, include_dashboard=False,
                     log_to_driver=True, _system_config={"worker_niceness": 0})
            warm = ray.remote(num_cpus=1)(warm_worker)
            for _ in range(backend.workers):  # import the simulation while the driver prepares its items
                warm.remote()
    except (ConnectionError, RuntimeError, ValueError, TimeoutError) as err:
        where = f"the Ray cluster at {backend.address}" if backend.address else "a local Ray instance"
        first = first_line(err)
        raise BackendError(f"{flag}: cannot connect to {where}: {first}") from None


WARM_MODULES = ("deft_gym.sim.simulation",)  # what every campaign's items import (highway-env, the ADS)


def warm_worker() -> None:
    """Ray runs this when it starts a worker process (before any task): the simulation stack is
    imported while the driver still prepares its items, not when the first item arrives."""
    import importlib

    for m in WARM_MODULES:
        importlib.import_module(m)


_READY: set[int] = set()  # ids of the initializers this worker process has run


def _task(fn: Callable[..., Any], item: Any, with_progress: bool, queue: Any,
          init: tuple[Any, tuple[Any, ...], dict[str, str | None]],
          artifacts: Sequence[str], token: str | None, mode: str, inputs: list[Any], cwd: str) -> tuple[Any, bytes | None]:
    """One item in a Ray worker process: ``(result, artifacts archive or None)``."""
    initializer, initargs, env = init
    apply_env(env)  # settings of the driver (e.g. --watchdog-s) that a worker must follow
    if os.getcwd() != cwd:
        transfer.enter_working_dir(cwd)
    if initializer is not None and id(initializer) not in _READY:
        initializer(*initargs)
        _READY.add(id(initializer))
    ship = mode == "return" or (mode == "auto" and token is not None and not os.path.exists(token))
    if ship and inputs:
        import ray

        transfer.unpack(ray.get(inputs[0]))
    res = fn(item, Progress(queue.put)) if with_progress else fn(item)
    blob = None
    if ship and artifacts:
        blob = transfer.pack(artifacts)
        transfer.remove(artifacts)
    return res, blob


class RayPool:
    """Items as Ray tasks; the connection is made by :func:`connect` (and kept: Ray shuts it
    down at exit)."""

    def __init__(self, backend: Backend, initializer: Callable[..., None] | None, initargs: tuple[Any, ...],
                 run_dir: Path | None, artifacts_mode: str | None) -> None:
        import ray

        connect(backend)
        self.ray = ray
        self.mode = transfer.mode(artifacts_mode)
        self.remote = ray.remote(_task).options(num_cpus=1, max_retries=backend.max_retries,
                                                retry_exceptions=False)
        self.concurrency = max(int(ray.cluster_resources().get("CPU", 1)), 1) if backend.address \
            else backend.workers
        self.init = (initializer, initargs, carried_env())
        self.retries = backend.max_retries
        self.token = None
        if run_dir is not None and self.mode == "auto":
            self.token = transfer.write_token(run_dir)
        self.remote_nodes = bool(backend.address) or self.mode == "return"
        self.queue: Any = None

    def submit(self, fn: Callable[..., Any], item: Any, with_progress: bool, artifacts: Sequence[str],
               inputs: Sequence[str]) -> Any:
        if with_progress and self.queue is None:
            from ray.util.queue import Queue

            self.queue = Queue(actor_options={"num_cpus": 0})
        # inputs travel only where a node may not see them; nested in a list, a task fetches them
        # only when it needs them
        blob = [self.ray.put(transfer.pack(inputs))] if inputs and self.remote_nodes and self.mode != "shared" else []
        return self.remote.remote(fn, item, with_progress, self.queue if with_progress else None, self.init,
                                  list(artifacts), str(self.token.resolve()) if self.token else None, self.mode, blob,
                                  os.getcwd())

    def wait(self, handles: list[Any], timeout: float) -> set[Any]:
        ready, _ = self.ray.wait(handles, num_returns=1, timeout=timeout)
        if ready:
            ready, _ = self.ray.wait(handles, num_returns=len(handles), timeout=0)
        return set(ready)

    def result(self, handle: Any) -> Any:
        from ray.exceptions import NodeDiedError, WorkerCrashedError

        try:
            value, blob = self.ray.get(handle)
        except (WorkerCrashedError, NodeDiedError) as err:  # after Ray's retries
            raise WorkerLost(f"an item was lost {1 + self.retries} times as its worker died: "
                             f"{first_line(err)}; the record keeps every finished item") from None
        if blob:
            transfer.unpack(blob)
        return value

    def cancel(self, handles: Iterable[Any]) -> None:
        for h in handles:
            self.ray.cancel(h)

    def drain(self) -> int:
        if self.queue is None:
            return 0
        n = self.queue.qsize()
        return int(sum(self.queue.get_nowait_batch(n))) if n else 0

    def close(self) -> None:
        if self.queue is not None:
            self.queue.shutdown()
            self.queue = None
        if self.token is not None:
            self.token.unlink(missing_ok=True)

