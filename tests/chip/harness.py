"""The chip tests' harness is the product's emulated Pico (host/emu: the Node host,
its pinned rp2040js and the Python set-up), shared with the `emu://` transport so
there is one host. This module keeps the names the chip tests and bench/chip.py use."""

from pathlib import Path

from steadytouch.emu import (  # noqa: F401
    BOARD,
    CACHE,
    EMULATOR,
    FIRMWARE,
    HOST_ONLY,
    NO_EMULATOR,
    ROOT,
    RP2040JS,
    SHARED,
    BoardReset,
    Chip,
    ChipError,
    ChipUnavailable,
    Host,
    NoEmulator,
    device_files,
    install_rp2040js,
    load_cfg,
    make_board,
    start_host,
)

HERE = Path(__file__).resolve().parent  # tests/chip (conftest: which tests are chip tests)
