"""Pictures of episodes.

- :mod:`.plot` - :class:`~.plot.EpisodeTrace` (hooks a simulation) and its plot and video;
  :func:`~.plot.draw_map`.

Imports: the world and the simulation (duck-typed), matplotlib and highway-env's graphics.
"""
