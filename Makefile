# svrobs: `make run` serves the embedded stack, `make test` runs the whole suite.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install lint run test test-core test-service test-integration test-faults bench clean

# The integration and PostgreSQL tests use the machine's PostgreSQL and Redis (as
# .ci/run does); `make test SVROBS_TEST_DATABASE_URL= SVROBS_TEST_BROKER_URL=` skips them.
SVROBS_TEST_DATABASE_URL ?= postgresql+psycopg://postgres@127.0.0.1:5432/test
SVROBS_TEST_BROKER_URL ?= redis://127.0.0.1:6379/5
export SVROBS_TEST_DATABASE_URL SVROBS_TEST_BROKER_URL

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/lint-imports
	$(BIN)/mypy --strict svrobs_client
	$(BIN)/mypy

run: $(STAMP)
	$(BIN)/svrobs serve

test: $(STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider -n 2 --dist loadscope --ignore=tests/faults

test-core: $(STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider tests/core

test-service: $(STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider tests/service tests/fuzz

test-integration: $(STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider tests/integration

# worker kills, Redis/PostgreSQL restarts, API kill, two beats, a poison unit: real
# processes on private servers (initdb + redis-server on spare loopback ports)
test-faults: $(STAMP)
	SVROBS_FAULTS_REPORT=var/faults-report.json $(BIN)/python -m pytest -q -p no:cacheprovider \
		-m faults --durations=0 tests/faults

bench: $(STAMP)
	$(BIN)/python bench/estimators.py
	$(BIN)/python bench/cost.py

clean:
	rm -rf var .pytest_cache .hypothesis .mypy_cache
