"""Pictures of episodes.

- :mod:`.episode` - plot and video of a recorded episode, drawn from its MCAP log alone
  (``deft-gym render``);
- :mod:`.plot` - :func:`~.plot.draw_map`, the road map of a live world.

Imports: the log's codec and messages, the road map (duck-typed), matplotlib, imageio.
"""
