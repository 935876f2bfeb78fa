"""Search baselines at a budget of simulated scenarios (Decictor Algorithm 1).

- ``decictor``: Decictor-GA as published - a population of N = 4 initialised with the seed;
  every generation mutates each individual once with the non-invasive operators (add / remove /
  change, :mod:`agents.mutation`), simulates each child, files its failures, keeps the children
  that passed the task check and the consistency check, and selects the N fittest of parents +
  children by the feedback :func:`feedback` (eq. 7-9: mean distance to the optimal path plus the
  MMD of the behaviour distributions, plus the consistency check's grid difference 1 - IoU, which
  the authors' implementation adds for every child that passed the check).
- ``random_delta``: the same loop and non-invasive mutation, random selection (the paper's
  Random-delta / F-Random: no feedback).
- ``random``: the same loop with unconstrained add / remove mutations and random selection.

Common to all three (and to the RL adversary in :mod:`agents.evaluate`): every primary
simulation is one unit of budget and yields one record (:func:`record_of`); a child that is a
near-duplicate of one already simulated is redrawn before it costs a simulation; every failure
(NoDS, ego-at-fault collision) and task failure is re-checked on a second jitter seed
(:func:`confirm`) and counts only when it reproduces with the same root cause - that run is reported (``sims``, time)
but is not a unit of budget. Task failures of valid mutations (timeout, stuck) are findings of
their own column; as in Algorithm 1 they do not join the population. Every record carries the
episode's driving-quality metrics (``metric_*``, docs/metrics.md); with a metric ``oracle`` the GA
selects by it and its findings are re-checked the same way (``oracle_signature``,
``oracle_confirmed``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from agents.mutation import Mutant, NonInvasiveMutator, RandomMutator
from deft_gym.metrics.episode import EpisodeMetrics
from deft_gym.metrics.oracle import (
    COUNTED_ORACLES,
    DECISION_ORACLES,
    ORACLES,
    confirm_findings,
    confirm_oracle,
    findings_by_oracle,
    record_columns,
    run_metrics,
    seed_finding,
    severity,
    severity_growth,
    unmutated_finding,
    violated,
)
from deft_gym.search.context import SeedContext
from deft_gym.search.episode import EpisodeRun, replay_record, run_scenario
from deft_gym.search.feasible import Layout
from deft_gym.search.nods import Verdict

SEARCH_METHODS = ("decictor", "random_delta", "random")
POPULATION = 4
REDRAWS = 10  # near-duplicate or roomless mutations redrawn before giving up on novelty


def feedback(v: Verdict) -> float:
    """The fitness the GA selects by: D = f_p + f_b (paper eq. 9) plus, for a run that passed the
    consistency check, its grid difference 1 - IoU - as Decictor's public implementation computes
    it (``fuzzer/decictor/fuzzer_runner.py`` adds the oracle's grid difference to the path and
    behaviour fitness of every child that is not a NoDS), so that selection also climbs towards the
    check's own threshold. Only children that passed both checks join the population, so the term
    is always there where it matters."""
    return v.f_p + v.f_b + (0.0 if v.nods else 1.0 - v.iou)


def fitness(ctx: SeedContext, v: Verdict, m: EpisodeMetrics, oracle: str) -> float:
    """What the GA selects by when aiming at ``oracle``: :func:`feedback` (the decision oracle),
    a metric oracle's severity, or for ``any`` the feedback plus the largest growth of a counted
    metric's severity over the seed's reference run (:func:`deft_gym.metrics.oracle.severity_growth`)."""
    if oracle == "default":
        return feedback(v)
    if oracle == "any":
        return feedback(v) + severity_growth(ctx, m)
    return severity(m, oracle)


def passes(ctx: SeedContext, v: Verdict, m: EpisodeMetrics, oracle: str) -> bool:
    """Whether a child passes what the GA aims at (then it may join the population): no NoDS
    (``default``), no NoDS and no metric finding (``any``), or no violation of the metric oracle."""
    if oracle == "default":
        return not v.nods
    if oracle == "any":
        return not (v.nods or findings_by_oracle(ctx, v.valid, m, COUNTED_ORACLES))
    return not violated(m, oracle)


def confirm(ctx: SeedContext, verdict: Verdict, specs: list[dict[str, Any]], jitter_seed: int,
            added_at: dict[str, float] | None = None) -> tuple[bool | None, float, float]:
    """Re-run a failing scenario with another jitter seed: ``(reproduced, wall s, cpu s)``;
    ``reproduced`` when the second run fails with the same root cause (the same kind, trigger,
    clearance band and mechanism: ``signature``), None when there is nothing to confirm (no
    failure, no task failure)."""
    if verdict.failure is None and verdict.task_failure is None:
        return None, 0.0, 0.0
    w0, c0 = time.perf_counter(), time.process_time()
    again = run_scenario(ctx, specs, jitter_seed, added_at=added_at).verdict
    same = again.failure == verdict.failure and again.task_failure == verdict.task_failure \
        and again.signature == verdict.signature
    return bool(same), time.perf_counter() - w0, time.process_time() - c0


def count_confirm_seed(jitter_seed: int) -> int:
    """The jitter seed on which the counted metric oracles' findings of a run on ``jitter_seed``
    are confirmed (derived, so that counting them draws nothing from the method's generator)."""
    return int(np.random.default_rng([jitter_seed, 15485863]).integers(2**31 - 1))


def record_of(v: Verdict, index: int, seconds: float, cpu_seconds: float, sims: int,
              confirmed: bool | None, jitter_seed: int, added: int, sim_time: float,
              extra: dict[str, Any] | None = None, confirm_seed: int | None = None) -> dict[str, Any]:
    """One line of a method's log: the verdict of one simulated scenario (the evaluation's record
    schema; see agents/evaluate.py); ``confirm_seed``, the jitter seed of the confirming run, is
    kept when there was one (``confirmed`` not None)."""
    rec = {"index": index, **{k: val for k, val in v.as_dict().items() if k != "collision_detail"},
           "confirmed": confirmed, "added": added, "sim_time": round(sim_time, 3),
           "seconds": round(seconds, 4), "cpu_seconds": round(cpu_seconds, 4), "sims": sims,
           "jitter_seed": jitter_seed}
    if confirmed is not None and confirm_seed is not None:
        rec["confirm_seed"] = confirm_seed
    if v.failure:
        rec["collision_detail"] = v.collision_detail
    return {**rec, **(extra or {})}


def oracle_columns(ctx: SeedContext, m: EpisodeMetrics, valid: bool, oracle: str, specs: list[dict[str, Any]],
                   rng: np.random.Generator, added_at: dict[str, float] | None = None,
                   count: tuple[str, ...] = (), jitter_seed: int = 0) -> tuple[dict[str, Any], float, float, int]:
    """The record's ``metric_*`` columns, and with a metric ``oracle`` its finding
    (``oracle_signature``: on a valid mutation, not one the seed's unmutated runs have -
    :func:`~deft_gym.metrics.oracle.unmutated_finding`; such a one goes to ``unmutated_signature``)
    and ``oracle_confirmed`` (re-checked on a jitter seed drawn from ``rng`` - only then -
    :func:`deft_gym.metrics.oracle.confirm_oracle`); with ``count`` (oracles counted beside the
    aimed one) ``found_by_oracle`` (those the unmutated runs have apart, in
    ``unmutated_by_oracle``) and ``confirmed_by_oracle``, re-checked together on one jitter seed
    derived from the run's ``jitter_seed`` (``rng`` untouched: the methods draw what they drew
    without counting); ``(columns, wall s, cpu s, extra simulations)``."""
    cols = record_columns(m)
    w = c = 0.0
    n = 0
    if count:
        raw = findings_by_oracle(ctx, valid, m, count)
        found = {o: sig for o, sig in raw.items() if not unmutated_finding(ctx, o, sig)}
        ok_by, w, c = confirm_findings(ctx, found, specs, count_confirm_seed(jitter_seed), added_at)
        cols = {**cols, "counted_oracles": list(count), "found_by_oracle": found, "confirmed_by_oracle": ok_by}
        if len(found) < len(raw):  # what the seed's unmutated runs do too: no finding, kept for the reader
            cols["unmutated_by_oracle"] = {o: sig for o, sig in raw.items() if o not in found}
        n = int(bool(found))
    if oracle in DECISION_ORACLES:  # the decision oracle's findings are the record's own
        return ({**cols, "oracle": oracle} if oracle != "default" else cols), w, c, n
    sig = seed_finding(ctx, valid, m, oracle)
    if sig is not None and unmutated_finding(ctx, oracle, sig):
        cols["unmutated_signature"], sig = sig, None
    again = int(rng.integers(2**31 - 1))
    ok, w2, c2 = confirm_oracle(ctx, oracle, sig, specs, again, added_at)
    cols = {**cols, "oracle": oracle, "oracle_signature": sig, "oracle_confirmed": ok}
    if ok is not None:
        cols["oracle_confirm_seed"] = again
    return cols, w + w2, c + c2, n + int(ok is not None)


def _run_record(ctx: SeedContext, run: EpisodeRun, index: int, t_mut: float, c_mut: float, rng: np.random.Generator,
                extra: dict[str, Any], m: EpisodeMetrics, oracle: str = "default",
                count: tuple[str, ...] = ()) -> dict[str, Any]:
    v = run.verdict
    specs = extra.pop("specs")
    again = int(rng.integers(2**31 - 1))
    confirmed, w_c, c_c = confirm(ctx, v, specs, again)
    cols, w_o, c_o, n_o = oracle_columns(ctx, m, v.valid, oracle, specs, rng, count=count,
                                         jitter_seed=run.result.jitter_seed)
    rec = record_of(v, index, t_mut + run.seconds + w_c + w_o, c_mut + run.cpu_seconds + c_c + c_o,
                    1 + (confirmed is not None) + n_o, confirmed, run.result.jitter_seed,
                    sum(1 for a in run.trace.actors if a.added), run.result.sim_time, {**extra, **cols}, again)
    if v.failure or v.task_failure or cols.get("oracle_signature") or cols.get("found_by_oracle"):
        rec["scenario_equivalent"] = replay_record(run.scenario, run.result.jitter_seed)
    return rec


def search(method: str, ctx: SeedContext, budget: int, seed: int, max_added: int = 8,
           log_dir: Callable[[int], Path | None] | None = None, rule: str = "closest",
           oracle: str = "default", count: tuple[str, ...] = ()) -> Iterator[dict[str, Any]]:
    """Run a search baseline for ``budget`` simulated scenarios under placement ``rule``; yields
    one record per primary simulation. ``log_dir(index)`` may give a directory for its MCAP log.
    ``oracle``: ``default`` selects by :func:`feedback` (the decision oracle); a metric oracle
    (:data:`deft_gym.metrics.oracle.ORACLES`) selects by its severity, and children that do not
    fail it join the population; ``any`` selects by :func:`fitness`, and children with no finding
    on any oracle join. ``count``: metric oracles whose findings are counted besides
    (:func:`oracle_columns`); selection does not see them."""
    if oracle not in ORACLES:
        raise ValueError(f"unknown oracle {oracle!r}; expected one of {ORACLES}")
    if method not in SEARCH_METHODS:
        raise ValueError(f"unknown search method {method!r}; expected one of {SEARCH_METHODS}")
    # each method its own stream: the GA and Random-delta would otherwise draw the same first
    # generation and both count it
    rng = np.random.default_rng([seed, 7919, SEARCH_METHODS.index(method)])
    mutator = (RandomMutator if method == "random" else NonInvasiveMutator)(ctx, rng, rule, max_added=max_added)
    population = [Mutant(Layout(ctx.areas), fitness=0.01) for _ in range(POPULATION)]
    seen: set[frozenset[Any]] = {population[0].key()}
    used = 0
    while used < budget:
        offspring: list[Mutant] = []
        for parent in population:
            if used >= budget:
                break
            w0, c0 = time.perf_counter(), time.process_time()
            child = None
            for _ in range(REDRAWS):  # a mutation without room or a near-duplicate costs no simulation
                cand = mutator.mutate(parent)
                if cand is not None and cand.key() not in seen:
                    child = cand
                    break
            if child is None:
                child = cand if cand is not None else parent.copy()
            seen.add(child.key())
            t_mut, c_mut = time.perf_counter() - w0, time.process_time() - c0
            run = run_scenario(ctx, child.specs, int(rng.integers(2**31 - 1)), log_dir(used) if log_dir else None)
            v = run.verdict
            m = run_metrics(ctx, run.trace, v.collision_detail)
            child.fitness = fitness(ctx, v, m, oracle)
            yield _run_record(ctx, run, used, t_mut, c_mut, rng,
                              {"mutation": child.history[-1] if child.history else "", "specs": child.specs},
                              m, oracle, count)
            used += 1
            if v.valid and v.outcome == "completed" and passes(ctx, v, m, oracle):
                offspring.append(child)
        pool = population + offspring
        if method == "decictor":
            population = sorted(pool, key=lambda m: -m.fitness)[:POPULATION]
        else:
            idx = rng.choice(len(pool), size=min(POPULATION, len(pool)), replace=False)
            population = [pool[int(i)] for i in idx]
