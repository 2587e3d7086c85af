"""A device behind any transport: decoded reports, lost-report counting, and
commands that wait for their ack (device result codes become DeviceError).

Keep-alive: the device stops every armed channel when the host has been silent
for its keep-alive timeout (default 1 s; it cannot be switched off). After
`keep_alive()`, every `read()` and every command's wait sends a KEEPALIVE
whenever the host has written nothing for a quarter of that timeout. The sender
is the thread that reads (a Device belongs to one thread; the transports are
not shared): a host whose loop stalls (a hung plot, a stopped terminal) goes
silent and the device stops, which is what the guard is for. `live()` wraps a
run: keep-alive on, DISARM on the way out whatever ends it."""

from __future__ import annotations

import dataclasses
import signal
import threading
import time
from collections import deque
from contextlib import contextmanager

import hid_protocol as hp
import sensation_core as sc

from .protocol import COMMAND_WORDS, RESULT_WORDS, Ack, CalInfo, Commands, Info, ProtocolError, decode
from .transport import Transport, TransportError

SEQ_MOD = 1 << 30
# The current a board reports for a pulse is its DAC code's, rounded up to the µA: at most one DAC
# step below the command, and a step is the full scale / 4096 — 2.44 µA at the realistic 10 mA, at
# most 24.4 µA at the driver's largest full scale (dac_mcp4822.FULL_UA_MAX, 100 mA). A host that
# waits for the report of a pulse it commanded accepts this far below it.
DAC_STEP_MAX_UA = 25
# SET_MODE refused for its rate byte (the frame does not fit): the ack's words
_RATE_REFUSED = f"{COMMAND_WORDS[hp.CMD_SET_MODE]}: {RESULT_WORDS[hp.RES_OUT_OF_RANGE]} (byte {hp.O_ARG + 1})"


class DeviceError(Exception):
    """The device refused a command (or did not answer); the message says which and why.
    refused: the device answered with an error code (so the command changed nothing);
    False when no answer came (whether it was carried out is unknown)."""

    def __init__(self, message: str, refused: bool = False):
        super().__init__(message)
        self.refused = refused


def vmon_warning(vmon_state: int) -> str | None:
    """One line when the board ignored its stored correction at boot (GET_INFO's vmon_state VMON_BAD: a file
    unreadable, or stored under other windows than this firmware's), else None. Every channel then
    runs uncorrected: its Rp off by the board's own errors, its hard current limit held low."""
    if vmon_state != hp.VMON_BAD:
        return None
    return ("warning: the board ignored its stored correction at boot (vmon_cal.txt unreadable or outside this "
            "firmware's windows): every channel runs uncorrected, its hard current limit held "
            f"{100 - hp.VMON_DAC_PPM_MIN / 1e4:g} % low; run `steadytouch selftest` again")


class Device:
    def __init__(self, transport: Transport):
        self.t = transport
        self.cmds = Commands()
        self.last_seq: int | None = None
        self.lost = 0
        self.received = 0
        self._pending: deque = deque()
        self.bad = 0  # reports that did not decode (skipped while streaming)
        self.ka_ms = 0  # host keep-alive: off until keep_alive()
        self._ka_every_s = 0.0
        self._last_write = time.monotonic()
        self.disarmed: bool | None = None  # after live(): whether the closing DISARM was acknowledged
        self._own_hard: tuple | None = None  # the board's own hard limits (page 1), once asked; () none told

    def _write(self, report: bytes) -> None:
        self.t.write(report)
        self._last_write = time.monotonic()

    def _tick(self) -> float:
        """Send a KEEPALIVE if it is due (its ack is read like any report); return the
        seconds until the next one is due (inf: keep-alive off)."""
        if not self._ka_every_s:
            return float("inf")
        due = self._last_write + self._ka_every_s - time.monotonic()
        if due <= 0.001:
            self._write(self.cmds.keepalive(self.ka_ms))
            due = self._ka_every_s
        return due

    def feed(self, min_age_s: float = 0.05) -> None:
        """Send a KEEPALIVE now (keep-alive on, the last command older than min_age_s): before
        a long stretch of host work between reads (the live view's redraw), so it gets the
        whole timeout rather than what is left of it."""
        if self._ka_every_s and time.monotonic() - self._last_write >= min_age_s:
            self._write(self.cmds.keepalive(self.ka_ms))

    def keep_alive(self, timeout_ms: int = hp.KEEPALIVE_DEFAULT_MS) -> None:
        """Set the device's keep-alive timeout and keep it fed from now on (every timeout/4)."""
        self.keepalive(timeout_ms)
        self.ka_ms = timeout_ms
        self._ka_every_s = timeout_ms / 4000.0

    def safe_disarm(self, timeout_s: float = 1.0) -> bool:
        """DISARM every channel on the way out; False if the device could not be told."""
        self._ka_every_s = 0.0
        # a second Ctrl-C / SIGTERM waits until the DISARM is out (at most timeout_s), then acts
        stoppers = {signal.SIGINT, signal.SIGTERM} | ({signal.SIGHUP} if hasattr(signal, "SIGHUP") else set())
        blocked = hasattr(signal, "pthread_sigmask") and threading.current_thread() is threading.main_thread()
        old = signal.pthread_sigmask(signal.SIG_BLOCK, stoppers) if blocked else None
        try:
            self.command(self.cmds.disarm(), timeout_s=timeout_s)
            return True
        except (DeviceError, TransportError, ProtocolError):
            return False
        finally:
            if blocked:
                signal.pthread_sigmask(signal.SIG_SETMASK, old)

    @contextmanager
    def live(self, timeout_ms: int = hp.KEEPALIVE_DEFAULT_MS, arm: int | None = None):
        """Keep the device alive while the block runs (arm channel `arm` first if
        given); DISARM on any exit: normal, error, Ctrl-C or SIGTERM (cli.main). The
        session begins here: a simulated device starts its scenario now (Transport.begin;
        a wrapper that has none, e.g. a test's recording one, starts nothing)."""
        begin = getattr(self.t, "begin", None)
        if begin is not None:
            begin()
        if self.t.realtime:
            self.keep_alive(timeout_ms)
        try:
            if arm is not None:
                self.arm(arm)
            yield self
        finally:
            try:
                self.disarmed = self.safe_disarm()
            except KeyboardInterrupt:  # a second Ctrl-C that came in before the signals were blocked
                self.disarmed = self.safe_disarm()
                raise

    def _decode(self, raw: bytes):
        rep = decode(raw)
        if self.last_seq is not None:
            self.lost += (rep.seq - self.last_seq - 1) % SEQ_MOD
        self.last_seq = rep.seq
        self.received += 1
        return rep

    def read(self, timeout_s: float = 1.0):
        """The next decoded IN report, or None on timeout. A report that does not
        decode is counted in `bad` and skipped; keep-alives go out while waiting."""
        if self._pending:
            return self._pending.popleft()
        deadline = time.monotonic() + timeout_s
        while True:
            due = self._tick()
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            raw = self.t.read(min(left, due))
            if raw is None:
                continue
            try:
                return self._decode(raw)
            except ProtocolError:
                self.bad += 1

    def command(self, report: bytes, timeout_s: float | None = None):
        """Send one OUT report; return its Ack/Info; DeviceError if refused or unanswered
        within timeout_s (default: the transport's answer_s)."""
        if timeout_s is None:
            timeout_s = getattr(self.t, "answer_s", 2.0)
        self.cmds.forget(report)  # a SET_VMON may move the hard limits in force: read them again before SET_LIMITS
        self._write(report)
        name = COMMAND_WORDS.get(report[0], f"0x{report[0]:02x}")
        deadline = time.monotonic() + timeout_s
        while True:
            due = self._tick()
            left = deadline - time.monotonic()
            if left <= 0:
                raise DeviceError(f"no answer to '{name}' within {timeout_s:g} s: is the device running?")
            raw = self.t.read(min(left, 0.2, due))
            if raw is None:
                continue
            rep = self._decode(raw)
            if isinstance(rep, (Ack, Info, CalInfo)) and rep.tag == report[1] and (
                not isinstance(rep, Ack) or rep.command == report[0]
            ):
                if not rep.ok:
                    if rep.result == hp.RES_BAD_CHANNEL and report[0] != hp.CMD_GET_INFO:
                        raise DeviceError(self._no_such_channel(name, report[hp.O_OUT_CH]), refused=True)
                    raise DeviceError(rep.words() if isinstance(rep, Ack) else f"{name}: result {rep.result}",
                                      refused=True)
                self.cmds.applied(report)  # a new rate or t_max: the host's frame check follows it
                return rep
            self._pending.append(rep)

    def _no_such_channel(self, name: str, ch: int) -> str:
        """A command refused for its channel: the channels the device has (GET_INFO, read now if not yet known)."""
        if self.cmds.frame is None:
            try:
                self.info()
            except (DeviceError, TransportError, ProtocolError):
                return f"{name}: no such channel: {ch} (the device did not say how many it has)"
        n = self.cmds.frame[0]
        return f"{name}: channel {ch} out of range: the device has channel{'s 0..' if n > 1 else ' '}{n - 1}"

    # convenience wrappers, each waiting for its ack
    def info(self) -> Info:
        """GET_INFO: the limits in force. Where they are below the board's own (held, or lowered by a DAC gain
        below 1) the board's own hard limits are asked once (page 1) and carried (Info.nominal), so every
        refusal and `info` name both."""
        info = self.command(self.cmds.get_info())
        if info.lowered_reason() and self._own_hard is None:
            own = self.own_limits()
            self._own_hard = (own.hard_i_max_ua, own.hard_q_max_pc) if own is not None else ()
        if self._own_hard:
            info = dataclasses.replace(info, own_hard=self._own_hard)
        self.cmds.know(info)  # from now on a rate or t_max that cannot fit is refused on the host
        return info

    def own_limits(self) -> Info | None:
        """GET_INFO page 1 (hid_protocol INFO_PAGE_OWN; firmware 0.3.0 on): the board's nominal hard limits and
        its soft limits as last set, before the firmware lowered them to the hard limits in force. None from
        firmware before it: it answers page 0, or refuses the page (an error code: nothing changed)."""
        try:
            own = self.command(self.cmds.get_info(page=hp.INFO_PAGE_OWN))
        except DeviceError as e:
            if e.refused:
                return None
            raise
        return own if own.page == hp.INFO_PAGE_OWN else None

    def calibration(self, ch: int) -> CalInfo:
        return self.command(self.cmds.get_info(ch))

    def arm(self, ch=hp.CH_ALL):
        return self.command(self.cmds.arm(ch))

    def disarm(self, ch=hp.CH_ALL):
        return self.command(self.cmds.disarm(ch))

    def calibrate(self, i0_ua, t0_us, x_star_ohm, y_star_pc, ch=hp.CH_ALL):
        return self.command(self.cmds.calibrate(i0_ua, t0_us, x_star_ohm, y_star_pc, ch))

    def limits(self, i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc):
        """SET_LIMITS, checked first against the hard limits the device reports (GET_INFO, read
        here if not yet known): an i_max or q_max above them, e.g. held for want of a DAC gain,
        is refused on the host with the reason (CommandError), nothing sent."""
        if self.cmds.check and self.cmds.hard is None:
            self.info()
        return self.command(self.cmds.set_limits(i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc))

    def mode(self, mode, rate_hz=0):
        """SET_MODE; a new rate is first checked against the frame the device reports (GET_INFO, read here if not
        yet known: its channels and t_max): a rate that cannot fit is refused on the host naming the rates that
        can (CommandError), nothing sent. The device's own refusal of the rate byte says the same words."""
        if rate_hz and self.cmds.check and self.cmds.frame is None:
            self.info()
        try:
            return self.command(self.cmds.set_mode(mode, rate_hz))
        except DeviceError as e:
            if rate_hz and e.refused and self.cmds.frame is not None and str(e) == _RATE_REFUSED:
                n, _, t_max = self.cmds.frame
                raise DeviceError(f"rate_hz={rate_hz} out of range: the device refused it; with {n} channel(s) and "
                                  f"t_max_us={t_max} it accepts {hp.RATE_MIN_HZ}..{hp.rate_max_fitting(n, t_max)} Hz, "
                                  f"{hp.RATE_MIN_HZ}..{hp.rate_max_fitting(n, t_max, 1)} Hz with a skin model set "
                                  "(hid_protocol.frame_fits)", refused=True) from None
            raise

    def skin(self, rs_ohm, beta_q16, cp_pf, ch=hp.CH_ALL, tau_q16=sc.SKIN_TAU_OFF):
        return self.command(self.cmds.set_skin(rs_ohm, beta_q16, cp_pf, ch, tau_q16))

    def set_vmon(self, ch, gain_ppm, offset_mv, store=False, dac_gain_ppm=0):
        """Channel ch's monitor correction and DAC gain, in RAM (store=False) or also in the board's flash."""
        return self.command(self.cmds.set_vmon(ch, gain_ppm, offset_mv, store, dac_gain_ppm), timeout_s=max(
            5.0, getattr(self.t, "answer_s", 2.0)))

    def set_vmon_all(self, values, store=False):
        """Every channel's correction in one command ([(gain_ppm, offset_mv, dac_gain_ppm)] per
        channel): the device writes its flash once and applies all, or changes nothing."""
        return self.command(self.cmds.set_vmon_all(values, store), timeout_s=max(
            5.0, getattr(self.t, "answer_s", 2.0)))

    def keepalive(self, timeout_ms=hp.KEEPALIVE_DEFAULT_MS):
        return self.command(self.cmds.keepalive(timeout_ms))
