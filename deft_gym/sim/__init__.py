"""The simulation of one episode: world + ADS modules on the bus + recorder + episode oracle.

- :mod:`.simulation` - :class:`~.simulation.Simulation` wires a scenario's world to the modules
  on the bus, records the log and judges the outcome; :func:`~.simulation.run_episode`;
- :mod:`.oracles` - the episode oracle (collision, completed, timeout, stuck).

Imports everything below it (world, bus, record, planner, modules, scenarios), nothing above.
"""
