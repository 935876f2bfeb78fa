"""What generated module tests import: load a frames file, build the planner, replay the frames.

A frames file (``frames.jsonl``, format ``deft_gym.frames/1``) is self-contained: its first line
is a header (planner class, parameters and map; input roles; scenario; oracle data), every other
line one frame ``{"index", "time", "inputs": {role: payload | null}, "input_seqs", "expected",
"planning_seq", "publish_ns", "distance"}``. Payloads are the log's JSON, so floats round-trip
bit-exactly.

Frames are replayed *in order* through one fresh planner so that its internal state (trajectory
stitching, hysteresis) is rebuilt exactly as in the live run. Set ``DEFT_PLANNER=module:Class``
and/or ``DEFT_PLANNER_PARAMS='{"name": value}'`` to run the same tests against another planner
(a fix under development, a mutant).
"""

from __future__ import annotations

import hashlib
import inspect
import json
import math
import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from deft_gym.bus.codec import decode
from deft_gym.planner.base import Frame, Planner, import_object, load_planner
from extract.oracle import Track, overlapping_points
from extract.validator import distance

FORMAT = "deft_gym.frames/1"


class FramesError(ValueError):
    """A frames file is missing, damaged or of another format."""


def read_header(path: Path | str) -> dict[str, Any]:
    """The header line of a frames file."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            first = fh.readline()
    except OSError as exc:
        raise FramesError(f"{path}: cannot read frames: {exc.strerror or exc}") from None
    return _header(path, first)


def _header(path: Path, line: bytes) -> dict[str, Any]:
    try:
        header = decode(line)
    except ValueError:
        header = None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise FramesError(f"{path}: line 1: expected a header with format {FORMAT!r}")
    return header


def load_frames(path: Path | str) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """``(header, frames)`` of a frames file."""
    path = Path(path)
    try:
        lines = path.read_bytes().splitlines()
    except OSError as exc:
        raise FramesError(f"{path}: cannot read frames: {exc.strerror or exc}") from None
    if not lines:
        raise FramesError(f"{path}: empty; expected a {FORMAT} header line")
    header = _header(path, lines[0])
    frames = []
    for n, line in enumerate(lines[1:], start=2):
        try:
            frames.append(decode(line))
        except ValueError as exc:
            raise FramesError(f"{path}: line {n}: not valid JSON ({exc})") from None
    return header, frames


def planner_class(header: dict[str, Any]) -> str:
    """``module:Class`` of the planner to test (``DEFT_PLANNER`` overrides the header's)."""
    return os.environ.get("DEFT_PLANNER") or header["planner"]["class"]


def make_planner(header: dict[str, Any]) -> Planner:
    """A fresh planner as the header describes it (``DEFT_PLANNER``/``DEFT_PLANNER_PARAMS``
    override class and parameters)."""
    spec = header["planner"]
    params = dict(spec.get("params") or {})
    extra = os.environ.get("DEFT_PLANNER_PARAMS")
    if extra:
        try:
            params.update(json.loads(extra))
        except ValueError as exc:
            raise FramesError(f"DEFT_PLANNER_PARAMS: expected a JSON object, got {extra!r} ({exc})") from None
    return load_planner(planner_class(header), spec["map"], params)


def to_frame(frame: dict[str, Any]) -> Frame:
    """The planner input of one frame record."""
    return Frame(frame["time"], frame["inputs"])


def replay(planner: Planner, frames: Iterable[dict[str, Any]]) -> Iterator[dict[str, Any] | None]:
    """Plan every frame in order (state carried over); yields each output (None: no plan)."""
    for fr in frames:
        yield planner.plan(to_frame(fr))


class EpisodeReplay:
    """One episode's frames, replayed lazily and once, for the generated tests.

    ``output(i)`` advances the planner through frames ``0..i`` as needed, so a single test can
    run alone (``pytest -k``) and still see the right planner state."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self.header = read_header(self.path)
        self._lines: list[bytes] | None = None
        self._frames: dict[int, dict[str, Any]] = {}
        self._planner: Planner | None = None
        self._outputs: list[dict[str, Any] | None] = []
        self.theta = float(self.header.get("theta", 0.0))
        self.measure = str(self.header.get("measure", "lsed"))
        cls = import_object(planner_class(self.header))  # import now (collection), not inside a test
        recorded = self.header["planner"].get("source_sha256")
        self.source_changed = bool(recorded) and source_digest(cls) != recorded

    def frame(self, index: int) -> dict[str, Any]:
        """Frame record ``index`` (lines are decoded on first use: a failure test that replays
        a few frames does not pay for parsing all of them)."""
        fr = self._frames.get(index)
        if fr is None:
            if self._lines is None:
                try:
                    self._lines = self.path.read_bytes().splitlines()[1:]
                except OSError as exc:
                    raise FramesError(f"{self.path}: cannot read frames: {exc.strerror or exc}") from None
            try:
                fr = self._frames[index] = decode(self._lines[index])
            except (ValueError, IndexError) as exc:
                raise FramesError(f"{self.path}: line {index + 2}: not a valid frame ({exc})") from None
        return fr

    def output(self, index: int) -> dict[str, Any] | None:
        """The planner's output for frame ``index`` in this replay."""
        if self._planner is None:
            self._planner = make_planner(self.header)
        while len(self._outputs) <= index:
            self._outputs.append(self._planner.plan(to_frame(self.frame(len(self._outputs)))))
        return self._outputs[index]

    # -- reproduction tests -------------------------------------------------------------------
    def reproduction_cases(self) -> list[Any]:
        """One ``pytest.param`` per frame, named ``frame0042-t4.227s``; frames the extraction did
        not reproduce within theta are marked xfail with their distance."""
        import pytest

        cases = []
        for f in self.header["frames_index"]:
            marks = []
            if not (f["distance"] is not None and f["distance"] <= self.theta):
                d = "no output" if f["distance"] is None else f"{f['distance']:.3g} m"
                marks.append(pytest.mark.xfail(reason=f"not reproduced at extraction ({d} > theta)", strict=False))
            cases.append(pytest.param(f["index"], id=frame_id(f["index"], f["time"]), marks=marks))
        return cases

    def distance(self, index: int) -> float:
        """Distance [m] of the replayed output from the recorded one."""
        return distance(self.frame(index)["expected"], self.output(index), self.measure)

    def explain(self, index: int) -> str:
        """Why frame ``index`` is not reproduced: distance, and the first differing point."""
        fr = self.frame(index)
        out = self.output(index)
        head = (f"frame {index} (t={fr['time']:.3f} s, planning seq {fr['planning_seq']}): ")
        if self.source_changed:
            head = "[the planner's source file changed since extraction] " + head
        if out is None:
            return head + "the planner returned no output"
        exp, act = fr["expected"]["trajectory"], out["trajectory"]
        d = distance(fr["expected"], out, self.measure)
        for k, (a, b) in enumerate(zip(zip(exp["x"], exp["y"]), zip(act["x"], act["y"]))):
            if a != b:
                return (head + f"{self.measure} {d:.6g} m > theta {self.theta} m; first differing point {k} "
                        f"(t={exp['t'][k]:.2f} s): recorded ({a[0]:.3f}, {a[1]:.3f}), replayed ({b[0]:.3f}, {b[1]:.3f})")
        return head + f"{self.measure} {d:.6g} m > theta {self.theta} m (timestamps or length differ)"

    # -- failure test (oracle transformation) ---------------------------------------------------
    def failure_cases(self) -> list[Any]:
        """The P_faulty frame as one ``pytest.param`` named by frame, time and collision."""
        import pytest

        f = self.header.get("oracle", {}).get("faulty")
        if not f:
            return []
        fid = f"{frame_id(f['index'], f['time'])}-{_ident(f['participant'])}@{f['collision_time']:.2f}s"
        return [pytest.param(f["index"], id=fid)]

    def faulty_hit(self, index: int) -> str | None:
        """Why the replayed output of frame ``index`` is still the faulty plan, or None.

        Faulty: it plans the ego box onto the participant's recorded box at a planned time, or
        it is within theta of the recorded P_faulty (paper eq. 3). A fresh planner replays the
        frames from the header's ``replay_from`` (the shortest suffix that reproduced P_faulty
        at extraction; ``DEFT_FULL_PREFIX=1`` replays them all)."""
        oracle = self.header["oracle"]
        f = oracle["faulty"]
        start = 0 if os.environ.get("DEFT_FULL_PREFIX") else int(f.get("replay_from", 0))
        if start == 0 or index != f["index"]:
            out = self.output(index)
        else:  # the shortest suffix that reproduced P_faulty at extraction (extract.minimize)
            planner = make_planner(self.header)
            out = None
            for j in range(start, index + 1):
                out = planner.plan(to_frame(self.frame(j)))
        if out is None:
            return None
        track = Track.from_dict(oracle["track"])
        ego = (float(oracle["ego"]["length"]), float(oracle["ego"]["width"]))
        hits = overlapping_points(out["trajectory"], track, ego)
        d = distance(self.frame(index)["expected"], out, self.measure)
        if hits.size:
            k = int(hits[0])
            tr = out["trajectory"]
            return (f"the planner still plans into the collision with {f['participant']}: frame {index} "
                    f"(t={self.frame(index)['time']:.3f} s) plans the ego at ({tr['x'][k]:.2f}, {tr['y'][k]:.2f}) "
                    f"at t={tr['t'][k]:.2f} s, overlapping {f['participant']}'s recorded position "
                    f"({len(hits)} planned points overlap; {self.measure} from P_faulty {d:.3g} m)")
        if d <= self.theta:
            return (f"the planner still produces P_faulty at frame {index}: {self.measure} {d:.3g} m "
                    f"<= theta {self.theta} m")
        return None


def source_digest(cls: type) -> str | None:
    """sha256 of the source file defining a planner class (None when it has none)."""
    try:
        path = inspect.getsourcefile(cls)
        return hashlib.sha256(Path(path).read_bytes()).hexdigest() if path else None
    except (OSError, TypeError):
        return None


def frame_id(index: int, time: float) -> str:
    """Test id of a frame: ``frame0042-t4.227s``."""
    return f"frame{index:04d}-t{time:.3f}s"


def _ident(text: str) -> str:
    return "".join(c if c.isalnum() or c in "_-" else "_" for c in str(text)) or "participant"


def finite_or_none(x: float) -> float | None:
    """JSON-friendly distance."""
    return x if math.isfinite(x) else None
