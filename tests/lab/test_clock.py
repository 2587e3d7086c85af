"""The device's pulse time on the LSL clock (host/lsl/clock.py): jitter added to the
arrival times does not reach the timestamps; wraps, drift and an offset do."""

from __future__ import annotations

import struct

import numpy as np
import pytest

import hid_protocol as hp

from steadytouch.lsl.clock import WRAP_US, ClockMap, Unwrap
from steadytouch.lsl.streams import Feed, Tap
from steadytouch.protocol import _TELEMETRY
from steadytouch.record import COLUMNS


def telemetry_report(seq, time_us, ch=0, stop=hp.STOP_NONE, flags=hp.FLAG_ARMED):
    b = bytearray(_TELEMETRY.pack(hp.REP_TELEMETRY, ch, 0, stop, seq, time_us, 1000, 1000, 30000, 29000, 10**6,
                                  25000, 25010, 0, 1000, 1000, 0, 500, flags, 50, 0, 0))
    return bytes(b + bytes(hp.REPORT_LEN - len(b)))


def ack_report(seq, time_us, cmd, tag, result=hp.RES_OK):
    b = bytearray(hp.REPORT_LEN)
    b[0] = hp.REP_ACK
    struct.pack_into("<II", b, hp.O_SEQ, seq, time_us)
    b[hp.O_CMD], b[hp.O_RESULT], b[hp.O_TAG] = cmd, result, tag
    return bytes(b)


class FakeTransport:
    """Reports in order; `now` is what the tap reads as the LSL clock at each arrival."""

    realtime = True

    def __init__(self, reports, arrivals):
        self.reports = list(reports)
        self.arrivals = list(arrivals)
        self.now = 0.0
        self.sent = []

    def read(self, timeout_s):
        if not self.reports:
            return None
        self.now = self.arrivals.pop(0)
        return self.reports.pop(0)

    def write(self, r):
        self.sent.append(r)


class Sink:
    def __init__(self):
        self.samples, self.stamps, self.markers = [], [], []

    def telemetry(self, values, ts):
        self.samples.append(values)
        self.stamps.append(ts)

    def marker(self, text, ts):
        self.markers.append((text, ts))


def run(jitter_s, seconds=60, rate_hz=50, drift_ppm=40.0, latency_s=0.0015, seed=3, start_us=WRAP_US - 3_000_000):
    """A device whose clock runs drift_ppm slow against the host's, its time_us wrapping
    3 s in; reports reach the host latency_s + jitter after the pulse."""
    rng = np.random.default_rng(seed)
    n = int(seconds * rate_hz)
    dev_us = start_us + np.arange(n) * (1_000_000 // rate_hz)
    true_host_s = 1000.0 + (dev_us - start_us) / 1e6 * (1 + drift_ppm * 1e-6)  # when each pulse happened
    arrivals = true_host_s + latency_s + jitter_s(rng, n)
    reps = [telemetry_report(k, int(t) % WRAP_US) for k, t in enumerate(dev_us)]
    t = FakeTransport(reps, arrivals)
    sink = Sink()
    tap = Tap(t, Feed(sink, ClockMap()), lambda: t.now)
    while tap.read(0.1) is not None:
        pass
    return np.array(sink.stamps), true_host_s, arrivals, tap.feed.clock


def test_jitter_on_arrival_does_not_reach_the_timestamps():
    none = lambda rng, n: np.zeros(n)  # noqa: E731
    # USB polling, a busy host loop: up to 8 ms late, 2 ms on average, never early
    heavy = lambda rng, n: np.minimum(rng.exponential(0.002, n), 0.008)  # noqa: E731
    ts0, true, arr0, c0 = run(none)
    ts1, _, arr1, c1 = run(heavy)
    settled = slice(5 * 50, None)  # after the first 5 s (the fit needs two bins)
    jitter_in = np.std(arr1[settled] - true[settled])
    jitter_out = np.std(ts1[settled] - true[settled])
    assert jitter_in > 1.5e-3  # what reached the host
    assert jitter_out < 0.05e-3  # what reached the timestamps: over 30x less
    assert np.max(np.abs(ts1[settled] - ts0[settled])) < 0.2e-3
    # the timestamps keep the device's own spacing (its 20 ms frames on the host's clock)
    steps = np.diff(ts1[settled])
    assert np.max(np.abs(steps - 0.02 * (1 + 40e-6))) < 0.1e-3  # refits move them by tens of us
    assert abs(c1.drift * 1e6 - 40.0) < 5.0  # the drift is found
    assert c1.residual_s < 0.2e-3
    # the timestamps are the pulse times, less the minimum latency (a constant no host can see)
    assert abs(np.median(ts1[settled] - true[settled]) - 1.5e-3) < 0.1e-3


def test_the_wrap_of_time_us_is_no_jump():
    ts, true, _, _ = run(lambda rng, n: np.zeros(n), seconds=8)
    assert np.all(np.diff(ts) > 0.019) and np.all(np.diff(ts) < 0.021)


def test_unwrap_takes_an_older_report_as_older_not_as_a_wrap():
    u = Unwrap()
    assert u(WRAP_US - 10) == 0
    assert u(5) == 15  # wrapped
    assert u(2) == 12  # an older report (an ack stamped before the frame)
    assert u(WRAP_US // 2 - 100) > 12  # less than half the wrap ahead: ahead


def test_markers_from_acks_and_stops_at_the_device_time():
    from steadytouch.protocol import Commands

    c = Commands()
    arm, cal = c.arm(), c.calibrate(1000, 1000, -1670, 186000, 0)
    reps = [ack_report(0, 1000, hp.CMD_CALIBRATE, cal[1]), ack_report(1, 2000, hp.CMD_ARM, arm[1]),
            telemetry_report(2, 30000, flags=hp.FLAG_ARMED | hp.FLAG_CALIBRATING),  # Rp0 once two agree
            telemetry_report(3, 40000, flags=hp.FLAG_ARMED | hp.FLAG_CALIBRATING),
            telemetry_report(4, 50000, stop=hp.STOP_ELECTRODE_OFF, flags=0),
            telemetry_report(5, 70000, stop=hp.STOP_ELECTRODE_OFF, flags=0),
            ack_report(6, 80000, hp.CMD_ARM, arm[1] ^ 1),  # an ack of something this host did not send
            telemetry_report(7, 90000, stop=hp.STOP_KEEPALIVE, flags=0)]
    t = FakeTransport(reps, [5.0 + k * 0.05 for k in range(len(reps))])
    sink = Sink()
    tap = Tap(t, Feed(sink, ClockMap()), lambda: t.now)
    tap.write(cal)
    tap.write(arm)
    while tap.read(0.1) is not None:
        pass
    texts = [m for m, _ in sink.markers]
    assert texts == ["calibrate ch=0 i0_ua=1000 t0_us=1000 x_star_ohm=-1670 y_star_pc=186000", "arm ch=all",
                     "rp0 ch=0 rp0_ohm=29000", "stop ch=0 reason=electrode_off", "stop ch=0 reason=keepalive_lost"]
    assert t.sent == [cal, arm]
    assert len(sink.samples) == 5 and all(len(s) == len(COLUMNS) for s in sink.samples)
    m = dict(sink.markers)
    assert m["rp0 ch=0 rp0_ohm=29000"] == pytest.approx(sink.stamps[1])  # at the second calibration pulse
    assert m["stop ch=0 reason=electrode_off"] == pytest.approx(sink.stamps[2])
    assert m["arm ch=all"] < m["rp0 ch=0 rp0_ohm=29000"] < m["stop ch=0 reason=electrode_off"]


def test_a_refused_command_is_marked_as_refused():
    from steadytouch.protocol import Commands

    arm = Commands().arm()
    t = FakeTransport([ack_report(0, 1000, hp.CMD_ARM, arm[1], hp.RES_NOT_CALIBRATED)], [1.0])
    sink = Sink()
    tap = Tap(t, Feed(sink, ClockMap()), lambda: t.now)
    tap.write(arm)
    tap.read(0.1)
    assert sink.markers[0][0].startswith("arm ch=all refused: not_calibrated")


@pytest.mark.parametrize("stop", sorted(set(range(hp.STOP_ELECTRODE_OFF, hp.STOP_INTERNAL + 1))))
def test_every_latched_stop_is_marked_once_with_its_reason(stop):
    """Each latched stop code of hid_protocol (3..7) has its reason word and is marked once, at the
    report that first carries it; a disarm by command is no stop marker (its ack is the disarm)."""
    from steadytouch.lsl.streams import STOP_REASONS

    assert stop in STOP_REASONS and STOP_REASONS[stop].replace("_", "").isalpha()
    reps = [telemetry_report(0, 20000, ch=1), telemetry_report(1, 40000, ch=1, stop=stop, flags=0),
            telemetry_report(2, 60000, ch=1, stop=stop, flags=0),
            telemetry_report(3, 80000, ch=0, stop=hp.STOP_DISARMED, flags=0)]
    t = FakeTransport(reps, [1.0, 1.02, 1.04, 1.06])
    sink = Sink()
    tap = Tap(t, Feed(sink, ClockMap()), lambda: t.now)
    while tap.read(0.1) is not None:
        pass
    assert [m for m, _ in sink.markers] == [f"stop ch=1 reason={STOP_REASONS[stop]}"]
    assert sink.markers[0][1] == pytest.approx(sink.stamps[1])
