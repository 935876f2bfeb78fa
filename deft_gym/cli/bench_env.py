"""Throughput of ``deft_gym/Adversary-v0``: env steps/s, scenarios/hour, and where its CPU goes.

    deft-gym bench-env [--episodes 14] [--scenarios left_turn take_exit] [--policy random|noop]
    deft-gym bench-env --profile --config configs/train/adversary.yaml --episodes 60 --generated 5

Runs ``--episodes`` episodes on the seed scenarios (or ``--scenarios``) and ``--generated``
robust generated ones, in turn, and reports wall time split into simulation
(``Simulation.advance``) and the env's own work (placements, feasibility, observation, oracles),
scenarios per CPU-hour (one env process, no learner), and the machine's load average (the machine
is shared: compare runs at similar load). ``--config`` benchmarks a training config's env (its
placement, reward and recording settings; failing episodes are replayed into MCAP logs and
extracted as in training) instead of the env's defaults.

``--profile`` (the profile behind the training throughput): the same parts are also timed around
each call in those episodes, and as many other episodes run under cProfile; both shares are
printed (cProfile inflates the many small Python calls and hides the C parts, the timers do not).
"""

from __future__ import annotations

import contextlib
import cProfile
import os
import pstats
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.cli import common
from deft_gym.files import write_json_atomic

# (label, function name as pstats keys it: (file suffix, function name))
PARTS: list[tuple[str, str, str]] = [
    ("simulation (bus + modules + world)", "sim/simulation.py", "advance"),
    ("  planning", "modules/planning.py", "compute"),
    ("  world step", "world/world.py", "step"),
    ("  prediction", "modules/prediction.py", "compute"),
    ("  control", "modules/control.py", "compute"),
    ("episode end", "envs/adversary.py", "_finish"),
    ("  oracles (NoDS, collision)", "search/nods.py", "judge"),
    ("  failing episodes replayed into logs", "search/episode.py", "run_scenario"),
    ("  their tests extracted", "envs/sink.py", "_extract"),
    ("observation", "envs/adversary.py", "_obs"),
    ("placement", "envs/adversary.py", "_apply"),
]


# (label, module, class, method): timed with process_time around each call in the unprofiled
# episodes - cProfile inflates the many small Python calls and hides the C parts; a part's time
# includes the parts nested in it (a replay simulates too)
TIMED: list[tuple[str, str, str, str]] = [
    ("simulation (bus + modules + world)", "deft_gym.sim.simulation", "Simulation", "advance"),
    ("  planning", "deft_gym.modules.planning", "PlanningNode", "compute"),
    ("  world step", "deft_gym.world.world", "World", "step"),
    ("oracles (NoDS, collision)", "deft_gym.search.nods", "DecisionOracle", "judge"),
    ("failing episodes replayed into logs and extracted", "deft_gym.envs.adversary", "AdversaryEnv",
     "_replay_into_sink"),
    ("observation", "deft_gym.envs.adversary", "AdversaryEnv", "_obs"),
    ("  closest-cone probe", "deft_gym.envs.adversary", "AdversaryEnv", "_closest_static"),
    ("placement", "deft_gym.envs.adversary", "AdversaryEnv", "_apply"),
]


class _Timers:
    """Process CPU time [s] spent in each :data:`TIMED` method while active (restored on exit)."""

    def __init__(self) -> None:
        self.spent = {label: 0.0 for label, *_ in TIMED}
        self._saved: list[tuple[Any, str, Any]] = []

    def __enter__(self) -> _Timers:
        import importlib

        for label, module, cls_name, name in TIMED:
            cls = getattr(importlib.import_module(module), cls_name)
            fn = cls.__dict__[name]
            self._saved.append((cls, name, fn))
            setattr(cls, name, self._timed(fn, label))
        return self

    def _timed(self, fn: Any, label: str) -> Any:
        spent = self.spent

        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[label] += time.process_time() - t0
        return timed

    def __exit__(self, *exc: Any) -> None:
        for cls, name, fn in reversed(self._saved):
            setattr(cls, name, fn)


def build_parser() -> common.Parser:
    p = common.parser("bench-env", "deft_gym.cli.bench_env", __doc__)
    p.add_argument("--episodes", type=common.positive_int, default=14,
                   help="episodes to time (and, with --profile, as many to profile)")
    common.add_scenarios(p, help="seed scenarios (default: the seven seeds)")
    p.add_argument("--generated", type=int, default=0, help="robust generated scenarios besides them")
    p.add_argument("--policy", choices=("random", "noop"), default="random", help="the adversary's actions")
    p.add_argument("--config", type=Path, default=None,
                   help="training YAML whose env section is benchmarked, or a run's config.yaml "
                        "(default: none, the env's defaults)")
    p.add_argument("--profile", action="store_true",
                   help="also where the CPU goes: cProfile, and the parts timed around their calls "
                        "(default: off)")
    common.add_seed(p)
    common.add_out(p, None, help="also write the figures to this JSON file (default: none)", folder=False)
    common.add_output_flags(p)
    return p


def _episodes(env: Any, names: list[str], first: int, n: int, seed: int, policy: str) -> tuple[int, float]:
    """Episodes ``first .. first + n - 1`` (scenarios in turn): ``(env steps, simulation wall s)``."""
    steps, sim_s = 0, 0.0
    for ep in range(first, first + n):
        env.reset(seed=seed + ep, options={"scenario": names[ep % len(names)]})
        done = False
        while not done:
            a = env.action_space.sample() if policy == "random" else np.zeros(5, dtype=np.int64)
            _, _, term, trunc, _ = env.step(a)
            done = term or trunc
            steps += 1
        sim_s += env.sim._wall
    return steps, sim_s


def _shares_table(title: str, shares: dict[str, float]) -> Any:
    from rich.table import Table

    t = Table(title=title, title_justify="left")
    t.add_column("part")
    t.add_column("share", justify="right")
    for label, share in shares.items():
        t.add_row(label, f"{100 * share:.1f} %")
    return t


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    con = common.console(args)
    from deft_gym.config import ConfigError, load_mapping
    from deft_gym.envs.adversary import AdversaryEnv
    from deft_gym.search.context import SEED_SCENARIOS, robust_generated

    try:
        env_cfg = None if args.config is None else dict(load_mapping(args.config).get("env") or {})
    except (ConfigError, OSError) as err:
        return common.cli_error(f"--config {args.config}: {err}")
    names = list(args.scenarios or SEED_SCENARIOS)
    names += robust_generated(args.generated, 0) if args.generated > 0 else []
    with tempfile.TemporaryDirectory(prefix="bench_env_") as logs:  # the kept failures' logs (--config)
        env = (AdversaryEnv(scenario=names) if env_cfg is None
               else AdversaryEnv(config={**env_cfg, "scenarios": names, "log_dir": logs}))
        for n in names:  # contexts (reference runs, feasible areas) are built outside the timing
            env.reset(seed=args.seed, options={"scenario": n})
        env.action_space.seed(args.seed)
        timers = _Timers() if args.profile else contextlib.nullcontext()
        t0, c0 = time.perf_counter(), time.process_time()
        with timers:
            steps, sim_s = _episodes(env, names, 0, args.episodes, args.seed, args.policy)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        if args.profile:
            prof = cProfile.Profile(timer=time.process_time)
            prof.enable()
            _episodes(env, names, args.episodes, args.episodes, args.seed, args.policy)
            prof.disable()
    out = {"episodes": args.episodes, "steps": steps, "seconds": round(wall, 2),
           "env_steps_per_s": round(steps / wall, 2), "scenarios_per_hour": round(args.episodes / wall * 3600),
           "simulation_share": round(sim_s / wall, 3), "cpu_seconds": round(cpu, 2),
           "scenarios_per_cpu_hour": round(args.episodes / max(cpu, 1e-9) * 3600),
           "load_average": os.getloadavg()[0], "policy": args.policy,
           "config": None if args.config is None else str(args.config), "scenarios": names}
    con.print(f"{out['episodes']} episodes, {out['steps']} env steps in {out['seconds']} s: {out['env_steps_per_s']} "
              f"steps/s, {out['scenarios_per_hour']} scenarios/h; simulation {100 * out['simulation_share']:.0f} % "
              f"of the time (load average {out['load_average']:.1f}, policy {out['policy']})")
    con.print(f"{args.episodes} episodes in {cpu:.1f} CPU s -> {out['scenarios_per_cpu_hour']:,} scenarios per "
              f"CPU-hour (one env process, no learner{', parts timed' if args.profile else ''})")
    if args.profile:
        stats = pstats.Stats(prof).stats  # type: ignore[attr-defined]
        total = sum(v[2] for v in stats.values())  # own time of every function = the profiled CPU
        cum: dict[tuple[str, str], float] = {}
        for (file, _, fn), v in stats.items():
            for _, suffix, name in PARTS:
                if fn == name and file.endswith(suffix):
                    cum[(suffix, name)] = cum.get((suffix, name), 0.0) + v[3]
        profiled = {label: cum.get((suffix, name), 0.0) / max(total, 1e-9) for label, suffix, name in PARTS}
        timed = {label: timers.spent[label] / max(cpu, 1e-9) for label, *_ in TIMED}
        what = args.config or "the env's defaults"
        common.print_table(con, _shares_table(f"{args.episodes} episodes of {what} ({args.policy} actions), CPU shares under "
                                "cProfile", profiled))
        common.print_table(con, _shares_table(f"the same parts timed around each call, without cProfile ({args.episodes} "
                                "other episodes)", timed))
        out["profile"] = {"cprofile": {k.strip(): round(v, 4) for k, v in profiled.items()},
                          "timed": {k.strip(): round(v, 4) for k, v in timed.items()}}
    if args.out:
        write_json_atomic(Path(args.out), out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
