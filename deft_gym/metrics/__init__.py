"""Driving-quality metrics of one episode, computed from its trace (the per-world-step record of
the ego and the participants, :class:`deft_gym.search.trace.Trace`) and the scenario's map, lights
and route, in nuPlan's and CommonRoad's vocabulary: at-fault collision, time to collision,
drivable-area and driving-direction compliance, red lights, progress, comfort, speed limit,
standstill, time headway (ISO 15622), and their weighted score in [0, 1] (``episode.py``); the oracles built on them that
the adversary's reward and the baselines' fitness can aim at (``oracle.py``). Not simulation
code: nothing of the simulation imports it, and ``code_fingerprint`` leaves it out
(docs/metrics.md)."""
