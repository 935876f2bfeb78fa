"""Subsystem replay testing (ASTAA section 3.4.1): the planner alone, on DeFT-extracted frames.

A planner has no control loop of its own, so it can be tested without the simulation: the frames
DeFT extracted from a log (``extract.runtime.load_frames``) are replayed in order through a
fresh planner, and test ``i`` replaces some input fields of one frame ``k`` by dictionary values,
then plans ``turnover`` more unmodified frames (section 4.1.1: turnover messages pull a bad value
out of the planner's state). Planner states are snapshotted once per frame during a nominal pass,
so each test restores frame ``k``'s state and costs a few ``plan`` calls.

Monitors: a crash (``plan`` raised), a hang (``plan`` overran its CPU-time deadline) and the
``on: planning`` invariants of the invariants file, judged against the frame's original inputs.
Findings are minimised over the mutated fields (ddmin) and emitted like the extractor's tests: a
self-contained folder with the frames, one JSON case per finding and a pytest module whose tests
fail while the planner is not robust to the case and pass once it is.
"""

from __future__ import annotations

import copy
import json
import shutil
import textwrap
import traceback
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.files import write_atomic
from deft_gym.planner.base import Frame, Planner
from deft_gym.robustness import paths
from deft_gym.robustness.dictionary import candidates, mutate
from deft_gym.robustness.generate import case_rng
from deft_gym.robustness.invariants import InvariantMonitor, InvariantSet, load_invariants
from deft_gym.robustness.minimise import BudgetExhausted, ddmin
from deft_gym.robustness.monitors import DeadlineExceeded, deadline, location
from deft_gym.robustness.spec import TestSpecification


@dataclass
class FrameCase:
    """Mutate fields of frame ``index`` (``sets``: ``{role, path, value}``), then plan
    ``turnover`` unmodified frames."""

    index: int
    sets: list[dict[str, str]]
    turnover: int = 5

    def as_dict(self) -> dict[str, Any]:
        return {"index": self.index, "sets": self.sets, "turnover": self.turnover}


@dataclass
class FrameResult:
    signatures: list[str] = field(default_factory=list)
    detail: str = ""
    changed: list[dict[str, str]] = field(default_factory=list)  # concrete atoms


class FrameReplay:
    """Frames of one episode, a planner, per-frame state snapshots and the monitors."""

    def __init__(self, frames_path: Path | str, invariants: InvariantSet | str | None = None,
                 deadline_s: float = 1.0, hardening: bool = False) -> None:
        from extract.runtime import load_frames, make_planner

        self.path = Path(frames_path)
        self.header, self.frames = load_frames(self.path)
        self.planner: Planner = make_planner(self.header)
        inv = invariants if isinstance(invariants, InvariantSet) else load_invariants(invariants)
        self.invariants = InvariantSet([i for i in inv.invariants if i.spec.on == "planning"], inv.params, inv.source)
        self.deadline_s = deadline_s
        self.hardening = hardening
        self.rejected = 0
        self.snapshots: list[Any] = []
        self.nominal: list[set[str]] = []
        for k, fr in enumerate(self.frames):
            self.snapshots.append(self.planner.snapshot())
            self.nominal.append(set(self._plan_checked(fr, fr["inputs"], k)[0]))

    def _plan_checked(self, fr: dict[str, Any], inputs: dict[str, Any], k: int) -> tuple[list[str], str]:
        try:
            with deadline(self.deadline_s), warnings.catch_warnings(), np.errstate(all="ignore"):
                warnings.simplefilter("ignore", RuntimeWarning)
                out = self.planner.plan(Frame(fr["time"], inputs))
        except DeadlineExceeded as exc:
            return ["hang:planner:deadline"], f"frame {k}: plan() overran {self.deadline_s} s at {location(exc.__traceback__)}"
        except Exception as exc:
            return ([f"crash:planner:{type(exc).__name__}@{location(exc.__traceback__)}"],
                    f"frame {k}: {type(exc).__name__}: {exc}"[:300])
        if out is None:
            return [], ""
        mon = InvariantMonitor(self.invariants, self.header["planner"]["map"])
        for role, payload in fr["inputs"].items():
            if payload is not None:
                mon.latest[role] = _view(payload)
        mon.observe("planning", {"header": {"stamp": fr["time"]}, **out}, fr["time"])
        vs = mon.finish(None, fr["time"])
        return [v.signature for v in vs], "; ".join(f"frame {k}: {v.name}: {v.detail}" for v in vs)[:300]

    def run(self, case: FrameCase) -> FrameResult:
        """Run one case from frame ``case.index``'s snapshot."""
        k = case.index
        self.planner.restore(self.snapshots[k])
        fr = self.frames[k]
        inputs = copy.deepcopy(fr["inputs"])
        res = FrameResult()
        prev = self.frames[k - 1]["inputs"] if k > 0 else {}
        for s in case.sets:
            payload = inputs.get(s["role"])
            if payload is None:
                continue

            def fn(old: Any, concrete: str, s: dict[str, str] = s) -> Any:
                res.changed.append({"role": s["role"], "path": concrete, "value": s["value"]})
                try:
                    p = paths.get(prev.get(s["role"]) or {}, concrete)
                except (KeyError, IndexError, TypeError):
                    p = None
                return mutate(s["value"], old, p)

            paths.apply(payload, s["path"], fn)
        if self.hardening:
            self._sanitise(inputs, k)
        for j in range(k, min(k + 1 + case.turnover, len(self.frames))):
            frj = self.frames[j]
            sigs, detail = self._plan_checked(frj, inputs if j == k else frj["inputs"], j)
            new = [s for s in sigs if s not in self.nominal[j]]
            if new:
                res.signatures, res.detail = new, detail
                break
        return res

    def _sanitise(self, inputs: dict[str, Any], k: int) -> None:
        """What the hardened planning node does: an invalid input is replaced by the last valid
        one (here: the previous frame's input of that role)."""
        from deft_gym.robustness.sanitize import problem
        from deft_gym.world.roadmap import shared_roadmap

        if k == 0:
            return
        roadmap = shared_roadmap(self.header["planner"]["map"])
        fr, before = self.frames[k], self.frames[k - 1]
        seqs, prev_seqs = fr.get("input_seqs") or {}, before.get("input_seqs") or {}
        for role, payload in inputs.items():
            last = before["inputs"].get(role)
            if payload is None or last is None:
                continue
            new_message = seqs.get(role) is None or seqs.get(role) != prev_seqs.get(role)
            reason = problem(role, payload, fr["time"], last["header"]["stamp"] if new_message else None,
                             roadmap, last=last if new_message else None)
            if reason:
                inputs[role] = last
                self.rejected += 1

    def problem(self, case: dict[str, Any]) -> str | None:
        """For generated tests: why the planner is not robust to ``case`` (None when it is)."""
        r = self.run(FrameCase(case["index"], case["sets"], case.get("turnover", 5)))
        return None if not r.signatures else f"{', '.join(r.signatures)} - {r.detail}"


def _view(payload: dict[str, Any]) -> Any:
    from deft_gym.robustness.expr import View

    return View(payload)


def generate(replay: FrameReplay, spec: TestSpecification, seed: int, i: int, exceptional_share: float = 0.8,
             turnover: int = 5) -> FrameCase:
    """Test ``i``: one frame, one or two fields of one non-empty input."""
    rng = case_rng(seed, i)
    k = rng.randrange(len(replay.frames))
    roles = sorted(r for r, p in replay.frames[k]["inputs"].items() if p is not None)
    role = rng.choice(roles)
    fields = spec.select([role])
    sets = []
    for f in rng.sample(fields, min(rng.randint(1, 2), len(fields))):
        names = candidates(f, rng.random() < exceptional_share) or candidates(f)
        sets.append({"role": role, "path": f.path, "value": rng.choice(names)})
    return FrameCase(k, sets, turnover)


def minimise_frame_case(replay: FrameReplay, case: FrameCase, signature: str, max_runs: int = 60) -> FrameCase:
    """ddmin over the concrete fields the case changed."""
    atoms = replay.run(case).changed
    runs = [0]

    def test(sub: list[dict[str, str]]) -> bool:
        if runs[0] >= max_runs:
            raise BudgetExhausted()
        runs[0] += 1
        return signature in replay.run(FrameCase(case.index, sub, case.turnover)).signatures

    if not atoms or not test(atoms):
        return case
    return FrameCase(case.index, ddmin(atoms, test), case.turnover)


def _slug(s: str) -> str:
    out = "".join(c if c.isalnum() else "_" for c in s).strip("_")
    while "__" in out:
        out = out.replace("__", "_")
    return out[:80]


def run_subsystem(frames_path: Path | str, out_dir: Path | str, budget: int = 200, seed: int = 0,
                  invariants: str | None = None, turnover: int = 5, hardening: bool = False) -> dict[str, Any]:
    """A subsystem campaign on one frames file; writes the test folder and ``summary.json``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    replay = FrameReplay(frames_path, invariants, hardening=hardening)
    spec = TestSpecification.from_schemas()
    first: dict[str, tuple[int, FrameCase]] = {}
    counts: dict[str, int] = {}
    for i in range(budget):
        case = generate(replay, spec, seed, i, turnover=turnover)
        try:
            sigs = replay.run(case).signatures
        except Exception:  # a harness error: reported, never fatal
            counts["harness_errors"] = counts.get("harness_errors", 0) + 1
            traceback.print_exc()
            continue
        for s in sigs:
            counts[s] = counts.get(s, 0) + 1
            first.setdefault(s, (i, case))
    frames_name = "frames.jsonl"
    if Path(frames_path).resolve() != (out / frames_name).resolve():
        shutil.copyfile(frames_path, out / frames_name)
    cases = []
    for sig, (i, case) in first.items():
        small = minimise_frame_case(replay, case, sig)
        cases.append({"id": f"{_slug(sig)}_frame{small.index}", "signature": sig, "test": i, **small.as_dict(),
                      "atoms": len(small.sets)})
    name = _slug(str(replay.header.get("scenario") or Path(frames_path).parent.name))
    write_atomic(out / "cases.json", json.dumps(cases, indent=1) + "\n")
    write_atomic(out / f"test_robustness_{name}.py", pytest_module_source(name, frames_name, len(cases), hardening))
    summary = {"frames": str(frames_path), "tests": budget, "seed": seed, "hardening": hardening,
               "rejected_inputs": replay.rejected,
               "crashes": sum(n for s, n in counts.items() if s.startswith("crash:")),
               "hangs": sum(n for s, n in counts.items() if s.startswith("hang:")),
               "violations": {s.split(":", 1)[1]: n for s, n in counts.items() if s.startswith("violation:")},
               "harness_errors": counts.get("harness_errors", 0),
               "findings": {s: {"tests": counts[s], "first_test": first[s][0]} for s in first},
               "minimised": cases}
    write_atomic(out / "summary.json", json.dumps(summary, indent=1, allow_nan=True) + "\n")
    return summary


def pytest_module_source(name: str, frames_name: str, n: int, hardening: bool = False) -> str:
    """Source of the generated pytest module."""
    return textwrap.dedent(f'''\
        """ASTAA subsystem robustness tests of the planner, on DeFT-extracted frames ({n} cases).

        Generated by `deft-gym stress subsystem` (`python -m deft_gym.robustness.stress
        subsystem`). Each case replays the frames up to one frame, replaces input fields by
        exceptional values (cases.json), and plans a few more frames; a test fails while the
        planner crashes, hangs or produces an invalid plan, and passes once it is robust to the
        case. DEFT_PLANNER=module:Class tests another planner.
        """

        import json
        from pathlib import Path

        import pytest

        from deft_gym.robustness.subsystem import FrameReplay

        HERE = Path(__file__).parent
        CASES = json.loads((HERE / "cases.json").read_text())
        REPLAY = None


        def _replay() -> FrameReplay:
            global REPLAY
            if REPLAY is None:
                REPLAY = FrameReplay(HERE / {frames_name!r}, hardening={hardening!r})
            return REPLAY


        @pytest.mark.parametrize("case", CASES, ids=[c["id"] for c in CASES])
        def test_{name}_planner_is_robust(case: dict) -> None:
            """The planner neither crashes nor hangs nor plans invalidly on this input."""
            problem = _replay().problem(case)
            assert problem is None, problem
        ''')


__all__ = ["FrameCase", "FrameReplay", "generate", "minimise_frame_case", "run_subsystem"]
