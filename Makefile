# telesurg — the two commands a newcomer needs: `make demo` and `make test` (`make test-fast`: unit tests).
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test test-fast lint typecheck pytest clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

## demo: the whole simulated teleop session with the rerun web viewer (Ctrl-C stops it)
demo: $(STAMP)
	$(BIN)/telesurg demo

## test: ruff, mypy (shared/, services/, tools/, gym/) and pytest
test: lint typecheck pytest

lint: $(STAMP)
	$(BIN)/ruff check shared services tools gym tests
	$(BIN)/ruff format --check shared services tools gym tests

# mypy checks the sources under their installed names (telesurg.shared, telesurg.services, telesurg.tools): a tree
# of links in the venv maps the user's folders under the telesurg namespace, as pyproject does.
typecheck: $(STAMP)
	mkdir -p $(VENV)/typecheck/telesurg
	ln -sfn ../../../shared $(VENV)/typecheck/telesurg/shared
	ln -sfn ../../../services $(VENV)/typecheck/telesurg/services
	ln -sfn ../../../tools $(VENV)/typecheck/telesurg/tools
	ln -sfn ../../../gym $(VENV)/typecheck/telesurg/gym
	MYPYPATH=$(VENV)/typecheck $(BIN)/mypy $(VENV)/typecheck/telesurg

# the unit tests on both cores (pytest-xdist), then the process tests one at a time: they run real
# 1 kHz sites that need the two cores. Both parts run; either failing fails the target.
pytest: $(STAMP)
	rc=0; \
	$(BIN)/pytest -m "not process" -n 2 || rc=$$?; \
	$(BIN)/pytest -m process || rc=$$?; \
	exit $$rc

## test-fast: the unit tests, no service processes and no slow simulations (under 90 s)
test-fast: $(STAMP)
	$(BIN)/pytest -q -m "not process and not slow" -n 2

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache
