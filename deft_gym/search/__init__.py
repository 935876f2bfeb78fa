"""Decictor's search support, shared by the RL adversary's env and the search baselines.

- :mod:`.trace` - the ego and participant trace of a run, cached reference runs, content keys;
- :mod:`.refpath` - the reference (optimal) path of a seed scenario;
- :mod:`.feasible` - non-invasive feasible areas: where an object may be added without
  blocking the optimal path;
- :mod:`.vehicles` - NPC vehicle trajectories that respect the feasible areas;
- :mod:`.nods` - the non-optimal-decision oracle (grid consistency) and path/behaviour feedback;
- :mod:`.context` - a seed scenario with its reference run, feasible areas and oracle;
- :mod:`.episode` - simulating a seed with added objects and judging the run.

Imports: the simulation and everything below it; never :mod:`deft_gym.envs` or ``agents``.
"""
