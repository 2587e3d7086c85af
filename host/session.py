"""Guided calibration (the paper's Exp. 1 protocol) on a device or the simulator.

For each sensation level: a reference at T = 200 us, then T = 200..700 us in
50 us steps; at each step the person raises or lowers I until it feels like
the reference (the reference can be repeated on demand); then a re-check of
the 200 us point against a 700 us reference. Every presentation is a short
open-loop pulse train on the device (disarmed in between), so the device's own
hard and soft limits apply; the session also never asks for more than the soft
limits. One key stops everything (disarms at once).

Keys: u / + raise I, d / - lower I, r repeat the reference, Enter accept,
q stop.
"""

from __future__ import annotations

import statistics
import sys
import time
from dataclasses import dataclass, field

import numpy as np

import hid_protocol as hp
import sensation_core as sc

from .device import DAC_STEP_MAX_UA, Device, vmon_warning
from .protocol import Telemetry


T_STEPS_US = list(range(200, 701, 50))
STEP = 0.03  # relative change of I per key press


class Stopped(Exception):
    """The person pressed the stop key; the device is disarmed."""


@dataclass
class Presented:
    i_ua: int
    t_us: int
    rp_ohm: float


@dataclass
class SessionResult:
    rows: list[dict] = field(default_factory=list)
    recheck: dict = field(default_factory=dict)
    presentations: int = 0


class Session:
    def __init__(self, dev: Device, responder, channel=0, present_s=0.4, participant="P01", log=print):
        self.d = dev
        self.r = responder
        self.ch = channel
        self.present_s = present_s
        self.participant = participant
        self.log = log
        info = dev.info()
        if vmon_warning(info.vmon_state):
            log(vmon_warning(info.vmon_state))
        self.lim = (info.i_min_ua, info.i_max_ua, info.t_min_us, info.t_max_us, info.q_max_pc)
        self.n_present = 0

    def _clamp(self, i_ua, t_us):
        i_lo, i_hi, _, _, q_max = self.lim
        return int(max(i_lo, min(i_hi, i_ua, q_max // t_us)))

    def present(self, i_ua, t_us) -> Presented:
        """A pulse train at (I, T), open loop, for present_s (and at least 3 pulses);
        Rp = median over its last 10 pulses."""
        i_ua = self._clamp(i_ua, t_us)
        d = self.d
        d.disarm(self.ch)
        d.mode(sc.MODE_OPEN_LOOP)
        d.calibrate(i_ua, t_us, 0, 0, self.ch)
        d.arm(self.ch)
        t0 = time.monotonic()
        rps, t_end, t_give_up = [], t0 + self.present_s, t0 + max(3.0, 3 * self.present_s)
        try:
            while (time.monotonic() < t_end or len(rps) < 3) and time.monotonic() < t_give_up:
                rep = d.read(0.1)
                if isinstance(rep, Telemetry) and rep.channel == self.ch and rep.t_us == t_us \
                        and i_ua - DAC_STEP_MAX_UA <= rep.i_ua <= i_ua:  # delivered: up to a DAC step below
                    rps.append(rep.rp_ohm)
                    if rep.stop not in (hp.STOP_NONE,):
                        break
        finally:
            d.disarm(self.ch)
        self.n_present += 1
        if not rps:
            raise RuntimeError(f"no pulse was measured at {i_ua} uA, {t_us} us: is the electrode on?")
        return Presented(i_ua, t_us, float(statistics.median(rps[-10:])))

    def match(self, ref: Presented, t_us: int, i_start: float, level: str) -> Presented:
        """Let the person adjust I at t_us until it feels like the reference."""
        i = self._clamp(i_start, t_us)
        cur = self.present(i, t_us)
        while True:
            key = self.r.key(level=level, ref=ref, cur=cur)
            if key == "q":
                self.d.disarm()
                raise Stopped()
            if key == "r":
                self.present(ref.i_ua, ref.t_us)
                cur = self.present(cur.i_ua, t_us)
                continue
            if key == "enter":
                return cur
            if key in ("u", "d"):
                f = 1 + STEP if key == "u" else 1 - STEP
                nxt = self._clamp(round(cur.i_ua * f), t_us)
                if nxt == cur.i_ua:  # at a limit: say so, keep presenting
                    self.log(f"  I is at its limit ({cur.i_ua} uA at {t_us} us)")
                cur = self.present(nxt, t_us)

    def run(self, levels: dict[str, int]) -> SessionResult:
        """levels: name -> reference current (uA) at 200 us, e.g. {"weak": 1500, "strong": 2700}."""
        res = SessionResult()
        for level, i_ref in levels.items():
            self.log(f"level {level}: reference {i_ref} uA at {T_STEPS_US[0]} us")
            ref = self.present(i_ref, T_STEPS_US[0])
            res.rows.append(self._row(level, ref))
            prev = ref
            for t in T_STEPS_US[1:]:
                guess = prev.i_ua * (prev.t_us / t) ** 0.5  # start on I^2 T = const
                got = self.match(ref, t, guess, level)
                res.rows.append(self._row(level, got))
                self.log(f"  {t:4d} us: {got.i_ua} uA, Rp {got.rp_ohm / 1e3:.1f} kohm")
                prev = got
            # re-check: the 200 us point again, against the 700 us point as the reference
            again = self.match(prev, T_STEPS_US[0], ref.i_ua, level)
            res.recheck[level] = again.i_ua / ref.i_ua
            self.log(f"  re-check at 200 us against 700 us: {again.i_ua} uA ({again.i_ua / ref.i_ua - 1:+.1%})")
        res.presentations = self.n_present
        self.d.disarm()
        return res

    def _row(self, level, p: Presented) -> dict:
        return {"participant": self.participant, "condition": level, "t_us": p.t_us, "i_ua": p.i_ua,
                "rp_ohm": round(p.rp_ohm, 1)}


class SimResponder:
    """The simulated participant answering with keys: it knows the current that
    matches its reference at each duration (strength-duration law with its own
    exponent), and says up/down until within its just-noticeable difference."""

    def __init__(self, seed=1, a=None, jnd=0.04):
        rng = np.random.default_rng(seed)
        self.a = a if a is not None else float(rng.normal(0.5, 0.02))
        self.jnd = jnd
        self.rng = rng
        self.keys = 0

    def key(self, level, ref: Presented, cur: Presented) -> str:
        self.keys += 1
        target = ref.i_ua * (cur.t_us / ref.t_us) ** (-self.a)
        err = cur.i_ua / target - 1 + self.rng.normal(0, 0.005)
        if err < -self.jnd / 2:
            return "u"
        if err > self.jnd / 2:
            return "d"
        return "enter"


class KeyboardResponder:
    """Single keys from the terminal (no Enter needed for u/d/r/q)."""

    def __init__(self):
        if not sys.stdin.isatty():
            raise RuntimeError("the interactive session needs a terminal (or --participant sim)")

    def key(self, level, ref: Presented, cur: Presented) -> str:
        import termios
        import tty

        print(f"\r  {level}: {cur.i_ua} uA at {cur.t_us} us vs reference {ref.i_ua} uA at {ref.t_us} us "
              "- [u]p [d]own [r]eference Enter=same [q]uit ", end="", flush=True)
        fd = sys.stdin.fileno()
        old = termios.tcgetattr(fd)
        try:
            tty.setcbreak(fd)
            while True:
                c = sys.stdin.read(1)
                if c in ("u", "+", "k"):
                    return "u"
                if c in ("d", "-", "j"):
                    return "d"
                if c in ("r",):
                    return "r"
                if c in ("\n", "\r"):
                    print()
                    return "enter"
                if c in ("q", "\x1b", " "):
                    print()
                    return "q"
        finally:
            termios.tcsetattr(fd, termios.TCSADRAIN, old)
