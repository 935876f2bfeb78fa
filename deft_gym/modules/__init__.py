"""The ADS modules as bus nodes, modelled on Apollo's: routing, localization, perception,
traffic-light perception, prediction, planning and control."""
