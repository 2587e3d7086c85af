"""The gate's PIO program (firmware/pio_gate.py, the code the board runs),
assembled with adafruit_pioasm and run cycle-exactly in rp2040-pio-emulator:
gate widths equal T at 50 Hz, and a new width lands at the next frame."""

import importlib
import sys
from collections import deque

import pytest

from conftest import FIRMWARE

FRAME_CYCLES = 20000  # 50 Hz at 1 MHz


@pytest.fixture(scope="module")
def program():
    import fake_rp2

    fake_rp2.install()
    sys.path.insert(0, str(FIRMWARE))
    try:
        sys.modules.pop("pio_gate", None)
        gate = importlib.import_module("pio_gate")
    finally:
        sys.path.remove(str(FIRMWARE))
        sys.modules.pop("rp2", None)
    import adafruit_pioasm

    prog = adafruit_pioasm.Program(gate.gate.pioasm)
    return gate, list(prog.assembled), prog.pio_kwargs


def run_frames(opcodes, kw, words):
    """Push one word at the start of each frame; return the gate's high-run lengths and starts."""
    from pioemu import State, emulate

    fifo = deque()
    total = FRAME_CYCLES * len(words)
    highs, starts, cur, prev = [], [], 0, 0
    gen = emulate(
        opcodes,
        stop_when=lambda _op, st: st.clock >= total,
        initial_state=State(transmit_fifo=fifo),
        set_base=0,
        set_count=1,
        wrap_target=kw["wrap_target"],
        wrap_top=kw["wrap"],
    )
    for before, after in gen:
        if after.clock % FRAME_CYCLES == 1 and after.clock // FRAME_CYCLES < len(words):
            after.transmit_fifo.append(words[after.clock // FRAME_CYCLES])
        level = after.pin_values & 1
        if level:
            if not prev:
                starts.append(after.clock)
            cur += 1
        elif prev:
            highs.append(cur)
            cur = 0
        prev = level
    if prev:
        highs.append(cur)
    return highs, starts


def test_program_text(program):
    gate, opcodes, kw = program
    assert len(opcodes) == 5 and gate.GATE_OVERHEAD_US == 2


def test_widths_equal_t_at_50hz_and_changes_land_next_frame(program):
    gate, opcodes, kw = program
    widths = [50, 100, 700, 1000, 2000]
    highs, starts = run_frames(opcodes, kw, [t - gate.GATE_OVERHEAD_US for t in widths])
    assert highs == widths  # 0 cycles of error; each frame's word sets that frame's pulse
    assert all(0 <= s - k * FRAME_CYCLES <= 5 for k, s in enumerate(starts))
