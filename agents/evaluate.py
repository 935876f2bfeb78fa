"""Compare adversaries at an equal budget of simulated scenarios (Decictor Table I / Figure 7).

    deft-gym evaluate --methods rl decictor random_delta random --budget 100 --repeats 2 \\
        --scenarios left_turn right_turn --variants 1 --model runs/adversary/x/model.zip --out runs/eval/x

Methods: ``rl`` (the trained adversary, stochastic actions), ``decictor`` (Decictor-GA),
``random_delta``, ``random`` (see :mod:`agents.search`) and ``random_online`` (uniform random
actions in the adversary env: the env without learning, an ablation).

Every (method, placement rule, scenario, repeat) is one job of ``budget`` simulated scenarios;
jobs run in parallel worker processes, or as Ray tasks with ``--ray`` / ``--ray-address ADDR``
(:mod:`deft_gym.execution`; the records are the same on every backend and number of workers).
``random`` places with no feasibility constraint, so no placement rule applies: it runs under
the first rule of ``--placements`` and its records are copied to the others.
Outputs in ``--out``:

- ``records.jsonl`` - one line per simulated scenario (append-only; a rerun with the same
  ``--out`` skips the jobs already complete, so an interrupted evaluation resumes; records of
  other simulation code, of an edited scenario or of an unfinished job move to
  ``records.set_aside.jsonl``, never deleted);
- ``summary.json``, ``table.md``, ``cumulative_failures.png``, ``per_scenario.png`` - the
  comparison (:mod:`agents.eval_report` through :mod:`agents.stats`): per method, placement and
  scenario and per group (seeds, held-out, all) mean +- sd over repeats of counted failures (valid,
  confirmed NoDS + ego-at-fault collisions), NoDS, collisions, local NoDS, task failures, validity,
  distinct failures, s/scenario and distinct failures per CPU-hour; Mann-Whitney U and
  Vargha-Delaney A12 between methods; the check of issue 17's targets; RL's training episodes as a
  second budget column. ``python -m agents.eval_report OUT`` re-renders them from the records.

Held-out scenarios (``--held-out K``, default 10) are the first K *robust* generated scenarios
``gen:<seed>`` with seeds from 1000000 on (:mod:`deft_gym.scenarios.generate`; a model trained on
any of them is refused); ``--scenarios handwritten`` adds the hand-written group
(``configs/scenarios/handwritten``: scenarios written as users write them, never trained on;
``--held-out 0`` evaluates on them alone); ``--variants K`` adds the first K robust perturbed variants
``<seed>~v<1000000+i>`` of each seed scenario. Robust: their unmutated runs complete consistently
under eight jitter seeds (:func:`deft_gym.search.context.robust`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from deft_gym.cli import common
from deft_gym.config import ConfigError, load_mapping, validate_with_flags
from deft_gym.execution import Executor, add_backend_arguments, backend_from_args
from deft_gym.files import append_jsonl, first_line, read_jsonl, write_atomic, write_json_atomic
from deft_gym.record.recorder import init_pool_worker

METHODS = ("rl", "decictor", "random_delta", "random", "random_online")
DEFAULT_METHODS = ("rl", "random_online", "decictor", "random_delta", "random")
ONLINE = ("rl", "random_online")  # methods that place while the scenario runs (the adversary env)
PLACEMENT_FREE = ("random",)  # methods that place with no feasibility constraint: no placement rule
HELD_OUT_BASE = 1_000_000


def _seed_scenarios() -> list[str]:
    from deft_gym.search.context import SEED_SCENARIOS  # imported here: --help stays fast

    return list(SEED_SCENARIOS)


class EvalConfig(BaseModel):
    """``configs/eval/*.yaml`` (command-line options override it)."""

    model_config = ConfigDict(extra="forbid")

    methods: list[str] = Field(default_factory=lambda: list(DEFAULT_METHODS), min_length=1)
    budget: int = Field(50, ge=1, le=100_000)
    repeats: int = Field(1, ge=1, le=1000)
    scenarios: list[str] = Field(default_factory=lambda: _seed_scenarios(), max_length=10_000)
    held_out: int = Field(10, ge=0, le=10_000, description="held-out generated scenarios gen:<seed> (seeds from "
                          "1000000 on, never trained on; the first robust ones)")
    variants: int = Field(0, ge=0, le=1000, description="held-out perturbed variants per seed scenario")
    model: str | None = None
    deterministic: bool = False
    temperature: float = Field(1.0, gt=0.0, le=100.0, description="method rl: the policy's action logits are "
                               "divided by it before sampling (1: the trained policy; > 1 flatter, towards "
                               "random_online; ignored with deterministic)")
    workers: int = Field(2, ge=1, le=4096)
    seed: int = 0
    log_failures: bool = False
    max_added: int = Field(8, ge=1, le=100)
    placements: list[Literal["closest", "uniform"]] = Field(
        default_factory=lambda: ["closest", "uniform"], min_length=1,
        description="placement rules every method runs under (one table row per method and placement)")
    oracle: str | None = Field(None, description="what every method aims at and what counts: default (NoDS and "
                               "at-fault collisions, docs/search.md), any (those and every metric oracle's "
                               "findings; counts all of them) or a driving-quality metric oracle "
                               "(deft_gym.metrics.oracle.ORACLES, docs/metrics.md); default: the model's "
                               "training env.oracle, else default")
    count_oracles: list[str] = Field(default_factory=list, description="metric oracles whose confirmed findings "
                                     "are counted beside the aimed oracle's, on the same runs (per oracle and "
                                     "'any oracle' in table.md; all: every metric oracle but score); the search "
                                     "does not aim at them")
    validity: Literal["lane", "paper"] | None = Field(None, description="where static objects may stand: lane "
                                                      "(out of the ego's lane) or paper (Decictor's 0.5 m from "
                                                      "the optimal path; docs/search.md); default: the model's "
                                                      "training env.feasible, else lane")
    late_statics: Literal["from_start", "as_placed"] = Field(
        "from_start", description="methods rl and random_online place static objects while the scenario runs: "
        "from_start (a failure counts only when it reproduces on the second jitter seed with them there from "
        "t = 0, as parked cars and cones are: docs/search.md) or as_placed (the rule before 2026-11-28: "
        "confirmed with them joining when they joined)")
    ads: str | None = Field(None, description="ADS config YAML every method runs on, the planner under test "
                            "included (default: the model's training env.ads, else configs/ads/default.yaml), "
                            "e.g. configs/ads/commonroad.yaml")


def build_parser() -> common.Parser:
    p = common.parser("evaluate", "agents.evaluate", __doc__)
    p.add_argument("--config", type=Path, default=None, help="evaluation YAML (configs/eval/*.yaml; options "
                   "given here override it; default: the built-in defaults)")
    p.add_argument("--methods", nargs="+", action=common.ListAction, default=None, metavar="METHOD",
                   help=f"of {', '.join(METHODS)} (default: {' '.join(DEFAULT_METHODS)})")
    p.add_argument("--budget", type=common.int_range(1, 100_000), default=None,
                   help="simulated scenarios per method, scenario and repeat (default: 50)")
    p.add_argument("--repeats", type=common.int_range(1, 1000), default=None,
                   help="repeats with other seeds (default: 1)")
    common.add_scenarios(p, help="seed scenarios: names, YAML paths or specs; a group name (handwritten: the "
                         "scenarios of configs/scenarios/handwritten, never trained on) stands for its scenarios "
                         "(default: the seven seeds)")
    p.add_argument("--held-out", type=common.int_range(0, 10_000), default=None, dest="held_out",
                   help="held-out generated scenarios (default: 10)")
    p.add_argument("--variants", type=common.int_range(0, 1000), default=None, help="held-out perturbed variants per seed scenario "
                   "(default: 0)")
    p.add_argument("--placements", nargs="+", action=common.ListAction, default=None, metavar="RULE",
                   help="placement rules, of closest, uniform (default: both)")
    p.add_argument("--validity", choices=["lane", "paper"], default=None,
                   help="where static objects may stand: lane (out of the ego's lane) or paper (Decictor's 0.5 m "
                   "from the optimal path, which lets a parked car stand inside the lane); default: the model's "
                   "training config, else lane")
    p.add_argument("--late-statics", choices=["from_start", "as_placed"], default=None, dest="late_statics",
                   help="rl and random_online: confirm a failure with the static objects they placed mid-run there "
                   "from the start (from_start, the default) or joining when they joined (as_placed, the rule before "
                   "2026-11-28)")
    p.add_argument("--oracle", default=None, metavar="ORACLE",
                   help="default (NoDS, at-fault collisions), any (those and every metric oracle's findings: the GA "
                   "selects by both, counted oracle by oracle) or a metric oracle: collision, ttc, drivable_area, "
                   "direction, red_light, progress, comfort, speed_limit, standstill, score (docs/metrics.md; "
                   "default: the model's training env.oracle, else default)")
    p.add_argument("--count-oracles", nargs="+", action=common.ListAction, default=None, metavar="ORACLE",
                   dest="count_oracles", help="also count the confirmed findings of these metric oracles on the "
                   "same runs, without aiming at them: names as for --oracle, or all (every one but score); "
                   "table.md then has findings per oracle and RL's coverage by any oracle (default: none)")
    p.add_argument("--model", default=None, help="trained adversary (model.zip) for method 'rl', or 'default': the "
                   "adversary shipped in the package (deft_gym/models/adversary; default: none)")
    p.add_argument("--ads-config", type=Path, nargs="+", default=None, metavar="YAML",
                   help="ADS config, the planner under test included, e.g. configs/ads/commonroad.yaml; several: "
                   "one evaluation per planner in OUT/<file stem>, then OUT/planners.md compares them (default: the "
                   "config's ads, else the model's training env.ads, else configs/ads/default.yaml)")
    p.add_argument("--deterministic", action="store_true", default=None, help="greedy RL actions (default: off)")
    p.add_argument("--temperature", type=float, default=None, metavar="T",
                   help="RL actions sampled from the policy's logits divided by T (> 1: flatter, towards random "
                   "actions; default: the config's, else 1)")
    p.add_argument("--workers", type=common.positive_int, default=None, metavar="N",
                   help=f"parallel worker processes (default: the config's, else the CPUs, {common.cpus()} here)")
    common.add_seed(p, None, "seed of the methods' randomness (default: the config's, else 0)")
    p.add_argument("--log-failures", action="store_true", default=None,
                   help="keep MCAP logs of failing scenarios and extract tests from them (default: off)")
    common.add_out(p, common.RUNS / "evaluate")
    common.add_render(p)
    common.add_watchdog(p)
    common.add_output_flags(p)
    add_backend_arguments(p)
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    args = build_parser().parse_args(argv)
    args.out = Path(args.out)
    return args


def load_eval_config(args: argparse.Namespace) -> EvalConfig:
    data: dict[str, Any] = {}
    name = "<command line>"
    if args.config is not None:
        name = str(args.config)
        data = load_mapping(args.config)
    flags: dict[str, tuple[str, Any]] = {}
    for key in ("budget", "repeats", "held_out", "variants", "model", "deterministic", "temperature", "workers", "seed",
                "log_failures", "oracle", "validity", "late_statics"):
        flags[key] = ("--" + key.replace("_", "-"), getattr(args, key))
    ads_flag = getattr(args, "ads_config", None)
    flags["ads"] = ("--ads-config", str(ads_flag) if ads_flag is not None else None)
    for key in ("methods", "scenarios", "placements", "count_oracles"):
        value = getattr(args, key)
        flags[key] = ("--" + key.replace("_", "-"), common.split_list(value) if value is not None else None)
    data.setdefault("workers", common.cpus())
    from deft_gym.models import resolve_model

    # --model default: the adversary shipped in the package
    if isinstance(data.get("model"), str):
        data["model"] = resolve_model(data["model"])
    if isinstance(flags["model"][1], str):
        flags["model"] = (flags["model"][0], resolve_model(flags["model"][1]))
    cfg = validate_with_flags(EvalConfig, data, name, flags)
    from deft_gym.scenarios.scenario import expand_groups

    cfg.scenarios = expand_groups(cfg.scenarios)  # handwritten -> handwritten/<name>, ...

    def where(key: str) -> str:  # a problem names the flag that set the value, else the file's field
        return flags[key][0] if flags[key][1] is not None else f"{name}: {key}"

    if cfg.ads is not None:
        from deft_gym.search.context import ads_config

        try:
            ads_config(cfg.ads)
        except ConfigError as err:
            raise ConfigError(f"{where('ads')}: {err}") from None
    if cfg.oracle is not None:
        from deft_gym.metrics.oracle import ORACLES

        if cfg.oracle not in ORACLES:
            raise ConfigError(f"{where('oracle')}: unknown oracle {cfg.oracle!r}; expected one of {list(ORACLES)}")
    if cfg.count_oracles:
        from deft_gym.metrics.oracle import COUNTED_ORACLES, DECISION_ORACLES, ORACLES

        if cfg.count_oracles == ["all"]:
            cfg.count_oracles = list(COUNTED_ORACLES)
        metric = [o for o in ORACLES if o not in DECISION_ORACLES]
        bad = [o for o in cfg.count_oracles if o not in metric]
        if bad:
            raise ConfigError(f"{where('count_oracles')}: unknown {bad}; expected all or some of {metric}")
        cfg.count_oracles = list(dict.fromkeys(cfg.count_oracles))
    bad = [m for m in cfg.methods if m not in METHODS]
    if bad:
        raise ConfigError(f"{where('methods')}: unknown {bad}; expected some of {list(METHODS)}")
    if "rl" in cfg.methods and not cfg.model:
        raise ConfigError(f"{where('methods')}: method 'rl' needs --model (a trained model.zip)")
    # the baselines may run while the model trains: its run folder's config.yaml is enough
    if cfg.model and not Path(cfg.model).exists() and ("rl" in cfg.methods or not model_env_config(cfg.model)):
        raise ConfigError(f"{where('model')}: {cfg.model} does not exist")
    if cfg.model and "rl" in cfg.methods:
        check_model(cfg.model, where("model"))
    jobs = len(cfg.scenarios) * cfg.repeats * len(cfg.methods) * len(cfg.placements) * cfg.budget
    if jobs > MAX_SIMULATIONS:
        raise ConfigError(f"{name if args.config else 'the command line'}: {jobs:,} simulated scenarios (scenarios x repeats x methods x placements x "
                          f"budget); at most {MAX_SIMULATIONS:,} in one evaluation")
    from deft_gym.search.context import resolve_scenario  # names, paths, gen:<seed>, <name>~v<seed>

    for i, scenario in enumerate(dict.fromkeys(cfg.scenarios)):  # each resolves, before any worker starts
        try:
            resolve_scenario(scenario)
        except (ConfigError, ValueError, OSError) as err:
            at = "--scenarios" if flags["scenarios"][1] is not None else f"{name}: scenarios.{i}"
            raise ConfigError(f"{at}: {scenario!r} does not resolve ({first_line(err)[:300]})") from None
    return cfg


MAX_SIMULATIONS = 10_000_000  # simulated scenarios of one evaluation (checked before any work)


#: what a saved model holds only for training (the last observations, the episode buffers): an
#: evaluation does not unpickle it
TRAINING_STATE = ("_last_obs", "_last_episode_starts", "_last_original_obs", "ep_info_buffer", "ep_success_buffer")
SPACES = ("observation_space", "action_space")


def load_policy(path: str, env: Any) -> Any:
    """The SB3 model (PPO or A2C) at ``path`` for inference in ``env``. Its training state is not
    unpickled, and where its spaces do not unpickle - pickled under another numpy major version
    (numpy 2 on a lent machine, numpy 1.26 where the export extra pins it) - ``env``'s own are
    used: the policy's parameters still have to fit them. RuntimeError when neither loads."""
    from stable_baselines3 import A2C, PPO

    skip: dict[str, Any] = dict.fromkeys(TRAINING_STATE)
    spaces = {name: getattr(env, name) for name in SPACES}
    errors = []
    for custom in (skip, {**skip, **spaces}):
        for cls in (PPO, A2C):
            try:
                return cls.load(path, device="cpu", custom_objects=custom)
            except Exception as exc:  # not this algorithm, or spaces from another numpy
                errors.append(f"{cls.__name__}: {type(exc).__name__}: {first_line(exc, '')[:120]}")
    raise RuntimeError(f"cannot load model {path} ({'; '.join(errors)})")


def check_model(path: str, where: str) -> None:
    """ConfigError (one line) unless ``path`` is a readable SB3 model with a policy (an empty,
    truncated or foreign file is refused here, not in a worker's traceback)."""
    from stable_baselines3.common.save_util import load_from_zip_file

    try:  # the spaces and training state may be numpy 2 pickles under numpy 1: see load_policy
        data, params, _ = load_from_zip_file(path, device="cpu", load_data=True,
                                             custom_objects=dict.fromkeys((*TRAINING_STATE, *SPACES)))
    except Exception as exc:
        raise ConfigError(f"{where}: {path} is not a readable SB3 model ({type(exc).__name__}: "
                          f"{first_line(exc, '')[:200]})") from None
    if not isinstance(data, dict) or not params or "policy" not in params:
        raise ConfigError(f"{where}: {path} holds no policy (expected a model.zip written by agents.train)")


def model_env_config(model: str | None) -> dict[str, Any]:
    """The env section of the training config stored next to a model (or in its run folder)."""
    if not model:
        return {}
    p = Path(model)
    for d in (p.parent, p.parent.parent):
        if (d / "config.yaml").exists():
            return dict(load_mapping(d / "config.yaml").get("env") or {})
    return {}


def _key(r: dict[str, Any]) -> tuple[str, str, str, int]:
    """A record's job: (method, placement, scenario, repeat)."""
    return r["method"], r.get("placement", "closest"), r["scenario"], r["repeat"]


def _copy_placement_free(records: list[dict[str, Any]], copies: list[tuple[str, str, str, int]], first: str,
                         budget: int, rec_path: Path) -> list[dict[str, Any]]:
    """The records of each pending copy job (a method in :data:`PLACEMENT_FREE` under a placement
    rule other than ``first``) whose job under ``first`` is complete: the same records with the
    other rule's name, appended to the journal and taken off ``copies``."""
    out: list[dict[str, Any]] = []
    for key in list(copies):
        m, pl, scn, rep = key
        src = [r for r in records if _key(r) == (m, first, scn, rep)]
        if len(src) < budget:
            continue
        for r in sorted(src, key=lambda r: r["index"]):
            out.append({**r, "placement": pl})
            append_jsonl(rec_path, out[-1])
        copies.remove(key)
    return out


# -- one job --------------------------------------------------------------------------------------
_POLICIES: dict[str, Any] = {}


def seed_problem(item: dict[str, Any]) -> str | None:
    """Why ``item["scenario"]`` is no seed for the planner under test, else None: its reference run
    (the medoid of five jitter seeds) does not complete its task, or only just arrives
    (:func:`~deft_gym.search.context.arrival_problem`), or it is not robust (its unmutated runs on
    jitter seeds 1-8 do not all complete consistently with the reference; skipped for the held-out
    scenarios, chosen robust). Builds and caches what the jobs use (in a worker process), with
    metric oracles counted the signatures of those unmutated runs too."""
    from deft_gym.envs.adversary import load_env_config
    from deft_gym.metrics.oracle import DECISION_ORACLES, unmutated_signatures
    from deft_gym.search.context import arrival_problem, robust

    try:
        ctx = load_env_config(item["env"]).context(item["scenario"])
    except ValueError as err:
        return str(err)
    if (why := arrival_problem(ctx)) is not None:
        return why
    if item.get("check_robust", True) and not robust(ctx):
        return (f"scenario {ctx.name!r}: not robust on this planner: its unmutated runs on jitter seeds 1-8 do "
                "not all complete consistently with the reference (or the reference gives up a lane change)")
    if item.get("count") or item["env"].get("oracle", "default") not in DECISION_ORACLES:
        unmutated_signatures(ctx)  # what those runs violate counts nothing there: cached before the jobs ask
    return None


def run_job(job: dict[str, Any], progress: Any = None) -> list[dict[str, Any]]:
    """``budget`` simulated scenarios of one method on one scenario under one placement rule (in a
    worker process); one record per primary simulation (schema: :mod:`agents.stats`)."""
    from deft_gym.envs.adversary import load_env_config

    env_cfg = load_env_config(job["env"], placement=job["placement"])
    method, scenario, budget = job["method"], job["scenario"], job["budget"]
    seed = job["seed"]
    recs: list[dict[str, Any]] = []
    base = {"method": method, "placement": job["placement"], "scenario": scenario,
            "scenario_kind": job["scenario_kind"], "repeat": job["repeat"]}
    if method in ONLINE:
        recs = _run_rl(job, env_cfg, progress)
    else:
        from agents.search import search

        ctx = env_cfg.context(scenario)
        log_root = _log_root(job)

        def log_dir(i: int) -> Path | None:
            return (log_root / f"{i:05d}") if job["log_failures"] else None

        for rec in search(method, ctx, budget, seed, job["max_added"], log_dir, rule=job["placement"],
                          oracle=env_cfg.oracle, count=tuple(job.get("count", ()))):
            if job["log_failures"]:
                _keep_or_drop(log_dir(rec["index"]), rec)
            recs.append({**base, **rec})
            if progress is not None:
                progress.put(1)
    from deft_gym.metrics.oracle import oracle_code
    from deft_gym.search.trace import code_fingerprint

    code = code_fingerprint()  # the simulation code this job ran (a changed planner shows here)
    key = scenario_key(scenario, env_cfg.ads)  # and the scenario's content (an edited scenario file shows
    # here), the ADS config and the source of a planner the fingerprint does not hash; "judge": the
    # oracles' code (an edited oracle or metric shows here)
    return [{**base, **r, "code": code, "judge": oracle_code(), "scenario_key": key} for r in recs]


def scenario_key(spec: str, ads: str | None = None) -> str:
    """Hash of a scenario's content, the ADS config (``ads``, default: the default one; its
    planner's source when that is not the default planner) and the simulation code: a record made
    on another version of any of them is stale."""
    from deft_gym.search.context import ads_config, resolve_scenario
    from deft_gym.search.trace import content_key

    return content_key(resolve_scenario(spec), ads_config(ads), 0)


def _log_root(job: dict[str, Any]) -> Path:
    """Where one job's episode logs go: ``OUT/logs/<method>-<placement>/<scenario>/r<repeat>``,
    always inside ``OUT`` (:func:`folder_name`: a scenario given by a path, absolute or with
    ``..``, is one folder name)."""
    return Path(job["out"]) / "logs" / f"{job['method']}-{job['placement']}" / folder_name(job["scenario"]) / \
        f"r{job['repeat']}"


def folder_name(spec: str) -> str:
    """A scenario spec (a name, ``gen:7``, ``name~v3``, a YAML path) as one safe folder name: the
    name itself when it is one, else its file stem and a short hash of the whole spec."""
    import hashlib
    import re

    name = re.sub(r"[^A-Za-z0-9._-]+", "_", spec.replace("~", "_").replace(":", "_")).strip("._") or "scenario"
    if name == spec.replace("~", "_").replace(":", "_") and len(name) <= 100:
        return name
    stem = re.sub(r"[^A-Za-z0-9_-]+", "_", Path(spec).stem).strip("_")[:60] or "scenario"
    return f"{stem}-{hashlib.sha256(spec.encode()).hexdigest()[:8]}"


def _keep_or_drop(d: Path | None, rec: dict[str, Any]) -> None:
    import shutil

    if d is None:
        return
    if not (rec.get("failure") or rec.get("oracle_signature") or rec.get("found_by_oracle")):  # a failure, or a
        # metric oracle's finding
        shutil.rmtree(d, ignore_errors=True)
        return
    from deft_gym.envs.sink import extract_log

    write_json_atomic(d / "episode.json", rec)
    done = extract_log(d, test_suffix="_".join(d.parts[-4:]))
    rec["extraction"] = {k: done[k] for k in ("status", "test") if k in done}
    rec["log"] = str(d)


def _run_rl(job: dict[str, Any], env_cfg: Any, progress: Any) -> list[dict[str, Any]]:
    """``budget`` episodes of the adversary env (one scenario each) with the trained policy
    (``rl``) or uniform random actions (``random_online``); failures re-checked as the search
    baselines' are (:func:`agents.search.confirm`)."""
    import numpy as np
    import torch

    from agents.search import confirm, oracle_columns, record_of
    from deft_gym.envs.adversary import AdversaryEnv
    from deft_gym.search.episode import statics_from_start

    torch.set_num_threads(1)
    log_dir = None
    if job["log_failures"]:
        log_dir = str(_log_root(job))
    cfg = env_cfg.model_copy(update={"scenarios": [job["scenario"]], "variant_prob": 0.0, "log_dir": log_dir,
                                     "keep_passing": 0.0, "extract": True,
                                     "late_statics": "as_placed"})  # no reward here: the confirmation applies the rule
    env = AdversaryEnv(config=cfg)
    key = job["model"] if job["method"] == "rl" else None
    model = _POLICIES.get(key) if key else None
    if key and model is None:
        model = _POLICIES[key] = load_policy(key, env)
    temperature = float(job.get("temperature", 1.0))
    env.action_space.seed(job["seed"])
    rng = np.random.default_rng([job["seed"], 104729])
    recs = []
    for i in range(job["budget"]):
        w0, c0 = time.perf_counter(), time.process_time()
        obs, _ = env.reset(seed=job["seed"] * 100_003 + i)
        torch.manual_seed(job["seed"] * 100_003 + i)  # the policy's sampled actions: the same in any worker
        done = False
        info: dict[str, Any] = {}
        while not done:
            if model is None:  # random_online: uniform random actions in the same env
                action = env.action_space.sample()
            elif temperature == 1.0 or job["deterministic"]:
                action, _ = model.predict(obs, deterministic=job["deterministic"])
            else:
                action = tempered_action(model, obs, temperature)
            obs, _, done, _, info = env.step(action)
        v = env.last_verdict
        eq = env.equivalent_scenario()
        specs = eq["scenario"]["participants"][len(env.ctx.scenario.participants):]
        late = job.get("late_statics", "as_placed")
        again_at = statics_from_start(specs, eq["added_at"]) if late == "from_start" else eq["added_at"]
        again = int(rng.integers(2**31 - 1))
        confirmed, _, _ = confirm(env.ctx, v, specs, again, again_at)
        cols, _, _, n_o = oracle_columns(env.ctx, env.last_metrics, v.valid, env_cfg.oracle, specs, rng,
                                         again_at, tuple(job.get("count", ())), int(info["jitter_seed"]))
        cols["late_statics"] = late
        rec = record_of(v, i, time.perf_counter() - w0, time.process_time() - c0,
                        1 + (confirmed is not None) + n_o, confirmed, int(info["jitter_seed"]), int(info["added"]),
                        float(info["sim_time"]), cols, again)
        if model is not None:
            rec["temperature"] = temperature
        if v.failure or v.task_failure or cols.get("oracle_signature") or cols.get("found_by_oracle"):
            rec["scenario_equivalent"] = eq
            rec["ops"] = env.ops
            if info.get("log"):
                rec["log"], rec["extraction"] = info["log"], info.get("extraction")
        recs.append(rec)
        if progress is not None:
            progress.put(1)
    env.close()
    return recs


def tempered_action(model: Any, obs: Any, temperature: float) -> Any:
    """An action of a (Multi)Discrete-action SB3 policy sampled from each dimension's logits divided
    by ``temperature`` (torch's global generator, as ``predict`` samples)."""
    import torch
    from torch.distributions import Categorical

    with torch.no_grad():
        dist = model.policy.get_distribution(model.policy.obs_to_tensor(obs)[0])
        parts = getattr(dist, "distribution", None)
        if not isinstance(parts, list | tuple):  # Discrete: a single Categorical
            parts = [parts]
        if not all(isinstance(c, Categorical) for c in parts):
            raise ValueError(f"temperature needs a discrete action space; the policy's is {model.action_space}")
        action = torch.stack([Categorical(logits=c.logits / temperature).sample() for c in parts], dim=1)
    out = action.cpu().numpy()[0]
    return out if len(parts) > 1 else out[0]


def job_artifacts(job: dict[str, Any]) -> list[Path]:
    """What a job writes into the run folder: its episode logs and extracted tests."""
    return [_log_root(job)] if job["log_failures"] else []


def worker_preload(methods: list[str]) -> tuple[str, ...]:
    """Modules a local worker starts with already imported (a fork of a warm forkserver); torch
    (stable_baselines3) only where the env methods need it."""
    rl = any(m in ONLINE for m in methods)
    return ("deft_gym.envs.adversary", "agents.search", *(("stable_baselines3",) if rl else ()))


# -- main -----------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    with common.watchdog_env(args):
        planners = args.ads_config or [None]
        if len(planners) == 1:
            args.ads_config = planners[0]
            return _main(args)
        return _planners(args, planners)


def _planners(args: argparse.Namespace, planners: list[Path]) -> int:
    """One evaluation per ADS config (planner) in ``OUT/<file stem>``, then ``OUT/planners.md``."""
    labels = [p.stem for p in planners]
    if len(set(labels)) < len(labels):
        return common.cli_error(f"--ads-config: two configs share a file name ({labels}); each planner's "
                                "evaluation goes to OUT/<file stem>")
    out: Path = args.out
    for path, label in zip(planners, labels, strict=True):
        sub = argparse.Namespace(**{**vars(args), "ads_config": path, "out": out / label})
        code = _main(sub)
        if code:
            return code
    from agents.eval_report import write_planners_report

    text = write_planners_report(out)
    common.print_markdown(common.console(args), text)
    if args.quiet:
        print(f"planners: {out / 'planners.md'}")
    return 0


def _main(args: argparse.Namespace) -> int:
    con = common.console(args)
    try:
        cfg = load_eval_config(args)
        backend = backend_from_args(args, cfg.workers)
    except ConfigError as err:
        return common.cli_error(str(err))
    with common.locked_out(args.out):
        return _evaluate(args, con, cfg, backend)


def _evaluate(args: argparse.Namespace, con: Any, cfg: EvalConfig, backend: Any) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    seeds = list(cfg.scenarios)
    env = model_env_config(cfg.model)
    if cfg.ads is not None:  # the planner under test: the evaluation's, else the one the model trained on
        env["ads"] = cfg.ads
    if cfg.oracle is not None:  # what counts: the evaluation's, else the model's training objective
        env["oracle"] = cfg.oracle
    if env.get("oracle") == "any" and not cfg.count_oracles:  # the union (the evaluation's or the
        # model's training oracle) is counted oracle by oracle
        from deft_gym.metrics.oracle import COUNTED_ORACLES

        cfg.count_oracles = list(COUNTED_ORACLES)
    if cfg.validity is not None:  # where static objects may stand: the evaluation's, else the model's
        from deft_gym.search.feasible import PAPER, FeasibleConfig

        rule = PAPER if cfg.validity == "paper" else FeasibleConfig()
        env["feasible"] = {**(env.get("feasible") or {}), "static_margin": rule.static_margin,
                           "static_lane_depth": rule.static_lane_depth}
    from deft_gym.search.context import ads_config

    ads = ads_config(env.get("ads"))
    held_out = []
    if cfg.held_out:
        from deft_gym.scenarios.generate import HELD_OUT_BASE as GEN_BASE
        from deft_gym.scenarios.generate import disjoint, parse_spec
        from deft_gym.search.context import parse_config_spec, robust_generated

        con.print(f"choosing {cfg.held_out} robust held-out generated scenario(s) ...")
        held_out += robust_generated(cfg.held_out, GEN_BASE, ads=ads)
        # gen:<seed> of the default generator; gen:<seed>@<config> is another generator's scenario
        trained = [parse_spec(s) for s in env.get("scenarios", [])
                   if isinstance(s, str) and parse_config_spec(s) is None]
        try:
            disjoint([t for t in trained if t is not None], [parse_spec(h) for h in held_out])  # type: ignore[misc]
        except ValueError as err:
            print(f"error: {cfg.model}: {err}", file=sys.stderr)
            return 2
    if cfg.variants:
        from deft_gym.search.context import held_out_variants

        con.print(f"choosing {cfg.variants} robust held-out variant(s) per seed ...")
        for s in seeds:
            held_out += held_out_variants(s, cfg.variants, HELD_OUT_BASE, ads=ads) if "~v" not in s else []
    env["max_added"] = env.get("max_added", cfg.max_added)
    rec_path = out / "records.jsonl"
    done: dict[tuple[str, str, str, int], int] = defaultdict(int)
    records: list[dict[str, Any]] = []
    earlier: list[dict[str, Any]] = []  # what the journal held before this run
    if rec_path.exists():  # resume: keep what earlier runs simulated and judged with the same code
        from deft_gym.metrics.oracle import oracle_code
        from deft_gym.search.trace import code_fingerprint

        code, judge = code_fingerprint(), oracle_code()
        keys = {name: scenario_key(name, env.get("ads")) for name in seeds + held_out}
        records = read_jsonl(rec_path)
        earlier = list(records)
        stale = sum(1 for r in records if r.get("code") != code or r.get("judge") != judge
                    or (r["scenario"] in keys and r.get("scenario_key") != keys[r["scenario"]]))
        oracle = env.get("oracle", "default")  # records of another oracle count other findings
        records = [r for r in records if r["index"] < cfg.budget and r.get("code") == code
                   and r.get("judge") == judge and r.get("oracle", "default") == oracle and r.get("counted_oracles", []) == cfg.count_oracles
                   and (r["method"] != "rl" or r.get("temperature", 1.0) == cfg.temperature)
                   and (r["method"] not in ONLINE or r.get("late_statics", "as_placed") == cfg.late_statics)
                   and r["scenario"] in keys and r.get("scenario_key") == keys[r["scenario"]]]
        if stale:
            con.print(f"{stale} earlier record(s) ran other simulation code or another version of their "
                      "scenario, or were judged by other oracle code: simulating them again")
        for r in records:
            done[(r["method"], r.get("placement", "closest"), r["scenario"], r["repeat"])] += 1
    # a scenario is a seed only where the planner under test completes it unmutated: check each
    # (building the references the jobs use, in parallel) and leave out the others, named
    todo = seeds + held_out
    unfit: dict[str, str] = {}
    if todo:
        con.print(f"checking {len(todo)} scenario(s): does the planner under test complete each unmutated, "
                  "robustly ...")
        bar = common.Bar(len(todo), "scenarios checked", common.show_progress(args))
        with Executor(backend, initializer=init_pool_worker, initargs=(cfg.workers,),
                      preload=("deft_gym.envs.adversary",), run_dir=out) as ex:
            items = [{"scenario": s, "env": env, "check_robust": s not in held_out, "count": bool(cfg.count_oracles)}
                     for s in todo]
            for name, problem in zip(todo, ex.map(seed_problem, items, progress=bar.update), strict=True):
                if problem:
                    unfit[name] = problem
        bar.close()
        for name, problem in unfit.items():
            con.print(f"left out {name}: {problem}", highlight=False)
        seeds = [s for s in seeds if s not in unfit]
        held_out = [s for s in held_out if s not in unfit]
        if not seeds + held_out:
            print("error: no scenario is a seed for the planner under test (see above)", file=sys.stderr)
            return 2
    jobs = []
    copies: list[tuple[str, str, str, int]] = []
    from agents.stats import kind_of_name

    kinds = {**{s: "seed" if kind_of_name(s) != "handwritten" else "handwritten" for s in seeds},
             **{h: "held_out" for h in held_out}}
    for rep in range(cfg.repeats):
        for scn in seeds + held_out:
            for m in cfg.methods:
                for pl in cfg.placements:
                    key = (m, pl, scn, rep)
                    if done[key] >= cfg.budget:
                        continue
                    records = [r for r in records if _key(r) != key]
                    if m in PLACEMENT_FREE and pl != cfg.placements[0]:
                        copies.append(key)  # the same scenarios as under the first rule: copied, not re-run
                        continue
                    jobs.append({"method": m, "placement": pl, "scenario": scn, "scenario_kind": kinds[scn],
                                 "repeat": rep, "budget": cfg.budget, "seed": cfg.seed * 1000 + rep, "env": env,
                                 "model": cfg.model, "deterministic": cfg.deterministic,
                                 "temperature": cfg.temperature, "out": str(out),
                                 "log_failures": cfg.log_failures, "max_added": cfg.max_added,
                                 "late_statics": cfg.late_statics,
                                 "count": list(cfg.count_oracles)})
    from deft_gym.envs.adversary import load_env_config

    write_json_atomic(out / "eval_config.json", {**cfg.model_dump(), "ads": env.get("ads"), "held_out": held_out,
                                                 "unfit": unfit,
                                                 "feasible": load_env_config(env).feasible.model_dump()})
    # rewrite the journal without partial jobs and stale records (set aside, never deleted), then
    # append as jobs finish
    kept, aside = {id(r) for r in records}, out / "records.set_aside.jsonl"
    already = {json.dumps(r, sort_keys=True) for r in read_jsonl(aside)} if aside.exists() else set()
    for r in earlier:  # (a kill between the two steps must not set a record aside twice)
        if id(r) not in kept and json.dumps(r, sort_keys=True) not in already:
            append_jsonl(aside, r)
    write_atomic(rec_path, "".join(json.dumps(r, sort_keys=True) + "\n" for r in records))
    records += _copy_placement_free(records, copies, cfg.placements[0], cfg.budget, rec_path)
    total = sum(j["budget"] for j in jobs)
    con.print(f"{len(jobs)} jobs, {total} simulated scenarios, {backend.describe()} -> {out}")
    t0 = time.time()
    if jobs:
        bar = common.Bar(total, "simulated scenarios", common.show_progress(args))
        with Executor(backend, initializer=init_pool_worker, initargs=(cfg.workers,),
                      preload=worker_preload(cfg.methods), run_dir=out) as ex:
            # in job order, whatever order they finish in: the same records on every backend
            for recs in ex.map(run_job, jobs, progress=bar.update, item_progress=True, artifacts=job_artifacts):
                for r in recs:
                    append_jsonl(rec_path, r)
                records.extend(recs)
                records += _copy_placement_free(records, copies, cfg.placements[0], cfg.budget, rec_path)
        bar.close()
    from agents.eval_report import build_summary, headline_markdown, targets_markdown, write_report
    from agents.stats import RecordError

    try:
        summary = build_summary(records, cfg.model_dump(), seeds, held_out, str(rec_path))
    except RecordError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    summary["wall_seconds"] = round(time.time() - t0, 1)
    summary["unfit"] = unfit
    write_report(records, summary, out)
    if args.render != "none":  # pictures of the failing scenarios whose logs were kept
        from deft_gym.viz.episode import render_failures

        with common.bar(args, None, "pictures of failures") as b:
            render_failures(out / "logs", progress=lambda done, n: b.set(done, n))
    common.print_markdown(con, headline_markdown(summary))
    common.print_markdown(con, targets_markdown(summary["targets"]))
    con.print(f"tables and plots: {common.shown(out / 'table.md')}, {common.shown(out / 'cumulative_failures.png')}; "
              f"report: {common.tool('deft-gym')} report {common.shown(out)}", soft_wrap=True)
    if args.quiet:
        print(f"evaluation: {out / 'summary.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
