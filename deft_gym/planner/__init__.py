"""Planners: the interface (:mod:`.base`) and the reference lattice planner (:mod:`.lattice`)."""

from deft_gym.planner.base import Frame, Planner, import_object, load_planner

__all__ = ["Frame", "Planner", "import_object", "load_planner"]
