"""Shared fixtures (small episodes recorded once per test session) and helpers; a pytest plugin
of ``tests/conftest.py``, imported by tests as ``tests.support.fixtures``."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("SDL_AUDIODRIVER", "dummy")

ROOT = Path(__file__).resolve().parents[2]
SCENARIOS = ROOT / "configs" / "scenarios"


def float_bits(values: object) -> bytes:
    """The bytes of ``values`` as float64 (signed zeros and NaN payloads included)."""
    import numpy as np

    return np.asarray(values, dtype=float).tobytes()


def same_values(a: object, b: object) -> bool:
    """Equal types all the way down, dict keys in the same order, floats with the same bits."""
    import struct

    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return struct.pack("<d", a) == struct.pack("<d", b)
    if isinstance(a, dict):
        return list(a) == list(b) and all(same_values(k, j) and same_values(a[k], b[j])
                                          for k, j in zip(a, b, strict=True))
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(same_values(x, y) for x, y in zip(a, b, strict=True))
    return a == b


@pytest.fixture(scope="session")
def lane_follow_log(tmp_path_factory: pytest.TempPathFactory):
    """One recorded episode of the lane-following seed (jitter seed 7)."""
    from deft_gym.sim.simulation import run_episode

    out = tmp_path_factory.mktemp("lane_follow")
    return run_episode(SCENARIOS / "lane_follow_static.yaml", jitter_seed=7, out_dir=out)
