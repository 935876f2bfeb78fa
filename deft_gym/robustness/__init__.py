"""ASTAA-style robustness testing on DeFT-Gym's bus.

One concept per module:

- :mod:`.spec` - the test specification derived from the message schemas (topics, fields, types,
  brittle fields);
- :mod:`.paths` - addressing fields inside payloads (``obstacles[*].x``);
- :mod:`.dictionary` - the exceptional (and likely-valid) values per field type;
- :mod:`.testcase` - interception policies, concrete instances and replayable test cases;
- :mod:`.interception` - applying policies live on the bus (interception and interleaving);
- :mod:`.monitors` - crash and hang monitors (supervisor with a watchdog, silence detection);
- :mod:`.expr` and :mod:`.mapquery` - the safe expression language of invariants and its map helpers;
- :mod:`.invariants` - safety invariants in YAML and their online monitor;
- :mod:`.offline` - the same invariants on a recorded log (MCAP);
- :mod:`.runner` - running one test case and classifying the result;
- :mod:`.generate` - random test cases from the specification and the dictionary;
- :mod:`.minimise` - delta debugging over message instances, then over fields;
- :mod:`.faults` - planted faults modelled on the paper's bugs (off by default);
- :mod:`.sanitize` and :mod:`.hardening` - sanitisation/consistency wrappers for the modules;
- :mod:`.campaign` - the campaign loop behind :mod:`.stress`;
- :mod:`.subsystem` - subsystem replay testing of the planner on DeFT-extracted frames;
- :mod:`.stress` - the command (``deft-gym stress``, ``python -m deft_gym.robustness.stress``):
  the campaign and its ``replay``, ``check``, ``spec``, ``compare`` and ``subsystem``
  subcommands. The package's library modules never import it.
"""
