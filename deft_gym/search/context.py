"""A seed scenario ready for adversarial testing: its reference run and everything derived from it.

:class:`SeedContext` bundles the scenario, its cached reference run, the road map, the motion
areas, the reference-path frame and the decision oracle; :func:`seed_context` builds it once per
process. :func:`resolve_scenario` turns a name (``left_turn``), a path, or a held-out variant
name (``left_turn~v1000003``: :func:`deft_gym.scenarios.variants.perturb` with that seed) into a scenario.
"""

from __future__ import annotations

import functools
import hashlib
import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from deft_gym.bus.ads import AdsConfig, load_ads_config
from deft_gym.config import ConfigError, resolve_config_path
from deft_gym.planner.base import import_object
from deft_gym.scenarios.generate import SPEC_PREFIX
from deft_gym.scenarios.generate import resolve as resolve_generated
from deft_gym.scenarios.scenario import (
    SCENARIO_GROUPS,
    Scenario,
    destination_xy,
    group_path,
    group_scenarios,
    list_scenarios,
    load_scenario,
)
from deft_gym.search.feasible import FeasibleConfig, MotionAreas, motion_areas
from deft_gym.search.nods import DecisionOracle, reserved_path
from deft_gym.search.refpath import RefPath
from deft_gym.search.trace import (
    CACHE_DIR,
    Trace,
    aborted_changes,
    content_key,
    record_run,
    reference_run,
)
from deft_gym.world.roadmap import RoadMap, shared_roadmap

SEED_SCENARIOS = ("left_turn", "right_turn", "lane_follow_static", "u_turn", "cross_intersection",
                  "take_exit", "blocked_red_light")
VARIANT_STRENGTH = 1.0
TIME_FACTOR, TIME_SLACK = 1.5, 10.0  # [-], [s]: mutated runs last at most this long (see seed_context)
# [s] a mutated run whose ego stands this long, not held by a red light, is stuck. In 400 episodes
# of random placements no run that went on to complete stood so for more than 1.75 s
STUCK_TIME = 10.0
FIT_RUNS = 8  # unmutated runs (jitter seeds 1..8) a seed scenario must pass to be fit (robust)


def resolve_scenario(spec: str | Path | Scenario, strength: float = VARIANT_STRENGTH) -> Scenario:
    """A scenario from a name, a YAML path, ``gen:<seed>`` (a generated scenario,
    :mod:`deft_gym.scenarios.generate`), ``gen:<seed>@<config.yaml>`` (the same with another
    generator config, :func:`generated_with`), ``<group>/<name>`` (a scenario of a group such as
    ``handwritten``, ``configs/scenarios/<group>/<name>.yaml``) or ``<name>~v<seed>`` (a perturbed variant)."""
    if isinstance(spec, Scenario):
        return spec
    text = str(spec)
    generated = generated_with(text)  # gen:<seed>@<generator config YAML>
    if generated is None:
        generated = resolve_generated(text)  # gen:<seed>
    if generated is not None:
        return generated
    if "~v" in text:
        from deft_gym.scenarios.variants import perturb

        base, seed = text.rsplit("~v", 1)
        try:
            vseed = int(seed)
        except ValueError:
            raise ConfigError(f"scenario {text!r}: expected '<name>~v<integer seed>'") from None
        return perturb(resolve_scenario(base), vseed, strength)
    grouped = group_path(text)  # handwritten/<name>
    if grouped is not None:
        return load_scenario(grouped)
    path = Path(text)
    if path.exists() or path.suffix:
        return load_scenario(path)
    names = [p.stem for p in list_scenarios()]
    if text not in names:
        grouped_as = [f"{g}/{text}" for g in SCENARIO_GROUPS if f"{g}/{text}" in group_scenarios(g)]
        hint = f"; did you mean {grouped_as[0]!r}?" if grouped_as else ""
        raise ConfigError(f"scenario {text!r}: not a file and not one of {names}{hint}")
    return load_scenario(text)


def parse_config_spec(spec: str) -> tuple[int, str] | None:
    """The seed and generator config path of ``gen:<seed>@<config.yaml>``, None for any other
    string (``gen:<seed>`` included); ``ConfigError`` for a malformed one."""
    if not spec.startswith(SPEC_PREFIX) or "@" not in spec:
        return None
    seed_text, _, config = spec[len(SPEC_PREFIX):].partition("@")
    if not seed_text.isdigit() or not config:
        raise ConfigError(f"scenario {spec!r}: expected '{SPEC_PREFIX}<seed>@<generator config YAML>' with a seed >= 0")
    return int(seed_text), config


def generated_with(spec: str) -> Scenario | None:
    """The scenario of ``gen:<seed>@<config.yaml>``: generator seed ``<seed>`` under the generator
    config in that YAML file (:class:`~deft_gym.scenarios.generate.GeneratorConfig` fields; a
    ``configs/...`` path also names a shipped one) - the scenario ``python -m
    deft_gym.cli.generate --config <config.yaml> --seeds <seed>`` writes, without the file. None
    for any other spec."""
    parsed = parse_config_spec(spec)
    if parsed is None:
        return None
    from deft_gym.config import load_mapping, validate
    from deft_gym.scenarios.generate import GeneratorConfig, generate

    seed, config = parsed
    path = resolve_config_path(config)
    if not path.is_file():
        raise ConfigError(f"scenario {spec!r}: generator config {config!r} is not a file")
    cfg = _GEN_CONFIGS.get(str(path))
    if cfg is None:
        cfg = _GEN_CONFIGS[str(path)] = validate(GeneratorConfig, load_mapping(path), str(path))
    return generate(seed, cfg)


_GEN_CONFIGS: dict[str, Any] = {}
_ADS: dict[str, AdsConfig] = {}


def ads_config(path: str | Path | None = None) -> AdsConfig:
    """The ADS config a campaign runs on (memoised per process): ``path`` (a YAML file; ``configs/...``
    also names a shipped config in an installed package), or ``configs/ads/default.yaml``. Naming
    ``configs/ads/commonroad.yaml`` runs every campaign against CommonRoad's reactive planner."""
    key = str(path) if path else ""
    ads = _ADS.get(key)
    if ads is None:
        ads = _ADS[key] = load_ads_config(resolve_config_path(path) if path else None)
    return ads


@dataclass
class SeedContext:
    """A seed scenario with its reference run and derived geometry."""

    scenario: Scenario
    ads: AdsConfig
    ref: Trace
    roadmap: RoadMap
    areas: MotionAreas
    path: RefPath
    oracle: DecisionOracle
    feasible: FeasibleConfig

    @property
    def name(self) -> str:
        return self.scenario.name


_CTX: dict[Any, SeedContext] = {}


def seed_context(spec: str | Path | Scenario, feasible: FeasibleConfig | None = None, ads: AdsConfig | None = None,
                 reference_seed: int = 0, grid: str = "lane", threshold: float = 0.6) -> SeedContext:
    """Build (or reuse) the :class:`SeedContext` of a scenario. Raises ``ValueError`` when the
    scenario's reference run does not complete (then it is no optimal-decision seed). The
    context's scenario lasts at most ``TIME_FACTOR`` x the reference run's time + ``TIME_SLACK``
    and calls an ego standing for ``STUCK_TIME`` stuck: every mutated run (search baselines, the
    env, confirmations, robustness) ends there. A scenario whose own duration ends its runs before
    ``TIME_FACTOR`` x the reference's time makes its timeouts no task failures (``Verdict.cut_short``)."""
    sc = resolve_scenario(spec)
    ads = ads or load_ads_config()
    feasible = feasible or FeasibleConfig()
    key = (content_key(sc, ads, reference_seed), feasible, grid, threshold)
    ctx = _CTX.get(key)
    if ctx is None:
        hard = import_object(ads.planning.planner.cls).hard_clearance(ads.planning.planner.params)
        if feasible.margin < hard:
            raise ConfigError(f"feasible.margin: {feasible.margin} m is below the planner's own hard clearance "
                              f"{hard} m (planning.planner.params); objects that close invade the optimal path")
        ref = reference_run(sc, ads, reference_seed)
        # mutated runs end when the ego has clearly failed to finish: an ego that needs more than
        # TIME_FACTOR x the reference run's time + TIME_SLACK has timed out (task failure)
        limit = round(min(sc.duration, ref.sim_time * TIME_FACTOR + TIME_SLACK), 3)
        # a scenario written to end sooner (slow_truck: 70 s for a 67 s reference) ends its runs
        # before an ego has needed TIME_FACTOR x the reference's time: its timeouts are no task failures
        timeouts_count = limit >= ref.sim_time * TIME_FACTOR
        stuck = min(sc.stuck_time, STUCK_TIME)
        if limit < sc.duration or stuck < sc.stuck_time:
            sc = sc.model_copy(update={"duration": limit, "stuck_time": stuck})
        rm = shared_roadmap(sc.map)
        # validity and placement reserve the reference path on to the destination itself
        reserved = reserved_path(ref, destination_xy(rm, sc.ego.destination)[0])
        areas = motion_areas(reserved, rm, feasible, sc.duration)
        oracle = DecisionOracle(ref, rm, threshold=threshold, grid_kind=grid,  # type: ignore[arg-type]
                                clearance=feasible.margin, window=(feasible.early_window, feasible.late_window),
                                spawn_distance=feasible.spawn_distance, static_clearance=feasible.static_margin,
                                ego_lanes=areas.ego_lanes, reserved=reserved, timeouts_count=timeouts_count)
        if len(_CTX) > 256:
            _CTX.clear()
        ctx = _CTX[key] = SeedContext(sc, ads, ref, rm, areas, RefPath(ref, rm), oracle, feasible)
    return ctx


#: functions of ``search/trace.py`` that find and cache reference runs but judge none: an edit to
#: them leaves cached verdicts valid (a change to how the reference is chosen bumps ``TRACE_FORMAT``,
#: which the verdict's content key holds)
_NOT_JUDGING = frozenset({"reference_run", "_failed_reference", "code_fingerprint", "content_key",
                          "planner_source"})


@functools.cache
def _judge_key() -> str:
    """Hash of the source that judges a run robust - ``search/trace.py`` (the lane-change give-ups,
    the recorded trace) less its cache plumbing (:data:`_NOT_JUDGING`), and the consistency oracle
    (``search/nods.py``) - which the simulation's :func:`~deft_gym.search.trace.code_fingerprint`
    leaves out: an edit there makes cached verdicts stale. Hashed as syntax trees, so comments
    and layout do not count."""
    return judge_hash([(Path(__file__).parent / name).read_bytes() for name in ("trace.py", "nods.py")])


def judge_hash(sources: Iterable[bytes | str]) -> str:
    """8 hex digits of the syntax trees of ``sources`` (Python modules), the functions named in
    :data:`_NOT_JUDGING` left out."""
    import ast

    h = hashlib.sha256()
    for source in sources:
        tree = ast.parse(source)
        tree.body = [n for n in tree.body if not (isinstance(n, ast.FunctionDef) and n.name in _NOT_JUDGING)]
        h.update(ast.unparse(tree).encode())
    return h.hexdigest()[:8]


def robust(ctx: SeedContext, runs: int = FIT_RUNS, cache_dir: Path | str | None = CACHE_DIR) -> bool:
    """Is the scenario an optimal-decision seed under timing noise? Its reference must not give up a
    lane change it began (:func:`~deft_gym.search.trace.aborted_changes`), and its unmutated runs
    with jitter seeds 1..``runs`` (8) must all complete without a collision and stay consistent
    with the reference (IoU above the threshold). A variant that fails this would report failures the adversary did
    not cause. Cached on disk next to the reference."""
    key = f"{ctx.name}-{content_key(ctx.scenario, ctx.ads, 0)}-robust{runs}-{ctx.oracle.grid_kind}-{_judge_key()}"
    path = Path(cache_dir) / f"{key}.json" if cache_dir else None
    if path is not None and path.exists():
        return bool(json.loads(path.read_text())["robust"])
    ok = not aborted_changes(ctx.ref)  # a reference that gives up a lane change is no optimal path
    for js in range(1, runs + 1 if ok else 1):
        tr = record_run(ctx.scenario, ctx.ads, js)
        if tr.outcome != "completed" or ctx.oracle.iou(tr.xy) <= ctx.oracle.threshold:
            ok = False
            break
    if path is not None:
        from deft_gym.files import write_json_atomic

        write_json_atomic(path, {"robust": ok, "runs": runs})
    return ok


ARRIVAL_MARGIN = 0.5  # [m] the reference arrives at least this far inside the reach radius sideways


def arrival_problem(ctx: SeedContext, margin: float = ARRIVAL_MARGIN) -> str | None:
    """Why the reference run of ``ctx`` arrives too narrowly to be a seed, else None: its last pose
    (the first within ``REACH_RADIUS``, 3 m, of the destination) lies more than ``REACH_RADIUS -
    margin`` beside the destination lane's centre line. The ego then brushes the radius from the
    side - CommonRoad's on ``dense_cut_ins`` arrives 2.75 m beside it, by 7 cm - and a mutated run
    ``margin`` (0.5 m, validity's clearance) wider misses its destination: a task failure the
    adversary did not cause."""
    from deft_gym.sim.oracles import REACH_RADIUS

    dest = ctx.scenario.ego.destination
    _, beside = ctx.roadmap.geom(tuple(dest.lane)).frenet_point(*ctx.ref.xy[-1])
    if abs(beside) <= REACH_RADIUS - margin:
        return None
    return (f"scenario {ctx.name!r}: its reference run arrives {abs(beside):.2f} m beside its destination's lane, "
            f"within {REACH_RADIUS - abs(beside):.2f} m of missing it (less than {margin} m): move the "
            "destination to where the ego has settled in a lane")


def _first_robust(names: Iterable[str], count: int, ads: AdsConfig | None = None) -> list[str]:
    """The first ``count`` of ``names`` whose context (under ``ads``, default: the default ADS
    config) is robust (see :func:`robust`) and arrives clearly (:func:`arrival_problem`); names
    that do not resolve or whose reference run fails are skipped."""
    out: list[str] = []
    for name in names:
        if len(out) >= count:
            break
        try:
            ctx = seed_context(name, ads=ads)
            if arrival_problem(ctx) is None and robust(ctx):
                out.append(name)
        except (ValueError, ConfigError):
            continue
    return out


def held_out_variants(seed_name: str, count: int, base: int = 1_000_000, tries: int = 20,
                      ads: AdsConfig | None = None) -> list[str]:
    """The first ``count`` robust perturbed variants ``<seed>~v<base + i>`` of a seed scenario
    (under ``ads``: robust for the planner it names)."""
    return _first_robust((f"{seed_name}~v{base + i}" for i in range(tries)), count, ads)


def robust_generated(count: int, base: int, tries: int | None = None, ads: AdsConfig | None = None) -> list[str]:
    """The first ``count`` robust generated scenarios ``gen:<seed>`` from seed ``base`` on (their
    reference run completes and their unmutated runs stay consistent under timing noise; under
    ``ads``: for the planner it names); at most ``tries`` seeds are looked at (default ``4 count + 20``)."""
    seeds = range(tries if tries is not None else 4 * count + 20)
    return _first_robust((f"gen:{base + i}" for i in seeds), count, ads)
