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
