"""Command-line programs of the simulation (each has ``--help``):

- ``python -m deft_gym.cli.run`` - run a scenario (reruns, logs, plots, video);
- ``python -m deft_gym.cli.calibrate`` - how many collision scenarios are flaky over reruns;
- ``python -m deft_gym.cli.bench`` - simulation speed;
- ``python -m deft_gym.cli.seeds`` - every seed scenario, a few reruns;
- ``python -m deft_gym.cli.digest`` - behaviour digests that prove a change neutral;
- ``python -m deft_gym.cli.generate`` - generated scenarios as YAML, optionally run once each.

The adversary, evaluation and robustness programs are in ``agents``; extraction is
``python -m extract``.
"""
