"""Throughput of ``deft_gym/Adversary-v0`` in one process: env steps/s and scenarios/hour.

    deft-gym bench-env [--episodes 14] [--scenarios left_turn take_exit] [--policy random|noop]

Reports wall time split into simulation (``Simulation.advance``) and the env's own work
(placements, feasibility, observation, oracles), and the machine's load average (the machine is
shared: compare runs at similar load).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from deft_gym.cli import common
from deft_gym.files import write_json_atomic


def main(argv: list[str] | None = None) -> int:
    p = common.parser("bench-env", "deft_gym.cli.bench_env", __doc__)
    p.add_argument("--episodes", type=common.positive_int, default=14, help="episodes to time")
    common.add_scenarios(p, help="seed scenarios (default: the seven seeds)")
    p.add_argument("--policy", choices=("random", "noop"), default="random", help="the adversary's actions")
    common.add_seed(p)
    common.add_out(p, None, help="also write the figures to this JSON file (default: none)", folder=False)
    common.add_output_flags(p)
    args = p.parse_args(argv)
    from deft_gym.envs.adversary import AdversaryEnv
    from deft_gym.search.context import SEED_SCENARIOS

    names = args.scenarios or list(SEED_SCENARIOS)
    env = AdversaryEnv(scenario=names)
    for n in names:  # build the references outside the timing
        env.reset(seed=args.seed, options={"scenario": n})
    env.action_space.seed(args.seed)
    steps, sim_s = 0, 0.0
    t0 = time.perf_counter()
    for ep in range(args.episodes):
        env.reset(seed=args.seed + ep, options={"scenario": names[ep % len(names)]})
        done = False
        while not done:
            a = env.action_space.sample() if args.policy == "random" else np.zeros(5, dtype=np.int64)
            _, _, done, _, _ = env.step(a)
            steps += 1
        sim_s += env.sim._wall
    wall = time.perf_counter() - t0
    out = {"episodes": args.episodes, "steps": steps, "seconds": round(wall, 2),
           "env_steps_per_s": round(steps / wall, 2), "scenarios_per_hour": round(args.episodes / wall * 3600),
           "simulation_share": round(sim_s / wall, 3), "load_average": os.getloadavg()[0], "policy": args.policy}
    con = common.console(args)
    con.print(f"{out['episodes']} episodes, {out['steps']} env steps in {out['seconds']} s: {out['env_steps_per_s']} "
              f"steps/s, {out['scenarios_per_hour']} scenarios/h; simulation {100 * out['simulation_share']:.0f} % "
              f"of the time (load average {out['load_average']:.1f}, policy {out['policy']})")
    if args.out:
        write_json_atomic(Path(args.out), out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
