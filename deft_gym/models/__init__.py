"""Trained models that ship with the package.

``adversary/``: the RL adversary (PPO) trained by the project's own ``configs/train/adversary.yaml``
- ``model.zip`` (stable-baselines3), beside it the training run's ``config.yaml`` (the env the model
expects, read by ``deft-gym evaluate``), ``summary.json`` (its training budget and outcome) and
``provenance.json`` (the commit and command it was trained with). ``deft-gym evaluate --model
default`` and the demo use it.
"""

from __future__ import annotations

from pathlib import Path

DEFAULT = "default"  # the name --model takes for the shipped adversary


def default_model() -> Path:
    """Where the shipped adversary's ``model.zip`` is (inside the installed package)."""
    return Path(__file__).resolve().parent / "adversary" / "model.zip"


def resolve_model(name: str | None) -> str | None:
    """``name`` as a model path: ``default`` is the shipped adversary, anything else is a path."""
    return str(default_model()) if name == DEFAULT else name
