"""Recording: every bus message to an MCAP log, and the truth file of what the planner consumed.

- :mod:`.recorder` - :class:`~.recorder.McapRecorder` (in-process or in a recorder process), the
  truth file, the recorder mode of pool workers;
- :mod:`.worker` - the recorder process and the batch framing it reads;
- :mod:`.scene` - the Foxglove scene topics; :mod:`.textformat` - their JSON text's
  ``template % args``, compiled in ``_format_c`` (Python's ``%`` without it);
- ``_snapshot_c`` - optional compiled payload snapshots (pickle without it).

Imports: :mod:`deft_gym.bus` (messages, codec), :mod:`deft_gym.config` and :mod:`deft_gym.files`.
"""

from __future__ import annotations

from pathlib import Path


def read_metadata(log: Path | str) -> dict[str, dict[str, str]]:
    """The metadata records of an MCAP log by name (``deft_gym.episode``, ``deft_gym.outcome``,
    ...); the reader's exception when the file is missing or not MCAP (callers decide what that
    means)."""
    from mcap.reader import make_reader

    with open(log, "rb") as f:
        return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
