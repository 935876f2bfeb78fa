"""Offline invariant checking on a recorded episode log (MCAP).

The same YAML invariants as online, on the same stream: the log holds what subscribers saw, so
the original of every intercepted message (channel ``/astaa/original<topic>``) replaces it and
injected messages (listed on ``/astaa/events``) are skipped - exactly the original messages the
online monitor observed, in publish order. The map comes from the log's episode record and the
``outcome`` from its outcome record.

Only an intact log is judged: its chunks' CRCs, message counts and footer are verified first
(:func:`extract.verify.verify`); a damaged or truncated one is :class:`LogDamaged` (one line: what
is damaged and how many messages are lost), never "no invariant violated" on what is left.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from mcap.reader import make_reader

from deft_gym.bus.messages import NS_PER_S, log_start_ns
from deft_gym.bus.ros1 import ChannelDecoders
from deft_gym.record.recorder import EPISODE_METADATA, OUTCOME_METADATA
from deft_gym.robustness.interception import EVENTS_TOPIC, ORIGINAL_PREFIX
from deft_gym.robustness.invariants import (
    InvariantMonitor,
    InvariantSet,
    Violation,
    load_invariants,
)


def _metadata(reader: Any) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for rec in reader.iter_metadata():
        vals = {}
        for k, v in rec.metadata.items():
            try:
                vals[k] = json.loads(v)
            except json.JSONDecodeError:
                vals[k] = v
        out[rec.name] = vals
    return out


class LogDamaged(ValueError):
    """The log is not intact (or not an episode log): its invariants are not judged."""


def require_intact(path: Path) -> None:
    """:class:`LogDamaged` unless every chunk of the log passes its CRC, the counts match its
    summary and it ends with its footer."""
    from extract.logs import LogError
    from extract.verify import verify

    try:
        log = verify(path)
    except LogError as err:
        raise LogDamaged(str(err)) from None
    if log.status != "complete":
        raise LogDamaged(f"{path}: {log.status}; a damaged log is not judged (deft-gym verify {path} says where)")


def check_log(path: Path | str, invariants: InvariantSet | Path | str | None = None) -> list[Violation]:
    """Evaluate ``invariants`` (a set or a YAML path; default the project's) on an intact log
    (:class:`LogDamaged` otherwise)."""
    inv = invariants if isinstance(invariants, InvariantSet) else load_invariants(invariants)
    path = Path(path)
    require_intact(path)
    with open(path, "rb") as f:
        reader = make_reader(f)
        meta = _metadata(reader)
    episode = meta.get(EPISODE_METADATA, {})
    if "map" not in episode:
        raise ValueError(f"{path}: no {EPISODE_METADATA} record with the map")
    originals: dict[tuple[str, int], dict[str, Any]] = {}
    injected: set[tuple[str, int]] = set()
    roles: dict[str, str] = {}
    last_ns = 0
    decode = ChannelDecoders()
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            topic = channel.topic
            if topic.startswith(ORIGINAL_PREFIX):
                originals[(topic[len(ORIGINAL_PREFIX):], message.sequence)] = decode(schema, channel, message.data)
            elif topic == EVENTS_TOPIC:
                ev = decode(schema, channel, message.data)
                if ev.get("mode") == "inject":
                    injected.add((ev["bus_topic"], ev["bus_seq"]))
            elif "role" in channel.metadata:
                roles[topic] = channel.metadata["role"]
    monitor = InvariantMonitor(inv, episode["map"])
    start = log_start_ns(episode)  # log_time = epoch start + sim time
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            role = roles.get(channel.topic)
            if role is None:
                continue
            key = (channel.topic, message.sequence)
            if key in injected:
                continue
            payload = originals.get(key)
            if payload is None:
                payload = decode(schema, channel, message.data)
            last_ns = max(last_ns, message.log_time - start)
            monitor.observe(role, payload, (message.log_time - start) / NS_PER_S)
    outcome = meta.get(OUTCOME_METADATA)
    return monitor.finish(outcome, float((outcome or {}).get("sim_time", last_ns / NS_PER_S)))
