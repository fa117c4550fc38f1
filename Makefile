# svrobs: `make run` serves the embedded stack, `make test` runs the whole suite.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# what running needs (`make run`), and the test extras on top (`make test`, `make lint`)
RUNTIME_STAMP := $(VENV)/.installed-runtime
TEST_STAMP := $(VENV)/.installed-test
# `make run PORT=8010 HOST=0.0.0.0` (default: SVROBS_API_PORT / SVROBS_API_HOST, 127.0.0.1:8000)
PORT ?=
HOST ?=

.PHONY: install install-runtime lint types run test test-core test-service test-integration test-faults bench clean

# The integration and PostgreSQL tests use the machine's PostgreSQL and Redis (as
# .ci/run does); `make test SVROBS_TEST_DATABASE_URL= SVROBS_TEST_BROKER_URL=` skips them.
SVROBS_TEST_DATABASE_URL ?= postgresql+psycopg://postgres@127.0.0.1:5432/test
SVROBS_TEST_BROKER_URL ?= redis://127.0.0.1:6379/5
export SVROBS_TEST_DATABASE_URL SVROBS_TEST_BROKER_URL

$(RUNTIME_STAMP): pyproject.toml
	@echo "svrobs: [1/2] creating the virtual environment $(VENV)"
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	@echo "svrobs: [2/2] installing svrobs and what it needs to run (pip's progress below)"
	$(BIN)/python -m pip install --disable-pip-version-check --progress-bar on -e .
	@touch $(RUNTIME_STAMP)

$(TEST_STAMP): $(RUNTIME_STAMP)
	@echo "svrobs: installing the test extras (pytest, playwright, scikit-learn, ...)"
	$(BIN)/python -m pip install --disable-pip-version-check --progress-bar on -e '.[test]'
	@touch $(TEST_STAMP)

install-runtime: $(RUNTIME_STAMP)

install: $(TEST_STAMP)

lint: $(TEST_STAMP) types
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/lint-imports

# mypy ([tool.mypy] in pyproject): strict on svrobs_client and svrobs_core, basic on
# the rest; every module passes, with no baseline
types: $(TEST_STAMP)
	$(BIN)/mypy --strict svrobs_client
	$(BIN)/mypy --strict svrobs_core
	$(BIN)/mypy

run: $(RUNTIME_STAMP)
	$(BIN)/svrobs serve $(if $(HOST),--host $(HOST)) $(if $(PORT),--port $(PORT))

# four pytest-xdist workers on two cores: the integration tests spend much of their
# time waiting on the processes they start (`make test TEST_WORKERS=3` to compare)
TEST_WORKERS ?= 4
test: $(TEST_STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider -n $(TEST_WORKERS) --dist loadscope --ignore=tests/faults \
		-m "not faults"

test-core: $(TEST_STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider tests/core

test-service: $(TEST_STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider tests/service tests/fuzz

test-integration: $(TEST_STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider tests/integration

# worker kills, Redis/PostgreSQL restarts, API kill, two beats, a poison unit, 50 stop
# cycles of `svrobs serve` (tests/faults/test_stop_cycles.py, the embedded stack): real
# processes on private servers (initdb + redis-server on spare loopback ports); and the
# integration tests marked `faults` (a killed worker's lease, a unit out of memory, a
# killed worker restarted by `svrobs serve`) on the machine's servers
test-faults: $(TEST_STAMP)
	SVROBS_FAULTS_REPORT=var/faults-report.json $(BIN)/python -m pytest -q -p no:cacheprovider \
		-m faults --durations=0 tests/faults \
		tests/integration/test_trust.py tests/integration/test_serve.py
	SVROBS_PROPERTY_EXAMPLES=2000 $(BIN)/python -m pytest -q -p no:cacheprovider \
		tests/core/test_property_specs.py

bench: $(TEST_STAMP)
	$(BIN)/python bench/estimators.py
	$(BIN)/python bench/cost.py

clean:
	rm -rf var .pytest_cache .hypothesis .mypy_cache
