"""Throughput of ``deft_gym/Adversary-v0`` in one process: env steps/s and scenarios/hour.

    python -m agents.bench_env [--episodes 14] [--scenarios left_turn,take_exit] [--policy random|noop]

Reports wall time split into simulation (``Simulation.advance``) and the env's own work
(placements, feasibility, observation, oracles), and the machine's load average (the machine is
shared: compare runs at similar load).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from deft_gym.envs.adversary import AdversaryEnv
from deft_gym.search.context import SEED_SCENARIOS


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m agents.bench_env", description=__doc__.split("\n\n")[0])
    p.add_argument("--episodes", type=int, default=14)
    p.add_argument("--scenarios", default=",".join(SEED_SCENARIOS))
    p.add_argument("--policy", choices=("random", "noop"), default="random")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    names = [s for s in args.scenarios.split(",") if s]
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
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
