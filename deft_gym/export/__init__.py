"""Failures that travel: an episode (scenario + log + outcome) in standard formats, and back.

- :mod:`.episode` - what an export needs of an episode: the map, the ego and every participant
  with its size and what it did at every world step (the log's episode simulated again with its
  jitter seed and checked against the log's ground truth, or the log's own samples), the light
  plan, the outcome and the failure; from a log, an episode folder or a scenario YAML;
- :mod:`.network` - the road map as roads, lanes and junctions in the export frame (y and
  headings negated: right-hand traffic with y up, as ``deft-gym render`` and Foxglove draw it);
- :mod:`.opendrive` - ASAM OpenDRIVE 1.7 (``.xodr``) with ``scenariogeneration``;
- :mod:`.openscenario` - ASAM OpenSCENARIO 1.2 (``.xosc``) with ``scenariogeneration``, and its
  reader;
- :mod:`.commonroad` - CommonRoad XML (``.cr.xml``, 2020a) with ``commonroad-io``: lanelets,
  obstacles, traffic lights, the ego's planning problem, and its reader; the drivability
  checker's collision test;
- :mod:`.roundtrip` - an exported file back to a scenario YAML whose participants replay what
  they did;
- :mod:`.checks` - the independent checks: ASAM's schemas and quality checkers;
- :mod:`.failures` - the failures of a run, evaluation or training folder and their export.

The third-party packages (the ``export`` extra: ``pip install 'deft-gym[export]'``) are imported
inside the functions that use them. Formats, mappings and losses: docs/interop.md.
"""
