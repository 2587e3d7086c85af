# steadytouch — one entry point for setup, tests, the main job and benchmarks.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: setup test run example bench mpy flash chip clean

## setup: create .venv and install the project with its pinned dev extras
setup: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else "steadytouch needs Python >= 3.10; set PYTHON=python3.11")'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[dev,lab,docs]'
	# the PIO assembler for the emulator tests; --no-deps: its deps would install fake micropython/board modules
	$(BIN)/python -m pip install --quiet --disable-pip-version-check --no-deps adafruit-circuitpython-pioasm==1.3.8
	@touch $@

## test: the whole suite (sets up first if needed), on every core: tests that share the emulated Pico or
##       LSL's network run in one worker (tests/conftest.py)
test: setup
	$(BIN)/python -m pytest -q -n auto --dist loadgroup

## run: the main job: the firmware in the MicroPython VM on the simulated peel test, telemetry on the host
run: setup
	$(BIN)/steadytouch sim peel --out out --overwrite  # (the run's own folder: replaced on every run)

## example: the paper's worked example through the core in the MicroPython VM
example: setup
	MICROPYPATH=shared $(BIN)/micropython firmware/worked_example.py

## mpy: compile firmware/ and shared/ for the RP2040 into build/device
mpy: setup
	$(BIN)/steadytouch flash --build-only --build-dir build/device

## flash: compile, deploy to a Pico over its serial REPL with the pinned USB libraries (offline), check it boots
##        and read the version back. Optional: PORT=/dev/ttyACM0 (or socket://127.0.0.1:N), LIB_DIR=folder with
##        the pinned usb-device sources, FLASH_ARGS=--online (fetch them once) or --dry-run
flash: setup
	$(BIN)/steadytouch flash --build-dir build/device $(if $(PORT),--port $(PORT)) $(if $(LIB_DIR),--lib-dir $(LIB_DIR)) $(FLASH_ARGS)

## chip: the real firmware and board layer on an emulated RP2040 (rp2040js; needs ../shared/emulator and Node >= 20): chip tests, then bench/chip.py
chip: setup
	$(BIN)/python -m pytest -q tests/chip
	$(BIN)/python bench/chip.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .hypothesis
