# symcal: `make demo` runs the bundled default calibration, `make test` runs the suite,
# `make test-fast` the suite without the tests marked slow (about 1 min of CPU; 26 s of
# wall time on 2 idle cores, 74 s at load average 3),
# `make docs` builds the documentation site into build/site (strict: a broken link, a
# page missing from the nav or a stale API name fails it).
# Each target creates .venv and installs what it needs.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
DEMO_DIR := build/demo
# The suite runs with one BLAS thread, symcal's own default around its passes (held there
# by threadpoolctl whatever the import order), for the tests' own numpy too.  OpenBLAS's
# threads made it 2.5x slower on 2 busy cores.
TEST_ENV := OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
# The suite runs on every core (pytest-xdist; `make test TEST_WORKERS=0` runs it in one
# process), the longest tests handed out first-come by work stealing.
TEST_WORKERS ?= auto
PYTEST := $(TEST_ENV) $(BIN)/python -m pytest -n $(TEST_WORKERS) --dist worksteal

.PHONY: demo test test-fast lint docs bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $@ $(VENV)/.installed

# the optional exact-Jacobian peers of `make bench` (JAX, pyceres, optimistix)
$(VENV)/.installed-bench: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[bench]"
	touch $@ $(VENV)/.installed

demo: $(VENV)/.installed
	$(BIN)/symcal simulate problems/scenarios/courier_platen.yaml -o $(DEMO_DIR)/courier.csv --seed 1
	$(BIN)/symcal solve problems/platen_self_calibration.yaml \
	  --data calibration=$(DEMO_DIR)/courier.calibration.csv \
	  --data flyby=$(DEMO_DIR)/courier.flyby.csv --out $(DEMO_DIR)/result

# Static checks run by `make test` before the suite: style and types.
lint: $(VENV)/.installed-test
	$(BIN)/ruff check symcal tests benchmarks
	$(BIN)/mypy

# The documentation (mkdocs.yml): docs/*.md, the examples' walkthroughs and ARCHITECTURE.md,
# with the API reference generated from the public API's docstrings (mkdocstrings).
docs: $(VENV)/.installed-test
	$(BIN)/mkdocs build --strict

test: lint docs
	$(PYTEST)

test-fast: $(VENV)/.installed-test
	$(PYTEST) -m "not slow"

bench: $(VENV)/.installed-bench
	$(BIN)/python benchmarks/run.py
	OPENBLAS_NUM_THREADS=1 $(BIN)/python benchmarks/nist_strd.py --out benchmarks/NIST.md

clean:
	rm -rf $(VENV) build
