"""How long mutated runs stand still when no light holds them: the evidence for the stuck time.

    deft-gym standing --episodes 400 --generated 20 --stuck-time 25

Runs ``--episodes`` episodes of the training config's env (random placements, each episode's
actions drawn from its own seed) on the seeds and ``--generated`` robust generated scenarios, with
mutated runs called stuck after ``--stuck-time`` seconds of standing (default: the search's
``STUCK_TIME``). For each run it finds the stretches in which the ego stands (speed < 0.05 m/s)
and is not held by a light (:func:`deft_gym.sim.oracles.held_by_light`), and prints, per outcome,
the longest such stretch; then, for shorter stuck times T, how many runs a T-second rule would
have ended earlier, how many of those were failures (NoDS, ego-at-fault collisions) or completed
runs - findings a shorter rule would lose - and the simulated time it saves. Run it with a stuck
time longer than the one in use (25 s was the old one) to see what the one in use costs.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from deft_gym.cli import common

STANDING = 0.05  # [m/s] the ego stands
THRESHOLDS = (5.0, 8.0, 10.0, 12.0, 15.0, 20.0)  # [s] stuck times compared


def build_parser() -> common.Parser:
    p = common.parser("standing", "deft_gym.cli.standing", __doc__)
    p.add_argument("--config", type=Path, default=Path("configs/train/adversary.yaml"),
                   help="training YAML whose env section runs the episodes (default: configs/train/adversary.yaml)")
    p.add_argument("--episodes", type=common.positive_int, default=400, help="episodes (default: 400)")
    p.add_argument("--generated", type=int, default=20, help="robust generated scenarios besides the seeds "
                   "(default: 20)")
    p.add_argument("--stuck-time", type=float, default=None, dest="stuck_time",
                   help="standing [s] after which a mutated run is stuck (default: the search's STUCK_TIME)")
    common.add_seed(p, 0, "first episode's seed (default: 0)")
    common.add_output_flags(p)
    return p


def unheld_standing(trace: Any, roadmap: Any, lights: Any) -> list[tuple[float, float]]:
    """``(start, end)`` [s] of every stretch of a run's trace in which the ego stands and no light
    holds it."""
    from deft_gym.sim.oracles import held_by_light

    out: list[tuple[float, float]] = []
    start = end = None
    for tick, row in zip(trace.ticks, trace.ego):
        t = float(tick) * trace.world_dt
        standing = row[3] < STANDING
        if standing and not held_by_light(roadmap, lights, roadmap.locate(row[:2], float(row[2])), t):
            start = t if start is None else start
            end = t
        elif start is not None:
            out.append((start, end))
            start = None
    if start is not None:
        out.append((start, end))
    return out


def run(args: Any) -> list[dict[str, Any]]:
    import numpy as np

    import deft_gym.search.context as context
    from deft_gym.config import load_mapping
    from deft_gym.envs.adversary import AdversaryEnv

    if args.stuck_time is not None:
        context.STUCK_TIME = args.stuck_time  # read when each scenario's context is built
    env_cfg = dict(load_mapping(args.config).get("env") or {})
    names = list(context.SEED_SCENARIOS) + context.robust_generated(args.generated, 0)
    env = AdversaryEnv(config={**env_cfg, "scenarios": names})
    rows = []
    bar = common.Bar(args.episodes, "episodes", common.show_progress(args))
    for ep in range(args.seed, args.seed + args.episodes):
        env.reset(seed=ep)
        rng = np.random.default_rng(ep)
        done, info = False, {}
        while not done:
            _, _, done, _, info = env.step(np.array([rng.integers(n) for n in env.action_space.nvec]))
        stretches = unheld_standing(env.recorder.trace(), env.ctx.roadmap, env.sim.world.lights)
        rows.append({"scenario": info["scenario"], "outcome": info["outcome"], "failure": info["failure"],
                     "sim_time": info["sim_time"], "stretches": stretches})
        bar.update()
    bar.close()
    return rows


def shorter_rule(rows: list[dict[str, Any]], t_stuck: float) -> dict[str, float]:
    """What a stuck time of ``t_stuck`` [s] would have changed: runs ended earlier, of them
    failures and completed runs, and the share of simulated time saved."""
    ended = failures = completed = 0
    saved = 0.0
    for r in rows:
        long = [s for s, e in r["stretches"] if e - s >= t_stuck - 1e-6]
        cut = long[0] + t_stuck if long else None
        if cut is None or cut >= r["sim_time"] - 1e-6:
            continue
        ended += 1
        saved += r["sim_time"] - cut
        failures += bool(r["failure"])
        completed += r["outcome"] == "completed"
    total = sum(r["sim_time"] for r in rows) or 1.0
    return {"ended": ended, "failures": failures, "completed": completed, "saved": saved / total}


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    con = common.console(args)
    from rich.table import Table

    rows = run(args)
    by_outcome = Table(title=f"{len(rows)} episodes: longest standing not held by a light (s)")
    for col in ("outcome", "episodes", "longest", "failures"):
        by_outcome.add_column(col, justify="right")
    for outcome in sorted({r["outcome"] for r in rows}):
        rs = [r for r in rows if r["outcome"] == outcome]
        longest = max((e - s for r in rs for s, e in r["stretches"]), default=0.0)
        by_outcome.add_row(outcome, str(len(rs)), f"{longest:.2f}", str(sum(1 for r in rs if r["failure"])))
    rules = Table(title="a shorter stuck time")
    for col in ("stuck time (s)", "runs ended earlier", "of them failures", "of them completed", "simulated time saved"):
        rules.add_column(col, justify="right")
    for t_stuck in THRESHOLDS:
        c = shorter_rule(rows, t_stuck)
        rules.add_row(f"{t_stuck:g}", str(c["ended"]), str(c["failures"]), str(c["completed"]), f"{c['saved']:.1%}")
    common.print_table(con, by_outcome)
    common.print_table(con, rules)
    return 0


if __name__ == "__main__":
    sys.exit(main())
