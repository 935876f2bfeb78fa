"""Files that are never half-written: atomic writes (``<name>.tmp`` + rename) and append-only
JSON-lines records that survive a kill at any point (a torn last line is skipped on reading).
Shared by every package that writes results.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any


def write_atomic(path: Path | str, data: str | bytes) -> Path:
    """Write a file (text as UTF-8, or bytes) via ``<name>.tmp`` and rename, so readers never
    see half of it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data.encode() if isinstance(data, str) else data)
    os.replace(tmp, path)
    return path


@contextlib.contextmanager
def atomic_path(path: Path | str) -> Iterator[Path]:
    """A temporary name beside ``path`` (``.<stem>.tmp<suffix>``: the same suffix, for writers that
    pick the format from it) for a writer that needs a file name, renamed to ``path`` when the
    block succeeds and removed when it fails: a kill never leaves half a file under the name that
    says it is done."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def append_jsonl(path: Path | str, record: Any, fsync: bool = False) -> None:
    """Append one JSON line to ``path`` in a single write of the whole line (no torn lines on
    a crash); ``fsync`` also forces it to disk. A last line cut by an earlier crash (no newline
    at its end) is ended first, so it cannot swallow this record."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    line = json.dumps(record, sort_keys=True) + "\n"
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o644)
    try:
        size = os.fstat(fd).st_size
        if size and os.pread(fd, 1, size - 1) != b"\n":
            line = "\n" + line
        os.write(fd, line.encode())
        if fsync:
            os.fsync(fd)
    finally:
        os.close(fd)


def read_jsonl(path: Path | str) -> list[Any]:
    """The records of an append-only JSON-lines file (none if it does not exist); a line cut
    by an interruption is skipped."""
    path = Path(path)
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


def write_json_atomic(path: Path, data: Any) -> Path:
    """Write ``data`` as indented JSON, atomically (:func:`write_atomic`)."""
    return write_atomic(path, json.dumps(data, indent=1, sort_keys=True, default=str))


# -- one writer per output folder --------------------------------------------------------------------
LOCK_NAME = ".deft-gym.lock"


class FolderBusy(RuntimeError):
    """Another process is writing the output folder (one line: the folder and its holder)."""


_HELD: dict[tuple[int, int], list[Any]] = {}  # (device, inode) of a locked folder -> [fd, depth]


@contextlib.contextmanager
def folder_lock(folder: Path | str, what: str | None = None) -> Iterator[Path]:
    """Hold ``folder`` (created if needed) for this process while the block runs: a second
    process that asks for it gets :class:`FolderBusy` naming the folder and the holder (its pid,
    command and start time) at once, instead of both writing the same records and logs.

    The lock is ``flock`` on ``FOLDER/.deft-gym.lock``, which the kernel releases when the
    holder's process ends however it ends (``kill -9`` included): a lock left by a killed run
    never blocks the next one; the file itself stays, naming the last holder. Re-entrant within
    one process (a program that runs another program in-process on the same folder). The
    processes a holder starts (workers, a recorder) write under its lock. A folder this call
    created that holds nothing but the lock file at the end (a run refused before any work) is
    removed again."""
    import fcntl
    import socket
    import sys
    import time

    folder = Path(folder)
    made = [p for p in (folder, *folder.parents) if not p.exists()]  # the folders this call creates
    folder.mkdir(parents=True, exist_ok=True)
    st = os.stat(folder)
    key = (st.st_dev, st.st_ino)
    held = _HELD.get(key)
    if held is not None:
        held[1] += 1
        try:
            yield folder
        finally:
            held[1] -= 1
        return
    path = folder / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = _holder(fd)
        os.close(fd)
        raise FolderBusy(f"{folder} is being written by another process ({holder}); wait for it to end or "
                         "choose another --out") from None
    try:
        info = {"pid": os.getpid(), "host": socket.gethostname(), "since": time.strftime("%Y-%m-%d %H:%M:%S"),
                "command": what or " ".join([os.path.basename(sys.argv[0] or "python"), *sys.argv[1:]])[:300]}
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(info) + "\n").encode(), 0)
    except OSError:
        pass  # a full disk: the lock holds without its description
    _HELD[key] = [fd, 1]
    try:
        yield folder
    finally:
        _HELD.pop(key, None)
        if made and [p.name for p in folder.iterdir()] == [LOCK_NAME]:  # nothing written: nothing left
            with contextlib.suppress(OSError):
                path.unlink()
                for p in made:
                    p.rmdir()
        os.close(fd)  # releases the lock


def _holder(fd: int) -> str:
    """What the lock file says about its holder, one short phrase."""
    try:
        info = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
    except (OSError, ValueError):
        info = {}
    if not isinstance(info, dict) or "pid" not in info:
        return "its description is not readable"
    return f"pid {info.get('pid')} on {info.get('host', '?')}, since {info.get('since', '?')}: {info.get('command', '?')}"


# -- compiled kernels that match their sources ---------------------------------------------------------
def file_sha256(path: Path | str) -> str | None:
    """SHA-256 (hex) of a file's bytes, or None when it cannot be read."""
    import hashlib

    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return None


def stale_kernel(kernel: Any, c_source: Path | str, mirrors: Path | str) -> str | None:
    """Why a compiled kernel must not be used, or None when it was built from the files beside it:
    its ``BUILT_FROM`` (setup.py) holds the digests of its C source and of the Python file it stands
    in for; a build without them, or one older than an edit of either file, would run other code
    than the source says (an edit of the Python version would have no effect). A C source that is
    not installed (a wheel) is not compared; the Python file always is."""
    built = str(getattr(kernel, "BUILT_FROM", "") or "").split()
    name = getattr(kernel, "__name__", "kernel")
    if len(built) != 2:
        return f"{name} records no digests of its sources (built before they were recorded)"
    c_now, py_now = file_sha256(c_source), file_sha256(mirrors)
    if py_now is not None and py_now != built[1]:
        return f"{name} was built before the last edit of {Path(mirrors).name}"
    if c_now is not None and c_now != built[0]:
        return f"{name} was built before the last edit of {Path(c_source).name}"
    return None


def checked_kernel(kernel: Any, c_source: Path | str, mirrors: Path | str) -> Any:
    """``kernel`` when :func:`stale_kernel` finds nothing, else None after a warning (once per
    kernel) naming why and how to rebuild: the Python version runs, as the source says."""
    if kernel is None:
        return None
    why = stale_kernel(kernel, c_source, mirrors)
    if why is None:
        return kernel
    import warnings

    warnings.warn(f"{why}: using the Python version (the same results, slower); rebuild the kernels with "
                  "`pip install -e .` (or `make venv`)", RuntimeWarning, stacklevel=2)
    return None


def first_line(exc: BaseException, default: str | None = None) -> str:
    """The first non-blank line of ``str(exc)`` (for one-line error messages), else ``default``,
    else the exception's type name (an exception without a message has no line to show)."""
    for line in str(exc).splitlines():
        if line.strip():
            return line.strip()
    return type(exc).__name__ if default is None else default
