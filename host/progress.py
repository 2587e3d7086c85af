"""Progress and state of a long command on the terminal: pulses, rate, stops, time
left, redrawn in place on stderr (a terminal only), and a summary at the end."""

from __future__ import annotations

import sys
import time

import hid_protocol as hp

from .protocol import STOP_WORDS, Telemetry


class Progress:
    def __init__(self, what: str, total_s: float = 0.0, stream=None, every_s: float = 0.5, clock=time.monotonic):
        self.what = what
        self.total_s = total_s
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
        self.last_us: dict[int, int] = {}
        self.stops: dict[int, int] = {}
        self.shown = False

    def add(self, t: Telemetry) -> None:
        if t.i_ua:
            self.pulses += 1
            ch = t.channel
            if ch in self.last_us:
                self.span_us[ch] = self.span_us.get(ch, 0) + (t.time_us - self.last_us[ch]) % (1 << 30)
            self.last_us[ch] = t.time_us
            self.count[ch] = self.count.get(ch, 0) + 1
        if t.stop not in (hp.STOP_NONE, hp.STOP_IDLE):
            self.stops[t.channel] = t.stop
        elif t.stop == hp.STOP_NONE:
            self.stops.pop(t.channel, None)

    def rate_hz(self) -> float:
        """Pulses per second per channel (device clock), over the channels that pulsed."""
        r = [(self.count[c] - 1) * 1e6 / s for c, s in self.span_us.items() if s]
        return sum(r) / len(r) if r else 0.0

    def state(self) -> str:
        if not self.stops:
            return "no stops"
        return "; ".join(f"ch{c} {STOP_WORDS.get(w, w)}" for c, w in sorted(self.stops.items()))

    def line(self, extra: str = "") -> str:
        el = self.clock() - self.t0
        left = f", {max(0.0, self.total_s - el):.0f} s left" if self.total_s else ", until Ctrl-C"
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
        return (f"{self.what}: {self.pulses} pulses on {chans} channel(s) in {el:.1f} s "
                f"({self.rate_hz():.1f} Hz per channel); {self.state()}" + (f"; {extra}" if extra else ""))
