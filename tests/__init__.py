"""The test suite. ``tests/<package>/`` holds the tests of the package of that name
(``deft_gym/<package>/``, or the top-level ``agents/`` and ``extract/``), so a change's tests are
found by its path; ``tests/support/`` the
shared fixtures, helpers, test planners and recorded data; the top level the tests of the whole
house (``test_layout.py``: the layers; ``test_faults.py``: faults injected across the programs).

Every folder is a package (this ``__init__.py``): pytest puts the repository's root on
``sys.path``, test modules are imported by their dotted names (``tests.world.test_fast_paths``),
so two folders may hold test files of the same name, and helpers are imported from the root
(``from tests.support.fixtures import SCENARIOS``; planner classes as
``tests.support.lane_keeper:LaneKeeperPlanner``).
"""
