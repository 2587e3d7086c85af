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

# The frame's set-up on the chip, shared by tests/chip/test_chip_frame.py and bench/chip.py:
# each channel drives the electrode model LOAD (Rs 500 ohm + Rp 20 kohm || C, tau 450 us), or
# JUMP (Rp 20 <-> 40 kohm every pulse after the two calibration pulses: a skin model's search each
# time) with the skin model SKIN.
LOAD = {"rs_ohm": 500, "rp_ohm": 20000, "tau_us": 450, "open": False}
JUMP = {"cycle": [LOAD, dict(LOAD, rp_ohm=40000)], "lead": 2}
SKIN = (500, 36045, 14000)  # rs_ohm, beta_q16 (0.55), cp_pf (as bench/core_step.py)

# On a board made by make_board(): a Stimulator `s` of n channels at rate Hz in `mode`, every
# channel calibrated at 1000 uA x t0 us (the soft t_max raised to t0 where the boot default,
# which keeps room for a skin model, is lower), the skin model set if asked, armed, outputs set.
FRAME_SETUP = """
s = stim.Stimulator(b, board_rp2.Clock(), cfg, {n}, {rate})
reps = []
if {t0} > s.lim[3]:  # the boot default keeps room for a skin model; without one t_max may go higher
    reps.append(hp.cmd_set_limits(bytearray(64), s.lim[0], s.lim[1], s.lim[2], {t0}, s.lim[4]))
reps += [hp.cmd_set_mode(bytearray(64), {mode}), hp.cmd_calibrate(bytearray(64), hp.CH_ALL, 1000, {t0}, -1670, 186000)]
if {skin}:
    reps.append(hp.cmd_set_skin(bytearray(64), hp.CH_ALL, {skin_args}))
reps.append(hp.cmd_arm(bytearray(64), hp.CH_ALL))
for rep in reps:
    assert s.handle(rep, time.ticks_us()) == hp.RES_OK, rep[0]
s.sync_outputs()
"""


def setup_script(n: int, rate: int, mode: int, t0: int, skin: bool = False) -> str:
    """FRAME_SETUP for these settings."""
    return FRAME_SETUP.format(n=n, rate=rate, mode=mode, t0=t0, skin=bool(skin),
                              skin_args=", ".join(map(str, SKIN)) if skin else "")


def put_loads(chip, n: int, skin: bool = False) -> None:
    """LOAD (JUMP with a skin model) on channels 0..n-1."""
    for k in range(n):
        chip.host.call("load", ch=k, load=JUMP if skin else LOAD)


def frame_setup(chip, cfg, n: int, rate: int, mode: int, t0: int, skin: bool = False) -> str:
    """Make the board (n channels), put the loads on, and return setup_script(...): the
    caller appends its own frames and runs it (one board per booted chip: each takes a DMA
    channel)."""
    make_board(chip, cfg, n_channels=n)
    put_loads(chip, n, skin)
    return setup_script(n, rate, mode, t0, skin)

# After FRAME_SETUP: the CPU's work in each of {frames} frames (after {warm} warm-up frames),
# i.e. the frame (Stimulator.loop_us) minus the time the CPU idled in Board.wait() for a
# capture to end (the timing wrapper's own cost counts as work: an upper bound). Leaves
# `work` (array of emulated us) and `over` (the overruns, counted over the warm-up frames
# and one more pass of {frames} run back to back from the arming, calibration included).
CPU_WORK = """
s.run({warm} + {frames})
over = s.overruns
from array import array
idle = array('i', [0])
_w = s._wait
_t = time.ticks_us
_d = time.ticks_diff
def _timed():
    t0 = _t()
    _w()
    idle[0] += _d(_t(), t0)
s._wait = _timed
work = array('i', [0] * {frames})
for f in range({frames}):
    idle[0] = 0
    s.run(1)
    work[f] = s.loop_us - idle[0]
s._wait = _w
"""
