"""Calibration sweeps for MODE_FAST's skin model, measured on the device (`steadytouch sweep`).

MODE_FAST's model (docs/controller.md, "MODE_FAST with a skin model") is fitted to repeated
sweeps of the pulses `skin.sweep_wide` lists: 11 durations along the mE curve through the
operating pulse (I0, T0), every one at the calibrated pulse energy. This module pulses them on
one channel in open loop (each point: DISARM, CALIBRATE (I, T), ARM, the first pulse's telemetry:
Rp and the decay's log2 tau), sweep after sweep, and appends each reading to a CSV as it comes
(sweep, i_ua, t_us, rp_ohm, ltau_q16: what `steadytouch skin` reads), so an interrupted sweep
keeps every reading taken. Every point is checked against the limits in force before the first
pulse; the channel's calibration and the device's mode are put back afterwards, disarmed.
"""

from __future__ import annotations

import time

import hid_protocol as hp
import sensation_core as sc

from . import skin
from .protocol import STOP_WORDS, Telemetry

FIELDS = ("sweep", "i_ua", "t_us", "rp_ohm", "ltau_q16")
SWEEPS_RANGE = (3, skin.SWEEPS_MOST)  # 3: the fewest whose spread tells the shape's uncertainty


class SweepError(RuntimeError):
    """A sweep that cannot be run or went wrong; the message names the point and the limit."""


def points(i0_ua: int, t0_us: int, info) -> list[tuple[int, int]]:
    """The sweep's pulses for the operating pulse (I0, T0), each checked against the limits in force
    (info: Device.info()); SweepError naming the first that is outside them."""
    pts = skin.sweep_wide(i0_ua, t0_us, info.t_max_us)
    for i, t in pts:
        if not (info.i_min_ua <= i <= info.i_max_ua and info.t_min_us <= t <= info.t_max_us and i * t <= info.q_max_pc):
            raise SweepError(f"the sweep's pulse {i} uA x {t} us (on the mE curve of {i0_ua} uA x {t0_us} us) is "
                             f"outside the limits in force: I {info.i_min_ua}..{info.i_max_ua} uA, T {info.t_min_us}.."
                             f"{info.t_max_us} us, Q <= {info.q_max_pc} pC (`steadytouch limits`, or a smaller I0 x T0)")
    return pts


def read_point(d, ch: int, i_ua: int, t_us: int, timeout_s: float = 5.0) -> tuple[int, int]:
    """Pulse (i_ua, t_us) on channel ch in open loop and return (rp_ohm, ltau_q16) of its first pulse."""
    d.disarm(ch)
    d.calibrate(i_ua, t_us, 0, 0, ch=ch)  # open loop: every pulse is (I0, T0); x*, y* unused
    d.arm(ch)
    end = time.monotonic() + timeout_s
    while True:
        if time.monotonic() > end:
            raise SweepError(f"no pulse at {i_ua} uA x {t_us} us on channel {ch} within {timeout_s:g} s: "
                             "is the device running?")
        rep = d.read(0.5)
        if not isinstance(rep, Telemetry) or rep.channel != ch:
            continue
        if rep.stop in (hp.STOP_IDLE, hp.STOP_DISARMED):  # (a frame from before the ARM took effect)
            continue
        if rep.stop != hp.STOP_NONE:  # a latched stop: electrode off, Rp fault, a hard limit, ...
            raise SweepError(f"channel {ch} stopped at {i_ua} uA x {t_us} us ({STOP_WORDS.get(rep.stop, rep.stop)}): "
                             "check the electrodes' contact, then run the sweep again")
        if rep.t_us != t_us or not rep.i_ua or not 0 <= i_ua - rep.i_ua < 5:  # (one still queued from the point before)
            continue
        if not sc.RP_MIN_OHM <= rep.rp_ohm <= sc.RP_MAX_OHM:
            raise SweepError(f"channel {ch} read Rp {rep.rp_ohm} ohm at {i_ua} uA x {t_us} us, outside "
                             f"{sc.RP_MIN_OHM}..{sc.RP_MAX_OHM} ohm: check the electrodes' contact")
        return rep.rp_ohm, rep.ltau_q16


def run(d, ch: int, pts, k: int, out) -> None:
    """Sweep number k of pts on channel ch (the device in open loop, disarmed between points), each reading
    written to the open CSV `out` at once (flushed: an interruption keeps it)."""
    with d.live():  # keep-alive while pulsing; DISARM however it ends
        for i, t in pts:
            rp, lt = read_point(d, ch, i, t)
            out.write(f"{k},{i},{t},{rp},{lt}\n")
            out.flush()
