"""Recording: every bus message to an MCAP log, and the truth file of what the planner consumed.

- :mod:`.recorder` - :class:`~.recorder.McapRecorder` (in-process or in a recorder process), the
  truth file, the recorder mode of pool workers;
- :mod:`.worker` - the recorder process and the batch framing it reads;
- ``_snapshot_c`` - optional compiled payload snapshots (pickle without it).

Imports: :mod:`deft_gym.bus` (messages, codec), :mod:`deft_gym.config` and :mod:`deft_gym.files`.
"""
