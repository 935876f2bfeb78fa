"""What the tests share: fixtures (``fixtures.py``, loaded by ``tests/conftest.py``), helpers of
the extractor's and the search's tests, planners written for tests (a second design in
``lane_keeper.py``, planted faults in ``fault_planners.py``) and recorded data (``data/``)."""
