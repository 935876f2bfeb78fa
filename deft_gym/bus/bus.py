"""A discrete-event message bus on a simulated clock.

Time is integer nanoseconds. Nodes are periodic (a timer) or triggered (a subscribed topic);
each run of a node takes a frame of the latest message it has *received* on every subscribed
topic, computes, and publishes its outputs after a processing time drawn from the jitter model.
Each delivery to each subscriber has its own delay (or is dropped), so which message a module
sees depends on timing - the non-determinism DeFT is about.

Hooks for tools that sit on the bus without changing its core:

- ``taps``: called with every message at its publish time (the recorder, online monitors);
- ``interceptors``: may replace a published message by others before delivery (ASTAA);
- ``supervisor``: runs every node computation and decides what a raised exception means.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable
from typing import Any, Protocol

from deft_gym.bus.jitter import JitterModel
from deft_gym.bus.messages import NS_PER_S, Message

Tap = Callable[[Message], None]
Interceptor = Callable[[Message], list[Message]]


class Supervisor(Protocol):
    """Runs node computations; the default lets exceptions propagate."""

    def run(self, node: Node, fn: Callable[..., Any], *args: Any) -> Any: ...


class _Direct:
    def run(self, node: Node, fn: Callable[..., Any], *args: Any) -> Any:
        return fn(*args)


class Bus:
    """Event queue, clock, topic registry and delivery with jitter."""

    def __init__(self, jitter: JitterModel) -> None:
        self.jitter = jitter
        self.now_ns = 0
        self._queue: list[tuple[int, float, int, Callable[..., None], tuple[Any, ...]]] = []
        self._counter = itertools.count()
        self._subscribers: dict[str, list[Node]] = {}
        self._seq: dict[str, int] = {}
        self.nodes: list[Node] = []
        self.taps: list[Tap] = []
        self.interceptors: list[Interceptor] = []
        self.supervisor: Supervisor = _Direct()
        self.stopped = False
        self.published = 0
        self.reliable: set[str] = set()  # topics whose deliveries are never lost

    # -- scheduling -------------------------------------------------------------------------
    def schedule(self, t_ns: int, fn: Callable[..., None], *args: Any) -> None:
        """Run ``fn(*args)`` at sim time ``t_ns`` (never in the past)."""
        if t_ns < self.now_ns:
            t_ns = self.now_ns
        heapq.heappush(self._queue, (t_ns, self.jitter.order_key(), next(self._counter), fn, args))

    def run(self, until_ns: int) -> None:
        """Process events in time order until ``until_ns`` or until :meth:`stop` is called."""
        queue = self._queue
        pop = heapq.heappop
        while queue and not self.stopped:
            if queue[0][0] > until_ns:
                break
            t_ns, _, _, fn, args = pop(queue)
            self.now_ns = t_ns
            fn(*args)
        if not self.stopped:
            self.now_ns = max(self.now_ns, until_ns)

    def stop(self) -> None:
        """End the run after the current event."""
        self.stopped = True

    @property
    def now(self) -> float:
        """Current sim time [s]."""
        return self.now_ns / NS_PER_S

    # -- topology ---------------------------------------------------------------------------
    def add(self, node: Node) -> Node:
        """Register a node and its subscriptions."""
        node.bus = self
        self.nodes.append(node)
        for topic in node.subscriptions:
            self._subscribers.setdefault(topic, []).append(node)
        return node

    def start(self) -> None:
        """Start every node (first timers, initial publications)."""
        for node in self.nodes:
            node.start()

    # -- messaging --------------------------------------------------------------------------
    def published_on(self, topic: str) -> int:
        """How many messages were published on ``topic`` so far."""
        return self._seq.get(topic, 0)

    def next_seq(self, topic: str) -> int:
        seq = self._seq.get(topic, 0)
        self._seq[topic] = seq + 1
        return seq

    def publish(self, topic: str, payload: dict[str, Any]) -> Message:
        """Publish now: stamp the header sequence number, notify taps, schedule deliveries."""
        seq = self.next_seq(topic)
        payload["header"]["seq"] = seq
        msg = Message(topic, seq, self.now_ns, payload)
        if self.interceptors:
            msgs = [msg]
            for icpt in self.interceptors:
                msgs = [out for m in msgs for out in icpt(m)]
            for m in msgs:
                self._dispatch(m)
        else:
            self._dispatch(msg)
        return msg

    def inject(self, msg: Message) -> None:
        """Put an externally built message on the bus now (interleaving)."""
        self._dispatch(msg)

    def _dispatch(self, msg: Message) -> None:
        self.published += 1
        for tap in self.taps:
            tap(msg)
        subs = self._subscribers.get(msg.topic)
        if not subs:
            return
        jitter = self.jitter
        reliable = msg.topic in self.reliable
        for node in subs:
            delay = jitter.delivery_ns(reliable)
            if delay is not None:
                self.schedule(self.now_ns + delay, node.receive, msg)


class Node:
    """A module on the bus.

    Subclasses implement :meth:`compute`, which sees ``self.latest`` (the latest received message
    per subscribed topic) and returns the payloads to publish as ``[(topic, payload), ...]``.
    The outputs appear on the bus ``processing`` later. A node is periodic when ``period_ns`` is
    set and triggered by ``trigger`` otherwise; while it is busy, ticks are missed (counted) and
    triggers are coalesced into one pending run.
    """

    def __init__(
        self,
        name: str,
        subscriptions: list[str],
        *,
        period_ns: int | None = None,
        trigger: str | None = None,
        processing: Any = None,
        phase_ns: int = 0,
    ) -> None:
        self.name = name
        self.subscriptions = list(subscriptions)
        self.period_ns = period_ns
        self.trigger = trigger
        self.processing = processing
        self.phase_ns = phase_ns
        self.latest: dict[str, Message] = {}
        self.bus: Bus = None  # type: ignore[assignment]
        self.busy = False
        self.pending = False
        self.runs = 0
        self.missed_ticks = 0
        self.last_publish_ns: int | None = None
        self.alive = True

    # -- lifecycle --------------------------------------------------------------------------
    def start(self) -> None:
        if self.period_ns:
            self.bus.schedule(self.phase_ns, self._tick, self.phase_ns)

    def _tick(self, nominal_ns: int) -> None:
        bus = self.bus
        bus.schedule(nominal_ns + self.period_ns + bus.jitter.timer_lateness_ns(), self._tick,
                     nominal_ns + self.period_ns)
        if self.busy:
            self.missed_ticks += 1
            return
        self._begin()

    def receive(self, msg: Message) -> None:
        """A delivery: keep it as the latest of its topic; maybe start a triggered run."""
        self.latest[msg.topic] = msg
        if msg.topic == self.trigger:
            if self.busy:
                self.pending = True
            else:
                self.busy = True
                bus = self.bus
                bus.schedule(bus.now_ns + bus.jitter.duration_ns(bus.jitter.config.dispatch),
                             self._begin)

    def _begin(self) -> None:
        bus = self.bus
        self.busy = True
        self.runs += 1
        if not self.alive:
            self.busy = False
            return
        outputs = bus.supervisor.run(self, self.compute, bus.now_ns)
        done = bus.now_ns + (bus.jitter.duration_ns(self.processing) if self.processing else 0)
        bus.schedule(done, self._finish, outputs)

    def _finish(self, outputs: list[tuple[str, dict[str, Any]]] | None) -> None:
        bus = self.bus
        if outputs and self.alive:
            bus.supervisor.run(self, self._publish, outputs)
        self.busy = False
        if self.pending:
            self.pending = False
            self._begin()

    def _publish(self, outputs: list[tuple[str, dict[str, Any]]]) -> None:
        """Put the outputs on the bus (run by the supervisor: a tap or interceptor that fails on
        them is reported against this node)."""
        bus = self.bus
        for topic, payload in outputs:
            self.on_published(bus.publish(topic, payload))
        self.last_publish_ns = bus.now_ns

    # -- to implement -----------------------------------------------------------------------
    def on_published(self, msg: Message) -> None:
        """Called with each message this node published (after interception)."""

    def compute(self, now_ns: int) -> list[tuple[str, dict[str, Any]]] | None:
        """Produce outputs from ``self.latest`` at frame time ``now_ns``."""
        raise NotImplementedError


def header(stamp_s: float, module: str) -> dict[str, Any]:
    """A payload header; the bus fills in ``seq`` when the message is published."""
    return {"seq": 0, "stamp": stamp_s, "module": module}


class TimingSupervisor:
    """Runs node computations and accumulates their wall time per node [s] (for benchmarks)."""

    def __init__(self) -> None:
        import time

        self._clock = time.perf_counter
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}

    def run(self, node: Node, fn: Callable[..., Any], *args: Any) -> Any:
        t0 = self._clock()
        try:
            return fn(*args)
        finally:
            self.seconds[node.name] = self.seconds.get(node.name, 0.0) + self._clock() - t0
            self.calls[node.name] = self.calls.get(node.name, 0) + 1
