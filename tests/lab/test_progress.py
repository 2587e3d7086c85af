"""The status line and summary of long commands (host/progress.py)."""

from __future__ import annotations

import io

import hid_protocol as hp

from steadytouch.progress import Progress
from steadytouch.protocol import Telemetry


class Tty(io.StringIO):
    def isatty(self):
        return True


def tel(seq, t_us, ch, stop=hp.STOP_NONE, i=1000):
    return Telemetry(seq, t_us, ch, 0, stop, 0 if stop else i, 1000, 3000, 30000, 10**6, 25000, 25000, 0, i, 1000,
                     0, 300, 0 if stop else hp.FLAG_ARMED, 50)


def test_status_line_and_summary():
    now = [100.0]
    out = Tty()
    p = Progress("record", total_s=60, stream=out, every_s=0.5, clock=lambda: now[0])
    seq = 0
    for f in range(101):  # 2 s at 50 Hz on two channels, the device wrapping its clock on the way
        for ch in range(2):
            stop = hp.STOP_ELECTRODE_OFF if ch == 1 and f >= 80 else hp.STOP_NONE
            p.add(tel(seq, ((1 << 30) - 1_000_000 + f * 20_000) % (1 << 30), ch, stop))
            seq += 1
    now[0] = 112.0
    p.tick("0 reports lost")
    line = out.getvalue()
    assert line.startswith("\r\x1b[K") and "181 pulses" in line and "50.0 Hz per channel" in line
    assert "ch1 ELECTRODE OFF (latched)" in line and "12 s, 48 s left" in line and "0 reports lost" in line
    p.tick("again")  # not yet due: nothing more
    assert out.getvalue() == line
    s = p.summary("0 reports lost")
    assert s == ("record: 181 pulses on 2 channel(s) in 12.0 s (50.0 Hz per channel); ch1 ELECTRODE OFF (latched); "
                 "latched stops seen: 1; 0 reports lost")
    assert out.getvalue().endswith("\r\x1b[K")  # the status line is cleared before the summary


def test_no_status_line_off_a_terminal():
    out = io.StringIO()
    p = Progress("monitor", stream=out, clock=lambda: 5.0)
    p.add(tel(0, 0, 0))
    p.tick()
    assert out.getvalue() == ""
    assert "until Ctrl-C" in p.line()


def test_time_left_from_the_work_done_and_the_rate_without_the_pauses():
    """sim, calibrate --interactive, selftest: time left = elapsed x (total - done) / done; a
    channel pulsing 50 Hz in bursts with pauses between them (disarmed) is 50 Hz, not less."""
    now = [0.0]
    p = Progress("calibrate", stream=io.StringIO(), clock=lambda: now[0])
    p.work(0, 22)
    assert p.line().endswith("0 s, time left not known yet")
    t_us, seq = 0, 0
    for burst in range(5):
        for k in range(10):
            p.add(tel(seq, t_us, 0))
            seq += 1
            t_us += 20_000
        t_us += 2_000_000  # 2 s disarmed: the person chooses
    now[0] = 30.0
    p.work(5, 22)
    assert p.rate_hz() == 50.0
    assert "50 pulses, 50.0 Hz per channel" in p.line() and "30 s, about 102 s left" in p.line()
    p.work(22, 22)
    assert "about 0 s left" in p.line()


class FakeDevice:
    def __init__(self, reps):
        self.reps = list(reps)
        self.lost = 3

    def read(self, timeout_s=1.0):
        return self.reps.pop(0) if self.reps else None


def test_watch_feeds_the_progress_from_another_modules_reads():
    from steadytouch.progress import Watch

    now = [0.0]
    out = Tty()
    p = Progress("selftest", stream=out, every_s=0, clock=lambda: now[0])
    w = Watch(FakeDevice([tel(0, 0, 0), None, tel(1, 20_000, 0, hp.STOP_ELECTRODE_OFF)]), p, lambda: "point 1 of 6")
    assert w.lost == 3  # the device's own attributes
    reps = [w.read(0.1) for _ in range(3)]
    assert reps[1] is None and reps[2].stop == hp.STOP_ELECTRODE_OFF
    assert p.pulses == 1 and p.latched == 1
    assert "selftest: 1 pulses" in out.getvalue() and "point 1 of 6" in out.getvalue()
