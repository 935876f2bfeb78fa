"""``(template % args).encode()`` for the viewer topics' JSON, compiled where it can be.

The Foxglove scene (:mod:`deft_gym.record.scene`) is JSON text with ~90 numbers per message
written as ``%.3f`` (mm) and ``%.6f``; Python formats each through its exact decimal conversion,
~0.35 us a number, which made the scene a third of what recording costs. :func:`format_bytes`
gives ``(template % args).encode()`` - the same bytes - from the compiled ``_format_c`` where the
template is ASCII and holds only ``%d`` (an ``int``), ``%s`` (an ASCII ``str``), ``%.Nf`` (a
``float``, N <= 9, magnitude below 2**52 / 10**N) and ``%%``: exact fixed-point rounding (ties to
even, as Python's), several times faster. Anything else - another conversion or type, a
non-finite or huge value - is formatted by Python's ``%`` itself.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from deft_gym.files import checked_kernel

try:  # the formatter compiled (setup.py); Python's `%` without it
    from deft_gym.record import _format_c
except ImportError:  # pragma: no cover - the build is optional
    _format_c = None
# a kernel built before this file or _format_c.c was edited is not used (the edit must count)
_format_c = checked_kernel(_format_c, Path(__file__).with_name("_format_c.c"), Path(__file__))
_kernel = None if os.environ.get("DEFT_GYM_PURE_PYTHON") else getattr(_format_c, "format_bytes", None)


def format_bytes(template: str, args: tuple[Any, ...]) -> bytes:
    """``(template % args).encode()`` (the compiled formatter for what it takes, Python's ``%``
    for the rest: the same bytes either way)."""
    if _kernel is not None:
        data = _kernel(template, args)
        if data is not NotImplemented:
            return data
    return (template % args).encode()
