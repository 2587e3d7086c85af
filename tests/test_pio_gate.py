"""The gate's PIO program (firmware/pio_gate.py, the code the board runs),
assembled with adafruit_pioasm and run cycle-exactly in rp2040-pio-emulator:
gate widths equal T at 50 Hz, a new width lands at the next frame, and no word
that reaches the state machine (0xFFFFFFFF, -1 truncated by put, 2**31 ...)
holds the gate high longer than HARD_T_MAX_US. The same program on the
emulated chip: tests/chip/test_chip_gate.py."""

import importlib
import sys
from collections import deque

import pytest

from conftest import FIRMWARE

import hid_protocol as hp


@pytest.fixture(scope="module")
def program():
    import fake_rp2

    fake_rp2.install()
    sys.path.insert(0, str(FIRMWARE))
    try:
        sys.modules.pop("pio_gate", None)
        gate = importlib.import_module("pio_gate")
        cfg = importlib.import_module("board_config")
    finally:
        sys.path.remove(str(FIRMWARE))
        sys.modules.pop("rp2", None)
        sys.modules.pop("pio_gate", None)
    import adafruit_pioasm

    prog = adafruit_pioasm.Program(gate.gate.pioasm)
    return gate, cfg, list(prog.assembled), prog.pio_kwargs


def run_frames(program, words, frame_us=20000, tail_us=0):
    """Push one word at the start of each frame (50 Hz by default); return the
    gate's high-run lengths and rising-edge times, both in microseconds."""
    from pioemu import State, emulate

    gate, _cfg, opcodes, kw = program
    per_us = gate.FREQ_HZ // 1000000
    frame = frame_us * per_us
    fifo = deque()
    total = frame * len(words) + tail_us * per_us
    highs, starts, cur, prev = [], [], 0, 0
    gen = emulate(
        opcodes,
        stop_when=lambda _op, st: st.clock >= total,
        initial_state=State(transmit_fifo=fifo),
        set_base=0,
        set_count=1,
        shift_isr_right=gate.gate.config["in_shiftdir"] == 1,
        wrap_target=kw["wrap_target"],
        wrap_top=kw["wrap"],
    )
    for _before, after in gen:
        if after.clock % frame == 1 and after.clock // frame < len(words):
            after.transmit_fifo.append(words[after.clock // frame] & 0xFFFFFFFF)
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
    assert all(h % per_us == 0 for h in highs), highs  # whole microseconds
    return [h // per_us for h in highs], [s / per_us for s in starts]


def test_program_shape(program):
    gate, cfg, opcodes, kw = program
    assert len(opcodes) <= 32 and gate.GATE_OVERHEAD_US == 2
    assert gate.T_MAX_US == cfg.HARD_T_MAX_US and gate.BOUND == cfg.HARD_T_MAX_US - 2
    # no delays: rp2040js (the emulated chip) does not time them
    assert all((op >> 8) & 0x1F == 0 for op in opcodes)


def test_widths_equal_t_at_50hz_and_changes_land_next_frame(program):
    gate = program[0]
    widths = [hp.T_FLOOR_US, 100, 700, 1000, 2000]
    highs, starts = run_frames(program, [t - gate.GATE_OVERHEAD_US for t in widths])
    assert highs == widths  # 0 us of error; each frame's word sets that frame's pulse
    assert all(0 <= s - k * 20000 <= 10 for k, s in enumerate(starts))


def test_the_longest_accepted_pulse_is_exact(program):
    gate, cfg = program[0], program[1]
    t = cfg.HARD_T_MAX_US
    highs, _ = run_frames(program, [t - gate.GATE_OVERHEAD_US, t - 1 - gate.GATE_OVERHEAD_US], frame_us=10000)
    assert highs == [t, t - 1]


@pytest.mark.parametrize("word", [0xFFFFFFFF, -1, 1 << 31, 0x7FFFFFFF, 8001, 0x10000 + 5])
def test_no_word_holds_the_gate_longer_than_the_hard_limit(program, word):
    """The stuck gate of issue 11: T = 1 used to push -1, i.e. 0xFFFFFFFF, i.e. 2**32 us high."""
    cfg = program[1]
    highs, _ = run_frames(program, [word], frame_us=cfg.HARD_T_MAX_US + 100)
    assert highs == [cfg.HARD_T_MAX_US]


def test_word_zero_is_the_shortest_pulse(program):
    highs, _ = run_frames(program, [0], frame_us=50)
    assert highs == [program[0].GATE_OVERHEAD_US]
