"""Timed traffic-light cycles.

Lights are grouped: the lights of one group show the same colour, and the two groups of an
intersection (north-south = 0, east-west = 1) alternate. One cycle is
``green, yellow, all-red`` for group 0 followed by the same for group 1; ``offset`` [s] shifts
the whole plan (a scenario can start anywhere in the cycle).
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class LightPlan(BaseModel):
    """Durations [s] of one group's phases and the plan offset [s]."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    green: float = Field(default=12.0, gt=0.0)
    yellow: float = Field(default=3.0, ge=0.0)
    all_red: float = Field(default=1.0, ge=0.0)
    offset: float = 0.0


class TrafficLights:
    """Colour of every light at any sim time."""

    def __init__(self, groups: dict[str, int], plan: LightPlan | None = None) -> None:
        self.groups = dict(groups)
        self.plan = plan or LightPlan()
        p = self.plan
        self.half = p.green + p.yellow + p.all_red
        self.cycle = 2 * self.half

    @property
    def ids(self) -> list[str]:
        return list(self.groups)

    def color(self, light_id: str, t: float) -> str:
        """``GREEN``, ``YELLOW`` or ``RED`` of ``light_id`` at time ``t`` [s]."""
        p = self.plan
        phase = (t + p.offset - self.groups[light_id] * self.half) % self.cycle
        if phase < p.green:
            return "GREEN"
        if phase < p.green + p.yellow:
            return "YELLOW"
        return "RED"

    def time_to_change(self, light_id: str, t: float) -> float:
        """Seconds [s] until the colour of ``light_id`` next changes (ground truth)."""
        p = self.plan
        phase = (t + p.offset - self.groups[light_id] * self.half) % self.cycle
        for edge in (p.green, p.green + p.yellow, self.cycle):
            if phase < edge:
                return edge - phase
        return self.cycle - phase
