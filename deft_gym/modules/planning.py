"""The planning module: runs a :class:`~deft_gym.planner.base.Planner` on frames.

Triggered by prediction (configurable); each run takes the latest *received* message of every
subscribed role as its frame at the frame time. It also records, for evaluation only, which
message of each topic every output consumed (the truth file); the extractor never reads it.
With ``publish_input_headers`` the output carries the sequence numbers of its inputs in
``debug.input_seqs``, like Apollo's planning debug field.
"""

from __future__ import annotations

from typing import Any

from deft_gym.bus.ads import PlanningConfig
from deft_gym.bus.bus import Node, header
from deft_gym.bus.messages import NS_PER_S, Message
from deft_gym.config import ConfigError
from deft_gym.planner.base import Frame, Planner, resolve_inputs


def frame_roles(planner: type[Planner], cfg: PlanningConfig, source: str = "ADS config") -> list[str]:
    """The roles of the planner's frame: its :attr:`Planner.inputs`; ConfigError (one line, naming
    ``source``) when the ADS config's ``planning.subscribe`` names other roles."""
    try:
        return resolve_inputs(planner, cfg.subscribe)
    except ValueError as exc:
        raise ConfigError(f"{source}: {exc}") from None


class PlanningNode(Node):
    """Planner behind the bus: frame in, trajectory out."""

    def __init__(self, planner: Planner, cfg: PlanningConfig, topics: dict[str, str]) -> None:
        #: the roles of the frame: the planner's inputs (Planner.inputs)
        self.roles = frame_roles(type(planner), cfg)
        self.role_topics = {role: topics[role] for role in self.roles}
        trigger = topics[cfg.trigger] if cfg.trigger else None
        super().__init__("planning", list(self.role_topics.values()), trigger=trigger,
                         processing=cfg.processing)
        self.planner = planner
        self.out_topic = topics["planning"]
        self.publish_headers = cfg.publish_input_headers
        self.truth: list[dict[str, Any]] = []
        self._frame_record: dict[str, Any] | None = None

    def compute(self, now_ns: int) -> list[tuple[str, dict[str, Any]]] | None:
        t = now_ns / NS_PER_S
        used = {role: self.latest.get(topic) for role, topic in self.role_topics.items()}
        frame = Frame(t, {role: (m.payload if m is not None else None) for role, m in used.items()})
        result = self.planner.plan(frame)
        if result is None:
            self._frame_record = None
            return None
        seqs = {role: (m.seq if m is not None else None) for role, m in used.items()}
        payload = {"header": header(t, self.name), **result}
        if self.publish_headers:
            payload["debug"] = {"input_seqs": dict(seqs)}
        self._frame_record = {"frame_time": t, "frame_ns": now_ns, "inputs": seqs}
        return [(self.out_topic, payload)]

    def on_published(self, msg: Message) -> None:
        if self._frame_record is not None and msg.topic == self.out_topic:
            self.truth.append({"seq": msg.seq, "publish_ns": msg.publish_ns, **self._frame_record})
