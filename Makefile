# Two commands on a fresh machine:
#   make demo   set up, then run the main job (writes outputs/demo/)
#   make test   set up, then lint and run the test suite
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test test-all lint bench-env clean

setup: $(STAMP)

# torch==2.13.0 first: it is the CPU build on this machine's disk; the package's range admits it.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e ".[dev]"
	touch $(STAMP)

demo: setup
	$(BIN)/seqtrojan demo --out outputs/demo

lint: setup
	$(BIN)/ruff check seqtrojan tests benchmarks
	$(BIN)/ruff format --check seqtrojan tests benchmarks

test: lint
	$(BIN)/python -m pytest -n 2 -m "not slow" -q

test-all: lint
	$(BIN)/python -m pytest -n 2 -q

bench-env: setup
	$(BIN)/python benchmarks/env_throughput.py

clean:
	rm -rf $(VENV) outputs .pytest_cache .ruff_cache
