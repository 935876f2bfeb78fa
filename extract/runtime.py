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

import json
import math
import os
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from deft_gym.bus.codec import decode
from deft_gym.planner.base import (
    Frame,
    Planner,
    import_object,
    load_planner,
    planner_provenance,
    source_digest,
)
from extract.oracle import Track, overlapping_points
from extract.validator import Comparison, Tolerances, compare, distance

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
    run alone (``pytest -k``) and still see the right planner state. :meth:`check` is the
    reproduction test: the first frame (in time order) whose whole replayed output differs from
    the recorded one fails with the fields, values and decision that differ; the frames after it
    that differ too, one after the other, are reported as its consequence (xfail), since one
    stateful planner replays them all; a later frame that replays equal passes, and a difference
    after it fails again (a second regression is never hidden behind the first)."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self.header = read_header(self.path)
        self._lines: list[bytes] | None = None
        self._frames: dict[int, dict[str, Any]] = {}
        self._planner: Planner | None = None
        self._outputs: list[dict[str, Any] | None] = []
        self._comparisons: dict[int, Comparison] = {}
        self.theta = float(self.header.get("theta", 0.0))
        self.measure = str(self.header.get("measure", "lsed"))
        self.tolerances = Tolerances.from_dict(self.header.get("tolerances"), self.theta)
        self.index = {int(f["index"]): f for f in self.header["frames_index"]}
        cls = import_planner(self.header)  # import now (collection), not inside a test
        recorded = self.header["planner"].get("source_sha256")
        self.source_changed = bool(recorded) and source_digest(cls) != recorded
        self.changes = provenance_changes(self.header["planner"].get("provenance"), cls)
        self.seed_note: str | None = None

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
        not reproduce are marked xfail with what differed."""
        import pytest

        cases = []
        for f in self.header["frames_index"]:
            marks = []
            if not self.reproduced_at_extraction(f["index"]):
                d = "no output" if f["distance"] is None else f"position {f['distance']:.3g} m"
                why = f"; {f['after_lost']}" if f.get("after_lost") else ""
                marks.append(pytest.mark.xfail(reason=f"not reproduced at extraction ({d}){why}", strict=False))
            cases.append(pytest.param(f["index"], id=frame_id(f["index"], f["time"]), marks=marks))
        return cases

    def reproduced_at_extraction(self, index: int) -> bool:
        """Whether the extraction reproduced frame ``index`` (whole output, within tolerances)."""
        f = self.index[index]
        if "reproduced" in f:
            return bool(f["reproduced"])
        return f["distance"] is not None and f["distance"] <= self.theta  # frames files before fields

    def comparison(self, index: int) -> Comparison:
        """The replayed output of frame ``index`` against the recorded one (whole output)."""
        c = self._comparisons.get(index)
        if c is None:
            c = self._comparisons[index] = compare(self.frame(index)["expected"], self.output(index),
                                                   self.tolerances, self.measure)
        return c

    def distance(self, index: int) -> float:
        """Position distance [m] of the replayed output from the recorded one."""
        return self.comparison(index).distance

    def first_divergence(self, upto: int) -> int | None:
        """The first frame ``<= upto`` reproduced at extraction whose replay is not (None: none)."""
        for j in sorted(k for k in self.index if k <= upto):
            if self.reproduced_at_extraction(j) and not self.comparison(j).reproduced:
                return j
        return None

    def divergence_start(self, index: int) -> int | None:
        """Where the divergence that frame ``index`` belongs to began: the first frame of the run
        of consecutive differing frames (among those reproduced at extraction) that ends at
        ``index``; None when ``index`` replays equal. A frame that replays equal ends a run: a
        difference after it is a divergence of its own (a second regression), not a consequence."""
        if self.comparison(index).reproduced:
            return None
        start = index
        for j in sorted((k for k in self.index if k < index and self.reproduced_at_extraction(k)), reverse=True):
            if self.comparison(j).reproduced:
                break
            start = j
        return start

    def check(self, index: int) -> None:
        """The reproduction test of frame ``index``: passes when its replay is the recorded output
        (also after an earlier divergence: the planner came back), fails when it is the first
        frame of a divergence, and xfails as a consequence of the divergence it continues (every
        frame between them differs too)."""
        import pytest

        __tracebackhide__ = True  # pytest then reports the test's line only (cheap for many xfails)
        j = self.divergence_start(index)
        if j is None:
            return
        if j < index:
            fields = ", ".join(dict.fromkeys(d.field for d in self.comparison(j).diffs))
            pytest.xfail(f"a consequence of {self._where(j)}, where a divergence began ({fields}); every frame "
                         "since differs too")
        pytest.fail(self.explain(index), pytrace=False)

    def explain(self, index: int) -> str:
        """Why frame ``index`` is not reproduced: every field beyond its tolerance at full
        precision, the decision diff, and what became of the later frames."""
        c = self.comparison(index)
        j = self.divergence_start(index)
        first = self.first_divergence(index)
        what = (" - the first frame of this episode that does" if first == index else
                " - a divergence of its own: the frames before it replay equal" if j == index else "")
        lines = [self._notes() + f"{self._where(index)}: the replayed output differs from the recorded one" + what]
        lines += ["  " + d.text() for d in c.diffs]
        same = [k for k, v in c.deviations.items() if v == 0.0]
        if same:
            lines.append(f"  identical: {', '.join(same)}")
        if j == index:
            later = [k for k in sorted(self.index) if k > index and self.reproduced_at_extraction(k)]
            run = []
            for k in later:
                if self.comparison(k).reproduced:
                    break
                run.append(k)
            back = [k for k in later[len(run):] if self.comparison(k).reproduced]
            again = [k for k in later[len(run):] if not self.comparison(k).reproduced]
            if run:
                lines.append(f"consequences: the next {len(run)} of the {len(later)} later frames differ too "
                             f"(frames {run[0]}-{run[-1]}); their tests xfail as consequences of this one")
            elif later:
                lines.append(f"consequences: none - the next frame replays equal again ({len(later)} later frames)")
            if back:
                lines.append(f"after them {len(back)} frame(s) replay equal again (they pass)"
                             + (f"; {len(again)} differ again later (first: frame {again[0]}) and fail as "
                                "divergences of their own" if again else ""))
        return "\n".join(lines)

    def _where(self, index: int) -> str:
        fr = self.index[index]
        seq = self.frame(index).get("planning_seq")
        return f"frame {index} (t={fr['time']!r} s, planning seq {seq})"

    def _notes(self) -> str:
        notes = []
        if self.source_changed:
            notes.append("the planner's source file changed since extraction")
        notes += self.changes
        if os.environ.get("DEFT_PLANNER") or os.environ.get("DEFT_PLANNER_PARAMS"):
            notes.append(f"planner {planner_class(self.header)} {os.environ.get('DEFT_PLANNER_PARAMS', '')}".strip())
        return "".join(f"[{n}] " for n in notes)

    # -- failure test (oracle transformation) ---------------------------------------------------
    def failure_cases(self) -> list[Any]:
        """The P_faulty frame as one ``pytest.param`` named by frame, time and collision."""
        import pytest

        f = self.header.get("oracle", {}).get("faulty")
        if not f:
            return []
        fid = f"{frame_id(f['index'], f['time'])}-{_ident(f['participant'])}@{f['collision_time']:.2f}s"
        return [pytest.param(f["index"], id=fid)]

    def faulty_output(self, index: int) -> dict[str, Any] | None:
        """The planner's output at the P_faulty frame, reached the cheapest way the extraction
        verified: a fresh planner seeded with the state recorded at that frame (planners that
        declare it, :meth:`Planner.export_state`), else fed the shortest suffix of frames that
        reproduced P_faulty (``replay_from``), else every frame. ``DEFT_FULL_PREFIX=1`` replays
        them all."""
        oracle = self.header["oracle"]
        return self._oracle_output(index, oracle["faulty"], oracle.get("seed"))

    def _oracle_output(self, index: int, target: dict[str, Any], seed: dict[str, Any] | None) -> dict[str, Any] | None:
        """The output at a failure test's frame ``target["index"]`` (P_faulty, P_departure): from
        the ``seed`` state recorded there, else the shortest suffix from ``target["replay_from"]``,
        else every frame (see :meth:`faulty_output`)."""
        if os.environ.get("DEFT_FULL_PREFIX") or index != target["index"]:
            return self.output(index)
        if seed is not None and int(seed["frame"]) == index:
            planner = make_planner(self.header)
            try:
                planner.load_state(seed["state"])
            except (ValueError, TypeError, KeyError) as exc:
                self.seed_note = f"seeding failed ({exc}); replayed frames instead"
            else:
                return planner.plan(to_frame(self.frame(index)))
        start = int(target.get("replay_from", 0))
        if start == 0:
            return self.output(index)
        planner = make_planner(self.header)  # the shortest suffix that reproduced the frame (extract.minimize)
        out = None
        for j in range(start, index + 1):
            out = planner.plan(to_frame(self.frame(j)))
        return out

    def faulty_hit(self, index: int) -> str | None:
        """Why the replayed output of frame ``index`` is still the faulty plan, or None.

        Faulty: it plans the ego box onto the participant's recorded box at a planned time, or
        it is within theta of the recorded P_faulty (paper eq. 3)."""
        oracle = self.header["oracle"]
        f = oracle["faulty"]
        out = self.faulty_output(index)
        if out is None:
            return None
        track = Track.from_dict(oracle["track"])
        ego = (float(oracle["ego"]["length"]), float(oracle["ego"]["width"]))
        hits = overlapping_points(out["trajectory"], track, ego)
        d = distance(self.frame(index)["expected"], out, self.measure)
        note = self._notes() + (f"[{self.seed_note}] " if self.seed_note else "")
        if hits.size:
            k = int(hits[0])
            tr = out["trajectory"]
            return (note + f"the planner still plans into the collision with {f['participant']}: frame {index} "
                    f"(t={self.frame(index)['time']:.3f} s) plans the ego at ({tr['x'][k]!r}, {tr['y'][k]!r}) "
                    f"at t={tr['t'][k]!r} s, overlapping {f['participant']}'s recorded position "
                    f"({len(hits)} planned points overlap; {self.measure} from P_faulty {d!r} m)")
        if d <= self.theta:
            return (note + f"the planner still produces P_faulty at frame {index}: {self.measure} {d!r} m "
                    f"<= theta {self.theta} m")
        return None

    # -- the non-optimal-decision test ---------------------------------------------------------
    def _oracle_case(self, key: str, what: str) -> list[Any]:
        """The frame of the header's oracle ``key`` (P_departure, P_wrong_way, P_stall, P_off_road) as one
        ``pytest.param`` named by frame, time and ``what``; none when the episode has no such oracle."""
        import pytest

        o = self.header.get("oracle", {}).get(key)
        return [pytest.param(o["index"], id=f"{frame_id(o['index'], o['time'])}-{what}")] if o else []

    def _oracle_replay(self, key: str, index: int) -> tuple[dict[str, Any], dict[str, Any] | None]:
        """The header's oracle ``key`` (P_departure, P_wrong_way, P_off_road, P_stall) and the
        replayed output of frame ``index`` (from its seed state, else as :meth:`_oracle_output`)."""
        o = self.header["oracle"]
        return o[key], self._oracle_output(index, o[key], o.get(f"{key}_seed"))

    def departure_cases(self) -> list[Any]:
        """The P_departure frame as one ``pytest.param`` named by frame and time."""
        return self._oracle_case("departure", "off-path")

    def departure_problem(self, index: int) -> str | None:
        """Why the replayed output of frame ``index`` still leaves the optimal path, or None."""
        from extract.oracle import off_path, optimal_path

        path, limit = optimal_path(self.header["oracle"]["optimal_path"])
        _, out = self._oracle_replay("departure", index)
        if out is None:
            return None
        hit = off_path(out.get("trajectory") or {}, path, limit)
        if hit is None:
            return None
        k, dist = hit
        tr = out["trajectory"]
        return (self._notes() + f"the planner still leaves the optimal path: frame {index} "
                f"(t={self.frame(index)['time']:.3f} s) plans the ego at ({tr['x'][k]!r}, {tr['y'][k]!r}) at "
                f"t={tr['t'][k]!r} s, {dist:.2f} m from the optimal path (limit {limit:.2f} m)")

    # -- the driving-direction test ----------------------------------------------------------------
    def wrong_way_cases(self) -> list[Any]:
        """The P_wrong_way frame as one ``pytest.param`` named by frame and time."""
        return self._oracle_case("wrong_way", "wrong-way")

    def wrong_way_problem(self, index: int) -> str | None:
        """Why the replayed output of frame ``index`` still plans the ego against the lane direction
        (at least the limit's metres of path in lanes that all point against it, on the log's map),
        or None."""
        from extract.oracle import map_lanes, wrong_way_length

        w, out = self._oracle_replay("wrong_way", index)
        if out is None:
            return None
        tr = out.get("trajectory") or {}
        k, length = wrong_way_length(tr, map_lanes(self.header["oracle"].get("wrong_way_map")))
        if length < float(w["limit"]):
            return None
        return (self._notes() + f"the planner still plans the ego against the lane direction: frame {index} "
                f"(t={self.frame(index)['time']:.3f} s) plans {length:.2f} m of path in lanes that all point "
                f"against it (limit {float(w['limit']):.2f} m), from ({tr['x'][k]!r}, {tr['y'][k]!r}) at "
                f"t={tr['t'][k]!r} s")

    # -- the drivable-area test ------------------------------------------------------------------
    def off_road_cases(self) -> list[Any]:
        """The P_off_road frame as one ``pytest.param`` named by frame and time."""
        return self._oracle_case("off_road", "off-road")

    def off_road_problem(self, index: int) -> str | None:
        """Why the replayed output of frame ``index`` still plans the ego's box more than the limit
        outside the drivable area of the log's map near where the run left the road, or None."""
        from extract.oracle import map_area, off_road_near

        w, out = self._oracle_replay("off_road", index)
        if out is None:
            return None
        tr = out.get("trajectory") or {}
        ego = (float(w["ego"]["length"]), float(w["ego"]["width"]))
        k, depth = off_road_near(tr, map_area(self.header["oracle"].get("off_road_map")), ego, w["place"], float(w["radius"]))
        if depth <= float(w["limit"]):
            return None
        return (self._notes() + f"the planner still plans the ego off the road: frame {index} "
                f"(t={self.frame(index)['time']:.3f} s) plans the ego's box {depth:.2f} m outside the drivable area "
                f"(limit {float(w['limit']):.2f} m) at ({tr['x'][k]!r}, {tr['y'][k]!r}) at t={tr['t'][k]!r} s, "
                f"{float(w['radius']):g} m or less from where the run left the road")

    # -- the near-miss test ------------------------------------------------------------------------
    def near_miss_cases(self) -> list[Any]:
        """The P_near_miss frame as one ``pytest.param`` named by frame and time."""
        return self._oracle_case("near_miss", "near-miss")

    def near_miss_problem(self, index: int) -> str | None:
        """Why the replayed output of frame ``index`` still plans the ego's box within the
        clearance of the participant it passed too close in the run (at its recorded position at
        the planned time, relative speed above the oracle's), or None."""
        from extract.oracle import near_gaps

        w, out = self._oracle_replay("near_miss", index)
        if out is None:
            return None
        tr = out.get("trajectory") or {}
        ego = (float(w["ego"]["length"]), float(w["ego"]["width"]))
        gaps = near_gaps(tr, Track.from_dict(w["track"]), ego, float(w["speed"]), float(w["clearance"]))
        k = int(gaps.argmin()) if len(gaps) else -1
        if k < 0 or gaps[k] >= float(w["clearance"]):
            return None
        return (self._notes() + f"the planner still plans the ego past {w['participant']} too close: frame {index} "
                f"(t={self.frame(index)['time']:.3f} s) plans the ego's box {gaps[k]:.2f} m from it (clearance "
                f"{float(w['clearance']):.2f} m, relative speed above {float(w['speed']):g} m/s) at "
                f"({tr['x'][k]!r}, {tr['y'][k]!r}) at t={tr['t'][k]!r} s")

    # -- the red-light test ------------------------------------------------------------------------
    def red_light_cases(self) -> list[Any]:
        """The P_red_light frame as one ``pytest.param`` named by frame and time."""
        return self._oracle_case("red_light", "red-light")

    def red_light_problem(self, index: int) -> str | None:
        """Why the replayed output of frame ``index`` still plans the ego's front over the stop line
        the run crossed at red while its light is red (its recorded colours at the planned times),
        or None."""
        from extract.oracle import red_crossings

        w, out = self._oracle_replay("red_light", index)
        if out is None:
            return None
        tr = out.get("trajectory") or {}
        hits = red_crossings(tr, w["line"], w["timeline"], float(w["ego_length"]))
        if not len(hits):
            return None
        k = int(hits[0])
        return (self._notes() + f"the planner still plans to run the red light {w['light']}: frame {index} "
                f"(t={self.frame(index)['time']:.3f} s, the light {w['colour']}) plans the ego's front over its stop "
                f"line at t={tr['t'][k]!r} s, when the light was red")

    # -- the yellow-light test ---------------------------------------------------------------------
    def yellow_cases(self) -> list[Any]:
        """The P_yellow frame as one ``pytest.param`` named by frame and time."""
        return self._oracle_case("yellow", "yellow")

    def yellow_problem(self, index: int) -> str | None:
        """Why the replayed output of frame ``index`` still gives up the stop before the yellow
        light's line that its start left room for at the oracle's deceleration, or None."""
        from extract.oracle import yellow_stop

        w, out = self._oracle_replay("yellow", index)
        if out is None:
            return None
        tr = out.get("trajectory") or {}
        ahead, possible, given_up = yellow_stop(tr, w["lines"], float(w["ego_length"]), float(w["decel"]))
        if not (possible and given_up):
            return None
        return (self._notes() + f"the planner still drives on at the yellow light {w['light']}: frame {index} "
                f"(t={self.frame(index)['time']:.3f} s) starts {ahead:.1f} m before its line at {tr['v'][0]:.1f} m/s "
                f"(a stop there needs {tr['v'][0] ** 2 / (2 * ahead):.1f} m/s^2, at most {float(w['decel']):g} allowed) "
                f"and ends at {tr['v'][-1]:.1f} m/s where that stop is no longer possible")

    # -- the stuck test ----------------------------------------------------------------------------
    def stall_cases(self) -> list[Any]:
        """The P_stall frame as one ``pytest.param`` named by frame and time."""
        return self._oracle_case("stall", "stands")

    def stall_problem(self, index: int) -> str | None:
        """Why the replayed output of frame ``index`` still leaves the ego standing (a planned path
        shorter than the limit), or None."""
        from extract.oracle import planned_travel

        w, out = self._oracle_replay("stall", index)
        if out is None:
            return (self._notes() + f"the planner still gives no plan at frame {index} "
                    f"(t={self.frame(index)['time']:.3f} s), where the run stood stuck")
        travel = planned_travel(out.get("trajectory") or {})
        if travel >= float(w["limit"]):
            return None
        return (self._notes() + f"the planner still leaves the ego standing: frame {index} "
                f"(t={self.frame(index)['time']:.3f} s) plans {travel:.3f} m of path (limit {float(w['limit']):.2f} m); "
                f"the run stood from here to its end, stuck, no light holding it")


def import_planner(header: dict[str, Any]) -> type:
    """The planner class of a frames header (``DEFT_PLANNER`` overrides it). When it cannot be
    imported from here, the folder it was imported from at extraction (``provenance.root``) is
    put on ``sys.path`` and it is tried again: generated tests run from any directory."""
    path = planner_class(header)
    try:
        return import_object(path)
    except ValueError as first:
        root = ((header["planner"].get("provenance") or {}).get("root")) if path == header["planner"]["class"] else None
        if not root or root in sys.path or not Path(root).is_dir():
            raise FramesError(f"{first}; the frames file records no folder it could be imported from") from None
        sys.path.insert(0, root)
        try:
            return import_object(path)
        except ValueError as exc:
            raise FramesError(f"{exc} (also with {root} on sys.path, where it was at extraction)") from None


def provenance_changes(recorded: dict[str, Any] | None, cls: type) -> list[str]:
    """What differs from the planner's provenance recorded at extraction: the package's and the
    dependencies' versions, the Python version (one phrase each; empty when all agree)."""
    if not recorded:
        return []
    now = planner_provenance(cls)
    out = []
    pairs = [("python", recorded.get("python"), now.get("python"))]
    rp, np_ = recorded.get("package") or {}, now.get("package") or {}
    if rp.get("name"):
        pairs.append((rp["name"], rp.get("version"), np_.get("version") if np_.get("name") == rp["name"] else None))
    for name, v in (recorded.get("dependencies") or {}).items():
        pairs.append((name, v, (now.get("dependencies") or {}).get(name)))
    for name, was, is_ in pairs:
        if was != is_:
            out.append(f"{name} {was} -> {is_ or 'not installed'} since extraction")
    return out


def frame_id(index: int, time: float) -> str:
    """Test id of a frame: ``frame0042-t4.227s``."""
    return f"frame{index:04d}-t{time:.3f}s"


def _ident(text: str) -> str:
    return "".join(c if c.isalnum() or c in "_-" else "_" for c in str(text)) or "participant"


def finite_or_none(x: float) -> float | None:
    """JSON-friendly distance."""
    return x if math.isfinite(x) else None
