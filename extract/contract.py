"""The planner contract, checked: run any planner over a log's frames and verify what DeFT relies on.

    python -m extract.contract runs/x/deft/frames.jsonl                 # the planner it was extracted with
    python -m extract.contract runs/x/episode.mcap                      # frames straight from a log
    python -m extract.contract runs/x/episode.mcap --planner mypkg.planner:MyPlanner --params '{"k": 1}'

From a test (the pytest helper)::

    from extract.contract import assert_contract
    assert_contract(lambda: MyPlanner(map_spec), "runs/x/deft/frames.jsonl")

Checks (:mod:`deft_gym.planner.base` states the contract):

``output``
    every output meets the output contract (:func:`deft_gym.planner.base.validate_output`);
``deterministic``
    two fresh planners fed the same frames give bit-identical outputs (the second run with the
    global random generators seeded differently);
``no_clock_or_global_rng``
    ``plan()`` calls no wall clock (``time.time``, ``perf_counter``, ``monotonic``,
    ``datetime.now`` ...), no global random generator (``random.*``, ``numpy.random.*``) and no
    ``os.urandom`` (seen by a profiling hook while it runs);
``snapshot_restore``
    ``snapshot()``, planning another frame (the next one, as the input search tries
    candidates), ``restore()`` - twice - and planning the frame gives the output of a clean
    replay, frame after frame (state outside ``self.state`` or a snapshot sharing objects with
    the live state breaks it);
``none_keeps_state``
    a frame with no inputs, on which the planner returns None, changes nothing: the outputs
    that follow are those of a clean replay;
``hidden_state``
    ``plan()`` changes no attribute of the planner but ``state`` and the caches it declares
    (:attr:`deft_gym.planner.base.Planner.caches`) - whether or not the frames at hand make the
    change show in an output (hidden state the frames never exercise passed the other checks).

Each violation names the frame (index and time) and what differed. Exit status: 0 when the
contract holds, 1 when it is violated, 2 on bad input.
"""

from __future__ import annotations

import datetime
import json
import math
import os
import random
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.bus.codec import encode
from deft_gym.files import first_line
from deft_gym.planner.base import Frame, Planner, load_planner, validate_output
from extract.validator import compare

CHECKS = ("output", "deterministic", "no_clock_or_global_rng", "snapshot_restore", "none_keeps_state",
          "hidden_state")

_CLOCKS = {time.time, time.time_ns, time.monotonic, time.monotonic_ns, time.perf_counter, time.perf_counter_ns,
           time.process_time, time.process_time_ns, time.thread_time, time.thread_time_ns, time.clock_gettime,
           time.clock_gettime_ns, time.localtime, time.gmtime, time.ctime, time.asctime, os.urandom}
_CLOCK_METHODS = {(datetime.datetime, "now"), (datetime.datetime, "utcnow"), (datetime.datetime, "today"),
                  (datetime.date, "today")}


@dataclass
class Violation:
    """One breach of the contract: which check, at which frame, what happened."""

    check: str
    frame: int | None
    time: float | None
    message: str

    def text(self) -> str:
        where = f"frame {self.frame} (t={self.time!r} s): " if self.frame is not None else ""
        return f"{self.check}: {where}{self.message}"


@dataclass
class ContractReport:
    """The verdict of every check (``ok``, ``violated`` or ``not checked: why``) and the
    violations, first per check."""

    planner: str
    frames: int
    checks: dict[str, str] = field(default_factory=dict)
    violations: list[Violation] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.violations

    def add(self, check: str, frame: int | None, t: float | None, message: str) -> None:
        self.violations.append(Violation(check, frame, t, message))
        self.checks[check] = "violated"

    def text(self) -> str:
        """A readable report: one line per check, then the violations."""
        lines = [f"planner contract of {self.planner} on {self.frames} frames: "
                 + ("holds" if self.ok else f"{len(self.violations)} violation(s)")]
        lines += [f"  {name}: {self.checks.get(name, 'not run')}" for name in CHECKS]
        lines += ["  - " + v.text() for v in self.violations]
        return "\n".join(lines)

    def as_dict(self) -> dict[str, Any]:
        return {"planner": self.planner, "frames": self.frames, "ok": self.ok, "checks": dict(self.checks),
                "violations": [v.__dict__ for v in self.violations], "seconds": self.seconds}


def check_contract(make_planner: Callable[[], Planner], frames: Sequence[Frame], name: str | None = None) -> ContractReport:
    """Run every check of the contract on ``frames`` with planners from ``make_planner``."""
    t0 = time.perf_counter()
    probe = make_planner()
    report = ContractReport(name or f"{type(probe).__module__}:{type(probe).__qualname__}", len(frames))
    saved = random.getstate(), np.random.get_state()
    try:
        clean = _clean_run(make_planner, frames, report)
        _deterministic(make_planner, frames, clean, report)
        _snapshot_restore(make_planner, frames, clean, report)
        _none_keeps_state(make_planner, frames, clean, report)
    finally:
        random.setstate(saved[0])
        np.random.set_state(saved[1])
    report.seconds = time.perf_counter() - t0
    return report


def _call(planner: Planner, frame: Frame) -> tuple[dict[str, Any] | None, BaseException | None]:
    try:
        return planner.plan(frame), None
    except Exception as exc:  # a crash is a finding here, never an abort
        return None, exc


def _same(a: Any, b: Any) -> bool:
    if a is None or b is None:
        return a is b
    return a == b or encode(a) == encode(b)


def _difference(expected: dict[str, Any] | None, actual: dict[str, Any] | None) -> str:
    """What differs between two outputs, shortly (the first differing field at full precision)."""
    if expected is None or actual is None:
        return f"{'no output' if actual is None else 'an output'} instead of {'an output' if actual is None else 'none'}"
    c = compare(expected, actual)
    return c.diffs[0].text() if c.diffs else "outputs differ in a field that is not compared"


def _clean_run(make_planner: Callable[[], Planner], frames: Sequence[Frame], report: ContractReport
               ) -> list[dict[str, Any] | None]:
    """Run 1: a fresh planner under the profiling hook, global generators seeded with 1; checks
    the output contract and clock / global-generator use."""
    planner = make_planner()
    random.seed(1)
    np.random.seed(1)
    seen: dict[str, int] = {}
    current = [0]

    def hook(_frame: Any, event: str, arg: Any) -> None:
        if event == "c_call" and (bad := _forbidden(arg)) is not None and bad not in seen:
            seen[bad] = current[0]

    outs: list[dict[str, Any] | None] = []
    bad_output = crashed = False
    hidden = _Attributes(planner)
    for i, fr in enumerate(frames):
        current[0] = i
        sys.setprofile(hook)
        try:
            out, exc = _call(planner, fr)
        finally:
            sys.setprofile(None)
        outs.append(out)
        if (changed := hidden.changed()) and "hidden_state" not in report.checks:
            report.add("hidden_state", i, fr.time, f"plan() changed {', '.join(f'self.{a}' for a in changed)}, "
                       "outside self.state: state that snapshot()/restore() and seeding do not carry (declare "
                       "memo caches and scratch buffers in the class's `caches`)")
        if exc is not None and not crashed:
            crashed = True
            report.add("output", i, fr.time, f"plan() raised {type(exc).__name__}: {exc}")
        problems = validate_output(out, fr.time)
        if problems and not bad_output:
            bad_output = True
            report.add("output", i, fr.time, "; ".join(problems))
    report.checks.setdefault("output", "ok")
    report.checks.setdefault("hidden_state", "ok")
    for what, i in seen.items():
        report.add("no_clock_or_global_rng", i, frames[i].time,
                   f"plan() called {what}; anything time-dependent must come from frame.time, randomness from "
                   "a generator the planner seeds itself")
    report.checks.setdefault("no_clock_or_global_rng", "ok")
    return outs


class _Attributes:
    """The planner's attributes but ``state`` and its declared caches, as bytes, to tell which
    ones a call changed."""

    def __init__(self, planner: Planner) -> None:
        self.planner = planner
        self.skip = {"state", *getattr(type(planner), "caches", ())}
        self.last = self._now()

    def _now(self) -> dict[str, bytes]:
        import io
        import pickle

        planner, state = self.planner, getattr(self.planner, "state", None)
        # a helper's reference back to the planner, its state or one of its caches: a name
        named = {id(planner): "planner", **({id(state): "state"} if state is not None else {}),
                 **{id(v): f"cache {n}" for n in self.skip - {"state"} if (v := getattr(planner, n, None)) is not None}}

        class Pickler(pickle.Pickler):
            def persistent_id(self, obj: Any) -> str | None:
                return named.get(id(obj))

        out = {}
        for name, value in vars(planner).items():
            if name in self.skip:
                continue
            buf = io.BytesIO()
            try:
                Pickler(buf, protocol=pickle.HIGHEST_PROTOCOL).dump(value)
                out[name] = buf.getvalue()
            except Exception:  # an attribute that cannot be pickled: its identity
                out[name] = f"{type(value).__qualname__}@{id(value)}".encode()
        return out

    def changed(self) -> list[str]:
        now = self._now()
        names = sorted(n for n in set(now) | set(self.last) if now.get(n) != self.last.get(n))
        self.last = now
        return names


def _forbidden(fn: Any) -> str | None:
    """The name of a wall-clock / global-generator builtin, or None."""
    try:
        if fn in _CLOCKS:
            return f"{getattr(fn, '__module__', None) or 'os'}.{fn.__name__}"
    except TypeError:  # unhashable callables
        return None
    owner = getattr(fn, "__self__", None)
    name = getattr(fn, "__name__", "")
    if owner is random._inst:  # type: ignore[attr-defined]
        return f"random.{name} (the global generator)"
    if owner is np.random.mtrand._rand:
        return f"numpy.random.{name} (the global generator)"
    if isinstance(owner, type) and (owner, name) in _CLOCK_METHODS:
        return f"{owner.__module__}.{owner.__name__}.{name}"
    return None


def _deterministic(make_planner: Callable[[], Planner], frames: Sequence[Frame], clean: list[Any],
                   report: ContractReport) -> None:
    planner = make_planner()
    random.seed(2)
    np.random.seed(2)
    for i, fr in enumerate(frames):
        out, _ = _call(planner, fr)
        if not _same(out, clean[i]):
            report.add("deterministic", i, fr.time, "a second fresh planner fed the same frames gives another output: "
                       + _difference(clean[i], out))
            return
    report.checks["deterministic"] = "ok"


def _snapshot_restore(make_planner: Callable[[], Planner], frames: Sequence[Frame], clean: list[Any],
                      report: ContractReport) -> None:
    if report.checks.get("deterministic") != "ok":
        report.checks["snapshot_restore"] = "not checked: the planner is not deterministic"
        return
    planner = make_planner()
    for i, fr in enumerate(frames):
        j = i + 1 if i + 1 < len(frames) else i - 1
        if j >= 0 and j != i:
            try:
                snap = planner.snapshot()
                for _ in range(2):
                    _call(planner, frames[j])
                    planner.restore(snap)
            except Exception as exc:
                report.add("snapshot_restore", i, fr.time, f"snapshot()/restore() raised {type(exc).__name__}: {exc}")
                return
        out, _ = _call(planner, fr)
        if not _same(out, clean[i]):
            report.add("snapshot_restore", i, fr.time,
                       f"after snapshot(), plan(frame {j}), restore() (twice), the output differs from a clean replay: "
                       f"{_difference(clean[i], out)} - state kept outside self.state, or a snapshot sharing objects "
                       "with the live state; the input search detects this and falls back to fresh replays (slow)")
            return
    report.checks["snapshot_restore"] = "ok"


def _none_keeps_state(make_planner: Callable[[], Planner], frames: Sequence[Frame], clean: list[Any],
                      report: ContractReport) -> None:
    if report.checks.get("deterministic") != "ok":
        report.checks["none_keeps_state"] = "not checked: the planner is not deterministic"
        return
    planner = make_planner()
    for i, fr in enumerate(frames):
        empty = Frame(fr.time, dict.fromkeys(fr.inputs))
        res, exc = _call(planner, empty)
        if exc is not None:
            report.add("none_keeps_state", i, fr.time, f"plan() raised {type(exc).__name__} on a frame with no inputs; "
                       f"the contract asks for None when it cannot plan ({exc})")
            return
        if res is not None:
            report.checks["none_keeps_state"] = (f"not checked: the planner plans on a frame with no inputs "
                                                 f"(frame {i})")
            return
        out, _ = _call(planner, fr)
        if not _same(out, clean[i]):
            report.add("none_keeps_state", i, fr.time, "plan() returned None on a frame with no inputs but changed "
                       "the state: the next output differs from a clean replay: " + _difference(clean[i], out))
            return
    report.checks["none_keeps_state"] = "ok"


# -- frames from a frames file or a log -------------------------------------------------------------
def frames_from_file(path: Path | str, max_frames: int | None = None) -> tuple[dict[str, Any], list[Frame]]:
    """``(planner spec, frames)`` of a frames file (``frames.jsonl`` of an extraction)."""
    from extract.runtime import load_frames, to_frame

    header, records = load_frames(path)
    frames = [to_frame(r) for r in records[:max_frames]]
    return dict(header["planner"]), frames


def frames_from_log(path: Path | str, mapping: Any = None, max_frames: int | None = None
                    ) -> tuple[dict[str, Any], list[Frame]]:
    """``(planner spec, frames)`` straight from an MCAP log: at each planning output's frame time
    (its publish time when the log does not state it), the latest message of every input role
    published by then (no search: any realistic sequence of frames serves the contract)."""
    from extract.episode import _planner_spec
    from extract.io_filter import PlanningIOFilter
    from extract.logs import read_log
    from extract.mapping import load_mapping

    mp = load_mapping(mapping)
    elog = read_log(path, sorted(set(mp.topics.values())), mp.seq_field)
    spec = _planner_spec(elog, mp)
    pif = PlanningIOFilter(elog, mp, spec["class"])
    frames = []
    for o in pif.outputs[:max_frames]:
        t_ns = o.frame_ns if o.frame_ns is not None else o.publish_ns
        t = o.frame_time if o.frame_time is not None else o.publish_time
        inputs = {}
        for r in pif.roles:
            k = pif.frame_bound(r, t_ns) - 1
            inputs[r] = pif.inputs[r].fresh(k) if k >= 0 else None
        frames.append(Frame(t, inputs))
    return spec, frames


def load_contract_frames(path: Path | str, mapping: Any = None, max_frames: int | None = None
                         ) -> tuple[dict[str, Any], list[Frame]]:
    """Frames of a frames file (``.jsonl``) or of an MCAP log."""
    return (frames_from_file(path, max_frames) if str(path).endswith(".jsonl")
            else frames_from_log(path, mapping, max_frames))


def check_path(path: Path | str, planner: str | None = None, params: dict[str, Any] | None = None,
               mapping: Any = None, max_frames: int | None = None) -> ContractReport:
    """:func:`check_contract` on the frames of a frames file or a log, with the planner it names
    (or ``planner`` = ``module:Class``; ``params`` replace its parameters)."""
    spec, frames = load_contract_frames(path, mapping, max_frames)
    cls = planner or spec["class"]
    prm = dict(spec.get("params") or {}) if params is None else dict(params)
    # in this process (isolation inline): the checks watch the planner's calls and attributes
    load_planner(cls, spec["map"], prm, isolation="inline")  # a bad class or parameter fails here, once
    return check_contract(lambda: load_planner(cls, spec["map"], prm, isolation="inline"), frames, cls)


def assert_contract(make_planner: Callable[[], Planner], frames: Sequence[Frame] | Path | str,
                    max_frames: int | None = None) -> ContractReport:
    """The pytest helper: check the contract and raise AssertionError with the report when it is
    violated; returns the report otherwise."""
    if isinstance(frames, str | Path):
        frames = load_contract_frames(frames, max_frames=max_frames)[1]
    report = check_contract(make_planner, list(frames)[:max_frames])
    if not report.ok:
        raise AssertionError(report.text())
    return report


def main(argv: list[str] | None = None) -> int:
    from rich.console import Console

    from deft_gym.cli import common
    from extract.logs import LogError
    from extract.mapping import MappingError
    from extract.runtime import FramesError

    ap = common.parser("check-planner", "extract.contract", __doc__, epilog="Checks: " + ", ".join(CHECKS))
    ap.add_argument("path", metavar="FRAMES_OR_LOG", help="frames.jsonl of an extraction, or an MCAP episode log")
    ap.add_argument("--planner", metavar="MODULE:CLASS", default=None, help="planner to check (default: the one named)")
    ap.add_argument("--params", metavar="JSON", default=None, help="its parameters (default: those named)")
    ap.add_argument("--mapping", metavar="FILE", default=None, help="topic-role mapping of a log")
    ap.add_argument("--max-frames", type=int, default=None, metavar="N", help="check the first N frames only")
    ap.add_argument("--json", action="store_true", help="print the report as JSON")
    common.add_output_flags(ap)
    args = ap.parse_args(argv)
    console = Console(highlight=False, soft_wrap=True, quiet=args.quiet)
    try:
        params = json.loads(args.params) if args.params else None
        if params is not None and not isinstance(params, dict):
            raise ValueError(f"--params: expected a JSON object, got {args.params!r}")
        if not Path(args.path).exists():
            raise ValueError(f"{args.path}: no such file; expected frames.jsonl or an .mcap log")
        report = check_path(args.path, args.planner, params, args.mapping, args.max_frames)
    except (LogError, MappingError, FramesError, ValueError, TypeError) as err:
        first = first_line(err)
        return common.cli_error(first)
    if args.json:
        print(json.dumps(report.as_dict(), indent=1, default=lambda x: None if not math.isfinite(x) else x))
    else:
        console.print(report.text())
    return 0 if report.ok else 1


if __name__ == "__main__":
    sys.exit(main())
