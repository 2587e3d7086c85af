"""The device's pulse time on the LSL clock.

Every report carries the device's own time (`time_us`: its ticks_us at the
start of the frame, wrapping at 2**30 us). The host notes the LSL clock when it
reads each report. Arrival = device time mapped + a transport delay that is
never negative and jitters (USB polling, the OS, a busy host loop). So the
mapping is fitted to the *lower envelope* of (arrival - device time):

1. unwrap time_us into device seconds (a step back of less than 2**29 us is a
   report older than the previous one, not a wrap);
2. in each bin of BIN_S device seconds keep the report with the smallest
   arrival - device time (the least delayed one: the jitter only ever adds);
3. fit offset + drift * device_s through the minima of the closed bins of the
   last WINDOW_S seconds by least squares (numpy.polyfit); until three closed
   bins span MIN_SPAN_S the drift is taken as 0 and the offset is the smallest
   residual so far.

A sample's LSL timestamp = device_s + offset + drift * device_s. It is never the
arrival time: jitter that delays some reports moves the minimum of a bin only if
it delays every report in that bin. `residual_s` is the RMS distance of the bin
minima from the fitted line (what the mapping cannot explain: the spread of the
minimum delay plus any non-linear drift)."""

from __future__ import annotations

from collections import deque

WRAP_US = 1 << 30


class Unwrap:
    """time_us (mod 2**30) -> monotonic device microseconds since the first report."""

    def __init__(self):
        self.last: int | None = None
        self.total_us = 0

    def __call__(self, time_us: int) -> int:
        if self.last is not None:
            d = (time_us - self.last) % WRAP_US
            if d >= WRAP_US // 2:
                d -= WRAP_US  # an older report (e.g. an ack from before the last frame), not a wrap
            self.total_us += d
        self.last = time_us
        return self.total_us


class ClockMap:
    BIN_S = 1.0
    WINDOW_S = 120.0
    MIN_SPAN_S = 2.0

    def __init__(self, bin_s: float = BIN_S, window_s: float = WINDOW_S):
        self.bin_s = bin_s
        self.unwrap = Unwrap()
        self.bins: deque = deque(maxlen=max(2, int(window_s / bin_s)))  # (device_s, residual_s) minima
        self.cur_bin: int | None = None
        self.cur_min: tuple[float, float] | None = None
        self.offset_s = 0.0
        self.drift = 0.0  # seconds of LSL clock per device second, minus 1
        self.residual_s = 0.0
        self.n = 0
        self.late_sum_s = 0.0  # arrival after the mapped time, summed (what the mapping kept out)
        self.late_max_s = 0.0

    def add(self, time_us: int, arrival_s: float) -> float:
        """Note one report (its device time and the LSL clock when it was read);
        return its device time in device seconds."""
        dev_s = self.unwrap(time_us) / 1e6
        r = arrival_s - dev_s
        b = int(dev_s // self.bin_s)
        self.n += 1
        if self.cur_bin is None or b != self.cur_bin:
            if self.cur_min is not None:
                self.bins.append(self.cur_min)
            self.cur_bin, self.cur_min = b, (dev_s, r)
            self._fit()
        elif r < self.cur_min[1]:
            self.cur_min = (dev_s, r)
            self._fit()
        late = r - (self.offset_s + self.drift * dev_s)  # how much later than the line it arrived
        self.late_sum_s += late
        self.late_max_s = max(self.late_max_s, late)
        return dev_s

    def _fit(self) -> None:
        pts = list(self.bins)  # closed bins only: an open bin's minimum may still be a late report
        if len(pts) < 3 or pts[-1][0] - pts[0][0] < self.MIN_SPAN_S:
            self.drift = 0.0
            self.offset_s = min(p[1] for p in pts + [self.cur_min])
            self.residual_s = 0.0
            return
        import numpy as np

        x = np.array([p[0] for p in pts])
        y = np.array([p[1] for p in pts])
        x0 = x.mean()  # centred: a well-conditioned fit over hours
        slope, icept = np.polyfit(x - x0, y, 1)
        self.drift = float(slope)
        self.offset_s = float(icept - slope * x0)
        self.residual_s = float(np.sqrt(np.mean((y - (self.offset_s + self.drift * x)) ** 2)))

    def to_lsl(self, dev_s: float) -> float:
        """A device time (seconds, as `add` returned it) on the LSL clock."""
        return dev_s + self.offset_s + self.drift * dev_s

    def words(self) -> str:
        late = self.late_sum_s / self.n * 1e6 if self.n else 0.0
        return (f"offset_s={self.offset_s:.6f} drift_ppm={self.drift * 1e6:.2f} "
                f"residual_us={self.residual_s * 1e6:.1f} reports={self.n} "
                f"arrival_late_us_mean={late:.0f} arrival_late_us_max={self.late_max_s * 1e6:.0f}")


class VirtualClock:
    """The simulator's virtual clock (`steadytouch sim`): device time since the run
    started, placed at the LSL clock of the start (no arrival times to fit)."""

    def __init__(self, start_lsl_s: float):
        self.unwrap = Unwrap()
        self.start = start_lsl_s
        self.n = 0
        self.offset_s, self.drift, self.residual_s = start_lsl_s, 0.0, 0.0

    def add(self, time_us: int, arrival_s: float = 0.0) -> float:
        self.n += 1
        return self.unwrap(time_us) / 1e6

    def to_lsl(self, dev_s: float) -> float:
        return self.start + dev_s

    def words(self) -> str:
        return f"virtual start_s={self.start:.6f} reports={self.n}"
