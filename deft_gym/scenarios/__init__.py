"""Scenarios: the YAML description of a test scenario and variants generated from it.

- :mod:`.scenario` - the scenario schema (ego, destination, map, participants, lights),
  loading with one-line errors, and building the :class:`~deft_gym.world.world.World`;
- :mod:`.variants` - perturbed, cut-in and hard-brake variants of a scenario;
- :mod:`.generate` - procedural scenarios ``gen:<seed>`` (highway, intersection, U-turn
  families with traffic and static objects), held-out seeds disjoint from training ones.

Imports: :mod:`deft_gym.world` and :mod:`deft_gym.config` (never the bus, the modules or the
simulation).
"""
