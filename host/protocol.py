"""Host side of the HID protocol: decode IN reports, build OUT reports.

Offsets and codes come from the shared module `hid_protocol` (the firmware's
own), so host and device cannot disagree about the layout.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import hid_protocol as hp

RESULT_WORDS = {
    hp.RES_OK: "ok",
    hp.RES_BAD_CRC: "bad CRC",
    hp.RES_UNKNOWN_COMMAND: "unknown command",
    hp.RES_BAD_CHANNEL: "no such channel",
    hp.RES_OUT_OF_RANGE: "value out of range",
    hp.RES_BAD_STATE: "not allowed while armed",
    hp.RES_NOT_CALIBRATED: "not calibrated (send calibrate first)",
    hp.RES_BAD_FORMAT: "malformed report",
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
}

_TELEMETRY = struct.Struct("<BBBBIIHHIiIiiHHHHHBB")  # bytes 0..47
assert _TELEMETRY.size == 48


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

    @property
    def ok(self) -> bool:
        return self.result == hp.RES_OK


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

    @property
    def ok(self) -> bool:
        return self.result == hp.RES_OK

    @property
    def calibrated(self) -> bool:
        return bool(self.flags & 1)


def decode(report: bytes):
    """One 64-byte IN report -> Telemetry, Ack or Info."""
    if len(report) != hp.REPORT_LEN:
        raise ProtocolError(f"report of {len(report)} bytes, expected {hp.REPORT_LEN}")
    typ = report[0]
    seq = struct.unpack_from("<I", report, hp.O_SEQ)[0]
    time_us = struct.unpack_from("<I", report, hp.O_TIME)[0]
    if typ == hp.REP_TELEMETRY:
        f = _TELEMETRY.unpack_from(report, 0)
        return Telemetry(
            seq=f[4], time_us=f[5], channel=f[1], mode=f[2], stop=f[3], i_ua=f[6], t_us=f[7], vp_mv=f[8],
            rp_ohm=f[9], me_ua2ms=f[10], mq_target_fc_per_ohm=f[11], mq_last_fc_per_ohm=f[12], status=f[13],
            next_i_ua=f[14], next_t_us=f[15], overruns=f[16], loop_us=f[17], flags=f[18], rate_hz=f[19],
        )
    if typ == hp.REP_ACK:
        return Ack(seq, time_us, report[hp.O_CMD], report[hp.O_RESULT], report[hp.O_TAG], report[hp.O_DETAIL])
    if typ == hp.REP_INFO:
        fw = report[hp.O_FW : hp.O_FW + 3]
        lim = struct.unpack_from("<HHHHI", report, hp.O_LIM)
        return Info(
            seq=seq, time_us=time_us, tag=report[hp.O_TAG], firmware="%d.%d.%d" % tuple(fw),
            n_channels=report[hp.O_FW + 3],
            hard_i_max_ua=struct.unpack_from("<H", report, hp.O_HARD_I)[0],
            hard_t_max_us=struct.unpack_from("<H", report, hp.O_HARD_T)[0],
            hard_q_max_pc=struct.unpack_from("<I", report, hp.O_HARD_Q)[0],
            compliance_mv=struct.unpack_from("<I", report, hp.O_COMPLIANCE)[0],
            i_min_ua=lim[0], i_max_ua=lim[1], t_min_us=lim[2], t_max_us=lim[3], q_max_pc=lim[4],
            mode=report[hp.O_INFO_MODE], rate_hz=report[hp.O_INFO_RATE],
            keepalive_ms=struct.unpack_from("<H", report, hp.O_INFO_KEEPALIVE)[0],
            board=bytes(report[hp.O_BOARD : hp.O_BOARD + hp.BOARD_LEN]).rstrip(b"\0").decode("ascii", "replace"),
            result=report[hp.O_RESULT],
        )
    if typ == hp.REP_CAL:
        i0, t0 = struct.unpack_from("<HH", report, hp.O_CAL_I0)
        x, y, rp0 = struct.unpack_from("<iii", report, hp.O_CAL_X)
        return CalInfo(seq, time_us, report[hp.O_TAG], report[hp.O_RESULT], report[hp.O_CAL_CH],
                       report[hp.O_CAL_FLAGS], i0, t0, x, y, rp0, report[hp.O_CAL_MODE])
    raise ProtocolError(f"unknown report type 0x{typ:02x}")


def split_stdio_stream(data: bytes):
    """The simulated board's stdout: MAGIC0 MAGIC1 + 64 bytes, repeated."""
    out, k = [], 0
    while k + 66 <= len(data):
        if data[k] == 0xA5 and data[k + 1] == 0x5A:
            out.append(bytes(data[k + 2 : k + 66]))
            k += 66
        else:
            k += 1
    return out


class Commands:
    """OUT report builders with a running tag (a thin layer over hid_protocol's)."""

    def __init__(self):
        self.tag = 0

    def _next(self) -> int:
        self.tag = (self.tag + 1) & 0xFF
        return self.tag

    def arm(self, ch=hp.CH_ALL) -> bytes:
        return bytes(hp.cmd_arm(bytearray(64), ch, self._next()))

    def disarm(self, ch=hp.CH_ALL) -> bytes:
        return bytes(hp.cmd_disarm(bytearray(64), ch, self._next()))

    def calibrate(self, i0_ua, t0_us, x_star_ohm, y_star_pc, ch=hp.CH_ALL) -> bytes:
        return bytes(hp.cmd_calibrate(bytearray(64), ch, i0_ua, t0_us, x_star_ohm, y_star_pc, self._next()))

    def set_limits(self, i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc) -> bytes:
        return bytes(hp.cmd_set_limits(bytearray(64), i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc, self._next()))

    def set_skin(self, rs_ohm, beta_q16, cp_pf, ch=hp.CH_ALL) -> bytes:
        """MODE_FAST's skin model (host/skin.py fits it); (0, 0, 0) removes it."""
        return bytes(hp.cmd_set_skin(bytearray(64), ch, rs_ohm, beta_q16, cp_pf, self._next()))

    def set_mode(self, mode, rate_hz=0) -> bytes:
        return bytes(hp.cmd_set_mode(bytearray(64), mode, rate_hz, self._next()))

    def keepalive(self, timeout_ms=0) -> bytes:
        return bytes(hp.cmd_keepalive(bytearray(64), timeout_ms, self._next()))

    def get_info(self, ch=hp.CH_ALL) -> bytes:
        return bytes(hp.cmd_get_info(bytearray(64), self._next(), ch))
