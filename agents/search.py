"""Search baselines at a budget of simulated scenarios (Decictor Algorithm 1).

- ``decictor``: Decictor-GA - population 4 initialised with the seed; every generation mutates
  each individual once with the non-invasive operators, simulates the offspring, files
  collisions and non-optimal decisions, keeps the valid offspring that passed both checks and
  selects the 4 fittest of parents + offspring by the feedback D = f_p + f_b.
- ``random_delta``: the same loop and non-invasive mutation, but random selection (Decictor's
  F-Random / Random-delta: no feedback).
- ``random``: the same loop with unconstrained add / remove mutations and random selection.

Every simulated scenario is one unit of budget and produces one record (see
:func:`record_of`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from agents.mutation import Mutant, NonInvasiveMutator, RandomMutator
from deft_gym.search.context import SeedContext
from deft_gym.search.episode import EpisodeRun, run_scenario
from deft_gym.search.feasible import Layout

SEARCH_METHODS = ("decictor", "random_delta", "random")
POPULATION = 4


def record_of(run: EpisodeRun, index: int, seconds: float, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """One line of a method's log: the verdict of one simulated scenario."""
    v = run.verdict
    rec = {"index": index, **{k: val for k, val in v.as_dict().items() if k != "collision_detail"},
           "added": sum(1 for a in run.trace.actors if a.added), "sim_time": round(run.result.sim_time, 3),
           "seconds": round(seconds, 4), "jitter_seed": run.result.jitter_seed}
    if v.failure:
        rec["scenario_equivalent"] = run.scenario
        rec["collision_detail"] = v.collision_detail
    return {**rec, **(extra or {})}


def search(method: str, ctx: SeedContext, budget: int, seed: int, max_added: int = 8,
           log_dir: Callable[[int], Path | None] | None = None) -> Iterator[dict[str, Any]]:
    """Run a search baseline for ``budget`` simulated scenarios; yields one record per scenario.
    ``log_dir(index)`` may give a directory for the episode's MCAP log."""
    if method not in SEARCH_METHODS:
        raise ValueError(f"unknown search method {method!r}; expected one of {SEARCH_METHODS}")
    rng = np.random.default_rng([seed, 7919])
    cls = RandomMutator if method == "random" else NonInvasiveMutator
    mutator = cls(ctx, rng, max_added=max_added)
    seed_mutant = Mutant(Layout(ctx.areas), fitness=0.01)
    population = [seed_mutant.copy() for _ in range(POPULATION)]
    used = 0
    while used < budget:
        offspring: list[Mutant] = []
        for parent in population:
            if used >= budget:
                break
            t0 = time.perf_counter()
            child = None
            for _ in range(5):  # a mutation that found no room costs no simulation: retry
                child = mutator.mutate(parent)
                if child is not None:
                    break
            if child is None:
                child = parent.copy()
            t_mut = time.perf_counter() - t0
            jitter = int(rng.integers(2**31 - 1))
            run = run_scenario(ctx, child.specs, jitter, log_dir(used) if log_dir else None)
            v = run.verdict
            child.fitness = v.f_p + v.f_b
            yield record_of(run, used, t_mut + run.seconds, {"mutation": child.history[-1] if child.history else ""})
            used += 1
            if v.valid and v.outcome == "completed" and not v.nods:
                offspring.append(child)
        pool = population + offspring
        if method == "decictor":
            population = sorted(pool, key=lambda m: -m.fitness)[:POPULATION]
        else:
            idx = rng.choice(len(pool), size=min(POPULATION, len(pool)), replace=False)
            population = [pool[int(i)] for i in idx]
