"""Metric oracles: a driving-quality metric as a failure that the adversary's reward and the
baselines' fitness can aim at (``oracle:`` in the train and evaluation configs; docs/metrics.md).

A finding on a metric oracle counts as the decision oracle's do: on a valid mutation only, not
when the seed's reference run has the same signature (the seed fails it without any mutation),
reproduced on a second jitter seed with the same signature (:func:`confirm_oracle`, the rule of
:func:`agents.search.confirm`), and distinct by signature per oracle. ``default`` keeps the present objective (NoDS and at-fault
collisions, docs/search.md).
"""

from __future__ import annotations

import functools
import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from deft_gym.metrics.episode import (
    COMFORT_BOUNDS,
    DIRECTION_BAD,
    HEADWAY_BOUND,
    HEADWAY_HOLD,
    STANDSTILL_BOUND,
    TTC_BOUND,
    EpisodeMetrics,
    MetricsContext,
    episode_metrics,
)
from deft_gym.search.context import FIT_RUNS, SeedContext, judge_hash
from deft_gym.search.trace import CACHE_DIR, Trace, content_key, record_run

#: the oracles a config may name (``default``: the decision oracle, no metric; ``any``: the
#: decision oracle and every counted metric oracle together)
ORACLES = ("default", "any", "collision", "ttc", "drivable_area", "direction", "red_light", "progress", "comfort",
           "speed_limit", "standstill", "headway", "score")
#: what ``count_oracles: all`` counts beside the aimed oracle: every metric oracle but ``score``
#: (a weighted sum of the others, so it would count their findings twice)
COUNTED_ORACLES = tuple(o for o in ORACLES if o not in ("default", "any", "score"))
#: the oracles whose aimed findings are the decision oracle's (NoDS, at-fault collisions)
DECISION_ORACLES = ("default", "any")
#: oracles whose signature names no participant or light (the first comfort signal out of bounds,
#: the violated metrics): a seed whose reference run fails one has no finding on it at all
UNSPECIFIC = ("comfort", "score")
PROGRESS_BAD = 0.8  # progress ratio below this is a progress violation
SCORE_BAD = 0.5  # score below this is a score violation


def violated(m: EpisodeMetrics, oracle: str) -> bool:
    """Whether episode ``m`` fails ``oracle``."""
    if oracle == "progress":
        return m.progress_ratio < PROGRESS_BAD
    if oracle == "score":
        return m.score < SCORE_BAD
    return oracle in m.violations()


def severity(m: EpisodeMetrics, oracle: str) -> float:
    """How close ``m`` is to failing ``oracle``, in [0, 1] (1: failed badly): the GA's fitness
    and the env's shaping when a config aims at a metric."""
    if oracle == "collision":
        return 1.0 if m.at_fault_collision else 0.0
    if oracle == "ttc":
        return 0.0 if m.min_ttc is None else math.exp(-max(m.min_ttc, 0.0) / TTC_BOUND)
    if oracle == "drivable_area":
        return min(1.0, m.off_road_max / 1.0)
    if oracle == "direction":
        return min(1.0, m.wrong_way_max_1s / DIRECTION_BAD)
    if oracle == "red_light":
        return 1.0 if m.red_lights else 0.0
    if oracle == "progress":
        return 1.0 - m.progress_ratio
    if oracle == "comfort":
        return min(1.0, max(abs(v / COMFORT_BOUNDS[k][v >= 0]) for k, v in m.comfort.items())) if m.comfort else 0.0
    if oracle == "speed_limit":
        return 1.0 - m.speed_score
    if oracle == "standstill":
        return min(1.0, m.standstill_max_s / (2 * STANDSTILL_BOUND))
    if oracle == "headway":  # half way at the bound held for the hold, 1 at a standing gap
        if m.min_headway is None:
            return 0.0
        near = 1.0 - min(m.min_headway, 2 * HEADWAY_BOUND) / (2 * HEADWAY_BOUND)
        return min(1.0, 0.5 * near + 0.5 * min(1.0, m.headway_below_max_s / HEADWAY_HOLD))
    if oracle == "score":
        return 1.0 - m.score
    raise ValueError(f"unknown oracle {oracle!r}; expected one of {ORACLES[1:]}")


def signature(m: EpisodeMetrics, oracle: str) -> str | None:
    """The root cause of a metric finding, ``metric:<oracle>:<detail>`` (None: no finding):
    what kind of participant was closest in TTC, which light was run, which comfort signal
    broke first, how the collision happened; one class per oracle otherwise."""
    if not violated(m, oracle):
        return None
    detail = {"collision": m.collision_how or "unknown", "ttc": m.ttc_trigger or "unknown",
              "headway": m.headway_trigger or "unknown",
              "red_light": ",".join(sorted({r["light"] for r in m.red_lights})),
              "comfort": m.uncomfortable[0] if m.uncomfortable else "",
              "score": "+".join(v for v in m.violations() if v != "standstill") or "low"}.get(oracle, oracle)
    return f"metric:{oracle}:{detail}"


@functools.cache
def oracle_code() -> str:
    """8 hex digits of the code that judges a run beyond simulating it - the decision oracle and the
    trace (``search/nods.py``, ``search/trace.py``, less their cache plumbing) and the metrics
    (``metrics/episode.py``, this file) - as syntax trees (:func:`~deft_gym.search.context.judge_hash`).
    ``code_fingerprint`` leaves them out, so that cached reference runs outlive an oracle's edit;
    an evaluation's records keep this beside it, and a resume judges again what other rules judged."""
    from deft_gym.metrics import episode
    from deft_gym.search import nods, trace

    return judge_hash([Path(m.__file__).read_bytes() for m in (nods, trace, episode)] + [Path(__file__).read_bytes()])


def _per_context(store: dict[int, tuple[Any, Any]], ctx: SeedContext, make: Callable[[], Any]) -> Any:
    """``make()`` memoised per seed context in ``store`` (keyed by its id, the context kept beside
    the value so that a reused id is not mistaken for it; cleared past 512 entries)."""
    hit = store.get(id(ctx))
    if hit is not None and hit[0] is ctx:
        return hit[1]
    if len(store) > 512:
        store.clear()
    value = make()
    store[id(ctx)] = (ctx, value)
    return value


_CONTEXTS: dict[int, tuple[Any, MetricsContext]] = {}


def seed_metrics_context(ctx: SeedContext) -> MetricsContext:
    """The :class:`MetricsContext` of a seed context: its map, lights and the reference run as
    the expert (progress along the expert's path, as nuPlan's); memoised per context."""
    return _per_context(_CONTEXTS, ctx, lambda: MetricsContext.of_scenario(ctx.scenario, ctx.roadmap, ctx.ref))


def run_metrics(ctx: SeedContext, trace: Trace, collision: dict[str, Any] | None) -> EpisodeMetrics:
    """The metrics of a run of a seed context's scenario (mutated or not)."""
    return episode_metrics(trace, seed_metrics_context(ctx), collision)


def record_columns(m: EpisodeMetrics) -> dict[str, Any]:
    """The columns an evaluation record keeps of an episode's metrics (``metric_*``)."""
    d = m.as_dict()
    return {"metric_score": d["score"], "metric_min_ttc": d["min_ttc"], "metric_ttc_below_s": d["ttc_below_s"],
            "metric_off_road_max": d["off_road_max"], "metric_wrong_way_m": d["wrong_way_m"],
            "metric_red_lights": len(d["red_lights"]), "metric_progress_ratio": d["progress_ratio"],
            "metric_uncomfortable": d["uncomfortable"], "metric_overspeed_integral": d["overspeed_integral"],
            "metric_standstill_s": d["standstill_s"], "metric_min_headway": d["min_headway"],
            "metric_headway_below_s": d["headway_below_max_s"], "metric_violations": d["violations"],
            "metric_cpu_s": d["cpu_s"]}


def oracle_finding(valid: bool, m: EpisodeMetrics, oracle: str, reference: str | None = None) -> str | None:
    """The signature of a finding on ``oracle`` - only for a valid mutation, and only when it is
    not the ``reference`` run's own signature on that oracle (what the seed scenario does
    without any mutation is no finding: the seed's parked car that every run closes on) - or None.
    On an :data:`UNSPECIFIC` oracle any reference violation rules findings out: a mutation that
    only changes which comfort signal breaks first finds nothing the seed does not."""
    if oracle in DECISION_ORACLES or not valid:
        return None
    sig = signature(m, oracle)
    if reference is not None and oracle in UNSPECIFIC:
        return None
    return None if sig is not None and sig == reference else sig


_REFERENCE: dict[int, tuple[Any, EpisodeMetrics]] = {}


def reference_metrics(ctx: SeedContext) -> EpisodeMetrics:
    """The metrics of the seed context's reference run (memoised per context)."""
    return _per_context(_REFERENCE, ctx, lambda: run_metrics(ctx, ctx.ref, None))


def reference_signature(ctx: SeedContext, oracle: str) -> str | None:
    """The seed context's reference run's own signature on ``oracle`` (None: it passes)."""
    return None if oracle in DECISION_ORACLES else signature(reference_metrics(ctx), oracle)


def severity_growth(ctx: SeedContext, m: EpisodeMetrics) -> float:
    """The largest growth of a counted metric oracle's :func:`severity` in run ``m`` over the
    seed's reference run, in [0, 1]: what the GA's fitness adds to the decision oracle's for
    ``any`` (a metric the seed already fails badly gives no pressure)."""
    ref = reference_metrics(ctx)
    return max(0.0, *(severity(m, o) - severity(ref, o) for o in COUNTED_ORACLES))


def seed_finding(ctx: SeedContext, valid: bool, m: EpisodeMetrics, oracle: str) -> str | None:
    """:func:`oracle_finding` of a run of ``ctx``'s scenario, its reference run's signature left out."""
    if oracle in DECISION_ORACLES or not valid:
        return None
    return oracle_finding(valid, m, oracle, reference_signature(ctx, oracle))


def rerun(ctx: SeedContext, specs: list[dict[str, Any]], jitter_seed: int,
          added_at: dict[str, float] | None = None) -> tuple[Any, EpisodeMetrics]:
    """``ctx``'s scenario with the added participants ``specs`` (those in ``added_at`` joining at
    that sim time [s]) simulated on ``jitter_seed``: ``(run, its metrics)``, what every
    confirmation judges."""
    from deft_gym.search.episode import run_scenario

    again = run_scenario(ctx, specs, jitter_seed, added_at=added_at)
    return again, run_metrics(ctx, again.trace, again.verdict.collision_detail)


def confirm_oracle(ctx: SeedContext, oracle: str, sig: str | None, specs: list[dict[str, Any]], jitter_seed: int,
                   added_at: dict[str, float] | None = None) -> tuple[bool | None, float, float]:
    """:func:`agents.search.confirm` for a metric oracle: the scenario again on another jitter
    seed; ``(reproduced, wall s, cpu s)``, reproduced when that run is valid and has the same
    signature on ``oracle``; None when there is no finding to confirm."""
    if sig is None:
        return None, 0.0, 0.0
    w0, c0 = time.perf_counter(), time.process_time()
    again, m = rerun(ctx, specs, jitter_seed, added_at)
    same = seed_finding(ctx, again.verdict.valid, m, oracle) == sig
    return bool(same), time.perf_counter() - w0, time.process_time() - c0


def findings_by_oracle(ctx: SeedContext, valid: bool, m: EpisodeMetrics, oracles: tuple[str, ...]) -> dict[str, str]:
    """:func:`seed_finding` on each of ``oracles``: ``{oracle: signature}`` of those with a finding."""
    found = {o: seed_finding(ctx, valid, m, o) for o in oracles}
    return {o: sig for o, sig in found.items() if sig is not None}


_UNMUTATED: dict[int, tuple[Any, dict[str, list[str]]]] = {}


def unmutated_signatures(ctx: SeedContext, cache_dir: Path | str | None = CACHE_DIR) -> dict[str, list[str]]:
    """Per counted metric oracle, the signatures of the seed's own unmutated runs on the fit
    check's jitter seeds 1..:data:`~deft_gym.search.context.FIT_RUNS` (what the scenario does under
    timing noise without any mutation; the reference run is one run of it); oracles none of them
    violates are left out. Memoised per context and cached on disk (the scenario's content key
    and :func:`oracle_code`)."""
    return _per_context(_UNMUTATED, ctx, lambda: _unmutated_cached(ctx, cache_dir))


def _unmutated_cached(ctx: SeedContext, cache_dir: Path | str | None) -> dict[str, list[str]]:
    """:func:`unmutated_signatures` from its cache file, else simulated and written there."""
    key = f"{ctx.name}-{content_key(ctx.scenario, ctx.ads, 0)}-unmutated{FIT_RUNS}-{oracle_code()}"
    path = Path(cache_dir) / f"{key}.json" if cache_dir else None
    if path is not None and path.exists():
        try:
            return {str(o): [str(s) for s in sigs] for o, sigs in json.loads(path.read_text())["signatures"].items()}
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            pass  # damaged: simulated again
    by_oracle: dict[str, set[str]] = {}
    for js in range(1, FIT_RUNS + 1):
        m = run_metrics(ctx, record_run(ctx.scenario, ctx.ads, js), None)
        for o in COUNTED_ORACLES:
            sig = signature(m, o)
            if sig is not None:
                by_oracle.setdefault(o, set()).add(sig)
    found = {o: sorted(sigs) for o, sigs in by_oracle.items()}
    if path is not None:
        from deft_gym.files import write_json_atomic

        write_json_atomic(path, {"signatures": found, "runs": FIT_RUNS})
    return found


def unmutated_finding(ctx: SeedContext, oracle: str, sig: str) -> bool:
    """Whether finding ``sig`` on ``oracle`` is one the seed's unmutated runs have too
    (:func:`unmutated_signatures`) - on an :data:`UNSPECIFIC` oracle, any violation of it - and so
    no finding of a mutation: CommonRoad's planner brakes beyond the comfort bound on take_exit at
    some jitter seeds unmutated, while its reference run happened to stay inside."""
    sigs = unmutated_signatures(ctx).get(oracle, [])
    return bool(sigs) if oracle in UNSPECIFIC else sig in sigs


def confirm_findings(ctx: SeedContext, found: dict[str, str], specs: list[dict[str, Any]], jitter_seed: int,
                     added_at: dict[str, float] | None = None) -> tuple[dict[str, bool], float, float]:
    """:func:`confirm_oracle` for several oracles with one run: the scenario again on
    ``jitter_seed``; ``({oracle: reproduced}, wall s, cpu s)``, nothing run when ``found`` is empty."""
    if not found:
        return {}, 0.0, 0.0
    w0, c0 = time.perf_counter(), time.process_time()
    again, m = rerun(ctx, specs, jitter_seed, added_at)
    same = {o: seed_finding(ctx, again.verdict.valid, m, o) == sig for o, sig in found.items()}
    return same, time.perf_counter() - w0, time.process_time() - c0
