# DeFT-Gym: `make demo` runs the main job end to end on a small budget, `make test` the test suite.
# Both create .venv on first use (torch==2.13.0 first, so pip never resolves a CUDA build), with
# the ray extra, so the Ray backend's tests run too.

PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: venv demo test test-slow bench lint clean

venv: $(STAMP)

$(STAMP): pyproject.toml setup.py deft_gym/planner/_lattice_c.c deft_gym/modules/_control_c.c deft_gym/record/_snapshot_c.c
	test -x $(PY) || $(PYTHON) -m venv $(VENV) || python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e ".[dev,ray]"
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m deft_gym.cli.demo --out runs/demo/seeds
	@if [ -f agents/demo.py ]; then $(PY) -m agents.demo --out runs/demo; fi

test: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile

test-slow: $(STAMP)
	$(PY) -m pytest -q -n 2 -m slow

bench: $(STAMP)
	$(PY) -m deft_gym.cli.bench --repeats 15 --out runs/bench.json

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) runs/demo build deft_gym/*/*.so
