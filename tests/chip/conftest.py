"""Fixtures of the chip tests: the real MicroPython firmware for the Pico on the
emulated RP2040 (rp2040js, pinned in tests/chip/package.json and its lock,
installed by npm into .cache/chip), with the project's device files compiled for
armv6m in the board's /lib. ../shared/emulator (firmware.uf2, boot ROM, runner)
is used in place; without it every chip test skips with one line."""

from __future__ import annotations

import pytest

from .harness import EMULATOR, HERE, NO_EMULATOR, ChipUnavailable, NoEmulator, load_cfg, make_board, start_host


def pytest_collection_modifyitems(config, items):
    """Without ../shared/emulator: one chip test reports the skip in one line, the rest are deselected."""
    if (EMULATOR / "firmware.uf2").exists():
        return
    chip = [it for it in items if HERE in it.path.parents]
    if not chip:
        return
    chip[0].add_marker(pytest.mark.skip(reason=NO_EMULATOR))
    rest = set(chip[1:])
    config.hook.pytest_deselected(items=chip[1:])
    items[:] = [it for it in items if it not in rest]


@pytest.fixture(scope="session")
def chip_host(mpy_cross):
    """The Node host with a flash image holding the device files (built once, cached by content)."""
    try:
        host = start_host(mpy_cross)
    except NoEmulator as e:
        pytest.skip(str(e))
    except ChipUnavailable as e:
        pytest.fail(str(e))
    try:
        yield host
    finally:
        host.close()


@pytest.fixture()
def chip(chip_host):
    """A freshly booted chip (the device files in /lib), no board constructed yet."""
    return chip_host.boot(chip_host.image)


@pytest.fixture(scope="module")
def board(chip_host, cfg):
    """One chip with the real board_rp2.Board (as `b` on the board) for a test module."""
    chip = chip_host.boot(chip_host.image)
    make_board(chip, cfg)
    return chip


@pytest.fixture()
def on_board(board):
    """The module's chip with its Board, every channel stopped and the host's records taken."""
    board.exec("b.stop_all()")
    board.take()
    return board


@pytest.fixture(scope="session")
def cfg():
    return load_cfg()
