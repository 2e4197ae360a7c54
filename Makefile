# jaxcal — every target sets up .venv/ on its own when needed.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export JAX_PLATFORMS ?= cpu

.PHONY: setup install test test-long test-all lint format train validate bench-engine bench battery paper npe-setup docs clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: setup

# The suite on $(TEST_WORKERS) pytest-xdist workers, one test file per worker at a time
# (module-scoped fixtures built once; tests/conftest.py hands out the longest files
# first). TEST_WORKERS=0 runs it in this process; `python -m pytest tests/<file>.py`
# runs one file without workers. The long studies (marked slow: each has a faster test
# of the same behaviour in `make test`) run in `make test-long`; `make test-all` runs
# both.
TEST_WORKERS ?= 2
XDIST := -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder

test: $(STAMP)
	$(BIN)/python -m pytest tests $(XDIST)

test-long: $(STAMP)
	$(BIN)/python -m pytest tests -m slow $(XDIST)

test-all: $(STAMP)
	$(BIN)/python -m pytest tests -m '' $(XDIST)

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
	$(BIN)/python -m jaxcal.validate
	$(BIN)/python -m jaxcal.validate --engine agtf30

bench-engine: $(STAMP)
	$(BIN)/python -m jaxcal.bench engine --out results/engine/bench_engine.json

# Every table and figure of the paper -> results/paper/REPORT.md (resumable; reuses
# data/*.h5 and runs/*). PRESET=quick: the same pipeline on tiny data in a few minutes
# (-> results/paper-quick); OUT=<dir> writes elsewhere; SKIP=LS,SAC leaves methods out.
PRESET ?= full
paper: $(STAMP)
	$(BIN)/python experiments/paper.py preset=$(PRESET) $(if $(OUT),out=$(OUT)) $(if $(SKIP),skip=$(SKIP))

# The NPE peer of the report (sbi, an optional extra): torch's CPU wheel first,
# pinned (as for bench), then sbi with the core's jax/numpy/scipy pinned. `make paper`
# runs the NPE steps when sbi imports and says how to install it when not.
NPE_STAMP := $(VENV)/.npe-installed
$(NPE_STAMP): $(STAMP)
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip freeze | grep -iE '^(jax|jaxlib|numpy|scipy|flax|optax)==' > $(VENV)/.npe-constraints
	$(BIN)/python -m pip install --quiet -c $(VENV)/.npe-constraints -e '.[npe]'
	touch $(NPE_STAMP)

npe-setup: $(NPE_STAMP)

# CPU throughput against peers (experiments/bench_cpu.py -> results/bench/bench_cpu.json).
# The peers are optional extras, installed here only: torch's CPU wheel first, pinned,
# because sbx-rl -> stable-baselines3 -> torch would otherwise pull a multi-GB CUDA
# build. BENCH_ARGS=--train also re-runs the ~12-minute training job.
BENCH_STAMP := $(VENV)/.bench-installed
$(BENCH_STAMP): $(STAMP)
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[bench]'
	touch $(BENCH_STAMP)

# ... and jaxcal.calibrate's first / repeat / new-process times (compile once:
# experiments/bench_compile.py -> results/bench/compile.json, ~30 min with the turbofan),
# and the policy's time to target on three models from unlabelled data (the default
# preset against the UKF, ~4 min -> results/bench/policy/results.json "time_to_target").
bench: $(BENCH_STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python experiments/bench_cpu.py $(BENCH_ARGS)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python experiments/bench_compile.py out=results/bench/compile.json
	OPENBLAS_NUM_THREADS=1 $(BIN)/python experiments/policy_any_model.py out=results/bench/policy data=data/bench_policy runs=runs/bench_policy

# The battery example (examples/battery): PyBaMM data, every calibrator, dynamax and
# PyBOP beside -> results/examples/battery/README.md. The extras are installed with
# the core's jax/numpy/flax/optax pinned (a constraints file of the installed versions).
EXAMPLES_STAMP := $(VENV)/.examples-installed
$(EXAMPLES_STAMP): $(STAMP)
	$(BIN)/python -m pip freeze | grep -iE '^(jax|jaxlib|numpy|flax|optax)==' > $(VENV)/.examples-constraints
	$(BIN)/python -m pip install --quiet -c $(VENV)/.examples-constraints -e '.[examples]'
	touch $(EXAMPLES_STAMP)

battery: $(EXAMPLES_STAMP)
	$(BIN)/python examples/battery/run.py $(BATTERY_ARGS)

# The documentation site (mkdocs.yml, docs/: the guide pages and the API reference
# generated from the docstrings) -> site/. Warnings are errors; offline; the suite runs
# the same build (tests/test_docs.py).
docs: $(STAMP)
	$(BIN)/python -m mkdocs build --strict --site-dir site

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
