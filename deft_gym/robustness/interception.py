"""Applying a test case live on the bus: interception and interleaving.

:class:`Interceptor` is a bus interceptor (``sim.bus.interceptors``): it sees every published
message before any subscriber or tap. Messages no policy targets flow unmodified, which is what
gets the system past start-up and keeps its control loops closed (section 3.2.1). A targeted
message is replaced by a modified deep copy (``intercept``), or followed ``delay_ms``
later by a modified copy put on the bus with its own sequence number (``inject``).

It also feeds *observers* with every original message (the invariant monitor judges what each
module said, not what the interceptor turned it into) and, when the run is recorded, writes the
test log ASTAA keeps (3.3.2): the recorder holds what subscribers saw; the original of every
modified message goes to the channel ``/astaa/original<topic>`` (same sequence number and
publish time) and every applied instance to ``/astaa/events``.

It never raises: an internal error is counted in :attr:`errors` (harness errors) and the message
passes unmodified.
"""

from __future__ import annotations

import copy
import traceback
from collections.abc import Callable
from typing import Any

from deft_gym.bus.messages import NS_PER_S, Message, to_ns
from deft_gym.robustness import paths
from deft_gym.robustness.dictionary import mutate
from deft_gym.robustness.testcase import Assignment, TestCase

ORIGINAL_PREFIX = "/astaa/original"
EVENTS_TOPIC = "/astaa/events"

Observer = Callable[[str, Message], None]


class Interceptor:
    """Applies a :class:`TestCase`'s policies (or instances) to the messages of a bus."""

    def __init__(self, case: TestCase, topics: dict[str, str], bus: Any, recorder: Any = None) -> None:
        self.case = case
        self.bus = bus
        self.recorder = recorder
        self.role_of = {topic: role for role, topic in topics.items()}
        self.topics = dict(topics)
        self.observers: list[Observer] = []
        self.applied: list[dict[str, Any]] = []
        self.errors: list[str] = []
        self._prev: dict[str, dict[str, Any]] = {}
        self._count = [0] * len(case.policies)
        self._by_role: dict[str, list[int]] = {}
        self._instances: dict[tuple[str, str, int], Any] = {}
        if case.instances is not None:
            for inst in case.instances:
                self._instances.setdefault((inst.mode, inst.topic, inst.seq), []).append(inst)
            self._roles = {inst.topic for inst in case.instances}
        else:
            for i, pol in enumerate(case.policies):
                self._by_role.setdefault(pol.topic, []).append(i)
            self._roles = set(self._by_role)

    # -- the interceptor --------------------------------------------------------------------
    def __call__(self, msg: Message) -> list[Message]:
        role = self.role_of.get(msg.topic)
        for obs in self.observers:
            try:
                obs(role or msg.topic, msg)
            except Exception:
                self._error("observer")
        if role is None or role not in self._roles:
            if role is not None:
                self._prev[role] = msg.payload
            return [msg]
        try:
            return self._apply(role, msg)
        except Exception:
            self._error("interceptor")
            return [msg]
        finally:
            self._prev[role] = msg.payload

    def _error(self, where: str) -> None:
        self.errors.append(f"{where}: {traceback.format_exc(limit=-3).strip()}")

    def _targets(self, role: str, msg: Message) -> list[tuple[Any, int | None]]:
        """``(policy or instance, policy index)`` of everything that applies to ``msg``."""
        if self.case.instances is not None:
            out = []
            for mode in ("intercept", "inject"):
                for inst in self._instances.get((mode, role, msg.seq), ()):
                    out.append((inst, None))
            return out
        t = msg.publish_ns / NS_PER_S
        out = []
        for i in self._by_role.get(role, ()):
            pol = self.case.policies[i]
            if pol.start <= t <= pol.end and (pol.max_count is None or self._count[i] < pol.max_count):
                self._count[i] += 1
                out.append((pol, i))
        return out

    def _apply(self, role: str, msg: Message) -> list[Message]:
        targets = self._targets(role, msg)
        if not targets:
            return [msg]
        out_payload = None
        intercept_sets: list[dict[str, Any]] = []
        policies: list[int] = []
        for target, pol in targets:
            if target.mode == "intercept":
                if out_payload is None:
                    out_payload = copy.deepcopy(msg.payload)
                intercept_sets.extend(self._set(role, out_payload, target.set))
                if pol is not None:
                    policies.append(pol)
            else:
                payload = copy.deepcopy(msg.payload)
                done = self._set(role, payload, target.set)
                self.bus.schedule(self.bus.now_ns + to_ns(target.delay_ms / 1000.0), self._inject, role, msg.seq,
                                  payload, done, pol, target.delay_ms)
        if out_payload is None or not any(s["changed"] for s in intercept_sets):
            return [msg]
        self._record(msg, "intercept", role, msg.seq, intercept_sets, policies, original=msg.payload)
        return [Message(msg.topic, msg.seq, msg.publish_ns, out_payload)]

    def _set(self, role: str, payload: dict[str, Any], sets: list[Assignment]) -> list[dict[str, Any]]:
        """Apply assignments in place; what each changed, as concrete paths."""
        prev = self._prev.get(role)
        out = []
        for a in sets:
            changed: list[str] = []

            def fn(old: Any, concrete: str, a: Assignment = a, changed: list[str] = changed) -> Any:
                changed.append(concrete)
                p = None
                if prev is not None:
                    try:
                        p = paths.get(prev, concrete)
                    except (KeyError, IndexError, TypeError):
                        p = None
                return mutate(a.value, old, p)

            paths.apply(payload, a.path, fn)
            out.append({"path": a.path, "value": a.value, "changed": changed})
        return out

    def _inject(self, role: str, template_seq: int, payload: dict[str, Any], sets: list[dict[str, Any]],
                pol: int | None, delay_ms: float) -> None:
        try:
            topic = self.topics[role]
            msg = Message(topic, self.bus.next_seq(topic), self.bus.now_ns, payload)
            self._record(msg, "inject", role, template_seq, sets, [] if pol is None else [pol], delay_ms=delay_ms)
            self.bus.inject(msg)
        except Exception:
            self._error("injector")

    def _record(self, msg: Message, mode: str, role: str, seq: int, sets: list[dict[str, Any]],
                policies: list[int], original: dict[str, Any] | None = None, delay_ms: float | None = None) -> None:
        """Remember an applied instance; write the original and the event to the test log."""
        event = {"mode": mode, "topic": role, "seq": seq, "publish_ns": msg.publish_ns,
                 "time": msg.publish_ns / NS_PER_S, "set": sets, "policies": policies}
        if mode == "inject":
            event["bus_seq"] = msg.seq
            event["delay_ms"] = delay_ms
        self.applied.append(event)
        if self.recorder is None:
            return
        try:
            if original is not None:
                self.recorder(Message(ORIGINAL_PREFIX + msg.topic, msg.seq, msg.publish_ns, original))
            self.recorder(Message(EVENTS_TOPIC, len(self.applied) - 1, msg.publish_ns,
                                  {"header": {"seq": len(self.applied) - 1, "stamp": msg.publish_ns / NS_PER_S,
                                              "module": "astaa"}, "bus_topic": msg.topic, **event}))
        except Exception:
            self._error("test log")

def attach(interceptor: Interceptor) -> None:
    """Install ``interceptor`` on its bus (first in line, so it sees unmodified messages)."""
    interceptor.bus.interceptors.insert(0, interceptor)
