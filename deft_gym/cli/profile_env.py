"""Where an adversary env process spends its CPU (the profile behind the training throughput).

    python -m deft_gym.cli.profile_env --config configs/train/adversary.yaml --episodes 60

Runs ``--episodes`` episodes of the training config's env (its placement, reward and recording
settings; failing episodes are replayed into MCAP logs and extracted as in training) on the seeds
and ``--generated`` robust generated scenarios, with random actions, under cProfile, and prints
the share of each part: the simulation (and its modules), the episode's end (oracles, recording,
extraction), the observation and the placement. Scenarios per CPU-hour are measured on a second,
unprofiled set of episodes, in which the same parts are also timed around each call (cProfile
inflates the many small Python calls and hides the C parts).
"""

from __future__ import annotations

import cProfile
import pstats
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from deft_gym.cli import common

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
    p = common.parser("profile-env", "deft_gym.cli.profile_env", __doc__)
    p.add_argument("--config", type=Path, default=Path("configs/train/adversary.yaml"),
                   help="training YAML whose env section is profiled (or a run's config.yaml)")
    p.add_argument("--episodes", type=common.positive_int, default=60, help="episodes profiled, and timed")
    p.add_argument("--generated", type=int, default=5, help="robust generated scenarios besides the seeds")
    common.add_seed(p, 0, "seed of the episodes and the random actions")
    common.add_output_flags(p)
    return p


def _episodes(env: Any, n: int, start: int) -> None:
    for ep in range(start, start + n):
        env.reset(seed=ep)
        done = False
        while not done:
            _, _, term, trunc, _ = env.step(env.action_space.sample())
            done = term or trunc


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    con = common.console(args)
    from deft_gym.config import ConfigError, load_mapping
    from deft_gym.envs.adversary import AdversaryEnv
    from deft_gym.search.context import SEED_SCENARIOS, robust_generated

    try:
        env_cfg = dict(load_mapping(args.config).get("env") or {})
    except (ConfigError, OSError) as err:
        return common.cli_error(f"--config {args.config}: {err}")
    names = sorted(SEED_SCENARIOS) + robust_generated(args.generated, 0)  # the order the figures were taken in
    with tempfile.TemporaryDirectory(prefix="profile_env_") as logs:  # the kept failures' logs
        env = AdversaryEnv(config={**env_cfg, "scenarios": names, "log_dir": logs})
        for name in names:  # contexts (reference runs, feasible areas) are built once per process
            env.reset(seed=0, options={"scenario": name})
        env.action_space.seed(args.seed)
        t0 = time.process_time()
        with _Timers() as timers:
            _episodes(env, args.episodes, args.seed + 10_000)
        cpu = time.process_time() - t0
        prof = cProfile.Profile(timer=time.process_time)
        prof.enable()
        _episodes(env, args.episodes, args.seed + 20_000)
        prof.disable()
    stats = pstats.Stats(prof).stats  # type: ignore[attr-defined]
    total = sum(v[2] for v in stats.values())  # own time of every function = the profiled CPU
    cum: dict[tuple[str, str], float] = {}
    for (file, _, fn), v in stats.items():
        for _, suffix, name in PARTS:
            if fn == name and file.endswith(suffix):
                cum[(suffix, name)] = cum.get((suffix, name), 0.0) + v[3]
    from rich.table import Table

    t = Table(title=f"{args.episodes} episodes of {args.config} (random actions), CPU shares under cProfile",
              title_justify="left")
    t.add_column("part")
    t.add_column("share", justify="right")
    for label, suffix, name in PARTS:
        t.add_row(label, f"{100 * cum.get((suffix, name), 0.0) / max(total, 1e-9):.1f} %")
    con.print(t)
    t = Table(title=f"the same parts timed around each call, without cProfile ({args.episodes} other episodes)",
              title_justify="left")
    t.add_column("part")
    t.add_column("share", justify="right")
    for label, *_ in TIMED:
        t.add_row(label, f"{100 * timers.spent[label] / max(cpu, 1e-9):.1f} %")
    con.print(t)
    con.print(f"unprofiled: {args.episodes} episodes in {cpu:.1f} CPU s -> "
              f"{args.episodes / max(cpu, 1e-9) * 3600:,.0f} scenarios per CPU-hour (one env process, no learner)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
