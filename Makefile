# svrobs: `make run` serves the embedded stack, `make test` runs the whole suite.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install run test test-core test-service test-integration bench clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

run: $(STAMP)
	$(BIN)/svrobs serve

test: $(STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider

test-core: $(STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider tests/core

test-service: $(STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider tests/service tests/fuzz

test-integration: $(STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider tests/integration

bench: $(STAMP)
	$(BIN)/python bench/estimators.py
	$(BIN)/python bench/cost.py

clean:
	rm -rf var .pytest_cache .hypothesis
