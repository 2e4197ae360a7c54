# jaxcal — every target sets up .venv/ on its own when needed.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export JAX_PLATFORMS ?= cpu

.PHONY: setup install test test-all lint format train validate bench-engine clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: setup

test: $(STAMP)
	$(BIN)/python -m pytest tests

test-all: $(STAMP)
	$(BIN)/python -m pytest tests -m ''

lint: $(STAMP)
	$(BIN)/ruff check jaxcal tests experiments
	$(BIN)/ruff format --check jaxcal tests experiments

format: $(STAMP)
	$(BIN)/ruff format jaxcal tests experiments
	$(BIN)/ruff check --fix jaxcal tests experiments

# The main job: generates data/cmapss.h5 if missing, fits D, trains CLAC, scores test units.
train: $(STAMP)
	$(BIN)/python -m jaxcal.train dataset=cmapss

validate: $(STAMP)
	$(BIN)/python -m jaxcal.physics.validate
	$(BIN)/python -m jaxcal.physics.validate --engine agtf30

bench-engine: $(STAMP)
	$(BIN)/python -m jaxcal.bench engine --out results/engine/bench_engine.json

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
