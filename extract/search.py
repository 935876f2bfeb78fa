"""The Time-sensitive Input Search Engine (DeFT section 4.2) with the Trajectory Validator in the loop.

Outputs are processed in order by one planner instance whose state is carried from frame to
frame, exactly as the module tests will replay them. For each output the search proposes
candidate frames, runs the planner on each from a snapshot of its state, and keeps the first
whose whole output (every trajectory field and the decision) the validator finds identical,
restoring the snapshot after every miss, so no candidate ever re-runs the prefix.

The answer must not depend on which candidates were tried. A planner whose ``restore()`` is
not faithful (state kept outside ``self.state``, a snapshot that shares objects with the live
state) would make it so; after the search, the chosen frames are replayed through a fresh
planner (DeFT's Algorithm 1 validation run) whenever a snapshot was restored, and from the first
output that replay does not give bit for bit, the search is redone without snapshots: every
candidate runs on a fresh planner fed the frames chosen so far (slower, always right).
Modes:

``heuristic``
    The paper's heuristics as a best-first search. H1: the frame time t_F lies between the
    trigger message and the output (known exactly when the output carries it, e.g.
    ``header.stamp``; otherwise guessed within those bounds). H2: only messages published no
    later than t_F can be in the frame, and newer ones are more likely: with a lognormal
    delivery delay D and drop rate q, message j (newest first) is the latest received at t_F
    with probability ``R(g_j) * prod_{k newer} (1 - R(g_k))``, ``R(g) = (1-q) P(D <= g)``,
    ``g = t_F - t_pub``; the newest trigger-role message is the one whose receipt started the
    run, so it is taken as received (the paper: the trigger message must be in the frame). H3:
    never older than the previous frame's choice per role (that one is known to have been
    received). Joint candidates are enumerated in decreasing probability across roles. When nothing in this space reproduces the output, H3 is relaxed (a delivery
    can overtake another); when still nothing does, the closest candidate is kept.
``last``
    The baseline: the latest message of each role published at or before the output.
``headers``
    The output names its inputs' sequence numbers (``debug.input_seqs``); outputs without them
    fall back to the heuristic.

Every ``plan()`` call runs under the wall-clock watchdog of :mod:`deft_gym.execution.watchdog`
(``watchdog_s``, else ``DEFT_GYM_WATCHDOG_S``, else 10 s): a call that blocks or spins past it is
a *hang* finding (:attr:`InputSearch.hang`: module, message, frame time, output) and no further
``plan()`` call is made - the planner's state is unknown after an interrupted call, and each
further call could cost the watchdog again - so the search finishes, every output after it
without a replayed plan.
"""

from __future__ import annotations

import heapq
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from deft_gym.bus.codec import encode
from deft_gym.bus.messages import NS_PER_S
from deft_gym.execution.isolation import HostDied
from deft_gym.execution.watchdog import (
    ModuleHang,
    Watchdog,
    describe_exception,
    interrupts,
    module_fault,
    watchdog_seconds,
)
from deft_gym.planner.base import Frame, Planner
from extract.io_filter import Output, PlanningIOFilter
from extract.mapping import get_field
from extract.validator import distance, measure_fn, same_output

MODES = ("heuristic", "last", "headers")
Choice = dict[str, int | None]


@dataclass(frozen=True)
class SearchConfig:
    """Knobs of the input search."""

    mode: str = "heuristic"
    measure: str = "lsed"
    max_tries: int = 64  #: candidate frames checked per output at most
    unsynced_tries: int = 6  #: ... while the previous output was not reproduced exactly
    depth: int = 6  #: candidates per role in the ranked stage (4x that when H3 is relaxed)
    time_guesses: int = 8  #: frame-time guesses per output when the log does not state it
    refine_steps: int = 14  #: ... then golden-section steps on the frame time of the closest

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"unknown mode {self.mode!r}; expected one of {list(MODES)}")
        measure_fn(self.measure)


@dataclass
class FrameChoice:
    """The frame chosen for one output and how well it reproduces it."""

    output: Output
    time: float  #: frame time t_F [s] given to the planner
    choice: Choice  #: message index per role (None: nothing received yet)
    distance: float  #: position distance [m] by the measure
    tries: int
    stage: str  #: first | ranked | relaxed | closest | last | headers | headers-fallback
    actual: dict[str, Any] | None = field(default=None, repr=False)
    exact: bool = False  #: the whole output reproduced bit for bit


class InputSearch:
    """Runs one of the modes over all outputs of a :class:`PlanningIOFilter`.

    ``factory`` builds fresh planners like ``planner`` (for the validation replay and the
    snapshot-free fallback; without it the search trusts ``snapshot()``/``restore()``).
    ``watchdog_s``: wall-clock seconds one ``plan()`` may take (None: ``DEFT_GYM_WATCHDOG_S`` or
    the default; 0: unwatched)."""

    def __init__(self, pif: PlanningIOFilter, planner: Planner, cfg: SearchConfig,
                 factory: Callable[[], Planner] | None = None, watchdog_s: float | None = None) -> None:
        self.pif, self.planner, self.cfg = pif, planner, cfg
        self.factory = factory
        self.dog = Watchdog(watchdog_seconds(watchdog_s))
        #: the first plan() that ran past the watchdog (kind, module, exception, time, output); no
        #: plan() is called after it
        self.hang: dict[str, Any] | None = None
        self._at: int | None = None  # the output being searched (or replayed)
        self.measure = measure_fn(cfg.measure)
        self.roles = pif.roles
        d = pif.mapping.delivery
        sigma2 = math.log1p((d.std_ms / d.mean_ms) ** 2)
        self._mu = math.log(d.mean_ms * 1e6) - sigma2 / 2  # lognormal in ns
        self._sigma = math.sqrt(sigma2) or 1e-9
        self._keep = 1.0 - d.drop_prob
        self.planner_s = 0.0
        self.plan_calls = 0
        self.errors: list[str] = []
        self.exceptions = 0  #: plan() calls that raised (all of them; ``errors`` keeps the first 20)
        self._seq_index: dict[str, dict[int, int]] | None = None
        self.restores = 0  #: snapshots restored (candidates tried after a miss)
        #: None: not checked (no snapshot restored, or no factory); True: the validation replay
        #: gave every chosen output; False: it did not, the search was redone without snapshots
        self.restore_faithful: bool | None = None
        self.unfaithful_at: int | None = None  #: first output the validation replay did not give
        self.nondeterministic_at: int | None = None  #: ... even after the snapshot-free search
        self._fresh = False
        self._chosen: list[FrameChoice] = []

    # -- running ------------------------------------------------------------------------------
    def run(self, on_frame: Callable[[FrameChoice], None] | None = None) -> list[FrameChoice]:
        """Choose a frame for every output, in order; ``on_frame`` sees each result (an output
        searched again after a failed validation replay is seen again)."""
        with self.dog.armed():
            return self._run(on_frame)

    def _run(self, on_frame: Callable[[FrameChoice], None] | None) -> list[FrameChoice]:
        out = self._chosen = []
        self._run_from(0, on_frame)
        if self.factory is None or not self.restores or self.hang is not None:
            return out
        k = self._validate(out)
        if self.hang is not None:  # the validation replay hung: nothing more is known
            return out
        self.restore_faithful = k is None
        if k is None:
            return out
        self.unfaithful_at = k
        self._fresh = True
        del out[k:]
        self.planner = self._replayed(k)
        self._run_from(k, on_frame)
        self.nondeterministic_at = self._validate(out)
        return out

    def _run_from(self, start: int, on_frame: Callable[[FrameChoice], None] | None) -> None:
        out = self._chosen
        prev = out[start - 1].choice if start else None
        synced = out[start - 1].exact if start else True
        step = {"heuristic": self._heuristic, "last": self._last, "headers": self._headers}[self.cfg.mode]
        for o in self.pif.outputs[start:]:
            self._at = o.index
            fc = step(o, prev, synced, out[-1] if out else None)
            fc.exact = fc.distance == 0.0 and same_output(o.payload, fc.actual)
            synced = fc.exact
            prev = fc.choice
            out.append(fc)
            if on_frame is not None:
                on_frame(fc)

    def frame_inputs(self, choice: Choice) -> dict[str, Any]:
        """Freshly decoded payloads of a choice (ValueError: one is not valid JSON)."""
        return {role: (self.pif.inputs[role].fresh(j) if j is not None else None) for role, j in choice.items()}

    def _validate(self, out: list[FrameChoice]) -> int | None:
        """Replay the chosen frames through a fresh planner; the first output it does not give
        bit for bit (None: all)."""
        planner = self.factory()
        for i, fc in enumerate(out):
            self._at = fc.output.index
            got = self._call(planner, fc.time, fc.choice)
            if not _same(got, fc.actual):
                return i
        return None

    def _replayed(self, n: int) -> Planner:
        """A fresh planner fed the first ``n`` chosen frames."""
        planner = self.factory()
        for fc in self._chosen[:n]:
            self._call(planner, fc.time, fc.choice)
        return planner

    def _snapshot(self) -> Any:
        """A token to return to the planner's current state (the number of chosen frames when
        snapshots are not trusted)."""
        if self.hang is not None:  # the planner is gone: nothing to return to
            return None
        try:
            return len(self._chosen) if self._fresh else self.planner.snapshot()
        except Exception as exc:  # a snapshot() that raises, a planner process that died
            self.note_failure(exc, "snapshot()")
            return None

    def _restore(self, snap: Any) -> None:
        if self.hang is not None:
            return
        self.restores += 1
        try:
            if self._fresh:
                self.planner = self._replayed(snap)
            else:
                self.planner.restore(snap)
        except Exception as exc:
            self.note_failure(exc, "restore()")

    def _plan(self, t: float, choice: Choice) -> dict[str, Any] | None:
        return self._call(self.planner, t, choice)

    def watched(self, planner: Planner) -> Planner:
        """``planner`` with its ``plan()`` under this search's watchdog (for other replays of the
        extraction, e.g. the failure-test minimisation; :class:`ModuleHang` propagates, see
        :meth:`note_hang`, and the caller arms the watchdog: ``with search.dog.armed()``)."""
        return _Watched(planner, self.dog)  # type: ignore[return-value]

    def note_hang(self, t: float | None, output: int | None, where: str = "") -> None:
        """Record a hang of ``plan()`` (the first one is kept)."""
        if self.hang is None:
            self.hang = {"kind": "hang", "module": "planning", "exception": self.dog.message("plan() gave no return"),
                         "time": t, "output": output, "during": where or "search"}
            self.errors.append(f"planner hung: {self.hang['exception']} at t={t if t is None else round(t, 3)}")

    def note_failure(self, exc: BaseException, call: str, t: float | None = None) -> None:
        """Record that the planner can no longer be called - its process died
        (:class:`~deft_gym.execution.isolation.HostDied`) or its ``snapshot()``/``restore()``
        raised - as the finding ``planner_crash`` (the first one is kept); like a hang, no
        ``plan()`` is called after it."""
        if self.hang is None:
            self.hang = {"kind": "crash", "module": "planning", "exception": describe_exception(exc),
                         "time": t, "output": self._at, "during": f"search ({call})"}
            self.errors.append(f"planner failed in {call}: {self.hang['exception']}")

    def _call(self, planner: Planner, t: float, choice: Choice) -> dict[str, Any] | None:
        if self.hang is not None:  # after a hang no plan() is called again
            return None
        try:
            inputs = self.frame_inputs(choice)
        except ValueError:
            if len(self.errors) < 20:
                bad = [f"{r} message {j}" for r, j in choice.items() if j is not None and j in self.pif.inputs[r].bad]
                self.errors.append(f"{', '.join(bad) or 'an input'}: payload is not valid JSON")
            return None
        t0 = time.perf_counter()
        before = interrupts()
        try:
            return self.dog.call(planner.plan, Frame(t, inputs))
        except ModuleHang:
            self.note_hang(t, self._at)
            return None
        except HostDied as exc:  # its process ended (os._exit, a signal, a segfault): nothing more to replay
            self.note_failure(exc, "plan()", t)
            return None
        except BaseException as exc:  # a candidate frame may be garbage to the planner: counted, reported
            if not module_fault(exc, before):
                raise  # the user's Ctrl-C
            self.exceptions += 1
            if len(self.errors) < 20:
                self.errors.append(f"planner raised {describe_exception(exc)} at t={t:.3f}")
            return None
        finally:
            self.planner_s += time.perf_counter() - t0
            self.plan_calls += 1

    def _single(self, o: Output, t: float, choice: Choice, stage: str) -> FrameChoice:
        actual = self._plan(t, choice)
        return FrameChoice(o, t, choice, distance(o.payload, actual, self.measure), 1, stage, actual)

    # -- modes ----------------------------------------------------------------------------------
    def _last(self, o: Output, prev: Choice | None, synced: bool, last: FrameChoice | None) -> FrameChoice:
        choice = {r: (int(self.pif.bound[r][o.index]) - 1 if self.pif.bound[r][o.index] > 0 else None)
                  for r in self.roles}
        t = o.frame_time if o.frame_time is not None else o.publish_time
        return self._single(o, t, choice, "last")

    def _headers(self, o: Output, prev: Choice | None, synced: bool, last: FrameChoice | None) -> FrameChoice:
        choice = self._header_choice(o)
        if choice is None:
            fc = self._heuristic(o, prev, synced, last)
            fc.stage = "headers-fallback"
            return fc
        if o.frame_time is not None:
            return self._single(o, o.frame_time, choice, "headers")
        stages = [_Stage(t, _one(choice), 1) for t in self._time_guesses(o, prev, last)]
        fc = self._search(o, stages, self.cfg.max_tries)
        fc.stage = "headers"
        return fc

    def _header_choice(self, o: Output) -> Choice | None:
        """Inputs named by the output's sequence numbers, or None when it names none (or some
        that are not in the log)."""
        if o.input_seqs is None:
            return None
        if self._seq_index is None:
            self._seq_index = {r: tm.index_of_seq() for r, tm in self.pif.inputs.items()}
        choice: Choice = {}
        for r in self.roles:
            s = o.input_seqs.get(r, o.input_seqs.get(self.pif.mapping.topics[r]))
            if s is None:
                choice[r] = None
            elif isinstance(s, int) and s in self._seq_index[r]:
                choice[r] = self._seq_index[r][s]
            else:
                return None
        return choice

    def _heuristic(self, o: Output, prev: Choice | None, synced: bool, last: FrameChoice | None) -> FrameChoice:
        budget = self.cfg.max_tries if synced else self.cfg.unsynced_tries
        if o.frame_time is not None:
            assert o.frame_ns is not None
            return self._search(o, [_Stage(o.frame_time, self._ranked(o.frame_ns, prev, False), budget),
                                    _Stage(o.frame_time, self._ranked(o.frame_ns, prev, True), budget, "relaxed")],
                                budget)
        return self._untimed(o, prev, last, budget)

    def _untimed(self, o: Output, prev: Choice | None, last: FrameChoice | None, budget: int) -> FrameChoice:
        """Heuristic search when the output does not state its frame time: the most likely
        inputs at each frame-time guess (an exact hit ends it), then golden-section refinement
        of the time of the closest, then the other ranked inputs at the refined time."""
        guesses = self._time_guesses(o, prev, last)
        stages = [_Stage(t, self._ranked(round(t * NS_PER_S), prev, False), 1) for t in guesses]
        fc = self._search(o, stages, len(guesses), refine=self.cfg.refine_steps)
        if fc.distance == 0.0 or not math.isfinite(fc.distance):
            return fc if math.isfinite(fc.distance) else self._search(
                o, [_Stage(t, self._ranked(round(t * NS_PER_S), prev, True), 2, name="relaxed")
                    for t in guesses], budget)
        if fc.distance <= 0.05:  # refined to centimetre agreement: the inputs are found
            return fc
        t_ns = round(fc.time * NS_PER_S)
        snap_tries = fc.tries + self.cfg.refine_steps + 2
        self._restore(self._pre)
        fc2 = self._search(o, [_Stage(fc.time, self._ranked(t_ns, prev, False), self.cfg.depth),
                               _Stage(fc.time, self._ranked(t_ns, prev, True), self.cfg.depth, name="relaxed")],
                           2 * self.cfg.depth)
        fc2.tries += snap_tries
        return fc2

    # -- the search loop -----------------------------------------------------------------------
    def _search(self, o: Output, stages: list[_Stage], budget: int, refine: int = 0) -> FrameChoice:
        """Try candidate frames stage by stage from one planner snapshot; keep the first that
        reproduces the whole output exactly, else the closest one (by position distance, then
        whether the other fields match), whose state is then adopted. ``refine``:
        golden-section steps on the frame time around the closest candidate (for logs that do
        not state it: the distance is smooth in t_F for a fixed input choice)."""
        snap = self._pre = self._snapshot()
        tried: set[tuple[float, tuple[int | None, ...]]] = set()
        best: tuple[float, bool, float, Choice] | None = None
        tries = 0
        for st in stages:
            n_here = 0
            for choice in st.choices:
                if tries >= budget or n_here >= st.cap:
                    break
                key = (st.time, tuple(choice[r] for r in self.roles))
                if key in tried:
                    continue
                tried.add(key)
                if tries:
                    self._restore(snap)
                tries += 1
                n_here += 1
                actual = self._plan(st.time, choice)
                d = distance(o.payload, actual, self.measure)
                other = not (d == 0.0 and same_output(o.payload, actual))
                if not other:
                    return FrameChoice(o, st.time, choice, 0.0, tries, "first" if tries == 1 else st.name, actual)
                if best is None or (d, other) < best[:2]:
                    best = (d, other, st.time, choice)
        if best is None:
            t = o.frame_time if o.frame_time is not None else o.publish_time
            return FrameChoice(o, t, dict.fromkeys(self.roles), math.inf, tries, "closest")
        _, _, t, choice = best
        if refine:
            w = 2e-3 * max(1.0, self.pif.mapping.delivery.mean_ms)
            t = self._golden(o, snap, choice, t - w, min(t + w, o.publish_time), refine, best[0], t)
        self._restore(snap)
        actual = self._plan(t, choice)  # adopt the closest candidate's state
        return FrameChoice(o, t, choice, distance(o.payload, actual, self.measure), tries, "closest", actual)

    def _golden(self, o: Output, snap: Any, choice: Choice, a: float, b: float, steps: int,
                d_best: float, t_best: float) -> float:
        """Golden-section search of the frame time in ``[a, b]`` minimising the distance."""
        g = (math.sqrt(5.0) - 1.0) / 2.0

        def f(t: float) -> float:
            self._restore(snap)
            return distance(o.payload, self._plan(t, choice), self.measure)

        c, d = b - g * (b - a), a + g * (b - a)
        fc, fd = f(c), f(d)
        for _ in range(steps):
            if fc <= fd:
                b, d, fd = d, c, fc
                c = b - g * (b - a)
                fc = f(c)
            else:
                a, c, fc = c, d, fd
                d = a + g * (b - a)
                fd = f(d)
        t, dd = (c, fc) if fc <= fd else (d, fd)
        return t if dd < d_best else t_best

    # -- heuristics ------------------------------------------------------------------------------
    def _received(self, gap_ns: int) -> float:
        """R(g): probability that a message published ``gap_ns`` before t_F was received by then."""
        if gap_ns <= 0:
            return 0.0
        z = (math.log(gap_ns) - self._mu) / self._sigma
        return self._keep * 0.5 * math.erfc(-z / math.sqrt(2.0))

    def _role_candidates(self, role: str, t_ns: int, prev: Choice | None, relaxed: bool) -> list[tuple[float, int | None]]:
        """(probability, index) of each candidate of ``role``, most probable first. The previous
        frame's choice is known to have been received; with ``relaxed`` it is not a lower bound."""
        pub = self.pif.inputs[role].publish_ns
        hi = self.pif.frame_bound(role, t_ns)
        pj = prev.get(role) if prev else None
        bounded = pj is not None and not relaxed and pj < hi
        lo = pj if bounded else 0
        depth = self.cfg.depth * (4 if relaxed else 1)
        cands: list[tuple[float, int | None]] = []
        surv = 1.0
        trigger = role == self.pif.mapping.trigger
        for j in range(hi - 1, lo - 1, -1):
            if len(cands) >= depth and not (bounded and j == pj):
                continue
            if bounded and j == pj:
                r = 1.0
            elif trigger and not cands and (pj is None or j > pj):
                # the run was started by receiving a trigger message: the newest one is it
                r = self._keep
            else:
                r = self._received(t_ns - int(pub[j]))
            cands.append((r * surv, j))
            surv *= 1.0 - r
            if bounded and len(cands) >= depth:  # jump to the previous choice
                cands.append((surv, pj))
                break
        if pj is None or not cands:
            cands.append((surv, None))
        cands.sort(key=lambda c: -c[0])
        return cands

    def _ranked(self, t_ns: int, prev: Choice | None, relaxed: bool) -> Iterator[Choice]:
        """Joint candidates over all roles in decreasing probability (best-first enumeration)."""
        lists = [self._role_candidates(r, t_ns, prev, relaxed) for r in self.roles]
        logs = [[math.log(p) if p > 0.0 else -1e6 for p, _ in lst] for lst in lists]
        n = len(lists)
        start = (0,) * n
        heap = [(-sum(lg[0] for lg in logs), start)]
        seen = {start}
        while heap:
            _, pos = heapq.heappop(heap)
            yield {self.roles[k]: lists[k][pos[k]][1] for k in range(n)}
            for k in range(n):
                if pos[k] + 1 < len(lists[k]):
                    nxt = (*pos[:k], pos[k] + 1, *pos[k + 1:])
                    if nxt not in seen:
                        seen.add(nxt)
                        score = sum(logs[m][nxt[m]] for m in range(n))
                        heapq.heappush(heap, (-score, nxt))

    def _time_guesses(self, o: Output, prev: Choice | None, last: FrameChoice | None) -> list[float]:
        """Frame-time guesses [s] when the output does not state t_F (heuristic 1: after the
        trigger message and the previous output, before this output), most likely first: the
        mapping's hint field, the trigger's publish time plus typical delivery and dispatch
        delays, the previous output's publish time (a run queued behind it starts then), then a
        grid over the whole interval."""
        hi = o.publish_ns
        lo = last.output.publish_ns if last is not None else 0
        trig = self.pif.mapping.trigger
        t_trig = None
        if trig is not None:
            k = self.pif.frame_bound(trig, hi) - 1
            pj = prev.get(trig) if prev else None
            if k >= 0 and (pj is None or k > pj):
                t_trig = int(self.pif.inputs[trig].publish_ns[k])
        cands: list[float] = []
        hint_field = self.pif.mapping.frame_time_hint
        if hint_field:
            h = get_field(o.payload, hint_field)
            if isinstance(h, int | float) and math.isfinite(h):
                cands.append(float(h))  # the hint's own float: bit-exact if it is t_F
        ns: list[int] = []
        d = self.pif.mapping.delivery
        if t_trig is not None:
            base = t_trig + round(d.dispatch_ms * 1e6)
            ns += [base + round(f * d.mean_ms * 1e6) for f in (1.0, 0.5, 1.5, 2.0, 3.0)]
        if last is not None:
            ns.append(lo)
        ns += [int(x) for x in np.linspace(max(lo, t_trig or 0), hi, self.cfg.time_guesses + 2)[1:-1].round()]
        cands += [g / NS_PER_S for g in ns]
        out: list[float] = []
        seen: set[int] = set()
        for t in cands:
            g = round(t * NS_PER_S)
            if lo <= g <= hi and g not in seen:
                seen.add(g)
                out.append(t)
        return out or [o.publish_time]


@dataclass
class _Stage:
    """Candidate frames at one frame time: ``cap`` of them at most."""

    time: float
    choices: Iterator[Choice]
    cap: int
    name: str = "ranked"


class _Watched:
    """A planner whose ``plan()`` runs under a watchdog (everything else is the planner's)."""

    def __init__(self, planner: Planner, dog: Watchdog) -> None:
        self._planner, self._dog = planner, dog

    def plan(self, frame: Frame) -> dict[str, Any] | None:
        return self._dog.call(self._planner.plan, frame)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._planner, name)


def _one(choice: Choice) -> Iterator[Choice]:
    yield choice


def _same(a: dict[str, Any] | None, b: dict[str, Any] | None) -> bool:
    """Two planner outputs equal bit for bit (NaN included)."""
    if a is None or b is None:
        return a is b
    if a == b:
        return True
    try:
        return encode(a) == encode(b)
    except (TypeError, ValueError):
        return False
