"""A device behind any transport: decoded reports, lost-report counting, and
commands that wait for their ack (device result codes become DeviceError)."""

from __future__ import annotations

import time
from collections import deque

import hid_protocol as hp

from .protocol import COMMAND_WORDS, Ack, CalInfo, Commands, Info, decode
from .transport import Transport

SEQ_MOD = 1 << 30


class DeviceError(Exception):
    """The device refused a command (or did not answer); the message says which and why."""


class Device:
    def __init__(self, transport: Transport):
        self.t = transport
        self.cmds = Commands()
        self.last_seq: int | None = None
        self.lost = 0
        self.received = 0
        self._pending: deque = deque()

    def _decode(self, raw: bytes):
        rep = decode(raw)
        if self.last_seq is not None:
            self.lost += (rep.seq - self.last_seq - 1) % SEQ_MOD
        self.last_seq = rep.seq
        self.received += 1
        return rep

    def read(self, timeout_s: float = 1.0):
        """The next decoded IN report, or None on timeout."""
        if self._pending:
            return self._pending.popleft()
        raw = self.t.read(timeout_s)
        return None if raw is None else self._decode(raw)

    def command(self, report: bytes, timeout_s: float = 2.0):
        """Send one OUT report; return its Ack/Info; DeviceError if refused or unanswered."""
        self.t.write(report)
        name = COMMAND_WORDS.get(report[0], f"0x{report[0]:02x}")
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise DeviceError(f"no answer to '{name}' within {timeout_s:g} s: is the device running?")
            raw = self.t.read(min(left, 0.2))
            if raw is None:
                continue
            rep = self._decode(raw)
            if isinstance(rep, (Ack, Info, CalInfo)) and rep.tag == report[1] and (
                not isinstance(rep, Ack) or rep.command == report[0]
            ):
                if not rep.ok:
                    raise DeviceError(rep.words() if isinstance(rep, Ack) else f"{name}: result {rep.result}")
                return rep
            self._pending.append(rep)

    # convenience wrappers, each waiting for its ack
    def info(self) -> Info:
        return self.command(self.cmds.get_info())

    def calibration(self, ch: int) -> CalInfo:
        return self.command(self.cmds.get_info(ch))

    def arm(self, ch=hp.CH_ALL):
        return self.command(self.cmds.arm(ch))

    def disarm(self, ch=hp.CH_ALL):
        return self.command(self.cmds.disarm(ch))

    def calibrate(self, i0_ua, t0_us, x_star_ohm, y_star_pc, ch=hp.CH_ALL):
        return self.command(self.cmds.calibrate(i0_ua, t0_us, x_star_ohm, y_star_pc, ch))

    def limits(self, i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc):
        return self.command(self.cmds.set_limits(i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc))

    def mode(self, mode, rate_hz=0):
        return self.command(self.cmds.set_mode(mode, rate_hz))

    def skin(self, rs_ohm, beta_q16, cp_pf, ch=hp.CH_ALL):
        return self.command(self.cmds.set_skin(rs_ohm, beta_q16, cp_pf, ch))

    def keepalive(self, timeout_ms=0):
        return self.command(self.cmds.keepalive(timeout_ms))
