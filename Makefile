# scandiff: every target installs what it needs first (idempotent: pip only runs when
# pyproject.toml changed since the last install).
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
SHARED_DATA ?= ../shared/data

.PHONY: install run test test-slow test-all lint format bench bench-paper clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

run: install
	$(BIN)/scandiff serve

test: install
	$(BIN)/python -m pytest -q

test-slow: install
	$(BIN)/python -m pytest -q -m slow; status=$$?; [ $$status -eq 0 ] || [ $$status -eq 5 ]

lint: install
	$(BIN)/ruff check app tests bench migrations
	$(BIN)/ruff format --check app tests bench migrations

format: install
	$(BIN)/ruff format app tests bench migrations
	$(BIN)/ruff check --fix app tests bench migrations

bench-paper: install
	$(BIN)/python bench/paper.py

BENCH_STAMP := $(VENV)/.installed-bench

$(BENCH_STAMP): pyproject.toml | $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[dev,bench]'
	touch $(BENCH_STAMP)

# paper + scenes + visibility (quick), then bench/perf.py: pipeline vs py4dgeo M3C2 and the cKDTree floor,
# ingest, service (~3 min; --large adds 5M points); M3C2 is skipped if py4dgeo is missing.
bench: $(BENCH_STAMP)
	OMP_NUM_THREADS=1 $(BIN)/python bench/paper.py --quick
	OMP_NUM_THREADS=1 $(BIN)/python bench/scenes.py --quick
	OMP_NUM_THREADS=1 $(BIN)/python bench/visibility.py --quick
	$(BIN)/python bench/perf.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache *.egg-info
