"""DeFT's experiments: the programs that answer the research questions on this testbed, and
the tools they are built from.

- :mod:`.extract_eval` - RQ1-RQ3 on a scenario pool (``deft-gym extract-eval``): reproduction
  of planning outputs and failures by system reruns vs extracted module tests, and their cost;
- :mod:`.extract_report` - its report, tables and plots, re-rendered from the records;
- :mod:`.record` - record one episode, optionally with renamed topics, input headers or another
  planner (``deft-gym record``);
- :mod:`.planner_edits` - do the generated tests catch small planner edits?
  (``deft-gym planner-edits``);
- :mod:`.log_damage` - damage logs on purpose and check what the reader recovers
  (``deft-gym log-damage``).

Imports: the simulation, ``extract`` and everything below them; never ``agents`` or
:mod:`deft_gym.cli` (but :mod:`deft_gym.cli.common`). Not simulation code: outside the code
fingerprint (:data:`deft_gym.search.trace._NOT_SIMULATION_PACKAGES`).
"""
