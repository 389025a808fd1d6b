# The two set-up commands of the README: `make test` and `make demo`.
# Both create the virtual environment and install everything on a fresh machine.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: test lint demo bench clean install kernels cluster-test

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): pyproject.toml clients/python/pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[dev]' -e clients/python
	touch $(STAMP)

install: $(STAMP) kernels

# The estimator's numba kernels compiled ahead of time into estimator/compiled/ (a worker then
# runs without numba and LLVM, ~130 MB less each); nothing is compiled when they are up to date.
kernels: $(STAMP)
	$(BIN)/python -m estimator.compiled

lint: $(STAMP)
	$(BIN)/ruff check .

test: lint kernels
	$(BIN)/python -m pytest

# The quick registration table, then the service: start it, stream a rendered sequence
# over WebSocket with the Python client, print the trajectory error, stop it.
demo: $(STAMP) kernels
	$(BIN)/swarmvo bench registration --quick --out demo-output/registration
	$(BIN)/python benchmarks/demo_service.py --frames 60 --out demo-output/service

# Every benchmark (tables on stdout, JSON/PNG under benchmarks/results), one core each.
bench: $(STAMP) kernels
	$(BIN)/python -m pip install --quiet -e '.[bench]'
	OMP_NUM_THREADS=1 $(BIN)/swarmvo bench registration --out benchmarks/results/registration
	OMP_NUM_THREADS=1 $(BIN)/swarmvo bench frontend --out benchmarks/results/frontend
	OMP_NUM_THREADS=1 $(BIN)/swarmvo bench frontend --data ../shared/data/euroc_mh01_moving \
		--out benchmarks/results/frontend/euroc_mh01_moving
	OMP_NUM_THREADS=1 $(BIN)/swarmvo bench odometry --out benchmarks/results/odometry
	OMP_NUM_THREADS=1 $(BIN)/swarmvo bench backend --out benchmarks/results/backend
	OMP_NUM_THREADS=1 $(BIN)/swarmvo bench driving --out benchmarks/results/driving
	OMP_NUM_THREADS=1 $(BIN)/swarmvo bench perturbations --out benchmarks/results/perturbations \
		--compare benchmarks/results/perturbations/before/perturbations.json
	$(BIN)/python benchmarks/load_test.py

# The fleet on loopback: PostgreSQL, 3 replicas and nginx (Debian packages), robots streaming,
# a replica killed and restarted; the table of docs/fleet.md, JSON in benchmarks/results/cluster.
cluster-test: $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[postgres]'
	OMP_NUM_THREADS=1 $(BIN)/python benchmarks/cluster.py

clean:
	rm -rf $(VENV) demo-output .pytest_cache .ruff_cache
