# Two commands on a fresh machine:
#   make reproduce   set up, then run the main job: a small end-to-end reproduction (writes results/smoke/report.html)
#   make test        set up, then lint and run the test suite
# make docs builds the documentation site (mkdocs.yml, docs/) into site/, failing on any warning.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup reproduce reproduce-paper demo test test-all lint bench docs clean

setup: $(STAMP)

# torch==2.13.0 first: it is the CPU build on this machine's disk; the package's range admits it.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e ".[dev,docs]"
	touch $(STAMP)

reproduce: setup
	$(BIN)/seqtrojan reproduce --scale smoke --out results/smoke

reproduce-paper: setup
	$(BIN)/seqtrojan reproduce --scale paper --out results/paper

demo: setup
	$(BIN)/seqtrojan demo --out outputs/demo

lint: setup
	$(BIN)/ruff check seqtrojan tests benchmarks scripts
	$(BIN)/ruff format --check seqtrojan tests benchmarks scripts
	$(BIN)/mypy seqtrojan

test: lint
	$(BIN)/python -m pytest -n 2 -m "not slow" -q

test-all: lint
	$(BIN)/python -m pytest -n 2 -q

bench: setup
	$(BIN)/python benchmarks/env_throughput.py
	$(BIN)/python benchmarks/train_throughput.py

docs: setup
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict -d site

clean:
	rm -rf $(VENV) outputs results site .pytest_cache .ruff_cache .mypy_cache
