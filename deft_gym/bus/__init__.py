"""The message bus: messages and topics, their encoding, timing noise and the bus itself.

- :mod:`.messages` - :class:`~.messages.Message`, topic roles, default topic names, schemas;
- :mod:`.codec` - JSON encoding of payloads that round-trips every float bit-exactly;
- :mod:`.jitter` - the timing-noise model (processing times, delays, drops, ordering), with its
  own RNG;
- :mod:`.bus` - the sim-clock event loop, :class:`~.bus.Node` (a module on the bus) and the
  timing supervisor.

Imports: :mod:`deft_gym.config` only (never the world, the modules or anything above).
"""
