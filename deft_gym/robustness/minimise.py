"""Test case minimisation: delta debugging over message instances, then over fields.

A finding's run touched a list of concrete message instances (:class:`~.testcase.Instance`).
Replayed with the same jitter seed, any sub-list is a deterministic test, so Zeller's ``ddmin``
finds a 1-minimal sub-list that still produces the finding's signature (section 3.3.2):

1. instances published after the finding cannot have caused it and are cut first;
2. ``ddmin`` over whole instances (each with all its assignments);
3. ``ddmin`` over *atoms* - one concrete field of one instance (``obstacles[*].x`` expanded to
   ``obstacles[0].x``, ``obstacles[1].x``, ...) - which plays the role of ASTAA's field-level
   step (HPSL, 3.3.2).

Every replay stops as soon as the signature appears (or a few seconds of sim time after the
original finding time). The result carries the mutation dimensionality of section 4.2.1:
interfaces ``field`` (one field of one message type), ``message`` (several fields of one type),
``multiple`` (several message types) or ``inject`` (an interleaved message, no field changed);
instances ``single`` or ``multiple``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

from deft_gym.robustness.runner import RunResult, run_case
from deft_gym.robustness.spec import TestSpecification
from deft_gym.robustness.testcase import Assignment, Instance, TestCase

T = TypeVar("T")
SLACK_S = 5.0  # [s] a replay may find the signature this much later than the original run


class BudgetExhausted(Exception):
    """The minimisation used all its replays."""


def ddmin(items: Sequence[T], test: Callable[[list[T]], bool]) -> list[T]:
    """Zeller's ddmin: a 1-minimal sub-list of ``items`` for which ``test`` holds (``test`` holds
    for ``items``). A :class:`BudgetExhausted` from ``test`` returns the smallest list so far."""
    items = list(items)
    n = 2
    try:
        while len(items) >= 2:
            size = len(items)
            chunks = [items[i * size // n:(i + 1) * size // n] for i in range(n)]
            chunks = [c for c in chunks if c]
            reduced = False
            for c in chunks:
                if test(c):
                    items, n, reduced = c, 2, True
                    break
            if not reduced:
                for c in chunks:
                    ids = {id(x) for x in c}
                    rest = [x for x in items if id(x) not in ids]
                    if len(chunks) > 2 and test(rest):
                        items, n, reduced = rest, max(n - 1, 2), True
                        break
            if not reduced:
                if n >= len(items):
                    break
                n = min(len(items), 2 * n)
    except BudgetExhausted:
        pass
    return items


def instances_of(result: RunResult, before: float | None = None) -> list[Instance]:
    """The concrete instances a run applied (only those published up to ``before`` [s])."""
    out = []
    for ev in result.applied:
        if before is not None and ev["time"] > before + 1e-9:
            continue
        sets = [Assignment(path=s["path"], value=s["value"]) for s in ev["set"] if s["changed"] or ev["mode"] == "inject"]
        if ev["mode"] == "intercept" and not sets:
            continue
        out.append(Instance(topic=ev["topic"], mode=ev["mode"], seq=ev["seq"], set=sets,
                            delay_ms=ev.get("delay_ms") or 20.0))
    return out


def atoms_of(result: RunResult, instances: list[Instance]) -> list[Instance]:
    """One atom per concrete field of each instance; an injection is also an atom of its own
    without any field (a stale duplicate), so ddmin can find that no field matters."""
    changed: dict[tuple[str, str, int, str, str], list[str]] = {}
    for ev in result.applied:
        for s in ev["set"]:
            changed.setdefault((ev["mode"], ev["topic"], ev["seq"], s["path"], s["value"]), []).extend(s["changed"])
    out = []
    for inst in instances:
        if inst.mode == "inject" or not inst.set:
            out.append(inst.model_copy(update={"set": []}))
        for a in inst.set:
            concrete = changed.get((inst.mode, inst.topic, inst.seq, a.path, a.value)) or [a.path]
            for path in dict.fromkeys(concrete):
                out.append(inst.model_copy(update={"set": [Assignment(path=path, value=a.value)]}))
    return out


def merge(atoms: list[Instance]) -> list[Instance]:
    """Atoms regrouped into one instance per message."""
    groups: dict[tuple[str, str, int, float], Instance] = {}
    for a in atoms:
        key = (a.mode, a.topic, a.seq, a.delay_ms)
        if key in groups:
            groups[key] = groups[key].model_copy(update={"set": [*groups[key].set, *a.set]})
        else:
            groups[key] = a
    return list(groups.values())


def dimensionality(instances: list[Instance], spec: TestSpecification | None = None) -> dict[str, Any]:
    """ASTAA's mutation dimensionality of a (minimal) list of instances."""
    spec = spec or TestSpecification.from_schemas()
    topics = sorted({i.topic for i in instances})
    fields = sorted({f"{i.topic}:{spec.normalise(i.topic, a.path)}" for i in instances for a in i.set})
    messages = {(i.mode, i.topic, i.seq) for i in instances}
    if not instances:
        interfaces = "none"
    elif len(topics) > 1:
        interfaces = "multiple"
    elif not fields:
        interfaces = "inject"
    else:
        interfaces = "field" if len(fields) == 1 else "message"
    return {"interfaces": interfaces, "instances": "single" if len(messages) <= 1 else "multiple",
            "topics": topics, "fields": fields, "messages": len(messages),
            "atoms": sum(max(1, len(i.set)) for i in instances)}


@dataclass
class Minimised:
    """The outcome of minimising one finding."""

    signature: str
    case: TestCase | None
    original_instances: int
    original_atoms: int = 0
    replays: int = 0
    reproduced: bool = False
    dimensionality: dict[str, Any] = field(default_factory=dict)
    note: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {"signature": self.signature, "reproduced": self.reproduced, "replays": self.replays,
                "original_instances": self.original_instances, "original_atoms": self.original_atoms,
                "dimensionality": self.dimensionality, "note": self.note}


def _finding_time(result: RunResult, signature: str) -> float | None:
    for f in result.failures:
        if f["signature"] == signature:
            return f["time"]
    for v in result.violations:
        if v["signature"] == signature:
            return v["time"]
    return None


def minimise(case: TestCase, result: RunResult, signature: str, max_replays: int = 120,
             spec: TestSpecification | None = None) -> Minimised:
    """Minimise the instances of ``result`` (a run of ``case``) that produce ``signature``."""
    t_fail = _finding_time(result, signature)
    everything = instances_of(result)
    out = Minimised(signature, None, len(everything))
    if t_fail is None:
        out.note = "signature not in the run"
        return out
    until = t_fail + SLACK_S
    cache: dict[str, bool] = {}

    def test(instances: list[Instance]) -> bool:
        key = "|".join(sorted(i.model_dump_json() for i in instances))
        if key in cache:
            return cache[key]
        if out.replays >= max_replays:
            raise BudgetExhausted()
        out.replays += 1
        r = run_case(case.with_instances(instances), stop_on=signature, until=until)
        ok = signature in r.signatures
        cache[key] = ok
        return ok

    current = instances_of(result, before=t_fail)
    try:
        if not test(current):
            if not test(everything):
                out.note = "does not reproduce in instance mode"
                return out
            current = everything
    except BudgetExhausted:
        out.note = "budget exhausted before the first replay"
        return out
    current = ddmin(current, test)
    atoms = atoms_of(result, current)
    out.original_atoms = len(atoms_of(result, everything))
    if len(atoms) > 1:
        atoms = ddmin(atoms, test)
    final = merge(atoms)
    out.case = case.with_instances(final)
    out.reproduced = True
    out.dimensionality = dimensionality(final, spec)
    if out.replays >= max_replays:
        out.note = "replay budget exhausted: 1-minimality not guaranteed"
    return out
