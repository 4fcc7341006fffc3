# scandiff: every target installs what it needs first (idempotent: pip only runs when
# pyproject.toml changed since the last install).
# PYTHON: the first interpreter >= 3.11 among python3, python3.13, python3.12, python3.11
# (override: make test PYTHON=python3.12 VENV=.venv-3.12). VENV: where it installs.
PYTHON_CANDIDATES := python3 python3.13 python3.12 python3.11
PYTHON_IS_SUPPORTED := -c 'import sys; sys.exit(sys.version_info < (3, 11))'
PYTHON ?= $(firstword $(foreach candidate,$(PYTHON_CANDIDATES),$(shell \
	$(candidate) $(PYTHON_IS_SUPPORTED) >/dev/null 2>&1 && echo $(candidate))))
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
SHARED_DATA ?= ../shared/data

.PHONY: install run test test-slow test-all lint format bench bench-paper bench-origins bench-maps clean

$(BIN)/python:
	@if [ -z "$(PYTHON)" ] || ! $(PYTHON) $(PYTHON_IS_SUPPORTED) >/dev/null 2>&1; then \
	  echo "scandiff needs Python 3.11, 3.12 or 3.13, found: $$(for c in $(or $(PYTHON),$(PYTHON_CANDIDATES)); do \
	    v=$$($$c -c 'import platform; print(platform.python_version())' 2>/dev/null) \
	    && printf '%s %s; ' "$$c" "$$v" || printf '%s (none); ' "$$c"; done)" >&2; \
	  echo "install one of them, or name it: make $(MAKECMDGOALS) PYTHON=/path/to/python3.12" >&2; \
	  exit 1; \
	fi
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): pyproject.toml setup.py app/core/localise/_plane_kernel.c app/core/localise/_knn_kernel.c | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

run: install
	$(BIN)/scandiff serve

# TEST_PROCESSES: pytest-xdist processes of make test.  Three on the 2-core target: about a
# third of the suite's time is spent waiting (service processes starting, workers polled, a
# browser rendering), which a third process fills; each test file stays in one process, so
# module fixtures are made once (make test TEST_PROCESSES=0 runs it in this process alone).
TEST_PROCESSES ?= 3

test: install
	$(BIN)/python -m pytest -q -n $(TEST_PROCESSES) --dist loadfile

test-slow: install
	$(BIN)/python -m pytest -q -m slow; status=$$?; [ $$status -eq 0 ] || [ $$status -eq 5 ]

lint: install
	$(BIN)/ruff check app tests bench migrations
	$(BIN)/ruff format --check app tests bench migrations

format: install
	$(BIN)/ruff format app tests bench migrations
	$(BIN)/ruff check --fix app tests bench migrations

BENCH_STAMP := $(VENV)/.installed-bench

$(BENCH_STAMP): pyproject.toml | $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[dev,bench]'
	touch $(BENCH_STAMP)

bench-paper: $(BENCH_STAMP)
	$(BIN)/python -m bench.paper

# paper + scenes + visibility + per-site calibration (quick), then bench/perf.py: pipeline vs py4dgeo M3C2 and the cKDTree floor,
# ingest, service (~3 min; --large adds 5M points); M3C2 is skipped if py4dgeo is missing.
bench: $(BENCH_STAMP)
	OMP_NUM_THREADS=1 $(BIN)/python -m bench.paper --quick
	OMP_NUM_THREADS=1 $(BIN)/python -m bench.scenes --quick
	OMP_NUM_THREADS=1 $(BIN)/python -m bench.visibility --quick
	OMP_NUM_THREADS=1 $(BIN)/python -m bench.calibration --quick
	$(BIN)/python -m bench.perf
	$(BIN)/python -m bench.perf_round2
	$(BIN)/python -m bench.perf_1m
	$(BIN)/python -m bench.perf_scaling --json bench/results/scaling.json
	$(MAKE) bench-origins

# issue 15's multi-station and 1M-point targets (~25 min): merged 3-5-station surveys with
# nothing given and with their stations given (decisions, IoU, quiet regions), then what
# estimating the origins adds to a compare at 1M points a scan (CPU on one thread, and wall
# time on two threads against the true origins given).
bench-origins: $(BENCH_STAMP)
	OMP_NUM_THREADS=1 $(BIN)/python -m bench.merged_stations --seeds 1 --modes default,given --output bench/results/merged_stations.md
	OMP_NUM_THREADS=1 $(BIN)/python -m bench.origins_speed --kinds single,merged --against-given 3

# issue 29's moving-sensor maps (~5 min): handheld RGB-D, robot / MLS and terrestrial scenes with
# per-point truth, nothing given; prints the issue's targets PASS/FAIL (add --modes
# default,trajectory for the maps with their trajectories, --real for the real pairs).
bench-maps: $(BENCH_STAMP)
	OMP_NUM_THREADS=1 $(BIN)/python -m bench.moving_maps --output bench/results/moving_maps.md

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache *.egg-info
