"""The adversaries and their evaluation: RL training (``train``, ``config``), the search
baselines (``search``, ``mutation``: Decictor-GA, Random-delta, Random) and the comparison at an
equal budget (``evaluate``, ``stats``, ``eval_report``)."""
