"""The command line: the ``deft-gym`` console script, the simulation's programs and the tools
(each has ``--help``; ``deft-gym <command>`` = ``python -m <module>``).

- :mod:`.main` - ``deft-gym``: names each command's module, imports it only when it runs;
- :mod:`.common` - the conventions every program shares (flags, errors, progress; layer 0);
- ``python -m deft_gym.cli.run`` - run a scenario (reruns, logs, plots, video);
- ``python -m deft_gym.cli.calibrate`` - how many collision scenarios are flaky over reruns;
- ``python -m deft_gym.cli.generate`` - generated scenarios as YAML, optionally run once each;
- ``python -m deft_gym.cli.bench`` - simulation speed;
- ``python -m deft_gym.cli.digest`` - behaviour digests that prove a change neutral;
- ``python -m deft_gym.cli.seeds`` - every seed scenario, a few reruns;
- ``python -m deft_gym.cli.render`` and ``python -m deft_gym.cli.report`` - pictures of
  episodes, the HTML page of a run folder;
- ``python -m deft_gym.cli.extract`` - ``python -m extract`` plus pictures;
- ``python -m deft_gym.cli.demo`` - the end-to-end demo (``make demo``);
- ``python -m deft_gym.cli.bench_env`` - the adversary env's throughput;
- ``python -m deft_gym.cli.bench_scale`` - a campaign at 1..N workers, local processes and Ray;
- ``python -m deft_gym.cli.standing`` - how long mutated runs stand with no light holding them.

The top layer: it may import every package (the demo runs them all). The adversary's programs
are in ``agents``, DeFT's experiments in :mod:`deft_gym.experiments`, the robustness campaign's
in :mod:`deft_gym.robustness.stress`; extraction is ``python -m extract``.
"""
