"""Progress and state of a long command on the terminal: pulses, rate, stops, time
left, redrawn in place on stderr (a terminal only), and a summary at the end.

Time left comes from the command's length (`total_s`: record/monitor/arm --seconds) or,
for a command with an amount of work (sim, calibrate --interactive, selftest), from the
share done so far (`work(done, total)`): elapsed x (total - done) / done."""

from __future__ import annotations

import sys
import time

import hid_protocol as hp

from .protocol import STOP_WORDS, Telemetry


class Progress:
    def __init__(self, what: str, total_s: float = 0.0, stream=None, every_s: float = 0.5, clock=time.monotonic,
                 total_pulses: int = 0):
        self.what = what
        self.total_s = total_s
        self.total_pulses = total_pulses  # a command that delivers a known number of pulses: its time left
        self.out = stream or sys.stderr
        self.tty = bool(getattr(self.out, "isatty", lambda: False)())
        self.every_s = every_s
        self.clock = clock
        self.t0 = clock()
        self.last_show = 0.0
        self.pulses = 0
        self.first_us: dict[int, int] = {}
        self.count: dict[int, int] = {}
        self.span_us: dict[int, int] = {}
        self.pairs: dict[int, int] = {}
        self.min_gap_us: dict[int, int] = {}  # the frame period, as seen
        self.last_us: dict[int, int] = {}
        self.stops: dict[int, int] = {}
        self.latched = 0  # latched stops seen (a channel entering ELECTRODE OFF, Rp fault, ...)
        self.work_done = 0.0
        self.work_total = 0.0
        self.shown = False

    def work(self, done: float, total: float) -> None:
        """How much of a command's work is done (any unit), for its time left."""
        self.work_done, self.work_total = done, total

    def add(self, t: Telemetry) -> None:
        if t.i_ua:
            self.pulses += 1
            ch = t.channel
            if ch in self.last_us:
                gap_us = (t.time_us - self.last_us[ch]) % (1 << 30)
                if gap_us:
                    self.min_gap_us[ch] = min(gap_us, self.min_gap_us.get(ch, gap_us))
                if gap_us <= 3 * self.min_gap_us.get(ch, 0) // 2:  # the rate while stimulating, not across a pause
                    self.span_us[ch] = self.span_us.get(ch, 0) + gap_us
                    self.pairs[ch] = self.pairs.get(ch, 0) + 1
            self.last_us[ch] = t.time_us
            self.count[ch] = self.count.get(ch, 0) + 1
        if t.stop not in (hp.STOP_NONE, hp.STOP_IDLE):
            if t.stop >= hp.STOP_ELECTRODE_OFF and self.stops.get(t.channel) != t.stop:
                self.latched += 1
            self.stops[t.channel] = t.stop
        elif t.stop == hp.STOP_NONE:
            self.stops.pop(t.channel, None)

    def rate_hz(self) -> float:
        """Pulses per second per channel while stimulating (device clock; a gap longer than 1.5 frame
        periods, the shortest gap seen, is a pause and left out), averaged over the channels that pulsed."""
        r = [self.pairs[c] * 1e6 / s for c, s in self.span_us.items() if s]
        return sum(r) / len(r) if r else 0.0

    def state(self) -> str:
        if not self.stops:
            return "no stops"
        return "; ".join(f"ch{c} {STOP_WORDS.get(w, w)}" for c, w in sorted(self.stops.items()))

    def left(self) -> str:
        el = self.clock() - self.t0
        done, total = (self.pulses, self.total_pulses) if self.total_pulses else (self.work_done, self.work_total)
        if total:
            if done <= 0:
                return ", time left not known yet"
            return f", about {el * max(0.0, total - done) / done:.0f} s left"
        return f", {max(0.0, self.total_s - el):.0f} s left" if self.total_s else ", until Ctrl-C"

    def line(self, extra: str = "") -> str:
        el = self.clock() - self.t0
        left = self.left()
        return (f"{self.what}: {self.pulses} pulses, {self.rate_hz():.1f} Hz per channel, {self.state()}, "
                f"{el:.0f} s{left}" + (f", {extra}" if extra else ""))

    def tick(self, extra: str = "") -> None:
        """Redraw the status line (a terminal only, at most every every_s)."""
        now = self.clock()
        if self.tty and now - self.last_show >= self.every_s:
            self.last_show = now
            self.out.write("\r\x1b[K" + self.line(extra))
            self.out.flush()
            self.shown = True

    def clear(self) -> None:
        if self.shown:
            self.out.write("\r\x1b[K")
            self.out.flush()
            self.shown = False

    def summary(self, extra: str = "") -> str:
        self.clear()
        el = self.clock() - self.t0
        chans = len(self.count)
        latched = f"; latched stops seen: {self.latched}" if self.latched else ""
        return (f"{self.what}: {self.pulses} pulses on {chans} channel(s) in {el:.1f} s "
                f"({self.rate_hz():.1f} Hz per channel); {self.state()}{latched}" + (f"; {extra}" if extra else ""))


class Watch:
    """A Device whose reports also feed a Progress and redraw its line: for commands whose
    pulses are read by another module's loop (the guided session, the self-test).
    Everything else is the device's own."""

    def __init__(self, dev, prog: Progress, extra=lambda: ""):
        self._dev, self._prog, self._extra = dev, prog, extra

    def __getattr__(self, name):
        return getattr(self._dev, name)

    def read(self, *a, **kw):
        rep = self._dev.read(*a, **kw)
        if isinstance(rep, Telemetry):
            self._prog.add(rep)
        self._prog.tick(self._extra())
        return rep
