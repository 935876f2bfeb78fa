# DeFT-Gym: `make demo` runs the main job end to end on a small budget, `make test` the test suite.
# Both create .venv on first use with Python 3.11 (and no other version), torch==2.13.0 (CPU) first
# so that pip never resolves a CUDA build, the ray extra, so the Ray backend's tests run too, and the
# export extra (OpenSCENARIO / CommonRoad export and their independent checkers) and the commonroad
# extra (CommonRoad's reactive planner), so their tests run.

PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
BROWSER_STAMP := $(VENV)/.browser

.PHONY: venv demo test test-slow test-browser browser test-foxglove foxglove bench lint clean check-python

venv: $(STAMP)

# Python 3.11 only: a clear error instead of a venv of another version
check-python:
	@command -v $(PYTHON) >/dev/null 2>&1 || { \
	  echo "error: DeFT-Gym needs Python 3.11, and '$(PYTHON)' was not found. Install it (Debian/Ubuntu:" \
	       "apt-get install python3.11 python3.11-venv; or pyenv install 3.11) or name it: make PYTHON=/path/to/python3.11" >&2; \
	  exit 2; }
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' || { \
	  echo "error: DeFT-Gym needs Python 3.11; '$(PYTHON)' is Python $$($(PYTHON) -c 'import platform; print(platform.python_version())')." \
	       "Run make PYTHON=/path/to/python3.11" >&2; \
	  exit 2; }
	@if [ -x $(PY) ] && ! $(PY) -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then \
	  echo "error: $(VENV) was made with Python $$($(PY) -c 'import platform; print(platform.python_version())'), not 3.11:" \
	       "remove it (make clean) and run make again" >&2; exit 2; fi

# the kernels record their C sources and the Python files they stand in for: an edit of either
# rebuilds them (a stale kernel is not loaded: deft_gym.files.checked_kernel)
KERNEL_SOURCES := deft_gym/planner/_lattice_c.c deft_gym/planner/lattice.py deft_gym/modules/_control_c.c \
                  deft_gym/modules/control.py deft_gym/record/_snapshot_c.c deft_gym/record/worker.py \
                  deft_gym/record/_tap_c.c deft_gym/record/recorder.py deft_gym/record/_format_c.c \
                  deft_gym/record/textformat.py deft_gym/record/_scene_c.c deft_gym/record/scene.py \
                  deft_gym/bus/_ros1_c.c deft_gym/bus/ros1.py

$(STAMP): pyproject.toml setup.py $(KERNEL_SOURCES) | check-python
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -qq --upgrade pip
	$(PY) -m pip install -qq torch==2.13.0
	$(PY) -m pip install -qq -e ".[dev,ray,commonroad,export]"
	$(PY) -c "import deft_gym, extract, agents" && touch $(STAMP)

demo: $(STAMP)
	$(PY) -m deft_gym.cli.demo --out runs/demo

test: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile

test-slow: $(STAMP)
	$(PY) -m pytest -q -n 2 -m slow

# the report checked in a real browser: Debian's chromium and chromedriver, selenium from PyPI
browser: $(BROWSER_STAMP)

$(BROWSER_STAMP): $(STAMP)
	command -v chromium >/dev/null && command -v chromedriver >/dev/null || \
	  { (apt-get update -qq && apt-get install -y -qq chromium chromium-driver) || \
	    { echo "error: could not install chromium and chromium-driver (apt-get, as root)" >&2; exit 2; }; }
	$(PY) -m pip install -qq "selenium>=4.20"
	touch $(BROWSER_STAMP)

test-browser: $(BROWSER_STAMP)
	$(PY) -m pytest -q -m slow tests/cli/test_scene_render_report.py -k browser

# the binary logs read by Foxglove's own ROS 1 libraries (Node.js, from the npm registry)
FOXGLOVE_STAMP := .foxglove/.installed
foxglove: $(FOXGLOVE_STAMP)

$(FOXGLOVE_STAMP):
	command -v npm >/dev/null || { echo "error: npm (Node.js) is needed for make foxglove" >&2; exit 2; }
	npm install --silent --no-save --prefix .foxglove @foxglove/rosmsg@5.0.5 \
	  @foxglove/rosmsg-serialization@2.0.4 tslib@2.9.1
	touch $(FOXGLOVE_STAMP)

test-foxglove: $(STAMP) $(FOXGLOVE_STAMP)
	$(PY) -m pytest -q -m slow tests/bus/test_ros1.py -k foxglove

bench: $(STAMP)
	$(PY) -m deft_gym.cli.bench --repeats 15 --out runs/bench.json

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) runs/demo build deft_gym/*/*.so .foxglove
