"""sensation_core: integer-only controller of Akhtar et al., Sci. Robot. 2018.

The paper's law, one function each: calibration mE = I0^2 T0 (Eq. 1,
Controller._set_me) and mQ = (Q0 - y*) / (Rp0 - x*) (Eq. 2, Controller._set_mq);
then, every pulse, the charge on the Q-Rp line Q = mQ (Rp - x*) + y* (Eq. 3,
_line) and the pulse I = mE / Q, T = Q^2 / mE (Eq. 4, _from_q, with the
bounds). Faults and bounds: Controller.update and _from_q; the baseline modes:
_fixed_current (the three are functions of the Controller, also its methods). MODE_FAST's step
is in fast_step.py, its skin model in skin_model.py (and skin_tau.py), the integer arithmetic in
fixmath.py. docs/controller.md maps every rule to its function.

Runs unchanged on CPython >= 3.10 and MicroPython >= 1.23 (RP2040). Every intermediate value stays
below 2**30 in magnitude, so a 32-bit MicroPython port never promotes to a heap-allocated long int,
and `Controller.update` allocates nothing. Formats and error bounds: docs/fixed-point.md.
Units: current uA, duration us, resistance ohm, charge pC (= uA*us), voltage mV.
"""

from array import array

try:
    import micropython
    from micropython import const
except ImportError:  # CPython: the decorator does nothing, ptr32 indexes the array itself

    class micropython:  # noqa: N801 (stands in for the module's decorators)
        viper = native = staticmethod(lambda f: f)

    def const(x):
        return x

    def ptr32(a):
        return a


from fast_step import FAST_ELASTICITY_Q12, Pulse, fast_pulse  # noqa: F401  (FAST_*: the public API)
from fixmath import div2, div_small, isqrt_round, log2q, muldiv, rp_from_vp, word  # noqa: F401 (rp_from_vp: the API)
from skin_model import (  # noqa: F401  (SKIN_*, FAST_MODEL_*: the public API)
    FAST_MODEL_RAISE_LOG2, FAST_MODEL_WORK_MAX, SKIN_BETA_MAX_Q16, SKIN_BETA_MIN_Q16, SKIN_CP_MAX_PF, SKIN_CP_MIN_PF,
    SKIN_RS_MAX_OHM, SKIN_TAU_MAX_Q16, SKIN_TAU_OFF, SkinModel,
)

VERSION = "0.1.0"

# ---- hard envelope of the arithmetic (no configuration may exceed these) ----
I_LIMIT_UA = const(20000)  # largest i_max_ua; i**2 < 2**29
T_LIMIT_US = const(8000)  # largest t_max_us; sqrt(T*T0) < 2**13
Q_LIMIT_PC = const(33554432)  # 2**25 pC = 33.5 uC, largest q_max_pc
RP_MIN_OHM = const(500)  # valid measured Rp range; outside it -> fault
RP_MAX_OHM = const(200000)
X_STAR_MIN_OHM = const(-20000)  # x* in [X_STAR_MIN_OHM, 0]
VP_LIMIT_MV = const(1000000)  # rp_from_vp: larger Vp reads as "electrode off"
RP_INVALID = const(-1)  # rp_from_vp result for a non-positive current
RP_OVER = const(1073741823)  # rp_from_vp result for Vp beyond VP_LIMIT_MV

# ---- status bit flags (Controller.status) ----
ST_OK = const(0)
ST_I_MIN = const(0x001)  # I held at i_min (T solved from mE where possible)
ST_I_MAX = const(0x002)  # I held at i_max (mE not kept: safety)
ST_T_MIN = const(0x004)  # T held at t_min, I solved from mE
ST_T_MAX = const(0x008)  # T at the ceiling: I = ceil(Q/t_max), T = Q/I <= t_max (charge on the line, not mE)
ST_Q_MAX = const(0x010)  # charge limited to q_max
ST_RP_LOW = const(0x020)  # fault: Rp below RP_MIN_OHM (or at/below x*)
ST_RP_HIGH = const(0x040)  # fault: Rp above RP_MAX_OHM (electrode off)
ST_Q_NONPOS = const(0x080)  # fault: estimated charge <= 0
ST_UNCALIBRATED = const(0x100)  # fault: update() before calibrate()
ST_BOUND_MASK = const(0x01F)
ST_FAULT_MASK = const(0x1E0)

# ---- controller modes (Controller.set_mode) ----
MODE_OPEN_LOOP = const(0)  # fixed I0, T0 (for comparison); faults still stop
MODE_CONSTANT_CHARGE = const(1)  # Kantor: I*T held at I0*T0 (split as at calibration)
MODE_CONSTANT_ENERGY = const(2)  # Tachi: Vp*I*T held, I fixed: T = T0 * Rp0 / Rp
MODE_PULSE_WIDTH_LINEAR = const(3)  # Kajimoto-style: T = a + b*Rp, I fixed
MODE_AKHTAR = const(4)  # the paper's Eqs. 1-4 (default)
MODE_FAST = const(5)  # the paper's target, reached sooner (fast_step.py, docs/controller.md)
MODES = (MODE_OPEN_LOOP, MODE_CONSTANT_CHARGE, MODE_CONSTANT_ENERGY, MODE_PULSE_WIDTH_LINEAR, MODE_AKHTAR, MODE_FAST)

_M15 = const(0x7FFF)
_T_SAT = const(0x8000)  # "T >= 2**15 us": beyond every t_max
_MQ_CAP = const(0x1FFFFFFF)

# the law's constants and the limits as words of one array, Controller._k (set_limits, calibrate, set_mode
# write it and the attributes of the same name): on the chip an attribute lookup costs ~2 us, a word read by
# viper nothing. Never negative (a 64-bit viper reads a ptr32 word unsigned): x* is kept as -x*.
_K_MODE = const(0)
_K_IMIN = const(1)  # i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc
_K_IMAX = const(2)
_K_TMIN = const(3)
_K_TMAX = const(4)
_K_QMAX = const(5)
_K_I0 = const(6)  # i0_ua (0: not calibrated), t0_us, rp0_ohm, -x_star_ohm
_K_T0 = const(7)
_K_RP0 = const(8)
_K_XSN = const(9)
_K_ME_HI = const(10)  # Eq. 1: mE = _k[_K_ME_HI] * 2**15 + _k[_K_ME_LO] (uA^2 us)
_K_ME_LO = const(11)
_K_MQN = const(12)  # _mq_num_pc, _mq_den_ohm, _y_q4 (y* in 1/16 pC), _line_cap_q4
_K_MQD = const(13)
_K_YQ4 = const(14)
_K_LCAP = const(15)
_K_RP = const(16)  # update's Rp, echoed
_K_B = const(17)  # 5 words: the pulse before the last, c.before (fast_step.Pulse: I, T, Q, Rp, clean)
_K_I = const(22)  # the next pulse and its status: c.i_ua, c.t_us, c.status (properties over the words:
_K_T = const(23)  # on the chip a plain attribute stored on an instance of a class with a property costs
_K_ST = const(24)  # ~25 us, a word nothing, so every attribute update() and MODE_FAST write is one)
_K_RPG = const(25)  # rp_ohm, the Rp last given to update() (_K_RPF 1: past +-2**30, in c._rp_big)
_K_MQL = const(26)  # mq_last_fc_per_ohm + _W_BIAS, drift_ohm + _W_BIAS (signed: a 64-bit viper reads unsigned)
_K_DR = const(27)
_K_FJ = const(28)  # fast_jumps, model_jumps, model_cuts
_K_MJ = const(29)
_K_MC = const(30)
_K_RPF = const(31)
_K_ME = const(32)  # me_ua2ms (mE in uA^2 ms: uA^2 us / 1000, floored), mq_target_fc_per_ohm (mQ in fC/ohm)
_K_MQT = const(33)
_K_LT = const(34)  # ltau_q16 (log2 tau, decay.ltau_q16), told for the next update: it moves it to _K_LTU (rule 7)
_K_LTU = const(35)
_K_N = const(36)
_W_BIAS = const(0x20000000)
_RP_LO = RP_MIN_OHM  # as an object


def _check(name, v, lo, hi):
    if not (lo <= v <= hi):
        raise ValueError("%s=%d out of range [%d, %d]" % (name, v, lo, hi))


@micropython.viper
def _line(c, rp_ohm: int) -> int:
    """Eq. 3: Q = mQ (Rp - x*) + y*, in 1/16 pC, saturating above q_max (Rp valid)."""
    k = ptr32(c._k)
    return k[_K_YQ4] + int(muldiv(k[_K_MQN], rp_ohm + k[_K_XSN], k[_K_MQD], 4, k[_K_LCAP]))


@micropython.viper
def _fixed_current(c, mode: int, rp_ohm: int) -> int:
    """The baseline laws: I = I0; T from the mode's law, then the bounds (viper, c._k)."""
    k = ptr32(c._k)
    t0 = k[_K_T0]
    t = t0  # MODE_OPEN_LOOP, MODE_CONSTANT_CHARGE (I0 * T0 held)
    if mode == MODE_CONSTANT_ENERGY:  # Rp I0^2 T = Rp0 I0^2 T0
        t = int(muldiv(t0, k[_K_RP0], rp_ohm, 1, _MQ_CAP))
        t = (t + 1) >> 1  # rounded
    elif mode == MODE_PULSE_WIDTH_LINEAR:  # tangent of Eq. 4 at Rp0: dT/dRp = 2 mQ / I0
        dr = rp_ohm - k[_K_RP0]
        x = int(muldiv(k[_K_MQN], dr if dr >= 0 else 0 - dr, k[_K_MQD], 1, _MQ_CAP))  # 2 mQ |dRp| in pC
        x = (x + (k[_K_I0] >> 1)) // k[_K_I0]
        t = t0 + x if dr >= 0 else t0 - x
    i = k[_K_I0]
    st = ST_OK  # then the bounds
    if t > k[_K_TMAX]:
        t = k[_K_TMAX]
        st = ST_T_MAX
    elif t < k[_K_TMIN]:
        t = k[_K_TMIN]
        st = ST_T_MIN
    if i * t > k[_K_QMAX]:
        t = k[_K_QMAX] // i
        st |= ST_Q_MAX
    k[_K_I] = i  # (c.i_ua, c.t_us, c.status)
    k[_K_T] = t
    k[_K_ST] = st
    return st


@micropython.viper
def _from_q(c, qf: int) -> int:
    """Eq. 4 and every bound, from a charge estimate in 1/16 pC (> 0). (viper: machine
    integers, every value below 2**30; the law from c._k; calls: div2, at the floor isqrt.)"""
    k = ptr32(c._k)
    st = ST_OK
    if qf > k[_K_QMAX] << 4:
        qf = k[_K_QMAX] << 4
        st = ST_Q_MAX
    # Eq. 4: I = 16 mE / qf (rounded), T = Q^2 / mE: with v = Q / i0 (= sqrt(T * t0)) in
    # Q.16, T = v^2 / t0 (rounded); _T_SAT if v >= 2**13 (T >= 2**26 / t0 > T_LIMIT_US)
    i0 = k[_K_I0]
    t0 = k[_K_T0]
    q1 = qf // i0
    t = _T_SAT
    if q1 < 0x20000:
        v = (q1 << 12) + ((qf - q1 * i0) << 12) // i0  # < 2**29
        h = v >> 15
        lo = v & _M15
        sq = ((h * h) << 1) + ((h * lo + ((lo * lo) >> 16)) >> 13)  # v^2 / 2**29
        t = (sq + (t0 << 2)) // (t0 << 3)
    t_min = k[_K_TMIN]
    t_max = k[_K_TMAX]
    # duration bounds. Ceiling (ours: the paper has none): keep the charge on the Q-Rp line
    # at T <= t_max: I = ceil(Q / t_max), T = round(Q / I), so I*T is within I/2 pC of Q (mE then above).
    # Floor (Discussion: a sensation threshold): hold T, solve I from mE.
    if t > t_max:
        i = (qf + (t_max << 4) - 1) // (t_max << 4)
        if k[_K_I] == i + 1:  # 1 uA of hysteresis: I does not flip between neighbours (c.i_ua)
            i += 1  # (Rp follows I, so the line's charge for I lies between the two)
        t = t_max
        if i <= k[_K_IMAX]:  # (above it the current ceiling below holds I at i_max)
            t = (qf + (i << 3)) // (i << 4)
            if t < t_min:  # T pinned (t_min near t_max): the current nearest Q / t_min (never above I)
                t = t_min
                i = (qf + (t_min << 3)) // (t_min << 4)
        st |= ST_T_MAX
    elif t < t_min:
        t = t_min
        i = int(isqrt_round(div_small(k[_K_ME_HI], k[_K_ME_LO], t_min)))
        st |= ST_T_MIN
    else:  # I from mE only where T is within its bounds (each bound sets its own: a call spared)
        i = int(div2((k[_K_ME_HI] << 4) + (k[_K_ME_LO] >> 11), (k[_K_ME_LO] << 4) & _M15, qf, 1))
    # current bounds: floor holds I and solves T; ceiling is safety (no mE)
    i_min = k[_K_IMIN]
    i_max = k[_K_IMAX]
    if i < i_min:
        i = i_min
        st |= ST_I_MIN
        t = int(div2(k[_K_ME_HI], k[_K_ME_LO], i * i, 1))
        if t > t_max:
            t = t_max
            st |= ST_T_MAX
        elif t < t_min:
            t = t_min
            st |= ST_T_MIN
    elif i > i_max:
        i = i_max
        st |= ST_I_MAX
    # charge ceiling (safety): shorten the pulse, then lower the current
    q_max = k[_K_QMAX]
    if i * t > q_max:
        st |= ST_Q_MAX
        t = q_max // i
        if t < t_min:
            t = t_min
            i = q_max // t_min
    elif st == ST_OK and k[_K_MODE] == MODE_FAST:
        # the integer pulse nearest the charge: I = round(Q / T), so I*T is
        # within T/2 pC of Q (mE then within 1/(2T) of its value)
        i2 = (qf + (t << 3)) // (t << 4)
        if i_min <= i2 and i2 <= i_max and i2 * t <= q_max:
            i = i2
    k[_K_I] = i  # (c.i_ua, c.t_us, c.status)
    k[_K_T] = t
    k[_K_ST] = st
    return st


class Controller:
    """Constant-sensation controller for one electrode channel.

    c = Controller(i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc)
    c.calibrate(i0_ua, t0_us, rp0_ohm, x_star_ohm, y_star_pc)
    status = c.update(rp_ohm)   # -> c.i_ua, c.t_us for the next pulse
    """

    i_ua, t_us, status = word(_K_I), word(_K_T), word(_K_ST)  # the next pulse (the one measured, in update)
    mode, me_ua2ms, mq_target_fc_per_ohm = word(_K_MODE), word(_K_ME), word(_K_MQT)  # (set_mode, calibrate)
    mq_last_fc_per_ohm, drift_ohm = word(_K_MQL, _W_BIAS), word(_K_DR, _W_BIAS)  # (see _K_I)
    fast_jumps, model_jumps, model_cuts, ltau_q16 = word(_K_FJ), word(_K_MJ), word(_K_MC), word(_K_LT)
    rp_ohm = property(lambda c: c._rp_big if c._k[_K_RPF] else c._k[_K_RPG], lambda c, x: c._rp(x))
    skin_tau_q16 = property(lambda c: c.skin.tau_gain_q16 if c.skin.tau_ok else SKIN_TAU_OFF)  # (set_skin's tau_q16)

    def _rp(self, x):  # rp_ohm's setter: a small int in c._k, else the int itself in c._rp_big (allocates nothing)
        big = 0 if -0x3FFFFFFF <= x <= 0x3FFFFFFF else 1
        self._k[_K_RPG] = 0 if big else x
        self._k[_K_RPF] = big
        if big:
            self._rp_big = x

    def __init__(self, i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc):
        self.skin = SkinModel(self)  # MODE_FAST's skin model (set_skin), built once
        self._k = self.v = array("i", bytes(4 * _K_N))  # the law, the limits, the next pulse: viper reads them
        self.before = Pulse(self._k)  # MODE_FAST: the pulse measured before the one just measured
        self.set_limits(i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc)
        self.mode = MODE_AKHTAR
        self.i0_ua = self.t0_us = self.rp0_ohm = self.x_star_ohm = self.y_star_pc = 0  # calibrate() sets them
        self._mq_num_pc, self._mq_den_ohm = 0, 1  # Eq. 2: mQ = _mq_num_pc / _mq_den_ohm = (Q0 - y*) / (Rp0 - x*)
        self._y_q4 = self._q_max_q4 = self._line_cap_q4 = 0  # y*, q_max, q_max - y* (Eq. 3 saturates) in 1/16 pC
        self._rp_big = self.mq_last_fc_per_ohm = self.drift_ohm = 0  # (words but _rp_big: _K_RPG ... _K_MC)
        self.skin_rs_ohm = self.skin_beta_q16 = self.skin_cp_pf = 0  # the skin model as set (set_skin; 0 = none)
        # the frame's call, bound once (a method is found after a miss in this map: ~15 us on the chip)
        self.update = self.update

    def set_limits(self, i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc):
        """Current, duration and charge limits; ValueError (nothing changed) if out
        of range. The calibration is dropped: calibrate() again before update()."""
        _check("i_max_ua", i_max_ua, 1, I_LIMIT_UA)
        _check("i_min_ua", i_min_ua, 1, i_max_ua)
        _check("t_max_us", t_max_us, 1, T_LIMIT_US)
        _check("t_min_us", t_min_us, 1, t_max_us)
        _check("q_max_pc", q_max_pc, i_min_ua * t_min_us, Q_LIMIT_PC)
        k = self._k
        k[_K_I0] = 0  # not calibrated
        k[_K_IMIN] = self.i_min_ua = i_min_ua
        k[_K_IMAX] = self.i_max_ua = i_max_ua
        k[_K_TMIN] = self.t_min_us = t_min_us
        k[_K_TMAX] = self.t_max_us = t_max_us
        k[_K_QMAX] = self.q_max_pc = q_max_pc
        self.skin.limits(i_min_ua, i_max_ua, t_max_us, q_max_pc)
        self.calibrated = False
        self.i_ua = self.t_us = 0
        self.status = ST_UNCALIBRATED

    def calibrate(self, i0_ua, t0_us, rp0_ohm, x_star_ohm, y_star_pc):
        """Set mE and mQ from a first pulse (i0, t0) that felt right, Rp0 on it.

        Raises ValueError (nothing changed) when an input is out of range. The
        next pulse is (i0, t0), which is also what the law gives at Rp0.
        """
        _check("i0_ua", i0_ua, self.i_min_ua, self.i_max_ua)
        _check("t0_us", t0_us, self.t_min_us, self.t_max_us)
        q0 = i0_ua * t0_us
        _check("i0_ua*t0_us", q0, 1, self.q_max_pc)
        _check("rp0_ohm", rp0_ohm, RP_MIN_OHM, RP_MAX_OHM)
        _check("x_star_ohm", x_star_ohm, X_STAR_MIN_OHM, 0)
        _check("y_star_pc", y_star_pc, 0, q0 - 1)
        self._set_me(i0_ua, t0_us)
        self._set_mq(q0, rp0_ohm, x_star_ohm, y_star_pc)
        k = self._k
        k[_K_YQ4] = self._y_q4 = y_star_pc << 4
        self._q_max_q4 = self.q_max_pc << 4
        k[_K_LCAP] = self._line_cap_q4 = (self.q_max_pc - y_star_pc) << 4
        k[_K_I0] = self.i0_ua = i0_ua
        k[_K_T0] = self.t0_us = t0_us
        k[_K_RP0] = self.rp0_ohm = rp0_ohm
        k[_K_XSN] = -x_star_ohm
        self.x_star_ohm = x_star_ohm
        self.y_star_pc = y_star_pc
        self.skin.law(self)
        self.mq_last_fc_per_ohm = self.mq_target_fc_per_ohm
        self._forget()
        self.rp_ohm = rp0_ohm
        self.i_ua = i0_ua
        self.t_us = t0_us
        self.status = ST_OK
        self.calibrated = True

    def _set_me(self, i0_ua, t0_us):
        """Eq. 1: mE = I0^2 T0 (uA^2 us), in two 15-bit limbs (it passes 2**30)."""
        i2 = i0_ua * i0_ua
        p = (i2 & _M15) * t0_us
        eh = (i2 >> 15) * t0_us + (p >> 15)
        el = p & _M15
        k = self._k
        k[_K_ME_HI] = eh
        k[_K_ME_LO] = el
        self.me_ua2ms = div_small(eh, el, 1000)

    def _set_mq(self, q0_pc, rp0_ohm, x_star_ohm, y_star_pc):
        """Eq. 2: mQ = (Q0 - y*) / (Rp0 - x*), kept as numerator (pC) and denominator (ohm)."""
        self._k[_K_MQN] = self._mq_num_pc = q0_pc - y_star_pc
        self._k[_K_MQD] = self._mq_den_ohm = rp0_ohm - x_star_ohm
        self.mq_target_fc_per_ohm = muldiv(self._mq_num_pc, 1000, self._mq_den_ohm, 0, _MQ_CAP)

    def set_mode(self, mode):
        """Select one of MODES (MODE_AKHTAR is the default); ValueError otherwise."""
        if not MODE_OPEN_LOOP <= mode <= MODE_FAST:
            raise ValueError("mode=%d out of range [%d, %d]" % (mode, MODE_OPEN_LOOP, MODE_FAST))
        if mode != self.mode:
            self._forget()
        self.mode = mode

    def set_skin(self, rs_ohm, beta_q16, cp_pf, tau_q16=SKIN_TAU_OFF):
        """MODE_FAST's electrode model (skin_model.py): series resistance Rs (ohm), current exponent beta (Q.16) and
        capacitance Cp (pF) of the pair, as fitted to the calibration pulses (host/skin.py), and the monitor's tau
        gain measured on them (log2 tau read / the skin's, Q.16; SKIN_TAU_OFF: rule 7 does not read tau). All three
        0: no model (and tau off). ValueError (nothing changed) when out of range."""
        if rs_ohm != 0 or beta_q16 != 0 or cp_pf != 0:
            _check("rs_ohm", rs_ohm, 0, SKIN_RS_MAX_OHM)
            _check("beta_q16", beta_q16, SKIN_BETA_MIN_Q16, SKIN_BETA_MAX_Q16)
            _check("cp_pf", cp_pf, SKIN_CP_MIN_PF, SKIN_CP_MAX_PF)
            if tau_q16 != SKIN_TAU_OFF:
                _check("tau_q16", tau_q16, -SKIN_TAU_MAX_Q16, SKIN_TAU_MAX_Q16)
        elif tau_q16 != SKIN_TAU_OFF:
            raise ValueError("tau_q16=%d with no skin model (off: %d)" % (tau_q16, SKIN_TAU_OFF))
        self.skin.set(rs_ohm, beta_q16, cp_pf)
        if tau_q16 != SKIN_TAU_OFF:
            self.skin.set_tau(1, tau_q16)
        self.skin_rs_ohm, self.skin_beta_q16, self.skin_cp_pf = rs_ohm, beta_q16, cp_pf

    @micropython.viper
    def delivered(self, i_ua, t_us, status):
        """The pulse delivered and its status bits where not the last output (the supervisor held or capped it): update()
        measures mQ, MODE_FAST's secant and path on them (stim._control: inline; docs/safety.md). Past q_max: the paper's step."""
        self.i_ua = i_ua
        self.t_us = t_us
        self.status = status

    def stop(self, status):
        """Next pulse: none (i_ua = t_us = 0), with the given fault status."""
        self._forget()
        self.i_ua = self.t_us = 0
        self.status = status
        return status

    def _forget(self):
        """MODE_FAST forgets the pulses it measured (new calibration, mode or a fault)."""
        self.before.clean = 0
        self.before.rp_ohm = 0
        self.drift_ohm = 0
        self.skin.jumped = 0

    @micropython.viper
    def update(self, rp_ohm) -> int:
        """Rp measured on the last pulse -> self.i_ua, self.t_us; returns status. (viper: the
        law's constants from self._k; Rp's range is checked on the object: every int.)"""
        ka = self._k
        k = ptr32(ka)
        k[_K_LTU] = k[_K_LT]  # the decay's tau is this update's only (a stale one never meets a later Rp)
        k[_K_LT] = 0
        if not k[_K_I0]:  # (below: the fault rules)
            return int(self.stop(ST_UNCALIBRATED))
        rp = int(rp_ohm)  # a machine word: an int beyond it is caught by the echo through _k
        if rp >= RP_MIN_OHM and rp <= RP_MAX_OHM:  # (Rp < RP_MIN_OHM also covers Rp <= x*, as x* <= 0)
            k[_K_RP] = rp
        if rp < RP_MIN_OHM or rp > RP_MAX_OHM or ka[_K_RP] != rp_ohm:
            self.rp_ohm = rp_ohm  # (the int given, a machine word or not)
            k[_K_MQL] = _W_BIAS  # (self.mq_last_fc_per_ohm = 0)
            return int(self.stop(ST_RP_LOW if rp_ohm < _RP_LO else ST_RP_HIGH))
        k[_K_RPG] = rp  # (self.rp_ohm)
        k[_K_RPF] = 0
        i_k = k[_K_I]  # the pulse this Rp was measured on (self.i_ua, self.t_us)
        t_k = k[_K_T]
        q_k = i_k * t_k
        mq = 0  # its mQ (telemetry)
        if i_k > 0:
            n = q_k - (k[_K_YQ4] >> 4)  # Q - y*
            mq = int(muldiv(n if n >= 0 else 0 - n, 1000, rp + k[_K_XSN], 0, _MQ_CAP))
            if n < 0:
                mq = 0 - mq
        k[_K_MQL] = mq + _W_BIAS  # (self.mq_last_fc_per_ohm)
        mode = k[_K_MODE]
        if mode < MODE_AKHTAR:
            return int(_fixed_current(self, mode, rp))
        qf = int(_line(self, rp))
        if qf <= 0:
            return int(self.stop(ST_Q_NONPOS))
        if mode != MODE_FAST or q_k > k[_K_QMAX]:  # (past q_max: told by delivered(), no jump from it)
            if mode == MODE_FAST:
                self._forget()
            return int(_from_q(self, qf))
        st = int(fast_pulse(self, qf, q_k, rp_ohm, _line, _from_q))
        k[_K_B] = i_k  # c.before, for the next secant, drift and two-pulse fit
        k[_K_B + 1] = t_k
        k[_K_B + 2] = q_k
        k[_K_B + 3] = rp
        k[_K_B + 4] = 1 if (st == ST_OK and q_k > 0) else 0
        return st

    # Eq. 3, Eq. 4 with the bounds, the baseline modes: module functions, also methods
    _line = _line
    _from_q = _from_q
    _fixed_current = _fixed_current
