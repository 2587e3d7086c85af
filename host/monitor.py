"""Live view of telemetry: per-channel state folded from reports, rendered as a
terminal screen (at most every `interval` seconds, so ingest never waits on
the screen); the window (`--plot`) is host/liveview.py."""

from __future__ import annotations

import hid_protocol as hp
import sensation_core as sc

from .liveview import LivePlot  # noqa: F401  (the window, for the CLI)
from .protocol import STOP_WORDS, Telemetry

_BOUND_WORDS = ((sc.ST_I_MIN, "I min"), (sc.ST_I_MAX, "I max"), (sc.ST_T_MIN, "T min"), (sc.ST_T_MAX, "T max"),
                (sc.ST_Q_MAX, "Q max"))


class MonitorState:
    def __init__(self):
        self.last: dict[int, Telemetry] = {}
        self.count: dict[int, int] = {}
        self.first_time: dict[int, int] = {}
        self.span_us: dict[int, int] = {}

    def add(self, t: Telemetry) -> None:
        ch = t.channel
        prev = self.last.get(ch)
        if prev is not None:
            self.span_us[ch] = self.span_us.get(ch, 0) + (t.time_us - prev.time_us) % (1 << 30)
        self.last[ch] = t
        self.count[ch] = self.count.get(ch, 0) + 1

    def rate_hz(self, ch: int) -> float:
        span = self.span_us.get(ch, 0)
        return (self.count[ch] - 1) * 1e6 / span if span else 0.0

    def render(self, url: str = "", lost: int = 0) -> str:
        head = f"steadytouch monitor  {url}   lost reports: {lost}"
        cols = (f"{'ch':>2} {'state':<24} {'I uA':>6} {'T us':>5} {'Vp mV':>7} {'Rp ohm':>7} {'tau us':>6} "
                f"{'mE uA2ms':>9} {'mQ target':>10} {'mQ meas':>10} {'err uC/kohm':>12} {'rate Hz':>7} {'bounds':<12}")
        lines = [head, cols, "-" * len(cols)]
        for ch in sorted(self.last):
            t = self.last[ch]
            state = STOP_WORDS.get(t.stop, f"stop {t.stop}")
            if t.flags & hp.FLAG_HELD:
                state += " (held)"
            err = (t.mq_last_fc_per_ohm - t.mq_target_fc_per_ohm) / 1e6 if t.i_ua else 0.0
            bounds = ",".join(w for b, w in _BOUND_WORDS if t.status & b)
            tau = f"{2 ** (t.ltau_q16 / 65536):.0f}" if t.ltau_q16 else "-"  # the skin's R Cp after the pulse
            lines.append(
                f"{ch:>2} {state:<24.24} {t.i_ua:>6} {t.t_us:>5} {t.vp_mv:>7} {t.rp_ohm:>7} {tau:>6} {t.me_ua2ms:>9} "
                f"{t.mq_target_fc_per_ohm / 1e6:>10.5f} {t.mq_last_fc_per_ohm / 1e6:>10.5f} {err:>12.2e} "
                f"{self.rate_hz(ch):>7.1f} {bounds:<12}")
        if self.last:
            any_t = next(iter(self.last.values()))
            lines.append(f"overruns {any_t.overruns}   loop {any_t.loop_us} us")
        return "\n".join(lines)
