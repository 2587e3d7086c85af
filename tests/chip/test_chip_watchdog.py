"""The hardware watchdog on the emulated chip (rp2040js 1.4.1 models it; the host
turns its reset into BoardReset): the real loop feeds it every frame, and a frame
that stalls resets the board within WATCHDOG_MS of the last feed."""

import pytest

from .harness import BoardReset, make_board

LOOP = """
_feeder.deinit()  # from here only the loop feeds the watchdog
s = stim.Stimulator(b, board_rp2.Clock(), cfg, 1, 50, hp.KEEPALIVE_MAX_MS)  # no host here: the longest keep-alive
buf = bytearray(hp.REPORT_LEN)
for rep in (hp.cmd_calibrate(buf, hp.CH_ALL, 1000, 1000, -1670, 186000), hp.cmd_arm(bytearray(64), hp.CH_ALL)):
    assert s.handle(rep, time.ticks_us()) == hp.RES_OK
s.sync_outputs()
gc.collect()  # the set-up's garbage now: an automatic collection (~250 us) must not land in a timed frame
s.run({frames})
"""


def test_the_loop_feeds_the_watchdog_every_frame(chip, cfg):
    make_board(chip, cfg)
    chip.load(0, rp_ohm=10000)
    chip.exec(LOOP.format(frames=60))  # 1.2 s at 50 Hz: longer than WATCHDOG_MS, no reset
    r = chip.take()
    frames = r["feeds"][-60:]  # the last feed before the loop is the set-up's
    gaps = [b - a for a, b in zip(frames, frames[1:])]
    assert max(gaps) <= 20_000_000 + 100_000  # one feed a frame (20 ms)
    assert len(r["pulses"]) == 60


@pytest.mark.parametrize("stall", ["capture", "loop"])
def test_a_stalled_frame_resets_the_board_within_watchdog_ms(chip, cfg, stall):
    make_board(chip, cfg)
    chip.load(0, rp_ohm=10000)
    chip.exec(LOOP.format(frames=10))
    fed = chip.take()["feeds"]
    if stall == "capture":  # e.g. a DMA transfer that never ends: the frame hangs in the board's wait()
        code = "def _stuck():\n    while True:\n        pass\ns._wait = _stuck\ns.run()"
    else:  # the loop stops calling the frame
        code = "while True:\n    pass"
    with pytest.raises(BoardReset) as e:
        chip.exec(code, timeout_ms=5000)
    assert e.value.reason == "watchdog timeout"
    last_feed = (fed + e.value.reply["feeds"])[-1]
    since = e.value.reset_ns - last_feed
    assert 0 < since <= cfg.WATCHDOG_MS * 1_000_000
    assert since >= (cfg.WATCHDOG_MS - 20) * 1_000_000  # it was the watchdog's time-out, not something sooner
