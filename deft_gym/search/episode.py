"""Run a seed scenario with added participants once and judge it (the search baselines' unit of
budget, and the replay of an adversary episode from its equivalent scenario)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from deft_gym.scenarios.scenario import scenario_from_dict, with_participants
from deft_gym.search.context import SeedContext
from deft_gym.search.nods import Verdict
from deft_gym.search.trace import Trace, TraceRecorder
from deft_gym.sim.simulation import EpisodeResult, Simulation


@dataclass
class EpisodeRun:
    """A judged run."""

    verdict: Verdict
    trace: Trace
    result: EpisodeResult
    scenario: dict[str, Any]
    seconds: float  # wall time: building, simulating and judging
    cpu_seconds: float = 0.0  # process CPU time of the same


def run_scenario(ctx: SeedContext, specs: list[dict[str, Any]], jitter_seed: int,
                 out_dir: Path | str | None = None, added_at: dict[str, float] | None = None,
                 watch: Callable[[Simulation], Any] | None = None) -> EpisodeRun:
    """Simulate the seed plus ``specs`` with ``jitter_seed`` and judge it against the reference.

    ``added_at`` (participant id -> sim time [s]) adds those participants mid-run, in the order
    of ``specs``, as the adversary env did - so an env episode's equivalent scenario replays it
    exactly; the others are part of the scenario from the start (the search baselines).
    ``watch(sim)`` runs before the episode starts, after the trace recorder (another tap)."""
    t0, c0 = time.perf_counter(), time.process_time()
    added_at = added_at or {}
    data = with_participants(ctx.scenario, f"{ctx.name}+mut", [s for s in specs if s["id"] not in added_at])
    recorder: list[TraceRecorder] = []

    def attach(sim: Simulation) -> None:
        recorder.append(TraceRecorder(sim, {s["id"] for s in specs}))
        if sim.recorder is not None:  # the log says what the run is judged against (extraction's NoDS test)
            write_optimal_path(sim.recorder, ctx)
        if watch is not None:
            watch(sim)

    res = simulate(data, ctx.ads, jitter_seed, out_dir, [s for s in specs if s["id"] in added_at], added_at,
                   source=f"{ctx.name} (mutated)", attach=attach)
    o = res.outcome
    trace = recorder[0].trace(o.outcome, o.sim_time)
    verdict = ctx.oracle.judge(trace, o.collision.as_dict() if o.collision else None)
    return EpisodeRun(verdict, trace, res, data, time.perf_counter() - t0, time.process_time() - c0)


def write_optimal_path(recorder: Any, ctx: SeedContext) -> None:
    """Add the optimal (reference) path of ``ctx`` and the half lane a plan may stray from it to a
    log being recorded (metadata ``deft_gym.optimal_path``, read by the extractor's NoDS test)."""
    from deft_gym.record.recorder import OPTIMAL_PATH_METADATA

    xy = ctx.ref.xy
    recorder.add_metadata(OPTIMAL_PATH_METADATA, {"x": [round(float(v), 3) for v in xy[:, 0]],
                                                  "y": [round(float(v), 3) for v in xy[:, 1]],
                                                  "limit": ctx.roadmap.spec.lane_width / 2})


def simulate(data: dict[str, Any], ads: Any, jitter_seed: int, out_dir: Path | str | None = None,
             later: list[dict[str, Any]] | None = None, added_at: dict[str, float] | None = None,
             source: str = "replay", attach: Callable[[Simulation], Any] | None = None,
             keep_planning: bool = False, compress: bool = False) -> EpisodeResult:
    """One episode of scenario ``data`` (plain data) on ``ads`` with ``jitter_seed``; the
    participants ``later`` join mid-run, in their order, at ``added_at[id]`` [s sim time] (as the
    adversary env added them). ``attach(sim)`` runs before the episode starts (a trace recorder)."""
    later, added_at = later or [], added_at or {}
    sc = scenario_from_dict(data, source=source)
    sim = Simulation(sc, ads, jitter_seed=jitter_seed, out_dir=out_dir, keep_planning=keep_planning,
                     compress=compress)
    if attach is not None:
        attach(sim)
    try:
        sim.start()
        for spec in later:
            t = added_at[spec["id"]]
            if t > 0.0 and sim.advance(t):
                break
            sim.add_participant(spec)
        sim.advance(sc.duration)
    finally:
        res = sim.finish()
    return res


# -- validity: static objects are there from the start -----------------------------------------
def late_statics(participants: list[dict[str, Any]], added_at: dict[str, float] | None) -> list[str]:
    """Ids of the static objects among ``participants`` (scenario participant specs) that join
    after t = 0 (``added_at``: participant id -> sim time [s])."""
    return [p["id"] for p in participants
            if p.get("type") == "static" and (added_at or {}).get(p["id"], 0.0) > 0.0]


def statics_from_start(participants: list[dict[str, Any]], added_at: dict[str, float] | None) -> dict[str, float] | None:
    """``added_at`` with the static objects among ``participants`` taken out: they stand in the
    scenario from t = 0, where the ego's sensors see them as it approaches. A parked car or a cone
    does not appear out of nowhere in front of a car, so an online adversary's failure counts
    only when it reproduces this way (docs/search.md, "Validity"); None when nothing joins later."""
    late = set(late_statics(participants, added_at))
    return {k: v for k, v in (added_at or {}).items() if k not in late} or None


# -- the one shape of a failure's scenario ----------------------------------------------------------
REPLAY_FORMAT = "deft_gym.replay/1"


def replay_record(scenario: dict[str, Any], jitter_seed: int, added_at: dict[str, float] | None = None) -> dict[str, Any]:
    """The one shape every failure's scenario is stored in (a record's ``scenario_equivalent``,
    ``episode.json``, ``replay_scenario.yaml``): ``{"format", "scenario", "added_at",
    "jitter_seed"}`` - the scenario as plain data with every participant, those named in
    ``added_at`` (id -> sim time [s]) joining mid-run, and the jitter seed that replays it."""
    return {"format": REPLAY_FORMAT, "scenario": scenario, "added_at": dict(added_at or {}),
            "jitter_seed": int(jitter_seed)}


def read_replay(eq: Any, jitter_seed: int | None = None) -> dict[str, Any] | None:
    """``eq`` in the one shape (:func:`replay_record`), or None when it holds no scenario. Reads
    records written before there was one shape too: the search baselines stored the scenario
    itself (its jitter seed is then ``jitter_seed``, the record's)."""
    if not isinstance(eq, dict):
        return None
    if isinstance(eq.get("scenario"), dict):
        seed = eq.get("jitter_seed", jitter_seed)
        return None if seed is None else replay_record(eq["scenario"], int(seed), eq.get("added_at"))
    if "participants" in eq and "ego" in eq and jitter_seed is not None:  # a scenario itself
        return replay_record(eq, int(jitter_seed))
    return None


def write_replay(path: Path | str, eq: dict[str, Any]) -> Path:
    """Write a failure's scenario (:func:`replay_record`) as YAML that ``deft-gym run PATH`` replays."""
    import yaml

    from deft_gym.files import write_atomic

    path = Path(path)
    head = (f"# a failure's scenario ({REPLAY_FORMAT}): deft-gym run {path.name} --reruns 1 --jitter-seed "
            f"{eq['jitter_seed']} replays it; participants in added_at join at that sim time [s]\n")
    write_atomic(path, head + yaml.safe_dump(eq, sort_keys=False))
    return path


def load_replay(path: Path | str) -> dict[str, Any] | None:
    """The failure's scenario in the YAML file ``path`` (:func:`write_replay`), or None when the
    file is something else (a plain scenario). Read as every config is (:func:`deft_gym.config.load_yaml`:
    a FIFO, a device, an oversized or malformed file is a one-line ConfigError, never a block)."""
    from deft_gym.config import load_yaml

    data = load_yaml(path)
    if not isinstance(data, dict) or data.get("format") != REPLAY_FORMAT:
        return None
    return read_replay(data)


def replay(eq: dict[str, Any], ads: Any, out_dir: Path | str | None = None, jitter_seed: int | None = None,
           keep_planning: bool = True, compress: bool = False,
           attach: Callable[[Simulation], Any] | None = None) -> EpisodeResult:
    """Simulate a failure's scenario (:func:`replay_record`) again, with its jitter seed unless
    ``jitter_seed`` is given; ``attach(sim)`` runs before the episode starts."""
    data = eq["scenario"]
    added_at = eq.get("added_at") or {}
    start = {**data, "participants": [p for p in data.get("participants", []) if p["id"] not in added_at]}
    later = [p for p in data.get("participants", []) if p["id"] in added_at]
    seed = eq["jitter_seed"] if jitter_seed is None else jitter_seed
    return simulate(start, ads, seed, out_dir, later, added_at, source=f"{data.get('name', 'scenario')} (replay)",
                    attach=attach, keep_planning=keep_planning, compress=compress)


def replay_of_log(log: Path | str) -> dict[str, Any] | None:
    """A log's episode in the one shape (:func:`replay_record`), from its metadata: the scenario
    it ran, its jitter seed and the participants added mid-run with their times; None when the
    log does not say (an old or damaged log)."""
    import json

    from deft_gym.record import read_metadata
    from deft_gym.record.recorder import EPISODE_METADATA, OUTCOME_METADATA

    try:
        meta = read_metadata(log)
        ep, oc = meta.get(EPISODE_METADATA) or {}, meta.get(OUTCOME_METADATA) or {}
        data = json.loads(ep["scenario"])
        seed = int(ep["jitter_seed"])
        added = json.loads(oc.get("participants_added") or "[]")
    except (OSError, KeyError, ValueError, TypeError, RuntimeError):
        return None
    if not isinstance(data, dict):
        return None
    added_at = {}
    for a in added:
        spec = {k: v for k, v in a.items() if k != "time"}
        data.setdefault("participants", []).append(spec)
        added_at[spec["id"]] = float(a.get("time", 0.0))
    return replay_record(data, seed, added_at)
