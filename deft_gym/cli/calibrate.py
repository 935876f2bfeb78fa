"""How flaky are collisions? Rerun scenario variants and count the non-deterministic ones.

    deft-gym calibrate --variants 10 --reruns 10 --jitter-seed 1000     # -> runs/calibration

For every seed scenario, ``--variants`` perturbations of it, ``--cut-ins`` variants with a
vehicle cutting in ahead of the ego and ``--brakes`` variants with a leader braking hard
(:mod:`deft_gym.scenarios.variants`), the scenario is run ``--reruns`` times with jitter seeds S, S+1, ...;
the first of them is the *initial execution* S0.

Two shares are reported:

- **paper definition** (DeFT section 5.2: 187 of 658 = 28 % in Apollo): a *collision scenario*
  collides in its initial execution S0; it is *flaky* when some rerun does not reproduce it;
- **any-rerun definition**: a collision scenario collides in at least one rerun; it is flaky when
  it does not collide in all of them (counts every scenario that *can* collide, so it is higher).

Every finished run is appended to ``OUT/runs.jsonl`` in run order; an interrupted calibration
resumes from it (runs already there are not repeated). The summary goes to ``OUT/calibration.json``.
Variants and runs are work items of :mod:`deft_gym.execution`: local processes, or Ray tasks with
``--ray`` / ``--ray-address ADDR``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path
from typing import Any

from deft_gym.cli import common
from deft_gym.config import ConfigError
from deft_gym.execution import Executor, Record, add_backend_arguments, backend_from_args
from deft_gym.files import read_jsonl, write_atomic


def _job(args: tuple[dict[str, Any], int, str | None, str]) -> dict[str, Any]:
    from deft_gym.bus.ads import load_ads_config
    from deft_gym.scenarios.scenario import scenario_from_dict
    from deft_gym.sim.simulation import run_episode

    data, seed, ads_path, key = args
    c0 = time.process_time()
    sc = scenario_from_dict(data, source=data["name"])
    r = run_episode(sc, load_ads_config(ads_path), jitter_seed=seed, keep_planning=False)
    s = r.summary()
    return {"key": key, "name": sc.name, "seed": seed, "outcome": s["outcome"], "collision": s["collision"],
            "with": s["collision_detail"]["participant"] if s["collision"] else None,
            "sim_time": s["sim_time"], "wall_time": s["wall_time"],
            "cpu_seconds": round(time.process_time() - c0, 4)}  # this process's CPU [s] (a timing)


def _variants(args: tuple[str, int, float, int, int, str | None]) -> list[tuple[dict[str, Any], str]]:
    """The variants of one seed scenario (perturbations, cut-ins, hard brakes: the cut-ins and
    brakes need its reference run) as ``(scenario dict, key)``."""
    from deft_gym.scenarios.scenario import load_scenario, scenario_to_dict
    from deft_gym.scenarios.variants import inject_cut_in, inject_hard_brake, perturb
    from deft_gym.sim.simulation import reference_path

    path, n_variants, strength, cut_ins, brakes, ads_config = args
    seed_sc = load_scenario(path)
    variants = [perturb(seed_sc, seed=v, strength=strength) if v else seed_sc for v in range(n_variants)]
    if cut_ins or brakes:
        ref = reference_path(seed_sc)
        variants += [inject_cut_in(seed_sc, ref, seed=c) for c in range(cut_ins)]
        variants += [inject_hard_brake(seed_sc, ref, seed=c) for c in range(brakes)]
    out = []
    for var in variants:
        data = scenario_to_dict(var)
        out.append((data, hashlib.sha256(json.dumps([data, ads_config], sort_keys=True).encode()).hexdigest()[:16]))
    return out


MAX_PER_SEED = 10_000  # variants of one kind per seed scenario
MAX_RUNS = 1_000_000  # runs of one calibration (variants x reruns x seed scenarios)


def build_parser() -> common.Parser:
    ap = common.parser("calibrate", "deft_gym.cli.calibrate", __doc__)
    common.add_scenarios(ap, help="seed scenarios (default: all in configs/scenarios except bench_*)")
    ap.add_argument("--variants", type=common.int_range(0, MAX_PER_SEED), default=10,
                    help="perturbed variants per seed (the seed scenario itself is variant 0)")
    ap.add_argument("--reruns", type=common.positive_int, default=10, help="reruns per variant")
    ap.add_argument("--strength", type=common.finite_float(0.0, 100.0), default=1.0,
                    help="perturbation strength, 0..100 (1: the calibrated size of a perturbation)")
    ap.add_argument("--cut-ins", type=common.int_range(0, MAX_PER_SEED), default=6, help="cut-in variants per seed")
    ap.add_argument("--brakes", type=common.int_range(0, MAX_PER_SEED), default=6,
                    help="hard-braking-leader variants per seed")
    common.add_jitter_seed(ap, "jitter seed of each scenario's initial execution S0; rerun i uses S+i "
                               "(a resumed calibration keeps its seeds)")
    common.add_workers(ap)
    ap.add_argument("--ads-config", default=None, metavar="YAML", help="ADS config (default: configs/ads/default.yaml)")
    common.add_out(ap, common.RUNS / "calibration")
    common.add_output_flags(ap)
    add_backend_arguments(ap)
    common.add_watchdog(ap)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    with common.watchdog_env(args):
        return _main(args)


def _main(args: argparse.Namespace) -> int:
    console = common.console(args)
    try:
        backend = backend_from_args(args, args.workers)
    except ConfigError as err:
        return common.cli_error(str(err))
    from deft_gym.bus.ads import load_ads_config
    from deft_gym.scenarios.scenario import list_scenarios, load_scenario
    from deft_gym.sim.simulation import build_planner

    paths = args.scenarios or [str(p) for p in list_scenarios() if not p.name.startswith("bench")]
    per_seed = args.variants + args.cut_ins + args.brakes
    if per_seed < 1:
        return common.cli_error("--variants, --cut-ins and --brakes are all 0: nothing to run")
    if len(paths) * per_seed * args.reruns > MAX_RUNS:  # bounded before any work, not a growing list
        return common.cli_error(f"{len(paths)} scenario(s) x {per_seed} variants x {args.reruns} reruns = "
                                f"{len(paths) * per_seed * args.reruns:,} runs; at most {MAX_RUNS:,} in one "
                                "calibration (lower --variants, --cut-ins, --brakes or --reruns)")
    try:  # a bad ADS config or scenario: one line, before any run (not a worker's traceback)
        ads = load_ads_config(args.ads_config)
        scenarios = [load_scenario(p) for p in paths]
        build_planner(ads, scenarios[0])
    except (ConfigError, ValueError) as err:
        return common.cli_error(str(err))
    with common.locked_out(args.out):
        return _calibrate(args, console, backend, paths)


def _calibrate(args: argparse.Namespace, console: Any, backend: Any, paths: list[str]) -> int:
    if args.jitter_seed is None:  # resuming: the seeds of the runs already there; else fresh ones
        prior = read_jsonl(Path(args.out) / "runs.jsonl")
        args.jitter_seed = min((r["seed"] for r in prior), default=None)
        args.jitter_seed = common.fresh_seed() if args.jitter_seed is None else args.jitter_seed
        console.print(f"jitter seeds {args.jitter_seed}..{args.jitter_seed + args.reruns - 1}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ads_name = args.ads_config or "configs/ads/default.yaml"
    record = Record(out / "runs.jsonl")  # the same scenario data and ADS config -> the same key
    with Executor(backend, preload=("deft_gym.sim.simulation",)) as ex:
        # the variants of every seed scenario (reference runs included) are work items too
        with common.bar(args, len(paths), "scenario variants") as bar:
            jobs = [(data, args.jitter_seed + r, args.ads_config, key)
                    for variants in ex.map(_variants, [(p, args.variants, args.strength, args.cut_ins, args.brakes,
                                                        args.ads_config) for p in paths], progress=bar.update)
                    for data, key in variants for r in range(args.reruns)]
        todo = record.todo(jobs, lambda j: (j[3], j[1]), "key", "seed")
        if len(todo) < len(jobs):
            console.print(f"resuming: {len(jobs) - len(todo)} of {len(jobs)} runs already in {record.path}")
        with common.bar(args, len(todo), "calibration runs") as bar:
            for res in ex.map(_job, todo, progress=bar.update):
                record.add(res)
    results = record.rows
    wanted = {(j[3], j[1]) for j in jobs}
    doc = summarise([r for r in results if (r.get("key"), r["seed"]) in wanted])
    doc.update({"reruns": args.reruns, "variants": args.variants, "cut_ins": args.cut_ins,
                "brakes": args.brakes, "strength": args.strength, "jitter_seed": args.jitter_seed,
                "ads_config": ads_name})
    write_atomic(out / "calibration.json", json.dumps(doc, indent=2))
    for s in sorted(doc["scenarios"], key=lambda s: s["name"]):
        if any(s["collided"]):
            flags = "".join("X" if c else "." for c in s["collided"])
            console.print(f"  {s['name']:34s} {flags}  {sum(s['collided']):2d}/{len(s['collided'])}"
                          f"{'  (flaky)' if s['flaky_collision'] else ''}")
    console.print("  (X = collision; first column = initial execution S0)")
    for label, key in (("paper definition (collision in S0)", "paper"), ("any-rerun definition", "any_rerun")):
        d = doc[key]
        share = "-" if d["share"] is None else f"{100 * d['share']:.0f} %"
        console.print(f"{label}: {d['flaky']} of {d['collision_scenarios']} collision scenarios flaky ({share})")
    if doc["reproduced_per_rerun"]:
        rep = doc["reproduced_per_rerun"]
        console.print(f"reruns 1-{len(rep)} reproduce {min(rep)}-{max(rep)} of the "
                      f"{doc['paper']['collision_scenarios']} collisions of S0")
    console.print(f"{doc['total_scenarios']} scenarios; outcome differs across reruns in "
                  f"{doc['outcome_flaky_scenarios']}; wrote {out / 'calibration.json'}")
    return 0


def summarise(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Per-scenario collision flags in jitter-seed order, and the flaky shares under both
    definitions (see the module docstring)."""
    by: dict[str, list[dict[str, Any]]] = {}
    for r in results:
        by.setdefault(r["name"], []).append(r)
    scenarios = []
    for name, rs in by.items():
        rs = sorted(rs, key=lambda r: r["seed"])
        collided = [bool(r["collision"]) for r in rs]
        scenarios.append({"name": name, "seeds": [r["seed"] for r in rs], "collided": collided,
                          "outcomes": sorted({r["outcome"] for r in rs}),
                          "flaky_collision": any(collided) and not all(collided)})

    def share(coll: list[dict[str, Any]]) -> dict[str, Any]:
        flaky = sum(s["flaky_collision"] for s in coll)
        return {"collision_scenarios": len(coll), "flaky": flaky,
                "share": flaky / len(coll) if coll else None}

    s0 = [s for s in scenarios if s["collided"][0]]  # the paper's collision scenarios
    n_reruns = min((len(s["collided"]) for s in s0), default=0)
    return {"scenarios": scenarios,
            "paper": share(s0),
            # of the collisions in S0, how many each rerun reproduces (the paper's Figure 7)
            "reproduced_per_rerun": [sum(s["collided"][k] for s in s0) for k in range(1, n_reruns)],
            "any_rerun": share([s for s in scenarios if any(s["collided"])]),
            "outcome_flaky_scenarios": sum(len(s["outcomes"]) > 1 for s in scenarios),
            "total_scenarios": len(scenarios),
            "sim_seconds": sum(r["sim_time"] for r in results),
            "wall_seconds": sum(r["wall_time"] for r in results)}


if __name__ == "__main__":
    sys.exit(main())
