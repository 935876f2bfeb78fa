"""The world: the highway-env road network and everything on it, stepped in sim time.

- :mod:`.geometry` - lane geometry, reference lines, oriented boxes and their gaps [m, rad];
- :mod:`.interp` - scalar linear interpolation equal to ``np.interp`` bit for bit;
- :mod:`.road` - the fast road wrapper around highway-env's ``Road``;
- :mod:`.roadmap` - the lane graph the ADS sees (lanes, successors, neighbours, stop lines);
- :mod:`.participants` - static obstacles, scripted vehicles (timed waypoints), reactive
  vehicles (IDM/MOBIL);
- :mod:`.traffic_lights` - timed light plans;
- :mod:`.world` - the ego (driven only by control commands), stepping and collision checks.

Imports: numpy, shapely, highway-env and :mod:`deft_gym.config` only - never the bus, the
modules or anything above them.
"""
