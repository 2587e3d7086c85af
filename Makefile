# steadytouch — one entry point for setup, tests, the main job and benchmarks.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: setup test run bench clean

## setup: create .venv and install the project with its pinned dev extras
setup: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else "steadytouch needs Python >= 3.10; set PYTHON=python3.11")'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[dev]'
	@touch $@

## test: the whole suite (sets up first if needed)
test: setup
	$(BIN)/python -m pytest -q

## run: the main job
run: setup
	MICROPYPATH=shared $(BIN)/micropython firmware/worked_example.py

## bench: the benchmarks whose figures are in docs/performance.md
bench: setup
	$(BIN)/python bench/core_step.py
	$(BIN)/python bench/core_accuracy.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .hypothesis
