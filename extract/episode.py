"""Extracting one episode: log -> frames -> validated frames -> oracle -> frames file, tests, summary.

:func:`extract_episode` is the library entry point (the CLI, the batch mode and the adversary
training call it); it writes ``frames.jsonl``, ``test_<scenario>.py`` and ``summary.json`` into
the output folder and returns an :class:`ExtractionResult`.
"""

from __future__ import annotations

import functools
import json
import math
import time
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.execution.watchdog import ModuleHang
from deft_gym.files import first_line, write_atomic
from deft_gym.planner.base import load_planner, planner_provenance, validate_output
from extract.emit import slug, test_module, write_frames
from extract.io_filter import PlanningIOFilter
from extract.logs import EpisodeLog, LogError, log_id, read_log
from extract.mapping import MappingError, TopicMapping, get_field, load_mapping
from extract.minimize import Minimised, Seed, frame_getter, seeded_start, shortest_replay
from extract.oracle import (
    Faulty,
    ego_size,
    find_departure,
    find_faulty,
    find_near_miss,
    find_off_road,
    find_red_light,
    find_stall,
    find_wrong_way,
    find_yellow,
    light_holds,
    light_timeline,
    map_area,
    map_lanes,
    map_stop_lines,
    optimal_path,
    participant_track,
    participant_tracks,
)
from extract.runtime import FORMAT, finite_or_none
from extract.search import FrameChoice, InputSearch, SearchConfig
from extract.truth import truth_agreement
from extract.validator import (
    SUMMARY_THETAS,
    Comparison,
    Tolerances,
    compare,
    field_summary,
    non_finite,
    reproduced_counts,
    theta_key,
)

SUMMARY_FORMAT = "deft_gym.extraction/1"
#: the oracle data keys of a frames header that each give a failure test (P_<key>)
FAILURE_ORACLES = ("faulty", "departure", "wrong_way", "off_road", "stall", "near_miss", "red_light", "yellow")
MAX_LAG_S = 3600.0  #: the latest an output may be logged after its frame time [s] for the times to map


@dataclass
class ExtractionResult:
    """What one extraction produced (``summary`` is also written as ``summary.json``)."""

    summary: dict[str, Any]
    frames_path: Path | None
    test_path: Path | None
    faulty: dict[str, Any] | None
    choices: list[FrameChoice] = field(default_factory=list, repr=False)
    comparisons: list[Comparison] = field(default_factory=list, repr=False)

    @property
    def ok(self) -> bool:
        return "error" not in self.summary

    @property
    def distances(self) -> list[float]:
        return [c.distance for c in self.choices]


def extract_episode(log: Path | str, out_dir: Path | str, *, mode: str = "heuristic", theta: float = 0.0,
                    mapping: TopicMapping | Mapping[str, Any] | str | Path | None = None, measure: str = "lsed",
                    emit_tests: bool = True, test_suffix: str | None = None, truth: Path | str | bool | None = True,
                    search: SearchConfig | None = None, minimize_failure: bool = True,
                    tolerances: Tolerances | Mapping[str, Any] | None = None,
                    on_frame: Callable[[int, int], None] | None = None,
                    xfail_failures: bool = False, watchdog_s: float | None = None) -> ExtractionResult:
    """Extract planning-module tests from one MCAP log.

    ``mapping``: None (deft_gym default), a YAML path, a dict or a :class:`TopicMapping`.
    ``tolerances``: how far each output field other than the positions may be from the
    recorded one (:class:`extract.validator.Tolerances` or its dict form; default 0 = equal);
    positions are judged by ``theta`` [m]. The test module is ``test_<scenario>_<log id>.py``
    (:func:`extract.logs.log_id`: unique per log, so any set of extraction folders is collected
    by one ``pytest A B C``; ``_<mode>`` added for modes other than heuristic); ``test_suffix``
    is accepted for older callers and no longer used. ``xfail_failures``: emit the failure
    oracle as a strict xfail (for CI). ``truth``: True looks for
    ``truth.jsonl`` beside the log (used only to report ``truth_agreement``), a path names it,
    False/None skips it. ``minimize_failure``: let the failure test start from the planner state
    recorded at P_faulty's frame (planners that can be seeded) or replay the shortest suffix of
    frames that still reproduces P_faulty exactly (:mod:`extract.minimize`).
    ``on_frame(done, total)`` reports progress. ``watchdog_s``: wall-clock seconds one ``plan()``
    may take (None: ``DEFT_GYM_WATCHDOG_S`` or 10 s; 0: unwatched); a ``plan()`` that runs past
    it is the finding ``planner_hang`` and no ``plan()`` is called after it. Raises :class:`LogError` /
    :class:`MappingError` (one-line messages) when the log or the mapping cannot be used."""
    t_start = time.perf_counter()
    log_path, out = Path(log), Path(out_dir)
    if theta < 0 or not math.isfinite(theta):
        raise ValueError(f"theta must be a finite distance >= 0 m, got {theta}")
    tol = (Tolerances(theta, tolerances.fields, tolerances.decision, tolerances.default)
           if isinstance(tolerances, Tolerances) else Tolerances.from_dict(tolerances, theta))
    cfg = search or SearchConfig(mode=mode, measure=measure)
    if search is not None and (search.mode != mode or search.measure != measure):
        cfg = SearchConfig(**{**search.__dict__, "mode": mode, "measure": measure})
    mp = load_mapping(mapping)
    elog = read_log(log_path, sorted(set(mp.topics.values())), mp.seq_field)
    planner_spec = _planner_spec(elog, mp)
    pif = PlanningIOFilter(elog, mp, planner_spec["class"])
    _check_fields(mp, pif)
    _check_tolerances(tol, pif)
    t_setup = time.perf_counter()
    try:
        planner = load_planner(planner_spec["class"], planner_spec["map"], planner_spec["params"])
    except (ValueError, TypeError) as exc:  # unknown class, bad parameters (pydantic errors are ValueErrors)
        first = first_line(exc)
        raise MappingError(f"{log_path}: cannot build planner {planner_spec['class']!r}: {first}") from None
    provenance = planner_provenance(type(planner))
    setup_s = time.perf_counter() - t_setup
    planner_spec["source_sha256"] = provenance["source_sha256"]
    planner_spec["provenance"] = provenance
    n = len(pif.outputs)

    def fresh() -> Any:
        return load_planner(planner_spec["class"], planner_spec["map"], planner_spec["params"])

    engine = InputSearch(pif, planner, cfg, factory=fresh, watchdog_s=watchdog_s)

    def tick(fc: FrameChoice) -> None:
        if on_frame is not None:
            on_frame(fc.output.index + 1, n)

    choices = engine.run(tick)
    comparisons = [compare(c.output.payload, c.actual, tol, cfg.measure) for c in choices]
    _contract_warnings(elog, engine, choices)
    for role, tm in pif.inputs.items():
        if tm.bad:
            elog.warnings.append(f"{len(tm.bad)} {role} message(s) with undecodable payloads were never used "
                                 f"(seq {', '.join(str(int(tm.seq[i])) for i in sorted(tm.bad)[:10])})")
    distances = [c.distance for c in choices]
    meta = elog.episode_meta()
    outcome = elog.metadata.get(mp.outcome_metadata or "", {})
    findings = _findings(elog, engine, choices, pif, outcome if isinstance(outcome, dict) else {})
    scenario = str(meta.get("scenario_name") or log_path.parent.name or log_path.stem)
    ego, ego_note = ego_size((mp.ego.length, mp.ego.width), meta.get("ego"))
    if ego_note:
        elog.warnings.append(ego_note)
    mini: list[Minimised | Seed] = []

    def minimize(index: int) -> tuple[int, dict[str, Any] | None]:
        """Where the failure test starts: seeded at ``index`` when the planner can be, else the
        shortest suffix of frames that reproduces P_faulty (every frame when a ``plan()`` of it
        hangs: the hang is a finding)."""
        frame = frame_getter([c.time for c in choices], lambda j: engine.frame_inputs(choices[j].choice))

        def watched() -> Any:
            return engine.watched(fresh())

        try:
            with engine.dog.armed():
                seed = seeded_start(watched, frame, index, lambda j: choices[j].output.payload)
                mini.append(seed)
                if seed.state is not None:
                    return index, {"frame": index, "state": seed.state}
                mini.append(shortest_replay(watched, frame, index, lambda j: choices[j].output.payload,
                                            cfg.measure))
        except ModuleHang:
            engine.note_hang(None, index, "failure-test minimisation")
            _hang_finding(elog, engine, findings, choices)
            return 0, None
        return mini[-1].replay_from, None

    reproduced = [c.reproduced for c in comparisons]
    after_lost = _after_lost_outputs(elog, mp, choices, reproduced)
    findings["after_lost_outputs"] = len(after_lost)
    faulty, oracle, oracle_note = _oracle(elog, mp, outcome, choices, distances, reproduced, ego, theta,
                                          minimize if minimize_failure and engine.hang is None else None)
    outputs = [(c.output.index, c.time, c.output.payload) for c in choices]
    ended = outcome.get("outcome") if isinstance(outcome, dict) else None
    # the other failure tests start where P_faulty's would: a seeded planner, else the shortest suffix
    views = _LogViews(elog, mp)
    for key, found in (("departure", _departure(elog, mp, outputs)),
                       ("stall", _stall(views, outputs, ego, ended)),
                       ("wrong_way", _wrong_way(views, outputs)),
                       ("off_road", _off_road(views, outputs, ego)),
                       ("near_miss", _near_miss(views, outputs, ego, outcome)),
                       ("red_light", _red_light(views, outputs, ego)),
                       ("yellow", _yellow(views, outputs, ego))):
        if found is None or found[key] is None:
            continue
        target = found[key]
        i = target["index"]
        if minimize_failure and engine.hang is None and reproduced[i] and choices[i].exact:
            target["replay_from"], seed = minimize(i)
            if seed is not None:
                found[f"{key}_seed"] = seed
        oracle = {**oracle, **found}

    header = {
        "format": FORMAT, "planner": planner_spec, "roles": list(pif.roles), "scenario": scenario,
        "log": str(log_path.resolve()), "jitter_seed": meta.get("jitter_seed"), "mapping": mp.as_dict(),
        "mode": cfg.mode, "theta": theta, "measure": cfg.measure, "tolerances": tol.as_dict(),
        "outcome": outcome.get("outcome"),
        "frames_index": [{"index": c.output.index, "time": c.time, "distance": finite_or_none(c.distance),
                          "reproduced": cmp.reproduced,
                          **({"after_lost": after_lost[c.output.index]} if c.output.index in after_lost else {})}
                         for c, cmp in zip(choices, comparisons)],
        "oracle": oracle, "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    out.mkdir(parents=True, exist_ok=True)
    frames_path = write_frames(out / "frames.jsonl", header, choices, pif)
    agreement = truth_agreement(_truth_path(log_path, truth), choices, pif) if truth else None
    summary = _summary(elog, log_path, scenario, meta, outcome, cfg, tol, choices, comparisons, engine,
                       faulty, oracle_note, agreement, mp)
    summary["findings"] = findings
    summary["failure_oracles"] = {f"P_{key}": {"index": oracle[key]["index"], "time": oracle[key]["time"]}
                                  for key in FAILURE_ORACLES if isinstance(oracle.get(key), dict)}
    if choices and len(choices) == findings["outputs_without_replay"]:  # nothing could be replayed: no tests
        summary["error"] = (f"none of the {len(choices)} planning outputs got a replayed plan; the generated tests "
                            f"would all fail ({elog.warnings[-1] if elog.warnings else 'see the warnings'})")
    test_path = None
    if emit_tests:
        name = f"test_{slug(scenario)}_{log_id(log_path)}" + (f"_{cfg.mode}" if cfg.mode != "heuristic" else "")
        for old in out.glob("test_*.py"):  # the module of an earlier extraction into this folder
            if old.name != f"{name}.py" and old.read_text().startswith('"""DeFT planning-module tests'):
                old.unlink()
        test_path = write_atomic(out / f"{name}.py", test_module(header, summary, frames_path.name,
                                                                  name.removeprefix("test_"), xfail_failures))
    total_s = time.perf_counter() - t_start
    summary.update(_timing(total_s, setup_s, engine, n, mini))
    summary["frames_path"] = str(frames_path)
    summary["test_path"] = str(test_path) if test_path else None
    write_atomic(out / "summary.json", json.dumps(summary, indent=2))
    return ExtractionResult(summary, frames_path, test_path, summary["faulty_trajectory"], choices, comparisons)


def _check_fields(mp: TopicMapping, pif: PlanningIOFilter) -> None:
    """MappingError (one line, before any search) when a field the mapping names is in none of
    the log's planning outputs - a typo would otherwise cost a blind search and give 0 %."""
    fields = [("frame_time_field", mp.frame_time_field), ("frame_time_hint", mp.frame_time_hint)]
    outputs = pif.outputs
    for key, path in fields:
        if path and outputs and all(get_field(o.payload, path) is None for o in outputs):
            raise MappingError(f"{mp.source}: {key}: {path!r} is in none of the {len(outputs)} planning outputs "
                               f"of the log (topic {mp.topic('planning')}); expected a dotted path present in "
                               "them, or null")
    # an output is published shortly after its frame time: when its frame time and its log time
    # are hours apart, the log's times cannot be mapped onto the frames (every replay would miss)
    lags = sorted(o.publish_time - o.frame_time for o in outputs if o.frame_time is not None)
    if lags:
        lag = lags[len(lags) // 2]
        if not -1.0 <= lag <= MAX_LAG_S:
            raise MappingError(f"{pif.log.path}: the planning outputs are logged {lag:.6g} s after their frame times "
                               f"({mp.frame_time_field}; median of {len(lags)}): the log's message times cannot be "
                               "mapped onto the frames (a deft_gym log without its deft_gym.episode metadata record, "
                               "which holds the epoch start of its log times?)")


def _after_lost_outputs(elog: EpisodeLog, mp: TopicMapping, choices: list[FrameChoice],
                        reproduced: list[bool]) -> dict[int, str]:
    """Outputs that do not reproduce because planning outputs before them were lost in a damaged
    part of the log (output index -> why): the planner did not plan the lost outputs' frames in
    the replay, so its state (its previous plan, its decisions) differs from the recorded run's
    although their own inputs are intact. From each gap in the planning outputs' sequence
    numbers, the outputs that follow it without reproducing, up to the first that does; stated
    as a warning (they are no fault of the planner) and as the reason of their tests' xfail."""
    topic = mp.topic("planning")
    lost = sorted({s for d in elog.integrity.damage for s in d.lost.get(topic or "", []) if s >= 0})
    if not lost or not choices:
        return {}
    out: dict[int, str] = {}
    gaps = []
    for k in range(len(choices)):
        prev = choices[k - 1].output.seq if k else -1
        cur = choices[k].output.seq
        missing = [s for s in lost if prev < s < cur]
        if not missing:
            continue
        why = (f"{len(missing)} planning output(s) before it were lost in a damaged part of the log (seq "
               f"{missing[0]}-{missing[-1]}): the replay did not plan their frames, so the planner's state differs")
        start = k
        while k < len(choices) and not reproduced[k]:
            out[choices[k].output.index] = why
            k += 1
        if k > start:
            gaps.append((missing, start, k - 1))
    for missing, a, b in gaps:
        elog.warnings.append(f"{b - a + 1} output(s) after {len(missing)} lost planning output(s) (seq "
                             f"{missing[0]}-{missing[-1]}) do not reproduce (frames {a}-{b}): the replay did not plan "
                             "the lost outputs' frames, so the planner's state differs from the recorded run's though "
                             "these frames' inputs are intact - a consequence of the damage, not of the planner; "
                             "their tests xfail saying so")
    return out


def _check_tolerances(tol: Tolerances, pif: PlanningIOFilter) -> None:
    """MappingError (one line) for a tolerance of a field no planning output of the log has: a
    typo (``--tolerance vv=0.1``) would otherwise leave the real field exact without a word."""
    if not tol.fields or not pif.outputs:
        return
    have: set[str] = set()
    for o in pif.outputs[:50]:
        tr = o.payload.get("trajectory") if isinstance(o.payload, dict) else None
        if isinstance(tr, dict):
            have.update(tr)
    unknown = sorted(set(tol.fields) - have)
    if unknown:
        raise MappingError(f"tolerance {', '.join(map(repr, unknown))}: no trajectory field of that name in the log's "
                           f"planning outputs (they have {', '.join(sorted(have)) or 'none'}; decision=... and "
                           "default=... are the other keys)")


def _findings(elog: EpisodeLog, engine: InputSearch, choices: list[FrameChoice],
              pif: PlanningIOFilter, outcome: dict[str, Any]) -> dict[str, Any]:
    """Faults of the planner or the run that the extraction met, counted (``summary.findings``)
    and each stated as a warning: a run that ended in a module crash or hang, recorded outputs
    holding NaN/inf, plan() calls that raised during the replays and the outputs left without a
    replayed plan because of it. None of them is ever a silent non-reproduction."""
    failure = outcome.get("failure")
    nan = [o.index for o in pif.outputs if non_finite(o.payload)]
    no_output = [c.output.index for c in choices if c.actual is None]
    if isinstance(failure, dict):
        elog.warnings.append(f"the run ended in a {failure.get('kind')} of module {failure.get('module')} at "
                             f"t={failure.get('time')}: {failure.get('exception')}")
    if nan:
        elog.warnings.append(f"{len(nan)} recorded planning output(s) hold NaN or inf (first: output {nan[0]}): "
                             "a planner fault, reported as a finding")
    if engine.exceptions:
        elog.warnings.append(f"the planner raised in {engine.exceptions} of {engine.plan_calls} replays "
                             f"({engine.errors[0] if engine.errors else '?'}); {len(no_output)} output(s) got no "
                             "replayed plan")
    elif no_output and engine.hang is None:
        elog.warnings.append(f"{len(no_output)} of {len(choices)} planning output(s) got no replayed plan: the planner "
                             f"returned None for every candidate frame (first: output {no_output[0]}) - inputs it "
                             "did not get, or a mapping that does not fit the log")
    found = {"run_failure": failure, "nan_outputs": len(nan), "nan_output_indices": nan[:50],
             "planner_exceptions": engine.exceptions, "planner_hang": None, "planner_crash": None,
             "outputs_without_replay": len(no_output)}
    _hang_finding(elog, engine, found, choices)
    return found


def _hang_finding(elog: EpisodeLog, engine: InputSearch, findings: dict[str, Any],
                  choices: list[FrameChoice]) -> None:
    """A ``plan()`` that ran past the watchdog (or the extraction's whole-run cap), as the finding
    ``planner_hang``, or a planner that could no longer be called - its process ended (``os._exit``,
    a signal, a segmentation fault) or its ``snapshot()``/``restore()`` raised - as
    ``planner_crash``; and a warning (once)."""
    hang = engine.hang
    key = "planner_hang" if hang is not None and hang["kind"] == "hang" else "planner_crash"
    if hang is None or findings.get(key) is not None:
        return
    findings[key] = hang
    at = f" at t={hang['time']:.3f} s" if hang.get("time") is not None else ""
    no_output = sum(1 for c in choices if c.actual is None)
    what = "hung" if key == "planner_hang" else "failed"
    elog.warnings.append(f"the planner {what} during the {hang['during']}{at} (output {hang['output']}): "
                         f"{hang['exception']}; no plan() was called after it, {no_output} output(s) got no "
                         "replayed plan")


def _contract_warnings(elog: EpisodeLog, engine: InputSearch, choices: list[FrameChoice]) -> None:
    """Warnings about the planner's contract seen while extracting: outputs that break the
    output contract, an unfaithful snapshot/restore, replays that differ from fresh planners."""
    bad = [(c.output.index, p) for c in choices for p in validate_output(c.actual, c.time)[:1]]
    if bad:
        elog.warnings.append(f"{len(bad)} replayed output(s) break the output contract, e.g. frame {bad[0][0]}: "
                             f"{bad[0][1]} (deft_gym.planner.base.validate_output)")
    if engine.restore_faithful is False:
        elog.warnings.append(
            f"the planner's snapshot()/restore() is not faithful: a fresh replay of the chosen frames differs at "
            f"frame {engine.unfaithful_at} (state kept outside self.state?); frames from there were searched again "
            "on fresh planners (check it with python -m extract.contract)")
    if engine.nondeterministic_at is not None:
        elog.warnings.append(f"the planner is not deterministic: two fresh replays of the same frames differ at "
                             f"frame {engine.nondeterministic_at}")


def _planner_spec(elog: EpisodeLog, mp: TopicMapping) -> dict[str, Any]:
    if mp.planner is not None:
        return {"class": mp.planner.cls, "params": dict(mp.planner.params), "map": dict(mp.planner.map)}
    meta = elog.episode_meta()
    spec, map_spec = meta.get("planner"), meta.get("map")
    if not isinstance(spec, dict) or "class" not in spec or not isinstance(map_spec, dict):
        raise MappingError(f"{elog.path}: the log names no planner (no deft_gym.episode metadata);"
                           f" set planner: {{class, params, map}} in the mapping {mp.source}")
    return {"class": spec["class"], "params": dict(spec.get("params") or {}), "map": map_spec}


def _truth_path(log_path: Path, truth: Path | str | bool | None) -> Path | None:
    if truth is True:
        p = log_path.with_name("truth.jsonl")
        return p if p.exists() else None
    return Path(truth) if truth else None


def _oracle(elog: EpisodeLog, mp: TopicMapping, outcome: dict[str, Any], choices: list[FrameChoice],
            distances: list[float], reproduced: list[bool], ego: tuple[float, float], theta: float,
            minimize: Callable[[int], tuple[int, dict[str, Any] | None]] | None = None
            ) -> tuple[Faulty | None, dict[str, Any], str | None]:
    """P_faulty and the oracle data the failure test needs (empty without a collision)."""
    coll = outcome.get("collision")
    if not isinstance(coll, dict):
        return None, {}, None if outcome else "no outcome record in the log"
    topic = mp.topic("perception_obstacles")
    if topic is None or topic not in elog.topics:
        return None, {}, "collision, but the mapping names no perception_obstacles topic"
    tm = elog.topics[topic]
    track = participant_track((tm.payload(i) for i in range(len(tm))), int(coll["participant_num"]),
                              str(coll.get("participant", coll["participant_num"])))
    if track is None:
        return None, {}, f"collision, but participant {coll.get('participant')} never appears in {topic}"
    outputs = [(c.output.index, c.time, c.output.publish_time, c.output.seq, c.output.payload) for c in choices]
    faulty = find_faulty(outputs, [d if ok else max(d, math.nextafter(theta, math.inf))
                                   for d, ok in zip(distances, reproduced)], track, ego, float(coll["time"]), theta)
    if faulty is None:
        return None, {}, ("collision, but no planning output before it plans the ego into the participant: "
                          "the vehicle left its plan, so by DeFT's criterion the planner is not the culprit")
    seed = None
    if minimize is not None and reproduced[faulty.index] and choices[faulty.index].exact:
        faulty.replay_from, seed = minimize(faulty.index)
        faulty.seeded = seed is not None
    oracle = {"collision": coll, "ego": {"length": ego[0], "width": ego[1]}, "track": track.as_dict(),
              "faulty": faulty.as_dict()}
    if seed is not None:
        oracle["seed"] = seed
    note = None if reproduced[faulty.index] else "P_faulty itself was not reproduced (whole output within tolerances)"
    return faulty, oracle, note


def _departure(elog: EpisodeLog, mp: TopicMapping, outputs: list[tuple[int, float, Any]]) -> dict[str, Any] | None:
    """The oracle of a non-optimal decision (``optimal_path`` and ``departure``, P_departure) when
    the log carries the optimal path it was judged against (a search run's log) and one of the
    plans ``(index, time, payload)`` took the ego off it; else None."""
    meta = elog.metadata.get(mp.optimal_path_metadata or "")
    found = optimal_path(meta)
    if found is None:
        return None
    path, limit = found
    dep = find_departure(outputs, path, limit)
    if dep is None:
        return None
    return {"optimal_path": {"x": meta["x"], "y": meta["y"], "limit": limit}, "departure": dep}


def _wrong_way(views: _LogViews, outputs: list[tuple[int, float, Any]]) -> dict[str, Any] | None:
    """The oracle of driving against the lane direction (``wrong_way``, P_wrong_way, with the lanes
    it is judged on, ``wrong_way_map``) when the log holds the road map (the mapping's ``map``
    role, whether or not the planner reads it) and one of the plans ``(index, time, payload)`` took
    the ego into lanes that all point against it for at least :data:`~extract.oracle.WRONG_WAY_LIMIT`
    m; else None."""
    lanes = map_lanes(views.map)
    ww = find_wrong_way(outputs, lanes)
    if ww is None:
        return None
    return {"wrong_way": ww, "wrong_way_map": {"lanes": [{"x": xy[:, 0].tolist(), "y": xy[:, 1].tolist(),
                                                          "width": 2.0 * half} for xy, half in lanes]}}


def map_payload(elog: EpisodeLog, mp: TopicMapping) -> dict[str, Any] | None:
    """The log's road map (the first message of the mapping's ``map`` role), or None."""
    maps = elog.topics.get(mp.topic("map") or "")
    return maps.payload(0) if maps is not None and len(maps) else None


def ego_poses(elog: EpisodeLog, mp: TopicMapping) -> dict[str, list[float]] | None:
    """The ego's poses from the log's ``localization`` role: ``t`` (the pose's ``header.stamp``,
    sim time [s] as the frame times, not the log's time), ``x``, ``y`` [m], ``heading`` [rad], ``v``
    [m/s] (0 where a pose has none); poses without the others are skipped. None when the log has
    no such topic."""
    locs = elog.topics.get(mp.topic("localization") or "")
    if locs is None:
        return None
    poses: dict[str, list[float]] = {"t": [], "x": [], "y": [], "heading": [], "v": []}
    for i in range(len(locs)):
        pose = locs.payload(i)
        try:
            values = [float(pose["header"]["stamp"]), float(pose["x"]), float(pose["y"]), float(pose["heading"]),
                      float(pose.get("v") or 0.0)]
        except (KeyError, TypeError, ValueError, AttributeError):
            continue
        for key, v in zip(poses, values):
            poses[key].append(v)
    return poses


@dataclass
class _LogViews:
    """What several failure oracles read from one log, each read and decoded once: the road map,
    the ego's poses (:func:`ego_poses`), the map's stop lines and each light's recorded colours
    (None without the mapping's ``traffic_light`` role)."""

    elog: EpisodeLog
    mp: TopicMapping

    @functools.cached_property
    def map(self) -> dict[str, Any] | None:
        return map_payload(self.elog, self.mp)

    @functools.cached_property
    def poses(self) -> dict[str, list[float]] | None:
        return ego_poses(self.elog, self.mp)

    @functools.cached_property
    def stop_lines(self) -> list[dict[str, Any]]:
        return map_stop_lines(self.map)

    @functools.cached_property
    def lights(self) -> dict[str, dict[str, list[Any]]] | None:
        topic = self.elog.topics.get(self.mp.topic("traffic_light") or "")
        return light_timeline(topic.payload(i) for i in range(len(topic))) if topic is not None else None


def _off_road(views: _LogViews, outputs: list[tuple[int, float, Any]],
              ego: tuple[float, float]) -> dict[str, Any] | None:
    """The oracle of leaving the road (``off_road``, P_off_road, with the map it is judged on,
    ``off_road_map``) when the log holds the road map and the ego's poses (the mapping's ``map``
    and ``localization`` roles) and the ego's box left the drivable area by more than
    :data:`~extract.oracle.OFF_ROAD_LIMIT` m where the plans before had put it; else None."""
    payload, poses = views.map, views.poses
    if payload is None or poses is None:
        return None
    found = find_off_road(outputs, poses, map_area(payload), ego)
    if found is None:
        return None
    return {"off_road": found, "off_road_map": {"lanes": [
        {k: lane[k] for k in ("x", "y", "width", "junction") if k in lane} for lane in payload["lanes"]]}}


def _near_miss(views: _LogViews, outputs: list[tuple[int, float, Any]], ego: tuple[float, float],
               outcome: Any) -> dict[str, Any] | None:
    """The oracle of passing a participant too close (``near_miss``, P_near_miss, with the
    participant's perceived track) when the log holds the ego's poses and the perceived obstacles
    (the mapping's ``localization`` and ``perception_obstacles`` roles) and the ego's box came
    within :data:`~extract.oracle.NEAR_MISS_CLEARANCE` m of a participant's, faster than
    :data:`~extract.oracle.NEAR_MISS_SPEED` m/s relative to it, where the plans before had put it;
    the participant the run collided with is P_faulty's, not this oracle's; else None."""
    topic = views.elog.topics.get(views.mp.topic("perception_obstacles") or "")
    if views.poses is None or topic is None:
        return None
    tracks = participant_tracks(topic.payload(i) for i in range(len(topic)))
    coll = outcome.get("collision") if isinstance(outcome, dict) else None
    if isinstance(coll, dict) and str(coll.get("participant_num", "")).lstrip("-").isdigit():
        tracks.pop(int(coll["participant_num"]), None)  # P_faulty's participant
    found = find_near_miss(outputs, views.poses, tracks.values(), ego)
    return {"near_miss": found} if found is not None else None


def _stall(views: _LogViews, outputs: list[tuple[int, float, Any]], ego: tuple[float, float],
           ended: str | None) -> dict[str, Any] | None:
    """The oracle of an ego left standing (``stall``, P_stall): for a run that ended ``stuck``, the
    first plan of the standing stretch that ends it; for one that timed out, the first such plan
    made while no light held the ego (:func:`~extract.oracle.light_holds`, from the map's stop
    lines and the light states when the log has them: a stop line ahead whose light was not green,
    or green for less than a second) - an ego that waits at a red light and does not move off at
    green; else None."""
    if ended == "stuck":
        return {"stall": find_stall(outputs)}
    if ended != "timeout":
        return None
    held = light_holds(outputs, views.stop_lines, views.lights or {}, ego[0])
    found = find_stall(outputs, free=[not h for h in held])
    return {"stall": found} if found is not None else None


def _red_light(views: _LogViews, outputs: list[tuple[int, float, Any]],
               ego: tuple[float, float]) -> dict[str, Any] | None:
    """The oracle of running a red light (``red_light``, P_red_light, with the stop line and its
    light's recorded colours) when the log holds the map's stop lines, the ego's poses and the
    light states (the mapping's ``map``, ``localization`` and ``traffic_light`` roles) and the
    ego's front crossed a stop line at red where the plans made after the light turned had put it;
    else None."""
    if not views.stop_lines or views.poses is None or views.lights is None:
        return None
    found = find_red_light(outputs, views.poses, views.stop_lines, views.lights, ego[0])
    return {"red_light": found} if found is not None else None


def _yellow(views: _LogViews, outputs: list[tuple[int, float, Any]],
            ego: tuple[float, float]) -> dict[str, Any] | None:
    """The oracle of giving up a stop that a yellow light left room for (``yellow``, P_yellow), in
    a run whose ego then crossed the line at red, from what :func:`_red_light` reads; else None."""
    if not views.stop_lines or views.poses is None or views.lights is None:
        return None
    found = find_yellow(outputs, views.poses, views.stop_lines, views.lights, ego[0])
    return {"yellow": found} if found is not None else None


def _summary(elog: EpisodeLog, log_path: Path, scenario: str, meta: dict[str, Any], outcome: dict[str, Any],
             cfg: SearchConfig, tol: Tolerances, choices: list[FrameChoice], comparisons: list[Comparison],
             engine: InputSearch, faulty: Faulty | None, oracle_note: str | None,
             agreement: dict[str, Any] | None, mp: TopicMapping) -> dict[str, Any]:
    """``summary.json``: ``reproduced`` counts positions within each threshold (the paper's
    measure); ``reproduced_all_fields`` the same with every other field within its tolerance;
    ``reproduced_at_theta`` whole outputs at the extraction's theta; ``fields`` per field."""
    n = len(choices)
    distances = [c.distance for c in choices]
    counts = reproduced_counts(distances)
    rest_ok = [all(d.field == "position" for d in c.diffs) for c in comparisons]
    whole = {theta_key(t): sum(1 for d, ok in zip(distances, rest_ok) if ok and d <= t) for t in SUMMARY_THETAS}
    finite = [d for d in distances if math.isfinite(d)]
    tries = np.array([c.tries for c in choices]) if choices else np.zeros(1)
    return {
        "format": SUMMARY_FORMAT, "log": str(log_path), "log_status": elog.status,
        "log_integrity": elog.integrity.as_dict(), "scenario": scenario,
        "jitter_seed": meta.get("jitter_seed"), "outcome": outcome.get("outcome"),
        "collision": outcome.get("collision"), "mode": cfg.mode, "theta": tol.theta, "measure": cfg.measure,
        "tolerances": tol.as_dict(), "mapping": mp.name, "frames": n, "reproduced": counts,
        "reproduced_share": {k: (v / n if n else None) for k, v in counts.items()},
        "reproduced_all_fields": whole,
        "reproduced_at_theta": sum(1 for c in comparisons if c.reproduced),
        "fields": field_summary(comparisons, tol),
        "not_reproduced": [{"index": c.output.index, "time": c.time, "distance": finite_or_none(c.distance),
                            "fields": list(dict.fromkeys(d.field for d in cmp.diffs))}
                           for c, cmp in zip(choices, comparisons) if not cmp.reproduced][:50],
        "distance": {"max": max(finite) if finite else None, "mean": float(np.mean(finite)) if finite else None,
                     "no_output": n - len(finite)},
        "search": {"plan_calls": engine.plan_calls, "tries_mean": float(tries.mean()), "tries_max": int(tries.max()),
                   "stages": dict(Counter(c.stage for c in choices)), "planner_errors": engine.errors[:5],
                   "restores": engine.restores, "restore_faithful": engine.restore_faithful,
                   "unfaithful_at": engine.unfaithful_at, "nondeterministic_at": engine.nondeterministic_at},
        "faulty_trajectory": faulty.as_dict() if faulty else None,
        "oracle_note": oracle_note,
        "truth_agreement": agreement["share"] if agreement else None,
        "truth": agreement,
        "warnings": list(elog.warnings),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }


def _timing(total_s: float, setup_s: float, engine: InputSearch, n: int,
            mini: list[Minimised | Seed]) -> dict[str, Any]:
    """Per-frame wall time of the extraction (without the one-time planner import and
    construction, ``planner_setup_ms``), split into the planner's own ``plan()`` time and the
    rest (reading, search, validation, oracle, writing). Preparing the failure test (seeding or
    minimising: replays through fresh planners) is reported apart, as ``failure_minimisation``."""
    per = 1000.0 / max(n, 1)
    mini_s = sum(m.seconds for m in mini)
    work = total_s - setup_s - mini_s
    out: dict[str, Any] = {
        "extraction_s": total_s, "ms_per_frame": work * per, "planner_ms_per_frame": engine.planner_s * per,
        "overhead_ms_per_frame": (work - engine.planner_s) * per, "planner_setup_ms": setup_s * 1000.0,
        "failure_minimisation": None}
    if mini:
        seed = next((m for m in mini if isinstance(m, Seed)), None)
        rest = next((m for m in mini if isinstance(m, Minimised)), None)
        out["failure_minimisation"] = {
            "seconds": mini_s, "seeded": seed is not None and seed.state is not None,
            "seed_note": seed.note if seed is not None else None,
            "candidates": rest.candidates if rest else 0,
            "plan_calls": sum(m.plan_calls for m in mini),
            "replay_from": rest.replay_from if rest else (seed.frame if seed else 0)}
    return out


__all__ = ["ExtractionResult", "LogError", "MappingError", "extract_episode", "theta_key"]
