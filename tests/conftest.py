"""The fixtures every test may use live in ``tests/support/fixtures.py``."""

pytest_plugins = ["tests.support.fixtures"]
