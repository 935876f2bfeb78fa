"""Moving an item's files between the driver and the node that runs it (Ray backend).

An item names the files it reads (``inputs``) and the files and folders it writes
(``artifacts``) by their paths on the driver. Two ways for them to travel:

- **shared path** (nothing travels): the run folder is on a file system every node mounts at the
  same path (NFS, a cluster file system). Detected per item: the driver writes a token file into
  the run folder and a task that can read it at the same path writes there directly. Forced with
  ``DEFT_GYM_ARTIFACTS=shared``.
- **returned to the driver**: a task that cannot see the token writes under the same path on its
  node (relative paths against the driver's working directory, made there if missing), then returns the artifacts as one tar archive with its result, and removes
  them from the node; the driver writes each file atomically (:func:`deft_gym.files.write_atomic`)
  where the item would have written it. Inputs go the other way, as an object in Ray's object
  store that the task fetches only when it cannot see them. Forced with ``DEFT_GYM_ARTIFACTS=return``.
"""

from __future__ import annotations

import io
import os
import shutil
import tarfile
import uuid
from collections.abc import Sequence
from pathlib import Path

from deft_gym.files import write_atomic

MODES = ("auto", "shared", "return")
ENV = "DEFT_GYM_ARTIFACTS"


def mode(override: str | None = None) -> str:
    """``auto`` (default), ``shared`` or ``return``: ``override``, else ``$DEFT_GYM_ARTIFACTS``."""
    m = override or os.environ.get(ENV) or "auto"
    if m not in MODES:
        from deft_gym.execution import BackendError

        raise BackendError(f"{ENV}: expected one of {', '.join(MODES)}, got {m!r}")
    return m


def write_token(run_dir: Path) -> Path:
    """A file only the driver's file system (and file systems shared with it) hold."""
    path = run_dir / f".execution-token-{uuid.uuid4().hex[:12]}"
    write_atomic(path, "run folder of a DeFT-Gym campaign; tasks that see this file write here directly\n")
    return path


def pack(paths: Sequence[str]) -> bytes:
    """The files under ``paths`` (files or folders; missing ones skipped) as a tar archive; a
    relative path stays relative (to the driver's working directory, where it is unpacked)."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for p in paths:
            if os.path.exists(p):
                name = os.path.normpath(p)
                tar.add(p, arcname=("abs" + name) if os.path.isabs(name) else ("rel/" + name))
    return buf.getvalue()


def unpack(blob: bytes) -> list[str]:
    """Write every file of a :func:`pack` archive where it was (relative paths against the
    working directory), atomically; returns the paths written."""
    out = []
    with tarfile.open(fileobj=io.BytesIO(blob), mode="r") as tar:
        for m in tar.getmembers():
            f = tar.extractfile(m) if m.isfile() else None
            if f is None:
                continue
            kind, _, name = m.name.partition("/")
            path = "/" + name if kind == "abs" else name
            write_atomic(path, f.read())
            out.append(path)
    return out


def enter_working_dir(cwd: str) -> None:
    """Resolve an item's relative paths as the driver does: work in the driver's working
    directory (created on a node that lacks it)."""
    try:
        os.makedirs(cwd, exist_ok=True)
        os.chdir(cwd)
    except OSError:
        import tempfile

        os.chdir(tempfile.mkdtemp(prefix="deft-gym-"))


def remove(paths: Sequence[str]) -> None:
    """Delete what :func:`pack` shipped from a node that does not share the run folder."""
    for p in paths:
        if os.path.isdir(p):
            shutil.rmtree(p, ignore_errors=True)
        elif os.path.exists(p):
            os.remove(p)
