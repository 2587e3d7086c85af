"""The two outlets (telemetry and markers), their layout and metadata, and the tap
that feeds them from a device's report stream (docs/lab.md has the layout)."""

from __future__ import annotations

import struct

import hid_protocol as hp
import sensation_core as sc

from ..protocol import RESULT_WORDS, Ack, ProtocolError, Telemetry, decode
from ..record import COLUMNS
from .clock import ClockMap

TELEMETRY_TYPE = "StimTelemetry"
MARKER_TYPE = "Markers"

# units of the columns whose name does not end in one (the project names units in names)
_NAMED_UNITS = {"seq": "count", "channel": "index", "status": "bits", "stop": "code", "mode": "code",
                "flags": "bits", "overruns": "count", "sent_status": "bits", "ltau_q16": "log2(us)*65536"}
# longest suffix first
_SUFFIX_UNITS = (("_fc_per_ohm", "fC/ohm"), ("_ua2ms", "uA^2*ms"), ("_ohm", "ohm"), ("_ua", "uA"), ("_us", "us"),
                 ("_mv", "mV"), ("_pc", "pC"), ("_ms", "ms"), ("_hz", "Hz"))


def unit(column: str) -> str:
    """The unit of a recording column (LSL's `unit` field of its channel)."""
    if column in _NAMED_UNITS:
        return _NAMED_UNITS[column]
    for suffix, u in _SUFFIX_UNITS:
        if column.endswith(suffix):
            return u
    raise KeyError(f"recording column {column!r} has no unit: name it with its unit (i_ua, t_us, ...) "
                   "or add it to host/lsl/streams.py")


STOP_REASONS = {hp.STOP_ELECTRODE_OFF: "electrode_off", hp.STOP_RP_FAULT: "rp_fault",
                hp.STOP_KEEPALIVE: "keepalive_lost", hp.STOP_LIMIT: "hard_limit", hp.STOP_INTERNAL: "firmware_error"}
MODE_NAMES = {sc.MODE_AKHTAR: "akhtar", sc.MODE_FAST: "fast", sc.MODE_OPEN_LOOP: "open",
              sc.MODE_CONSTANT_CHARGE: "charge", sc.MODE_CONSTANT_ENERGY: "energy",
              sc.MODE_PULSE_WIDTH_LINEAR: "pwlinear"}  # the CLI's words


def _ch_word(ch: int) -> str:
    return "all" if ch == hp.CH_ALL else str(ch)


def command_words(report: bytes) -> str | None:
    """The marker text of an OUT report the lab wants on its time line (arm, disarm,
    calibrate, mode, limits, skin); None for keep-alives and queries."""
    cmd, ch = report[hp.O_OUT_CMD], report[hp.O_OUT_CH]
    a = hp.O_ARG
    if cmd == hp.CMD_ARM:
        return f"arm ch={_ch_word(ch)}"
    if cmd == hp.CMD_DISARM:
        return f"disarm ch={_ch_word(ch)}"
    if cmd == hp.CMD_CALIBRATE:
        i0, t0, x, y = struct.unpack_from("<HHii", report, a)
        return f"calibrate ch={_ch_word(ch)} i0_ua={i0} t0_us={t0} x_star_ohm={x} y_star_pc={y}"
    if cmd == hp.CMD_SET_MODE:
        m, rate = report[a], report[a + 1]
        return f"mode {MODE_NAMES.get(m, m)} rate_hz={rate or 'unchanged'}"
    if cmd == hp.CMD_SET_LIMITS:
        i_min, i_max, t_min, t_max, q_max = struct.unpack_from("<HHHHi", report, a)
        return f"limits i_min_ua={i_min} i_max_ua={i_max} t_min_us={t_min} t_max_us={t_max} q_max_pc={q_max}"
    if cmd == hp.CMD_SET_SKIN:
        rs, beta, cp = struct.unpack_from("<Hii", report, a)
        return f"skin ch={_ch_word(ch)} rs_ohm={rs} beta_q16={beta} cp_pf={cp}"
    return None


def _meta_fields(meta: dict, keys) -> list[tuple[str, str]]:
    return [(k, str(meta[k])) for k in keys if k in meta]


LIMIT_KEYS = ("i_min_ua", "i_max_ua", "t_min_us", "t_max_us", "q_max_pc", "hard_i_max_ua", "hard_t_max_us",
              "hard_q_max_pc", "compliance_mv")
CAL_KEYS = ("i0_ua", "t0_us", "rp0_ohm", "x_star_ohm", "y_star_pc")
CLOCK_WORDS = ("device time_us (the frame's start on the device's clock) unwrapped, mapped onto the LSL clock by a "
               "least-squares line through the per-second minima of (arrival - device time); see docs/lab.md")


def calibrations(meta: dict, n_channels: int) -> list[dict]:
    """Per channel: I0, T0, Rp0, x*, y* from a recording's metadata (`chN_i0_ua`, ... or,
    for a simulation, one set for every channel); channels without one are left out."""
    out = []
    for ch in range(n_channels):
        c = {k: meta[f"ch{ch}_{k}"] for k in CAL_KEYS if f"ch{ch}_{k}" in meta}
        if not c and all(k in meta for k in ("i0_ua", "t0_us", "x_star_ohm", "y_star_pc")):
            c = {k: meta[k] for k in CAL_KEYS if k in meta}
        if c:
            c.setdefault("rp0_ohm", 0)  # a simulation streamed from its start: not measured yet (its rp0 marker has it)
            out.append({"index": ch, **c})
    return out


def telemetry_info(pylsl, meta: dict, n_channels: int, clock_words: str = CLOCK_WORDS):
    """The StimTelemetry stream: one int32 sample per pulse per channel, its channels
    the recording's CSV columns (label, unit), the session's metadata in <desc>."""
    serial = str(meta.get("serial", "unknown"))
    info = pylsl.StreamInfo("steadytouch telemetry", TELEMETRY_TYPE, len(COLUMNS), pylsl.IRREGULAR_RATE,
                            pylsl.cf_int32, f"steadytouch-{serial}-telemetry")
    d = info.desc()
    d.append_child_value("manufacturer", "steadytouch")
    chans = d.append_child("channels")
    for c in COLUMNS:
        e = chans.append_child("channel")
        e.append_child_value("label", c)
        e.append_child_value("unit", unit(c))
        e.append_child_value("type", "StimTelemetry")
    dev = d.append_child("device")
    for k, v in _meta_fields(meta, ("firmware", "board", "device", "scenario", "rate_hz")):
        dev.append_child_value(k, v)
    dev.append_child_value("serial", serial)
    dev.append_child_value("n_channels", str(n_channels))
    d.append_child_value("mode", str(meta.get("mode", "unknown")))
    lim = d.append_child("limits")
    for k, v in _meta_fields(meta, LIMIT_KEYS):
        lim.append_child_value(k, v)
    cal = d.append_child("calibration")
    cal.append_child_value("note", "rp0_ohm is measured on the first pulse after each arm (0: not yet); "
                                   "every measurement is also an `rp0` marker")
    for c in calibrations(meta, n_channels):
        e = cal.append_child("channel")
        for k, v in c.items():
            e.append_child_value(k, str(v))
    clk = d.append_child("clock")
    clk.append_child_value("timestamps", clock_words)
    return info


def marker_info(pylsl, meta: dict):
    serial = str(meta.get("serial", "unknown"))
    info = pylsl.StreamInfo("steadytouch markers", MARKER_TYPE, 1, pylsl.IRREGULAR_RATE, pylsl.cf_string,
                            f"steadytouch-{serial}-markers")
    d = info.desc()
    d.append_child_value("manufacturer", "steadytouch")
    d.append_child_value("serial", serial)
    d.append_child_value("events", "arm, disarm, calibrate, mode, limits, skin (acknowledged commands; "
                                   "'refused: why' appended otherwise), stop ch=N reason=R (latched stops, "
                                   "reason keepalive_lost for a silent host), rp0 ch=N rp0_ohm=R, clock (the fit, at the end)")
    return info


class LabStreams:
    """The two outlets. `sink` replaces pylsl's outlets in tests of the logic:
    an object with telemetry(values, ts) and marker(text, ts)."""

    def __init__(self, meta: dict, n_channels: int, pylsl=None, clock_words: str = CLOCK_WORDS):
        self.pylsl = pylsl
        self.tel = pylsl.StreamOutlet(telemetry_info(pylsl, meta, n_channels, clock_words))
        self.mark = pylsl.StreamOutlet(marker_info(pylsl, meta))
        self.samples = 0
        self.markers = 0

    def telemetry(self, values: list[int], ts: float) -> None:
        self.tel.push_sample(values, ts)
        self.samples += 1

    def marker(self, text: str, ts: float) -> None:
        self.mark.push_sample([text], ts)
        self.markers += 1

    def consumers(self) -> bool:
        """A recorder takes both streams (so the first markers, e.g. arm, are not lost)."""
        return self.tel.have_consumers() and self.mark.have_consumers()

    def close(self) -> None:
        self.tel = self.mark = None


class Feed:
    """Turns decoded reports into samples and markers on the LSL clock."""

    def __init__(self, streams, clock):
        self.s = streams
        self.clock = clock
        self.stop: dict[int, int] = {}
        self.cal_rp: dict[int, int] = {}  # channel -> its last calibration pulse's Rp, not yet confirmed
        self.pending: dict[int, list] = {}  # tag -> [(command, marker text)] of commands sent, until their ack
        self.samples = True  # False: markers only (a recording that has ended)

    def sent(self, report: bytes) -> None:
        words = command_words(report)
        if words is not None:
            self.pending.setdefault(report[hp.O_OUT_TAG], []).append((report[hp.O_OUT_CMD], words))

    def report(self, rep, arrival_s: float) -> None:
        ts = self.clock.to_lsl(self.clock.add(rep.time_us, arrival_s))
        if isinstance(rep, Telemetry):
            if self.samples:
                self.s.telemetry([getattr(rep, c) for c in COLUMNS], ts)
            r1 = self.cal_rp.pop(rep.channel, 0)
            if rep.flags & hp.FLAG_CALIBRATING and rep.rp_ohm > 0 and rep.i_ua > 0:
                rp0 = hp.cal_rp0(r1, rep.rp_ohm, rep.mode == sc.MODE_CONSTANT_ENERGY)  # Rp0 once two agree (as the device)
                if rp0:
                    self.s.marker(f"rp0 ch={rep.channel} rp0_ohm={rp0}", ts)
                else:
                    self.cal_rp[rep.channel] = rep.rp_ohm
            if rep.stop != self.stop.get(rep.channel) and rep.stop in STOP_REASONS:
                self.s.marker(f"stop ch={rep.channel} reason={STOP_REASONS[rep.stop]}", ts)
            self.stop[rep.channel] = rep.stop
        elif isinstance(rep, Ack):
            waiting = self.pending.get(rep.tag, [])
            k = next((k for k, (cmd, _) in enumerate(waiting) if cmd == rep.command), None)
            if k is not None:
                words = waiting.pop(k)[1]
                if not rep.ok:
                    words += " refused: " + RESULT_WORDS.get(rep.result, str(rep.result)).replace(" ", "_")
                self.s.marker(words, ts)

    def end(self) -> None:
        """The clock fit as a last marker (at the last report's time)."""
        if self.clock.n:
            last = self.clock.to_lsl(self.clock.unwrap.total_us / 1e6)
            self.s.marker("clock " + self.clock.words(), last)


class Tap:
    """A transport seen through: every IN report also goes to the LSL feed, stamped with
    the LSL clock at the moment it was read; every OUT report is noted for its marker."""

    def __init__(self, transport, feed: Feed | None, now):
        self.t = transport
        self.feed = feed
        self.now = now  # the LSL clock (pylsl.local_clock), injected

    def __getattr__(self, name):  # url, realtime, answer_s, ... of the transport
        return getattr(self.t, name)

    def read(self, timeout_s: float):
        raw = self.t.read(timeout_s)
        if raw is not None and self.feed is not None:
            arrival = self.now()
            try:
                rep = decode(raw)
            except ProtocolError:
                return raw  # the Device counts it as bad
            self.feed.report(rep, arrival)
        return raw

    def write(self, report: bytes) -> None:
        if self.feed is not None:
            self.feed.sent(report)
        self.t.write(report)

    def close(self) -> None:
        self.t.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def device_serial(transport, url: str) -> str:
    """The board's USB serial number (hidapi), else the one in the URL, else the URL itself."""
    dev = getattr(transport, "dev", None)
    try:
        s = dev.get_serial_number_string() if dev is not None else None
    except Exception:
        s = None
    if s:
        return s
    if url.startswith("hid://") and url.count("/") >= 3:
        return url.rsplit("/", 1)[1]
    return url  # a simulated or emulated board: its URL names it


def open_streams(meta: dict, n_channels: int, realtime: bool = True):
    """(LabStreams, Feed) with the right clock: fitted for a device in real time,
    virtual for a simulation on its own time line. LslMissing without pylsl."""
    from . import require

    pylsl = require()
    if realtime:
        clock = ClockMap()
        words = CLOCK_WORDS
    else:
        from .clock import VirtualClock

        clock = VirtualClock(pylsl.local_clock())
        words = ("the simulator's virtual device time since the run started, placed at the LSL clock of the start "
                 "(a simulation runs faster than real time)")
    streams = LabStreams(meta, n_channels, pylsl, words)
    return streams, Feed(streams, clock), pylsl
