"""The Planning IO Filter (DeFT section 4.1): planning outputs and their candidate inputs.

For every planning output P published at t_P, the candidate messages of each subscribed role
are those published no later than t_P (paper eq. 1). Messages of a topic are sorted by publish
time, so a candidate set is an index range ``[0, bound)`` found with one vectorised
``searchsorted`` for all outputs at once; the input search narrows it further.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from deft_gym.bus.messages import NS_PER_S
from extract.logs import EpisodeLog, LogError, TopicMessages
from extract.mapping import MappingError, TopicMapping, get_field, input_roles


@dataclass
class Output:
    """One recorded planning output."""

    index: int  # frame index (position among the usable outputs)
    msg: int  # index in the planning topic
    seq: int
    publish_ns: int
    payload: dict[str, Any]
    frame_time: float | None  # frame time [s] from the mapping's frame_time_field, when present
    frame_ns: int | None  # the same in ns (for comparing with publish times)
    input_seqs: dict[str, Any] | None  # headers mode: role -> seq

    @property
    def publish_time(self) -> float:
        return self.publish_ns / NS_PER_S


class PlanningIOFilter:
    """Outputs of one log and, per input role, the candidate bound of every output. The input
    roles are the planner's (``planner``: ``module:Class``, see :func:`extract.mapping.input_roles`),
    else the mapping's ``inputs``."""

    def __init__(self, log: EpisodeLog, mapping: TopicMapping, planner: str | None = None) -> None:
        self.log, self.mapping = log, mapping
        if planner is not None:
            roles = input_roles(mapping, planner)
        elif mapping.inputs is not None:
            roles = list(mapping.inputs)
        else:
            raise MappingError(f"{mapping.source}: inputs: not set, and no planner to take them from")
        missing = [(role, mapping.topics[role]) for role in ["planning", *roles]
                   if mapping.topics[role] not in log.channel_roles]
        if missing:
            raise MappingError(_missing_message(log, mapping, missing))
        self.roles = roles
        self.inputs: dict[str, TopicMessages] = {r: log.topics[mapping.topics[r]] for r in self.roles}
        self.planning = log.topics[mapping.topics["planning"]]
        self.outputs = self._outputs()
        if not self.outputs:
            raise LogError(f"{log.path}: no usable planning output on {mapping.topics['planning']!r}"
                           f" ({len(self.planning)} messages); nothing to extract")
        pub = np.fromiter((o.publish_ns for o in self.outputs), np.int64, len(self.outputs))
        #: per role: number of candidates of each output (messages published <= t_P)
        self.bound = {r: np.searchsorted(tm.publish_ns, pub, side="right") for r, tm in self.inputs.items()}

    def _outputs(self) -> list[Output]:
        tm, mp = self.planning, self.mapping
        outs: list[Output] = []
        skipped = 0
        for i in range(len(tm)):
            payload = tm.payload(i)
            if not isinstance(payload, dict) or not isinstance(payload.get("trajectory"), dict):
                skipped += 1
                continue
            frame_time = frame_ns = None
            if mp.frame_time_field:
                t = get_field(payload, mp.frame_time_field)
                if isinstance(t, int | float) and not isinstance(t, bool) and math.isfinite(t):
                    frame_time, frame_ns = float(t), round(t * NS_PER_S)
            seqs = get_field(payload, mp.input_seqs_field) if mp.input_seqs_field else None
            outs.append(Output(len(outs), i, int(tm.seq[i]), int(tm.publish_ns[i]), payload,
                               frame_time, frame_ns,
                               seqs if isinstance(seqs, dict) else None))
        if skipped:
            self.log.warnings.append(f"{skipped} planning message(s) without a decodable trajectory skipped")
        return outs

    def frame_bound(self, role: str, t_ns: int) -> int:
        """Number of messages of ``role`` published no later than ``t_ns`` (heuristic 2)."""
        return int(np.searchsorted(self.inputs[role].publish_ns, t_ns, side="right"))


def _missing_message(log: EpisodeLog, mapping: TopicMapping, missing: list[tuple[str, str]]) -> str:
    what = ", ".join(f"{role}={topic!r}" for role, topic in missing)
    hint = ""
    by_role = {r: t for t, r in log.channel_roles.items() if r}
    if by_role:
        hint = "; its channels declare " + ", ".join(f"{r}={t!r}" for r, t in sorted(by_role.items()))
    return (f"{log.path}: topic(s) {what} of mapping {mapping.source} not in the log{hint}"
            " - pass a mapping whose topics match (--mapping FILE)")
