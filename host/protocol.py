"""Host side of the HID protocol: decode IN reports, build OUT reports.

Offsets and codes come from the shared module `hid_protocol` (the firmware's
own), so host and device cannot disagree about the layout.
"""

from __future__ import annotations

import operator
import struct
from dataclasses import dataclass

import decay
import hid_protocol as hp
import sensation_core as sc

RESULT_WORDS = {
    hp.RES_OK: "ok",
    hp.RES_BAD_CRC: "bad CRC",
    hp.RES_UNKNOWN_COMMAND: "unknown command",
    hp.RES_BAD_CHANNEL: "no such channel",
    hp.RES_OUT_OF_RANGE: "value out of range",
    hp.RES_BAD_STATE: "not allowed while armed",
    hp.RES_NOT_CALIBRATED: "not calibrated (send calibrate first)",
    hp.RES_BAD_FORMAT: "malformed report",
    hp.RES_NO_FRAME_TIME: "no room in the frame for a skin model's work at this rate and t_max "
                          "(lower the rate or t_max first)",
    hp.RES_STORE_FAILED: "the board could not write its flash (nothing changed)",
}
STOP_WORDS = {
    hp.STOP_NONE: "stimulating",
    hp.STOP_IDLE: "idle",
    hp.STOP_DISARMED: "disarmed",
    hp.STOP_ELECTRODE_OFF: "ELECTRODE OFF (latched)",
    hp.STOP_RP_FAULT: "Rp fault (latched)",
    hp.STOP_KEEPALIVE: "host silent (latched)",
    hp.STOP_LIMIT: "hard limit (latched)",
    hp.STOP_INTERNAL: "firmware error (latched)",
}
COMMAND_WORDS = {
    hp.CMD_ARM: "arm",
    hp.CMD_DISARM: "disarm",
    hp.CMD_CALIBRATE: "calibrate",
    hp.CMD_SET_LIMITS: "limits",
    hp.CMD_SET_MODE: "mode",
    hp.CMD_KEEPALIVE: "keepalive",
    hp.CMD_GET_INFO: "info",
    hp.CMD_SET_SKIN: "skin",
    hp.CMD_SET_VMON: "monitor correction",
}
VMON_STATE_WORDS = {
    hp.VMON_NONE: "no correction stored (monitor uncorrected)",
    hp.VMON_LOADED: "stored correction loaded at boot",
    hp.VMON_BAD: "stored correction unreadable or out of range: ignored (monitor uncorrected)",
    hp.VMON_STORED: "correction stored since boot",
}

_TELEMETRY = struct.Struct("<BBBBIIHHIiIiiHHHHHBBHxxI")  # bytes 0..55
assert _TELEMETRY.size == 56


class ProtocolError(ValueError):
    """A report that cannot be decoded."""


@dataclass(frozen=True)
class Telemetry:
    seq: int
    time_us: int
    channel: int
    mode: int
    stop: int
    i_ua: int
    t_us: int
    vp_mv: int
    rp_ohm: int
    me_ua2ms: int
    mq_target_fc_per_ohm: int
    mq_last_fc_per_ohm: int
    status: int
    next_i_ua: int
    next_t_us: int
    overruns: int
    loop_us: int
    flags: int
    rate_hz: int
    # the status bits (bounds) of the pulse delivered in this frame, as the controller is told before its
    # update (firmware 0.4.0; 0 before it and when no pulse): `audit` replays it
    sent_status: int = 0
    # log2 of the monitor's decay time constant (tau = R_skin Cp, us) after the pulse, Q.16 (firmware 0.4.0; 0: none)
    ltau_q16: int = 0

    @property
    def armed(self) -> bool:
        return bool(self.flags & hp.FLAG_ARMED)


@dataclass(frozen=True)
class Ack:
    seq: int
    time_us: int
    command: int
    result: int
    tag: int
    detail: int

    @property
    def ok(self) -> bool:
        return self.result == hp.RES_OK

    def words(self) -> str:
        cmd = COMMAND_WORDS.get(self.command, f"command 0x{self.command:02x}")
        res = RESULT_WORDS.get(self.result, f"result {self.result}")
        extra = f" (byte {self.detail})" if self.detail and not self.ok else ""
        return f"{cmd}: {res}{extra}"


@dataclass(frozen=True)
class Info:
    seq: int
    time_us: int
    tag: int
    firmware: str
    n_channels: int
    hard_i_max_ua: int
    hard_t_max_us: int
    hard_q_max_pc: int
    compliance_mv: int
    i_min_ua: int
    i_max_ua: int
    t_min_us: int
    t_max_us: int
    q_max_pc: int
    mode: int
    rate_hz: int
    keepalive_ms: int
    board: str
    result: int = hp.RES_OK
    vmon_state: int = hp.VMON_NONE  # what the board's flash held at boot (VMON_STATE_WORDS)
    flags: int = 0  # hp.INFO_FLAG_* (O_INFO_FLAGS)
    # 0: the limits in force; hp.INFO_PAGE_OWN: the board's own (GET_INFO page 1: hard_* its nominal
    # hard limits, i_min/i_max/q_max the soft ones as last set, before the firmware lowered them)
    page: int = 0
    own_hard: tuple[int, int] | None = None  # page 0: the board's own hard limits from its page 1 (Device.info)

    @property
    def nominal(self) -> tuple[int, int] | None:
        """The board's own hard current and charge limits (uA, pC), not held: None if not known
        (firmware before GET_INFO page 1, or not asked)."""
        if self.page == hp.INFO_PAGE_OWN:
            return self.hard_i_max_ua, self.hard_q_max_pc
        return self.own_hard

    @property
    def ok(self) -> bool:
        return self.result == hp.RES_OK

    @property
    def dac_gain_applied(self) -> bool:
        """The board's DAC path applies a stored DAC gain (the ideal simulated board does not)."""
        return bool(self.flags & hp.INFO_FLAG_DAC_GAIN)

    @property
    def held(self) -> bool:
        """hard_i_max_ua / hard_q_max_pc are held below the board's nominal limits (x 0.965) because
        a channel has no DAC gain applied (INFO_FLAG_HELD; firmware before it: never set)."""
        return bool(self.flags & hp.INFO_FLAG_HELD)

    @property
    def reports_held_limits(self) -> bool:
        """Firmware 0.2.0 on: the hard fields are the limits in force (held, lowered) and SET_LIMITS refuses above
        them. Before it: the board's nominal limits, never flagged, while the gate latched above 9650 uA on a
        board with no DAC gain (an old board: `steadytouch flash` updates it)."""
        return tuple(int(x) for x in self.firmware.split(".")) >= FW_HELD_LIMITS

    @property
    def reports_skin(self) -> bool:
        """Firmware 0.4.1 on: each channel's Calibration report carries its skin model (before it: 0s there)."""
        return tuple(int(x) for x in self.firmware.split(".")) >= FW_SKIN

    @property
    def reports_tau(self) -> bool:
        """Firmware 0.5.0 on: the controller reads the decay's tau (rule 7) with the gain SET_SKIN gave, and the
        Calibration report carries that gain (bytes 62-63; before it: 0s there, read as off)."""
        return tuple(int(x) for x in self.firmware.split(".")) >= FW_TAU

    @property
    def dac_low(self) -> bool:
        """hard_i_max_ua / hard_q_max_pc are lowered below the board's nominal limits x the DAC gain applied on
        a channel / VMON_DAC_PPM_MAX (every channel has one; INFO_FLAG_DAC_LOW; firmware before it: never set)."""
        return bool(self.flags & hp.INFO_FLAG_DAC_LOW)

    def lowered_reason(self) -> str:
        """Why the hard current and charge limits are below the board's own, or '' (neither flag);
        the board's own limits named when known (nominal)."""
        if self.held:
            return held_reason(self.dac_gain_applied, self.nominal)
        if self.dac_low:
            return DAC_LOW_REASON + (" (the board's own: I {} uA, Q {} pC)".format(*self.nominal)
                                     if self.nominal else "")
        return ""


HELD_PCT = 100 - hp.VMON_DAC_PPM_MIN / 1e4  # how far the hard limits are held below nominal (3.5 %)


FW_HELD_LIMITS = (0, 2, 0)  # the first firmware whose Info carries the hard limits in force (Info.reports_held_limits)
FW_OWN_LIMITS = (0, 3, 0)  # the first released with GET_INFO page 1, the board's own limits (Device.own_limits)
FW_SKIN = (0, 4, 1)  # the first whose Calibration report carries the channel's skin model (Info.reports_skin)
FW_TAU = (0, 5, 0)  # the first whose SET_SKIN takes rule 7's tau gain and reports it (Info.reports_tau)
DAC_LOW_REASON = ("its hard limits are the board's own x the lowest DAC gain measured / {:g} (the top of the gain's "
                  "window: the current delivered stays within the board's own whatever the DAC's true gain; "
                  "`steadytouch info` shows each channel's DAC gain)").format(hp.VMON_DAC_PPM_MAX / 1e6)


def held_reason(takes_dac_gain: bool = True, nominal: tuple[int, int] | None = None) -> str:
    """Why a board's hard current and charge limits are held (Info.held), and how to lift it: one phrase, with
    the board's own limits (nominal: (uA, pC), GET_INFO page 1) when known. The advice to measure the DAC gain
    only for a board whose DAC path applies one (Info.dac_gain_applied)."""
    own = "the board's own" + (" (I {} uA, Q {} pC)".format(*nominal) if nominal else "")
    if not takes_dac_gain:
        return (f"its hard limits are held {HELD_PCT:g} % below {own} because no DAC gain is applied "
                "(this board's DAC path takes none: the hold stays)")
    return (f"its hard limits are held {HELD_PCT:g} % below {own} because no DAC gain was measured "
            "(run `steadytouch selftest --load-ohm OHMS --scope` to measure it and lift the hold: the limits are then "
            f"the board's own x the gain measured / {hp.VMON_DAC_PPM_MAX / 1e6:g})")


@dataclass(frozen=True)
class CalInfo:
    seq: int
    time_us: int
    tag: int
    result: int
    channel: int
    flags: int
    i0_ua: int
    t0_us: int
    x_star_ohm: int
    y_star_pc: int
    rp0_ohm: int  # 0 until the first pulse after arming measured it
    mode: int
    vmon_gain_ppm: int = 0  # the monitor correction applied to this channel (0: none)
    vmon_offset_mv: int = 0
    vmon_state: int = hp.VMON_NONE
    dac_gain_ppm: int = 0  # the amplitude DAC's gain applied (0: nominal)
    skin_rs_ohm: int = 0  # MODE_FAST's skin model as set (all 0: none; firmware before 0.4.1 sends 0s)
    skin_beta_q16: int = 0
    skin_cp_pf: int = 0
    skin_tau_q16: int = sc.SKIN_TAU_OFF  # rule 7's tau gain as set (firmware before 0.5.0 sends 0: off)

    @property
    def ok(self) -> bool:
        return self.result == hp.RES_OK

    @property
    def calibrated(self) -> bool:
        return bool(self.flags & 1)


_WRAP = 1 << 30  # seq and time_us wrap here; 32-bit fields stay below it in magnitude
_STATUS_BITS = sc.ST_BOUND_MASK | sc.ST_FAULT_MASK
_SENT_BITS = sc.ST_BOUND_MASK  # (a pulse is never sent with a fault)
_FLAG_BITS = hp.FLAG_ARMED | hp.FLAG_HELD | hp.FLAG_KEEPALIVE | hp.FLAG_CALIBRATING | hp.FLAG_MODE_SET


def _need(ok: bool, what: str, value, accepted: str):
    if not ok:
        raise ProtocolError(f"report field {what}={value} out of range (accepted: {accepted})")


def _rate_ok(r):
    return r == 0 or hp.RATE_MIN_HZ <= r <= hp.RATE_MAX_HZ


def _check_telemetry(t: Telemetry):
    _need(t.channel <= 3, "channel", t.channel, "0..3")
    _need(t.mode in sc.MODES, "mode", t.mode, f"{min(sc.MODES)}..{max(sc.MODES)}")
    _need(t.stop in STOP_WORDS, "stop", t.stop, f"0..{max(STOP_WORDS)}")
    _need(t.i_ua <= sc.I_LIMIT_UA, "i_ua", t.i_ua, f"0..{sc.I_LIMIT_UA}")
    _need(t.t_us <= sc.T_LIMIT_US, "t_us", t.t_us, f"0..{sc.T_LIMIT_US}")
    _need(t.vp_mv <= sc.VP_LIMIT_MV, "vp_mv", t.vp_mv, f"0..{sc.VP_LIMIT_MV}")
    _need(sc.RP_INVALID <= t.rp_ohm <= sc.RP_OVER, "rp_ohm", t.rp_ohm, f"{sc.RP_INVALID}..{sc.RP_OVER}")
    _need(t.me_ua2ms < _WRAP, "me_ua2ms", t.me_ua2ms, "0..2**30-1")
    for name in ("mq_target_fc_per_ohm", "mq_last_fc_per_ohm"):
        v = getattr(t, name)
        _need(-_WRAP < v < _WRAP, name, v, "|x| < 2**30")
    _need(not t.status & ~_STATUS_BITS, "status", f"0x{t.status:x}", f"bits of 0x{_STATUS_BITS:x}")
    _need(not t.sent_status & ~_SENT_BITS, "sent_status", f"0x{t.sent_status:x}", f"bits of 0x{_SENT_BITS:x}")
    _need(t.i_ua or not t.sent_status, "sent_status", f"0x{t.sent_status:x}", "0 in a frame without a pulse")
    _need(t.ltau_q16 < decay.LTAU_END, "ltau_q16", t.ltau_q16, f"0..{decay.LTAU_END - 1} (tau below 2**20 us)")
    _need(t.i_ua or not t.ltau_q16, "ltau_q16", t.ltau_q16, "0 in a frame without a pulse")
    _need(t.next_i_ua <= sc.I_LIMIT_UA, "next_i_ua", t.next_i_ua, f"0..{sc.I_LIMIT_UA}")
    _need(t.next_t_us <= sc.T_LIMIT_US, "next_t_us", t.next_t_us, f"0..{sc.T_LIMIT_US}")
    _need(not t.flags & ~_FLAG_BITS, "flags", f"0x{t.flags:x}", f"bits of 0x{_FLAG_BITS:x}")
    _need(_rate_ok(t.rate_hz), "rate_hz", t.rate_hz, f"0 or {hp.RATE_MIN_HZ}..{hp.RATE_MAX_HZ}")


def _check_info(i: Info):
    _need(i.result in RESULT_WORDS, "result", i.result, f"0..{max(RESULT_WORDS)}")
    _need(1 <= i.n_channels <= 4, "n_channels", i.n_channels, "1..4")
    _need(1 <= i.hard_i_max_ua <= sc.I_LIMIT_UA, "hard_i_max_ua", i.hard_i_max_ua, f"1..{sc.I_LIMIT_UA}")
    _need(1 <= i.hard_t_max_us <= sc.T_LIMIT_US, "hard_t_max_us", i.hard_t_max_us, f"1..{sc.T_LIMIT_US}")
    _need(1 <= i.hard_q_max_pc <= sc.Q_LIMIT_PC, "hard_q_max_pc", i.hard_q_max_pc, f"1..{sc.Q_LIMIT_PC}")
    _need(i.compliance_mv <= sc.VP_LIMIT_MV, "compliance_mv", i.compliance_mv, f"0..{sc.VP_LIMIT_MV}")
    _need(1 <= i.i_min_ua <= i.i_max_ua <= i.hard_i_max_ua, "i_min_ua/i_max_ua", f"{i.i_min_ua}/{i.i_max_ua}",
          "1 <= i_min <= i_max <= hard_i_max")
    _need(1 <= i.t_min_us <= i.t_max_us <= i.hard_t_max_us, "t_min_us/t_max_us", f"{i.t_min_us}/{i.t_max_us}",
          "1 <= t_min <= t_max <= hard_t_max")
    _need(1 <= i.q_max_pc <= i.hard_q_max_pc, "q_max_pc", i.q_max_pc, "1..hard_q_max_pc")
    _need(i.mode in sc.MODES, "mode", i.mode, f"{min(sc.MODES)}..{max(sc.MODES)}")
    _need(_rate_ok(i.rate_hz), "rate_hz", i.rate_hz, f"0 or {hp.RATE_MIN_HZ}..{hp.RATE_MAX_HZ}")
    _need(i.keepalive_ms == 0 or hp.KEEPALIVE_MIN_MS <= i.keepalive_ms <= hp.KEEPALIVE_MAX_MS, "keepalive_ms",
          i.keepalive_ms, f"0 (simulator only) or {hp.KEEPALIVE_MIN_MS}..{hp.KEEPALIVE_MAX_MS}")


def _check_cal(c: CalInfo):
    _need(c.result in RESULT_WORDS, "result", c.result, f"0..{max(RESULT_WORDS)}")
    _need(c.channel <= 3, "channel", c.channel, "0..3")
    _need(c.flags <= 31, "flags", f"0x{c.flags:x}", "bits of 0x1f")
    _need(c.dac_gain_ppm == 0 or hp.VMON_DAC_PPM_MIN <= c.dac_gain_ppm <= hp.VMON_DAC_PPM_MAX, "dac_gain_ppm",
          c.dac_gain_ppm, f"0 or {hp.VMON_DAC_PPM_MIN}..{hp.VMON_DAC_PPM_MAX}")
    _need(c.vmon_gain_ppm == 0 and c.vmon_offset_mv == 0 or (
        hp.VMON_GAIN_PPM_MIN <= c.vmon_gain_ppm <= hp.VMON_GAIN_PPM_MAX
        and hp.VMON_OFFSET_MV_MIN <= c.vmon_offset_mv <= hp.VMON_OFFSET_MV_MAX), "vmon",
        f"{c.vmon_gain_ppm} ppm, {c.vmon_offset_mv} mV",
        f"0, 0 or {hp.VMON_GAIN_PPM_MIN}..{hp.VMON_GAIN_PPM_MAX} ppm, {hp.VMON_OFFSET_MV_MIN}..{hp.VMON_OFFSET_MV_MAX} mV")
    _need(c.vmon_state in VMON_STATE_WORDS, "vmon_state", c.vmon_state, f"0..{max(VMON_STATE_WORDS)}")
    _need(c.i0_ua <= sc.I_LIMIT_UA, "i0_ua", c.i0_ua, f"0..{sc.I_LIMIT_UA}")
    _need(c.t0_us <= sc.T_LIMIT_US, "t0_us", c.t0_us, f"0..{sc.T_LIMIT_US}")
    _need(sc.X_STAR_MIN_OHM <= c.x_star_ohm <= 0, "x_star_ohm", c.x_star_ohm, f"{sc.X_STAR_MIN_OHM}..0")
    _need(0 <= c.y_star_pc <= sc.Q_LIMIT_PC, "y_star_pc", c.y_star_pc, f"0..{sc.Q_LIMIT_PC}")
    _need(c.rp0_ohm == 0 or sc.RP_MIN_OHM <= c.rp0_ohm <= sc.RP_MAX_OHM, "rp0_ohm", c.rp0_ohm,
          f"0 or {sc.RP_MIN_OHM}..{sc.RP_MAX_OHM}")
    _need(c.mode in sc.MODES, "mode", c.mode, f"{min(sc.MODES)}..{max(sc.MODES)}")
    skin = (c.skin_rs_ohm, c.skin_beta_q16, c.skin_cp_pf)
    _need(skin == (0, 0, 0) or (c.skin_rs_ohm <= sc.SKIN_RS_MAX_OHM
                                and sc.SKIN_BETA_MIN_Q16 <= c.skin_beta_q16 <= sc.SKIN_BETA_MAX_Q16
                                and sc.SKIN_CP_MIN_PF <= c.skin_cp_pf <= sc.SKIN_CP_MAX_PF), "skin",
          "%d ohm, %d, %d pF" % skin, f"0, 0, 0 or Rs 0..{sc.SKIN_RS_MAX_OHM} ohm, beta {sc.SKIN_BETA_MIN_Q16}.."
          f"{sc.SKIN_BETA_MAX_Q16} (Q.16), Cp {sc.SKIN_CP_MIN_PF}..{sc.SKIN_CP_MAX_PF} pF")
    _need(skin != (0, 0, 0) or c.skin_tau_q16 == sc.SKIN_TAU_OFF, "skin_tau_q16", c.skin_tau_q16,
          f"{sc.SKIN_TAU_OFF} (off) with no skin model")


def decode(report: bytes):
    """One 64-byte IN report -> Telemetry, Ack, Info or CalInfo.

    ProtocolError (naming the field) for a report of the wrong length, an unknown
    type, or any field outside the range the firmware can send (docs/protocol.md)."""
    if len(report) != hp.REPORT_LEN:
        raise ProtocolError(f"report of {len(report)} bytes, expected {hp.REPORT_LEN}")
    typ = report[0]
    seq = struct.unpack_from("<I", report, hp.O_SEQ)[0]
    time_us = struct.unpack_from("<I", report, hp.O_TIME)[0]
    _need(seq < _WRAP, "seq", seq, "0..2**30-1")
    _need(time_us < _WRAP, "time_us", time_us, "0..2**30-1")
    if typ == hp.REP_TELEMETRY:
        f = _TELEMETRY.unpack_from(report, 0)
        t = Telemetry(
            seq=f[4], time_us=f[5], channel=f[1], mode=f[2], stop=f[3], i_ua=f[6], t_us=f[7], vp_mv=f[8],
            rp_ohm=f[9], me_ua2ms=f[10], mq_target_fc_per_ohm=f[11], mq_last_fc_per_ohm=f[12], status=f[13],
            next_i_ua=f[14], next_t_us=f[15], overruns=f[16], loop_us=f[17], flags=f[18], rate_hz=f[19],
            sent_status=f[20], ltau_q16=f[21],
        )
        _check_telemetry(t)
        return t
    if typ == hp.REP_ACK:
        a = Ack(seq, time_us, report[hp.O_CMD], report[hp.O_RESULT], report[hp.O_TAG], report[hp.O_DETAIL])
        # any command byte: the device echoes an unknown or corrupted command in its refusal
        _need(a.result in RESULT_WORDS, "result", a.result, f"0..{max(RESULT_WORDS)}")
        _need(a.detail < hp.REPORT_LEN, "detail", a.detail, f"0..{hp.REPORT_LEN - 1}")
        return a
    if typ == hp.REP_INFO:
        fw = report[hp.O_FW : hp.O_FW + 3]
        lim = struct.unpack_from("<HHHHI", report, hp.O_LIM)
        raw_board = bytes(report[hp.O_BOARD : hp.O_BOARD + hp.BOARD_LEN]).rstrip(b"\0")
        _need(all(0x20 <= c < 0x7F for c in raw_board), "board", repr(raw_board), "printable ASCII")
        i = Info(
            seq=seq, time_us=time_us, tag=report[hp.O_TAG], firmware="%d.%d.%d" % tuple(fw),
            n_channels=report[hp.O_FW + 3],
            hard_i_max_ua=struct.unpack_from("<H", report, hp.O_HARD_I)[0],
            hard_t_max_us=struct.unpack_from("<H", report, hp.O_HARD_T)[0],
            hard_q_max_pc=struct.unpack_from("<I", report, hp.O_HARD_Q)[0],
            compliance_mv=struct.unpack_from("<I", report, hp.O_COMPLIANCE)[0],
            i_min_ua=lim[0], i_max_ua=lim[1], t_min_us=lim[2], t_max_us=lim[3], q_max_pc=lim[4],
            mode=report[hp.O_INFO_MODE], rate_hz=report[hp.O_INFO_RATE],
            keepalive_ms=struct.unpack_from("<H", report, hp.O_INFO_KEEPALIVE)[0],
            board=raw_board.decode("ascii"),
            result=report[hp.O_RESULT],
            vmon_state=report[hp.O_INFO_VMON],
            flags=report[hp.O_INFO_FLAGS],
            page=report[hp.O_INFO_PAGE],
        )
        _need(i.page <= hp.INFO_PAGE_OWN, "page", i.page, f"0..{hp.INFO_PAGE_OWN}")
        # flags: bits this host does not know are ignored (a later firmware may add one; docs/protocol.md)
        _need(i.vmon_state in VMON_STATE_WORDS, "vmon_state", i.vmon_state, f"0..{max(VMON_STATE_WORDS)}")
        _check_info(i)
        return i
    if typ == hp.REP_CAL:
        i0, t0 = struct.unpack_from("<HH", report, hp.O_CAL_I0)
        x, y, rp0 = struct.unpack_from("<iii", report, hp.O_CAL_X)
        vg, vo = struct.unpack_from("<ii", report, hp.O_CAL_VMON_GAIN)
        c = CalInfo(seq, time_us, report[hp.O_TAG], report[hp.O_RESULT], report[hp.O_CAL_CH],
                    report[hp.O_CAL_FLAGS], i0, t0, x, y, rp0, report[hp.O_CAL_MODE], vg, vo,
                    report[hp.O_CAL_VMON_STATE], struct.unpack_from("<i", report, hp.O_CAL_DAC_GAIN)[0],
                    *struct.unpack_from("<HII", report, hp.O_CAL_SKIN_RS),
                    struct.unpack_from("<H", report, hp.O_CAL_SKIN_TAU)[0] - 0x8000)
        _check_cal(c)
        return c
    raise ProtocolError(f"report field type=0x{typ:02x} unknown (accepted: 0x01 telemetry, 0x02 ack, 0x03 info, 0x04 calibration)")


def split_stdio_stream(data: bytes, rest: bool = False):
    """The simulated board's stdout: MAGIC0 MAGIC1 + 64 bytes, repeated. rest=True:
    (the reports, the bytes after the last whole one) for a stream read in chunks."""
    out, k = [], 0
    while k + 66 <= len(data):
        if data[k] == 0xA5 and data[k + 1] == 0x5A:
            out.append(bytes(data[k + 2 : k + 66]))
            k += 66
        else:
            k += 1
    return (out, data[k:]) if rest else out


class CommandError(ValueError):
    """A command argument the wire cannot carry or the device would refuse;
    raised before anything is sent. The message names the argument and its range."""


# what the host knows the device accepts (hid_protocol and sensation_core are the
# firmware's own modules; a board's hard limits are inside the core's envelope)
I_RANGE_UA = (1, sc.I_LIMIT_UA)
T_RANGE_US = (hp.T_FLOOR_US, sc.T_LIMIT_US)
Q_MAX_PC = sc.Q_LIMIT_PC
X_STAR_RANGE_OHM = (sc.X_STAR_MIN_OHM, 0)
KEEPALIVE_RANGE_MS = (hp.KEEPALIVE_MIN_MS, hp.KEEPALIVE_MAX_MS)
RATE_RANGE_HZ = (hp.RATE_MIN_HZ, hp.RATE_MAX_HZ)
CHANNELS = (0, 1, 2, 3, hp.CH_ALL)


def _whole(name, v) -> int:
    if isinstance(v, bool):
        raise CommandError(f"{name} must be a whole number, not {v!r}")
    if isinstance(v, float) and v.is_integer():
        return int(v)
    try:
        return operator.index(v)
    except TypeError:
        raise CommandError(f"{name} must be a whole number, not {v!r}") from None


def _in(name, v, lo, hi, unit="") -> int:
    v = _whole(name, v)
    if not lo <= v <= hi:
        raise CommandError(f"{name}={v} out of range: the device accepts {lo}..{hi}{' ' + unit if unit else ''}")
    return v


def _channel(ch) -> int:
    ch = _whole("channel", ch)
    if ch not in CHANNELS:
        raise CommandError(f"channel={ch} out of range: 0..3, or {hp.CH_ALL} for all channels")
    return ch


def check_vmon(gain_ppm, offset_mv, dac_gain_ppm=0):
    """One channel's correction as the device accepts it (hid_protocol's windows): (g, off, dac) as ints;
    CommandError names the value and the accepted range."""
    gain_ppm, offset_mv = _whole("gain_ppm", gain_ppm), _whole("offset_mv", offset_mv)
    if gain_ppm or offset_mv:
        gain_ppm = _in("gain_ppm", gain_ppm, hp.VMON_GAIN_PPM_MIN, hp.VMON_GAIN_PPM_MAX, "ppm")
        offset_mv = _in("offset_mv", offset_mv, hp.VMON_OFFSET_MV_MIN, hp.VMON_OFFSET_MV_MAX, "mV")
    dac_gain_ppm = _whole("dac_gain_ppm", dac_gain_ppm)
    if dac_gain_ppm:
        dac_gain_ppm = _in("dac_gain_ppm", dac_gain_ppm, hp.VMON_DAC_PPM_MIN, hp.VMON_DAC_PPM_MAX, "ppm")
    return gain_ppm, offset_mv, dac_gain_ppm


def check_calibration(i0_ua, t0_us, x_star_ohm, y_star_pc):
    """The calibration rules the device applies (soft limits aside): (i0, t0, x, y) as ints."""
    i0 = _in("i0_ua", i0_ua, *I_RANGE_UA, "uA")
    t0 = _in("t0_us", t0_us, *T_RANGE_US, "us")
    if i0 * t0 > Q_MAX_PC:
        raise CommandError(f"i0_ua*t0_us={i0 * t0} pC out of range: at most {Q_MAX_PC} pC")
    x = _in("x_star_ohm", x_star_ohm, *X_STAR_RANGE_OHM, "ohm")
    y = _whole("y_star_pc", y_star_pc)
    if not 0 <= y < i0 * t0:
        raise CommandError(f"y_star_pc={y} out of range: 0 <= y* < i0*t0 = {i0 * t0} pC")
    return i0, t0, x, y


def check_limits(i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc):
    i_max = _in("i_max_ua", i_max_ua, *I_RANGE_UA, "uA")
    i_min = _in("i_min_ua", i_min_ua, 1, i_max, "uA (up to i_max_ua)")
    t_max = _in("t_max_us", t_max_us, *T_RANGE_US, "us")
    t_min = _in("t_min_us", t_min_us, hp.T_FLOOR_US, t_max, "us (up to t_max_us)")
    q_max = _in("q_max_pc", q_max_pc, i_min * t_min, Q_MAX_PC, "pC (from i_min_ua*t_min_us)")
    return i_min, i_max, t_min, t_max, q_max


def check_skin(rs_ohm, beta_q16, cp_pf, tau_q16=sc.SKIN_TAU_OFF):
    """The model and rule 7's tau gain (sc.SKIN_TAU_OFF: tau not used): (rs, beta, cp, tau), checked."""
    rs, beta, cp = _whole("rs_ohm", rs_ohm), _whole("beta_q16", beta_q16), _whole("cp_pf", cp_pf)
    tau = _whole("tau_q16", tau_q16)
    if rs == beta == cp == 0:
        if tau != sc.SKIN_TAU_OFF:
            raise CommandError(f"tau_q16={tau} with no skin model: a tau gain goes with a model (off: "
                               f"{sc.SKIN_TAU_OFF})")
        return rs, beta, cp, tau  # removes the model
    if tau != sc.SKIN_TAU_OFF:
        _in("tau_q16", tau, -sc.SKIN_TAU_MAX_Q16, sc.SKIN_TAU_MAX_Q16, f"(log2 Q.16; off: {sc.SKIN_TAU_OFF})")
    return (_in("rs_ohm", rs, 0, sc.SKIN_RS_MAX_OHM, "ohm"),
            _in("beta_q16", beta, sc.SKIN_BETA_MIN_Q16, sc.SKIN_BETA_MAX_Q16, "(Q.16)"),
            _in("cp_pf", cp, sc.SKIN_CP_MIN_PF, sc.SKIN_CP_MAX_PF, "pF"), tau)


def check_mode(mode, rate_hz):
    mode = _in("mode", mode, min(sc.MODES), max(sc.MODES))
    rate = _whole("rate_hz", rate_hz)
    if rate and not RATE_RANGE_HZ[0] <= rate <= RATE_RANGE_HZ[1]:
        raise CommandError(f"rate_hz={rate} out of range: the device accepts {RATE_RANGE_HZ[0]}..{RATE_RANGE_HZ[1]} Hz "
                           "(0 keeps the current rate)")
    return mode, rate


class Commands:
    """OUT report builders with a running tag (a thin layer over hid_protocol's).

    Every argument is checked against what the wire carries and what the device
    accepts; an out-of-range value raises CommandError before a report exists.
    `Commands(check=False)` skips the checks: only for tests of the device's own
    refusals (the values are then masked to their field widths on the wire)."""

    def __init__(self, check: bool = True, frame: tuple[int, int, int] | None = None):
        self.tag = 0
        self.check = check
        # the device's (n_channels, rate_hz, t_max_us), once known (know(), applied()):
        # a rate or t_max whose worst-case frame cannot fit is then refused here, as the
        # device refuses it (hid_protocol.frame_fits); unknown: the device's answer says
        self.frame = frame
        # a skin model this host set (SET_SKIN acknowledged, not removed on every channel since):
        # the frame rule then counts the model's work (the device checks its own state)
        self.model = 0
        # the device's hard current and charge limits in force (GET_INFO: held while it has no DAC
        # gain) and whether they are held, once known (know()); unknown again after a SET_VMON
        self.hard: tuple[int, int, str] | None = None  # (I, Q, why they are below the board's own or '')

    def know(self, info: "Info") -> None:
        """What a GET_INFO answer says of the frame (channels, rate and soft t_max) and of the
        hard limits in force (SET_LIMITS above them is then refused here, as the device does)."""
        self.frame = (info.n_channels, info.rate_hz, info.t_max_us)
        self.hard = (info.hard_i_max_ua, info.hard_q_max_pc, info.lowered_reason())

    def applied(self, report: bytes) -> None:
        """The device acknowledged `report` (RES_OK): follow a new rate or t_max."""
        if self.frame is None:
            return
        n, rate, t_max = self.frame
        if report[0] == hp.CMD_SET_MODE and report[hp.O_ARG + 1]:
            rate = report[hp.O_ARG + 1]
        elif report[0] == hp.CMD_SET_LIMITS:
            t_max = hp.get_u16(report, hp.O_ARG + 6)
        elif report[0] == hp.CMD_SET_SKIN:
            if any(report[hp.O_ARG:hp.O_ARG + 10]):
                self.model = 1
            elif report[hp.O_OUT_CH] == hp.CH_ALL:
                self.model = 0
        self.frame = (n, rate, t_max)

    def forget(self, report: bytes) -> None:
        """A report was sent whose outcome may move the hard limits in force (SET_VMON: a DAC gain
        applied or removed), answered or not: they are unknown until the next GET_INFO."""
        if report[0] == hp.CMD_SET_VMON:
            self.hard = None

    def _within_hard(self, i_max: int, q_max: int) -> None:
        if self.hard is None:
            return
        hard_i, hard_q, reason = self.hard
        why = f": {reason}" if reason else ""
        if i_max > hard_i:
            raise CommandError(f"i_max_ua={i_max} out of range: the device accepts 1..{hard_i} uA{why}")
        if q_max > hard_q:
            raise CommandError(f"q_max_pc={q_max} out of range: the device accepts up to {hard_q} pC{why}")

    def _fits(self, rate_hz: int, t_max_us: int, what: str, model: int | None = None) -> None:
        n = self.frame[0]
        m = self.model if model is None else model
        if hp.frame_fits(rate_hz, n, t_max_us, m):
            return
        rule = "rate x hid_protocol.frame_us(channels, t_max) must stay within 1 s, as the device checks"
        with_model = " with a skin model set" if m else ""
        if what == "skin":
            raise CommandError(f"a skin model's work does not fit the frame with {n} channels at {rate_hz} Hz and "
                               f"t_max_us={t_max_us}: lower t_max_us to {hp.t_max_fitting(rate_hz, n, 1)} or the "
                               f"rate to {hp.rate_max_fitting(n, t_max_us, 1)} Hz first ({rule})")
        if what == "rate":
            lower = hp.t_max_fitting(rate_hz, n, m)
            how = (f"; for {rate_hz} Hz lower t_max_us to {lower} first (`steadytouch limits --t-max-us`)"
                   if lower >= hp.T_FLOOR_US else "")
            top = hp.rate_max_fitting(n, t_max_us, m)
            can = f"{hp.RATE_MIN_HZ}..{top} Hz" if top >= hp.RATE_MIN_HZ else "no rate"
            raise CommandError(f"rate_hz={rate_hz} out of range: with {n} channel(s) and t_max_us={t_max_us}"
                               f"{with_model} the device accepts {can}{how} ({rule})")
        raise CommandError(f"t_max_us={t_max_us} does not fit the frame with {n} channels at {rate_hz} Hz{with_model}: "
                           f"at most {hp.t_max_fitting(rate_hz, n, m)} us ({rule})")

    def _next(self) -> int:
        self.tag = (self.tag + 1) & 0xFF
        return self.tag

    def _ch(self, ch):
        return _channel(ch) if self.check else ch

    def arm(self, ch=hp.CH_ALL) -> bytes:
        return bytes(hp.cmd_arm(bytearray(64), self._ch(ch), self._next()))

    def disarm(self, ch=hp.CH_ALL) -> bytes:
        return bytes(hp.cmd_disarm(bytearray(64), self._ch(ch), self._next()))

    def calibrate(self, i0_ua, t0_us, x_star_ohm, y_star_pc, ch=hp.CH_ALL) -> bytes:
        ch = self._ch(ch)
        v = (i0_ua, t0_us, x_star_ohm, y_star_pc)
        if self.check:
            v = check_calibration(*v)
        return bytes(hp.cmd_calibrate(bytearray(64), ch, *v, self._next()))

    def set_limits(self, i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc) -> bytes:
        v = (i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc)
        if self.check:
            v = check_limits(*v)
            self._within_hard(v[1], v[4])
            if self.frame is not None:
                self._fits(self.frame[1], v[3], "t_max")
        return bytes(hp.cmd_set_limits(bytearray(64), *v, self._next()))

    def set_skin(self, rs_ohm, beta_q16, cp_pf, ch=hp.CH_ALL, tau_q16=sc.SKIN_TAU_OFF) -> bytes:
        """MODE_FAST's skin model (host/skin.py fits it); (0, 0, 0) removes it. tau_q16: the monitor's tau gain
        measured with it (skin.tau_gain; firmware 0.5.0 on), sc.SKIN_TAU_OFF: rule 7 does not read tau."""
        ch = self._ch(ch)
        v = (rs_ohm, beta_q16, cp_pf, tau_q16)
        if self.check:
            v = check_skin(*v)
            if any(v[:3]) and self.frame is not None:
                self._fits(self.frame[1], self.frame[2], "skin", 1)
        return bytes(hp.cmd_set_skin(bytearray(64), ch, *v[:3], self._next(), v[3]))

    def set_mode(self, mode, rate_hz=0) -> bytes:
        if self.check:
            mode, rate_hz = check_mode(mode, rate_hz)
            if rate_hz and self.frame is not None:
                self._fits(rate_hz, self.frame[2], "rate")
        return bytes(hp.cmd_set_mode(bytearray(64), mode & 0xFF, rate_hz & 0xFF, self._next()))

    def set_vmon(self, ch, gain_ppm, offset_mv, store=False, dac_gain_ppm=0) -> bytes:
        """Channel ch's voltage-monitor correction (steadytouch selftest); (0, 0): none;
        dac_gain_ppm: its amplitude DAC's gain (0: nominal). store: also written to the
        board's flash (read at every boot). Every channel at once: set_vmon_all."""
        ch = self._ch(ch)
        if self.check:
            if ch == hp.CH_ALL:
                raise CommandError("monitor correction: one channel (0..3) here; every channel at once: set_vmon_all")
            gain_ppm, offset_mv, dac_gain_ppm = check_vmon(gain_ppm, offset_mv, dac_gain_ppm)
        op = hp.VMON_STORE if store else hp.VMON_APPLY
        return bytes(hp.cmd_set_vmon(bytearray(64), ch, op, gain_ppm, offset_mv, self._next(), dac_gain_ppm))

    def set_vmon_all(self, values, store=False) -> bytes:
        """Every channel's correction in one command: values = [(gain_ppm, offset_mv, dac_gain_ppm)
        per channel]: exactly the device's channel count once GET_INFO told it (know()); before
        that 1..4, and the device reads the words of a channel it has but was not given as 0
        (uncorrected, DAC nominal). The device checks all, writes its flash once (store) and
        applies all, or changes nothing."""
        shape = "a list of (gain_ppm, offset_mv, dac_gain_ppm), one per channel"
        if self.check:
            if isinstance(values, (str, bytes, dict)):
                raise CommandError(f"monitor correction: {values!r} is not {shape}")
            try:
                values = list(values)
            except TypeError:
                raise CommandError(f"monitor correction: {values!r} is not {shape}") from None
            n = self.frame[0] if self.frame is not None else None
            if n is not None and len(values) != n:
                raise CommandError(f"monitor correction for {len(values)} channel(s): the device has {n}, "
                                   f"give exactly {n}")
            if not 1 <= len(values) <= 4:
                raise CommandError(f"monitor correction for {len(values)} channels: 1..4")
            for k, v in enumerate(values):
                if not isinstance(v, (tuple, list)) or len(v) != 3:
                    raise CommandError(f"monitor correction of channel {k}: {v!r} is not (gain_ppm, offset_mv, "
                                       "dac_gain_ppm)")
            values = [check_vmon(*v) for v in values]
        else:
            values = list(values)
        op = hp.VMON_STORE if store else hp.VMON_APPLY
        return bytes(hp.cmd_set_vmon_all(bytearray(64), op, values, self._next()))

    def keepalive(self, timeout_ms=hp.KEEPALIVE_DEFAULT_MS) -> bytes:
        """The host is alive; the device stops every channel if silent for timeout_ms (it cannot be switched off)."""
        if self.check:
            timeout_ms = _in("keepalive timeout_ms", timeout_ms, *KEEPALIVE_RANGE_MS, "ms")
        return bytes(hp.cmd_keepalive(bytearray(64), timeout_ms, self._next()))

    def get_info(self, ch=hp.CH_ALL, page=0) -> bytes:
        """GET_INFO: the limits in force (page 0), the board's own (page hp.INFO_PAGE_OWN, CH_ALL only), or
        channel ch's calibration."""
        if page not in (0, hp.INFO_PAGE_OWN) or (page and ch != hp.CH_ALL):
            raise CommandError(f"page={page!r} out of range: 0, or {hp.INFO_PAGE_OWN} (the board's own limits, "
                               "every channel)")
        return bytes(hp.cmd_get_info(bytearray(64), self._next(), self._ch(ch), page))
