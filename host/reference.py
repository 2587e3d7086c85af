"""Host-side references of the controller law in sensation_core.

- `exact_step`: the law with `fractions.Fraction` (square roots to 2**-64
  relative), the same bound rules as the core, no rounding.
- `float_steps`: the same law vectorised over an array of Rp with numpy float64,
  for analysis and plots.

Both follow docs/controller.md rule for rule; tests check the integer core
against them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

import sensation_core as sc


@dataclass(frozen=True)
class Limits:
    i_min_ua: int
    i_max_ua: int
    t_min_us: int
    t_max_us: int
    q_max_pc: int


@dataclass(frozen=True)
class Calibration:
    i0_ua: int
    t0_us: int
    rp0_ohm: int
    x_star_ohm: int
    y_star_pc: int

    @property
    def me(self) -> int:
        """mE = I0^2 T0 in uA^2*us (Eq. 1)."""
        return self.i0_ua * self.i0_ua * self.t0_us

    @property
    def mq(self) -> Fraction:
        """mQ = (I0 T0 - y*) / (Rp0 - x*) in pC/ohm (Eq. 2)."""
        return Fraction(self.i0_ua * self.t0_us - self.y_star_pc, self.rp0_ohm - self.x_star_ohm)


@dataclass(frozen=True)
class ExactStep:
    i_ua: Fraction
    t_us: Fraction
    status: int
    q_hat_pc: Fraction  # Eq. 3 before any bound (0 on a fault)
    i_free_ua: Fraction  # Eq. 4 after the q_max clamp of Q, before I/T bounds
    t_free_us: Fraction


def _sqrt(x: Fraction) -> Fraction:
    """sqrt(x) to within 2**-64 relative (exact Fractions have no sqrt)."""
    n, d = x.numerator, x.denominator
    return Fraction(math.isqrt((n * d) << 128), d << 64)


def exact_step(lim: Limits, cal: Calibration, rp_ohm: int, mode: int = sc.MODE_AKHTAR) -> ExactStep:
    zero = Fraction(0)
    if rp_ohm < sc.RP_MIN_OHM:
        return ExactStep(zero, zero, sc.ST_RP_LOW, zero, zero, zero)
    if rp_ohm > sc.RP_MAX_OHM:
        return ExactStep(zero, zero, sc.ST_RP_HIGH, zero, zero, zero)
    if mode == sc.MODE_OPEN_LOOP:
        i0, t0 = Fraction(cal.i0_ua), Fraction(cal.t0_us)
        return ExactStep(i0, t0, sc.ST_OK, i0 * t0, i0, t0)
    me = Fraction(cal.me)
    q_hat = cal.mq * (rp_ohm - cal.x_star_ohm) + cal.y_star_pc
    if q_hat <= 0:
        return ExactStep(zero, zero, sc.ST_Q_NONPOS, q_hat, zero, zero)
    st = 0
    q = q_hat
    if q > lim.q_max_pc:
        q = Fraction(lim.q_max_pc)
        st |= sc.ST_Q_MAX
    i_free = me / q
    t_free = q * q / me
    i, t = i_free, t_free
    if t > lim.t_max_us:  # the ceiling keeps the charge on the line
        t = Fraction(lim.t_max_us)
        i = q / t
        st |= sc.ST_T_MAX
    elif t < lim.t_min_us:
        t = Fraction(lim.t_min_us)
        i = _sqrt(me / t)
        st |= sc.ST_T_MIN
    if i < lim.i_min_ua:
        i = Fraction(lim.i_min_ua)
        st |= sc.ST_I_MIN
        t = me / (i * i)
        if t > lim.t_max_us:
            t = Fraction(lim.t_max_us)
            st |= sc.ST_T_MAX
        elif t < lim.t_min_us:
            t = Fraction(lim.t_min_us)
            st |= sc.ST_T_MIN
    elif i > lim.i_max_ua:
        i = Fraction(lim.i_max_ua)
        st |= sc.ST_I_MAX
    if i * t > lim.q_max_pc:
        st |= sc.ST_Q_MAX
        t = lim.q_max_pc / i
        if t < lim.t_min_us:
            t = Fraction(lim.t_min_us)
            i = Fraction(lim.q_max_pc, lim.t_min_us)
    return ExactStep(i, t, st, q_hat, i_free, t_free)


def float_steps(lim: Limits, cal: Calibration, rp_ohm) -> dict[str, np.ndarray]:
    """The law over an array of Rp in float64: keys i_ua, t_us, status, q_hat_pc."""
    rp = np.asarray(rp_ohm, dtype=np.float64)
    me = float(cal.me)
    mq = (cal.i0_ua * cal.t0_us - cal.y_star_pc) / (cal.rp0_ohm - cal.x_star_ohm)
    q_hat = mq * (rp - cal.x_star_ohm) + cal.y_star_pc
    st = np.zeros(rp.shape, dtype=np.int64)
    q = np.minimum(q_hat, lim.q_max_pc)
    st |= np.where(q_hat > lim.q_max_pc, sc.ST_Q_MAX, 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        i = me / q
        t = q * q / me
        hi_t = t > lim.t_max_us
        lo_t = ~hi_t & (t < lim.t_min_us)
        i = np.where(hi_t, q / lim.t_max_us, np.where(lo_t, np.sqrt(me / lim.t_min_us), i))
        t = np.where(hi_t, lim.t_max_us, np.where(lo_t, lim.t_min_us, t))
        st |= np.where(hi_t, sc.ST_T_MAX, 0) | np.where(lo_t, sc.ST_T_MIN, 0)
        lo_i = i < lim.i_min_ua
        hi_i = ~lo_i & (i > lim.i_max_ua)
        t_lo_i = me / float(lim.i_min_ua) ** 2
        st |= np.where(lo_i, sc.ST_I_MIN, 0) | np.where(hi_i, sc.ST_I_MAX, 0)
        st |= np.where(lo_i & (t_lo_i > lim.t_max_us), sc.ST_T_MAX, 0)
        st |= np.where(lo_i & (t_lo_i < lim.t_min_us), sc.ST_T_MIN, 0)
        t = np.where(lo_i, np.clip(t_lo_i, lim.t_min_us, lim.t_max_us), t)
        i = np.where(lo_i, lim.i_min_ua, np.where(hi_i, lim.i_max_ua, i))
        over_q = i * t > lim.q_max_pc
        st |= np.where(over_q, sc.ST_Q_MAX, 0)
        t = np.where(over_q, lim.q_max_pc / i, t)
        short = over_q & (t < lim.t_min_us)
        t = np.where(short, lim.t_min_us, t)
        i = np.where(short, lim.q_max_pc / lim.t_min_us, i)
    fault = np.where(rp < sc.RP_MIN_OHM, sc.ST_RP_LOW, 0) | np.where(rp > sc.RP_MAX_OHM, sc.ST_RP_HIGH, 0)
    fault = np.where(fault == 0, np.where(q_hat <= 0, sc.ST_Q_NONPOS, 0), fault)
    bad = fault != 0
    return {
        "i_ua": np.where(bad, 0.0, i),
        "t_us": np.where(bad, 0.0, t),
        "status": np.where(bad, fault, st),
        "q_hat_pc": np.where(bad, 0.0, q_hat),
    }
