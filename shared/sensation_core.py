"""sensation_core: integer-only controller of Akhtar et al., Sci. Robot. 2018.

Runs unchanged on CPython >= 3.10 and MicroPython >= 1.23 (RP2040). Every
intermediate value stays below 2**30 in magnitude, so a 32-bit MicroPython port
never promotes to a heap-allocated long int, and `Controller.update` allocates
nothing. Formats and error bounds: docs/fixed-point.md; rules: docs/controller.md.

Units: current uA, duration us, resistance ohm, charge pC (= uA*us), voltage mV.
"""

try:
    from micropython import const
except ImportError:  # CPython

    def const(x):
        return x


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
MODE_FAST = const(5)  # the paper's target, reached by a Newton step (docs/controller.md)
MODES = (MODE_OPEN_LOOP, MODE_CONSTANT_CHARGE, MODE_CONSTANT_ENERGY, MODE_PULSE_WIDTH_LINEAR, MODE_AKHTAR, MODE_FAST)

_M11 = const(0x7FF)
_M15 = const(0x7FFF)
_SAT15 = const(0x8000)  # "at least 2**15": larger than any bound
_SAT30 = const(0x3FFFFFFF)
_MQ_CAP = const(0x1FFFFFFF)
# MODE_FAST's prior: the least elasticity d(ln Rp)/d(ln Q) of the skin along the mE
# curve, in Q.12 (0.45: the current exponent beta >= 0.5 less the series resistance)
FAST_ELASTICITY_Q12 = const(1843)


def _muldiv(a, b, c, fbits, cap):
    """floor(a * b * 2**fbits / c), or cap + 1 if that exceeds cap.

    Needs 0 <= a < 2**30, 0 <= b <= 2**18, 256 <= c <= 2**18, 0 <= fbits <= 11,
    0 <= cap < 2**29. Long division over 11-bit limbs of a: every partial value
    is < 2**30.
    """
    x = (a >> 22) * b
    q = x // c
    r = x - q * c
    if q > cap >> (22 + fbits):
        return cap + 1
    x = (r << 11) + ((a >> 11) & _M11) * b
    d = x // c
    q = (q << 11) + d
    r = x - d * c
    if q > cap >> (11 + fbits):
        return cap + 1
    x = (r << 11) + (a & _M11) * b
    d = x // c
    q = (q << 11) + d
    r = x - d * c
    if q > cap >> fbits:
        return cap + 1
    if fbits:
        q = (q << fbits) + (r << fbits) // c
        if q > cap:
            return cap + 1
    return q


def _div2(hi, lo, dv, rnd):
    """(hi * 2**15 + lo) / dv, floored (rnd=0) or rounded half up (rnd=1).

    Needs 0 <= lo < 2**15, 1 <= dv <= 2**29. Returns _SAT15 when the quotient
    is >= 2**15. Restoring division, one bit per step: r < dv, so 2r+1 < 2**30.
    """
    if hi >= dv:
        return _SAT15
    r = hi
    q = 0
    bit = 0x4000
    while bit:
        r = r + r
        if lo & bit:
            r += 1
        q = q + q
        if r >= dv:
            r -= dv
            q += 1
        bit >>= 1
    if rnd and r + r >= dv:
        q += 1
    return q


def _div_small(hi, lo, dv):
    """floor((hi * 2**15 + lo) / dv) for 1 <= dv < 2**15; _SAT30 if >= 2**30."""
    q = hi // dv
    if q >= _SAT15:
        return _SAT30
    r = hi - q * dv
    return (q << 15) + ((r << 15) + lo) // dv


def _isqrt_round(n):
    """sqrt(n) rounded to nearest, for 0 <= n < 2**30 (digit-by-digit)."""
    r = 0
    b = 0x10000000
    while b > n:
        b >>= 2
    while b:
        if n >= r + b:
            n -= r + b
            r = (r >> 1) + b
        else:
            r >>= 1
        b >>= 2
    if n > r:  # n is now N - r*r; N >= (r + 1/2)**2  <=>  N - r*r > r
        r += 1
    return r


def _t_from_qf(qf, i0, t0):
    """round(Q^2 / mE) with Q = qf / 16 pC, mE = i0^2 t0; _SAT15 if huge.

    v = Q / i0 (= sqrt(T * t0)) in Q.16; T = v^2 / t0.
    """
    q1 = qf // i0
    if q1 >= 0x20000:  # v >= 2**13 -> T >= 2**26 / t0 > T_LIMIT_US
        return _SAT15
    v = (q1 << 12) + ((qf - q1 * i0) << 12) // i0  # < 2**29
    h = v >> 15
    lo = v & _M15
    sq = ((h * h) << 1) + ((h * lo + ((lo * lo) >> 16)) >> 13)  # v^2 / 2**29
    return (sq + (t0 << 2)) // (t0 << 3)


def _frac12(x, den):
    """floor(x * 2**12 / den) for 0 <= x < 2**27, 1 <= den < 2**25 (4-bit steps)."""
    q = x // den
    r = x - q * den
    k = 0
    while k < 3:
        r = r << 4
        d = r // den
        q = (q << 4) + d
        r = r - d * den
        k += 1
    return q


def _least_elastic(x):
    """x * FAST_ELASTICITY_Q12 / 2**12, floored, for 0 <= x < 2**30 (split: < 2**30)."""
    return (x >> 12) * FAST_ELASTICITY_Q12 + (((x & 0xFFF) * FAST_ELASTICITY_Q12) >> 12)


def _check(name, v, lo, hi):
    if not (lo <= v <= hi):
        raise ValueError("%s=%d out of range [%d, %d]" % (name, v, lo, hi))


def rp_from_vp(vp_mv, i_ua):
    """Peak resistance in ohm from peak voltage (mV) and current (uA), rounded.

    Returns RP_INVALID for i_ua <= 0 or vp_mv < 0 (update() faults on it) and
    RP_OVER for vp_mv > VP_LIMIT_MV (update() reads it as electrode off).
    """
    if i_ua <= 0 or vp_mv < 0:
        return RP_INVALID
    if vp_mv > VP_LIMIT_MV:
        return RP_OVER
    return (vp_mv * 1000 + (i_ua >> 1)) // i_ua


class Controller:
    """Constant-sensation controller for one electrode channel.

    c = Controller(i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc)
    c.calibrate(i0_ua, t0_us, rp0_ohm, x_star_ohm, y_star_pc)
    status = c.update(rp_ohm)   # -> c.i_ua, c.t_us for the next pulse
    """

    def __init__(self, i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc):
        self.set_limits(i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc)
        self.mode = MODE_AKHTAR
        self.rp_ohm = 0  # last Rp given to update()
        self.me_ua2ms = 0  # mE in uA^2*ms (= uA^2*us / 1000), floored
        self.mq_target_fc_per_ohm = 0  # target mQ in fC/ohm (= 1e-3 pC/ohm)
        self.mq_last_fc_per_ohm = 0  # mQ of the pulse Rp was measured on
        self.i0_ua = 0
        self.t0_us = 0
        self.rp0_ohm = 0
        self.x_star_ohm = 0
        self.y_star_pc = 0
        self._eh = 0  # mE = _eh * 2**15 + _el   (uA^2 us)
        self._el = 0
        self._e16h = 0  # 16 mE = _e16h * 2**15 + _e16l
        self._e16l = 0
        self._a = 0  # Q0 - y*  (pC)
        self._d0 = 1  # Rp0 - x*  (ohm)
        self._y16 = 0  # 16 y*
        self._qcap = 0  # 16 q_max
        self._pcap = 0  # 16 (q_max - y*)
        self._fq = 0  # MODE_FAST: charge (pC) and Rp of the pulse before the last one
        self._frp = 0
        self._fok = 0  # 1: that pulse was a clean step (no fault, no bound)
        self._fdr = 0  # MODE_FAST: Rp's last change not explained by our own step (ohm)
        self.fast_jumps = 0  # telemetry/diagnostics: Newton jumps taken

    def set_limits(self, i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc):
        """Current, duration and charge limits; ValueError (nothing changed) if out
        of range. The calibration is dropped: calibrate() again before update()."""
        _check("i_max_ua", i_max_ua, 1, I_LIMIT_UA)
        _check("i_min_ua", i_min_ua, 1, i_max_ua)
        _check("t_max_us", t_max_us, 1, T_LIMIT_US)
        _check("t_min_us", t_min_us, 1, t_max_us)
        _check("q_max_pc", q_max_pc, i_min_ua * t_min_us, Q_LIMIT_PC)
        self.i_min_ua = i_min_ua
        self.i_max_ua = i_max_ua
        self.t_min_us = t_min_us
        self.t_max_us = t_max_us
        self.q_max_pc = q_max_pc
        self.calibrated = False
        self.i_ua = 0
        self.t_us = 0
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
        i2 = i0_ua * i0_ua
        p = (i2 & _M15) * t0_us
        eh = (i2 >> 15) * t0_us + (p >> 15)
        el = p & _M15
        self._eh = eh
        self._el = el
        self._e16h = (eh << 4) + (el >> 11)
        self._e16l = (el << 4) & _M15
        self._a = q0 - y_star_pc
        self._d0 = rp0_ohm - x_star_ohm
        self._y16 = y_star_pc << 4
        self._qcap = self.q_max_pc << 4
        self._pcap = (self.q_max_pc - y_star_pc) << 4
        self.i0_ua = i0_ua
        self.t0_us = t0_us
        self.rp0_ohm = rp0_ohm
        self.x_star_ohm = x_star_ohm
        self.y_star_pc = y_star_pc
        self.me_ua2ms = _div_small(eh, el, 1000)
        self.mq_target_fc_per_ohm = _muldiv(self._a, 1000, self._d0, 0, _MQ_CAP)
        self.mq_last_fc_per_ohm = self.mq_target_fc_per_ohm
        self._fok = 0
        self._fdr = 0
        self.rp_ohm = rp0_ohm
        self.i_ua = i0_ua
        self.t_us = t0_us
        self.status = ST_OK
        self.calibrated = True

    def set_mode(self, mode):
        """Select one of MODES (MODE_AKHTAR is the default); ValueError otherwise."""
        if not MODE_OPEN_LOOP <= mode <= MODE_FAST:
            raise ValueError("mode=%d out of range [%d, %d]" % (mode, MODE_OPEN_LOOP, MODE_FAST))
        if mode != self.mode:
            self._fok = 0
            self._fdr = 0
        self.mode = mode

    def delivered(self, i_ua, t_us):
        """Tell the controller the pulse actually delivered, when it differs from
        its own last output (the firmware's supervisor may hold a proposal);
        update() then measures mQ, and MODE_FAST its secant, against it."""
        self.i_ua = i_ua
        self.t_us = t_us

    def stop(self, status):
        """Next pulse: none (i_ua = t_us = 0), with the given fault status."""
        self._fok = 0
        self._fdr = 0
        self.i_ua = 0
        self.t_us = 0
        self.status = status
        return status

    def update(self, rp_ohm):
        """Rp measured on the last pulse -> self.i_ua, self.t_us; returns status."""
        if not self.calibrated:
            return self.stop(ST_UNCALIBRATED)
        self.rp_ohm = rp_ohm
        if rp_ohm < RP_MIN_OHM:  # also covers Rp <= x*, as x* <= 0
            self.mq_last_fc_per_ohm = 0
            return self.stop(ST_RP_LOW)
        if rp_ohm > RP_MAX_OHM:
            self.mq_last_fc_per_ohm = 0
            return self.stop(ST_RP_HIGH)
        d = rp_ohm - self.x_star_ohm
        # mQ of the pulse this Rp was measured on (telemetry)
        if self.i_ua > 0:
            n = self.i_ua * self.t_us - self.y_star_pc
            if n >= 0:
                self.mq_last_fc_per_ohm = _muldiv(n, 1000, d, 0, _MQ_CAP)
            else:
                self.mq_last_fc_per_ohm = -_muldiv(-n, 1000, d, 0, _MQ_CAP)
        else:
            self.mq_last_fc_per_ohm = 0
        mode = self.mode
        q_k = self.i_ua * self.t_us  # the pulse this Rp was measured on
        if mode < MODE_AKHTAR:
            return self._fixed_current(mode, rp_ohm)
        qf = self._line(rp_ohm)
        if qf <= 0:
            self._fok = 0
            return self.stop(ST_Q_NONPOS)
        if mode == MODE_FAST:
            st = self._fast_pulse(qf, q_k, rp_ohm)
        else:
            st = self._from_q(qf)
        # MODE_FAST remembers this pulse for the next secant
        self._fq = q_k
        self._frp = rp_ohm
        self._fok = 1 if (st == ST_OK and q_k > 0) else 0
        return st

    def _line(self, rp_ohm):
        """Eq. 3: Q = mQ (Rp - x*) + y*, in 1/16 pC, saturating above q_max (Rp valid)."""
        return self._y16 + _muldiv(self._a, rp_ohm - self.x_star_ohm, self._d0, 4, self._pcap)

    def _measured(self, i_ua, t_us, status):
        """Put back the measured pulse (_from_q reads it) before another proposal."""
        self.i_ua = i_ua
        self.t_us = t_us
        self.status = status

    def _fast_pulse(self, qf, q_k, rp_ohm):
        """MODE_FAST's next pulse from the paper's step qf (1/16 pC): the drift
        prediction, then a Newton step that stays on the path of the measured pulse
        (mE curve or duration ceiling), else the paper's step, corrected when it
        enters the ceiling from a higher current. docs/controller.md gives the rules."""
        i_k = self.i_ua  # the measured pulse (_from_q reads it: restored for a retry)
        t_k = self.t_us
        s_k = self.status
        ceiling = s_k & ST_T_MAX
        qf = self._drift(qf, q_k, rp_ohm)
        # on the line within the pulse's resolution (1/2 uA and 1/2 us; at the ceiling,
        # where I and T are split for the charge, 1/2 us): the paper's step
        dq = qf - (q_k << 4)  # 1/16 pC
        if (dq if dq >= 0 else -dq) >= (i_k + (0 if ceiling else t_k)) << 3:
            q_new = self._fast(qf, q_k, rp_ohm)
            if q_new != qf:
                st = self._from_q(q_new)
                if (st & ST_T_MAX) == ceiling:
                    if self.fast_jumps < _SAT30:  # a counter must never become a long int
                        self.fast_jumps += 1
                    return st
                self._measured(i_k, t_k, s_k)
        st = self._from_q(qf)
        i = self.i_ua
        if st == ST_T_MAX and not ceiling and i < i_k:
            # entering the ceiling from the mE curve at a lower current I: Rp will rise
            # at least by the least elasticity, Rp (1 + e (I_k - I) / I); one more step
            # of the law on that Rp (I < 2**10: the divisor scaled into _muldiv's range)
            if i < 1024:
                dr = _muldiv(rp_ohm, i_k - i, i << 8, 8, _MQ_CAP)
            else:
                dr = _muldiv(rp_ohm, i_k - i, i, 0, _MQ_CAP)
            rp2 = rp_ohm + _least_elastic(dr)
            if rp2 <= RP_MAX_OHM:
                self._measured(i_k, t_k, s_k)
                st = self._from_q(self._line(rp2))
        return st

    def _drift(self, qf, q_k, rp_ohm):
        """MODE_FAST under a falling drift (sweat, gel soaking in): Rp's change since the
        last pulse less what our own step explains (with the least elasticity) is the
        skin moving; when it has fallen two pulses running, the law is applied to Rp
        one pulse ahead (the smaller of the two falls, at most Rp/16). Only falls:
        a rising drift would raise the charge on a prediction."""
        drift = 0
        if self._fok and q_k > 0:
            dq = q_k - self._fq
            adq = dq if dq >= 0 else -dq
            if adq < (q_k >> 5):  # a small step of our own (a large one is a jump: not drift)
                f = _frac12(adq, q_k)  # |dQ|/Q in Q.12, < 128
                e = _least_elastic((rp_ohm >> 12) * f + (((rp_ohm & 0xFFF) * f) >> 12))  # e Rp |dQ| / Q
                drift = rp_ohm - self._frp - (e if dq >= 0 else -e)
        prev = self._fdr
        self._fdr = drift
        if drift >= 0 or prev >= 0:
            return qf
        d = drift if drift > prev else prev  # the smaller fall
        if -d < rp_ohm >> 9:  # below 0.2 %: the quantisation of Rp and of the pulse, not drift
            return qf
        if -d > rp_ohm >> 4:
            d = -(rp_ohm >> 4)
        rp2 = rp_ohm + d
        if rp2 < RP_MIN_OHM:
            return qf
        return self._line(rp2)

    def _fixed_current(self, mode, rp_ohm):
        """The baseline laws: I = I0; T from the mode's law, then the bounds."""
        t0 = self.t0_us
        t = t0  # MODE_OPEN_LOOP, MODE_CONSTANT_CHARGE (I0 * T0 held)
        if mode == MODE_CONSTANT_ENERGY:  # Rp I0^2 T = Rp0 I0^2 T0
            t = _muldiv(t0, self.rp0_ohm, rp_ohm, 1, _MQ_CAP)
            t = (t + 1) >> 1  # rounded
        elif mode == MODE_PULSE_WIDTH_LINEAR:  # tangent of Eq. 4 at Rp0: dT/dRp = 2 mQ / I0
            dr = rp_ohm - self.rp0_ohm
            x = _muldiv(self._a, dr if dr >= 0 else -dr, self._d0, 1, _MQ_CAP)  # 2 mQ |dRp| in pC
            x = (x + (self.i0_ua >> 1)) // self.i0_ua
            t = t0 + x if dr >= 0 else t0 - x
        i = self.i0_ua
        st = ST_OK
        if t > self.t_max_us:
            t = self.t_max_us
            st = ST_T_MAX
        elif t < self.t_min_us:
            t = self.t_min_us
            st = ST_T_MIN
        if i * t > self.q_max_pc:
            t = self.q_max_pc // i
            st |= ST_Q_MAX
        self.i_ua = i
        self.t_us = t
        self.status = st
        return st

    def _fast(self, qf, q_k, rp_ohm):
        """MODE_FAST: a Newton step towards the self-consistent charge.

        With the skin's response to charge along the mE curve linearised, slope
        s = dRp/dQ, the fixed point of Q = L(Rp(Q)) is Q* = (L(Rp_k) - G Q_k) / (1 - G),
        G = mQ s. G comes from the last two pulses (a secant) when they are a
        trustworthy pair, else from the skin's least elasticity (FAST_ELASTICITY_Q12,
        a lower bound on G: the step then never passes the fixed point of a skin
        that follows the model). docs/controller.md gives the rules; the paper's
        step L(Rp_k) (= qf) is returned whenever neither applies.
        """
        if q_k <= 0:
            return qf
        g = _SAT15  # "no estimate"
        up = 1  # a jump that raises the charge: at most 2 paper steps (secant)
        if self._fok:
            dq = q_k - self._fq
            adq = dq if dq >= 0 else -dq
            if adq >= 64 and adq >= (q_k >> 5):  # enough excitation for a secant
                dr = rp_ohm - self._frp
                x = _muldiv(self._a, dr if dr >= 0 else -dr, self._d0, 0, _MQ_CAP)  # mQ |dRp| (pC)
                if x < adq << 1:  # else |G| >= 2: the linear model is not trustworthy
                    g = _frac12(x, adq)  # |G| in Q.12
                    if (dr < 0) != (dq < 0):
                        g = -g
                    if g > 3891 or g < -6144:  # G outside [-1.5, 0.95]: no stable fixed point nearby
                        g = _SAT15
        if g == _SAT15:  # the prior: |G| >= elasticity * mQ Rp / Q
            ceiling = self.status == ST_T_MAX  # the pulse just measured was held at t_max
            if self.status != ST_OK and not ceiling:  # another bound: no model of that path
                return qf
            x = _muldiv(self._a, rp_ohm, self._d0, 0, _MQ_CAP)  # mQ Rp (pC)
            if x >= q_k << 1:
                return qf
            g = (_frac12(x, q_k) * FAST_ELASTICITY_Q12) >> 12
            if ceiling:  # T fixed, only I moves: Rp falls as the charge rises, G < 0
                g = -g
            elif g > 3891:
                return qf
            up = 2  # the prior's step does not pass the fixed point: at most 4 paper steps
        lq = qf >> 4  # L(Rp_k) in pC
        gq = (q_k >> 12) * g + (((q_k & 0xFFF) * g) >> 12)  # G Q_k in pC
        n = lq - gq
        if n <= 0:
            return qf
        den = 4096 - g  # (1 - G) in Q.12, in [205, 10240]
        h = n // den
        if h > self.q_max_pc >> 12:  # Q* > q_max: no need to compute it (it would pass 2**30)
            q_new = self._qcap + 1  # _from_q clamps and flags it
        else:
            q_new = (h << 12) + (((n - h * den) << 12) // den)  # Q* in pC, < q_max + 2**12
            if q_new > self.q_max_pc:
                q_new = self._qcap + 1
            else:
                q_new = q_new << 4
        base = q_k << 4
        step = qf - base  # the paper's step, 1/16 pC
        jump = q_new - base
        if step == 0 or (jump > 0) != (step > 0):
            return qf  # not the paper's direction: keep the paper's step
        if step > 0:  # more charge: at most 2 (secant) or 4 (prior) paper steps: overshoot is felt
            if step < 0x4000000 and jump > step << up:
                q_new = base + (step << up)
        elif -step < 0x8000000 and -jump > -(step << 2):  # less charge: at most 4 paper steps
            q_new = base + (step << 2)
        if q_new <= 0:
            return qf
        return q_new

    def _from_q(self, qf):
        """Eq. 4 and every bound, from a charge estimate in 1/16 pC (> 0)."""
        st = ST_OK
        if qf > self._qcap:
            qf = self._qcap
            st = ST_Q_MAX
        # Eq. 4: I = mE / Q, T = Q^2 / mE
        i = _div2(self._e16h, self._e16l, qf, 1)
        t = _t_from_qf(qf, self.i0_ua, self.t0_us)
        t_min = self.t_min_us
        t_max = self.t_max_us
        # duration bounds. Ceiling (ours: the paper has none): keep the charge on
        # the Q-Rp line at T <= t_max: I = ceil(Q / t_max), T = round(Q / I), so
        # I*T is within I/2 pC of Q (mE then above its value).
        # Floor (Discussion: a sensation threshold): hold T, solve I from mE.
        if t > t_max:
            i = (qf + (t_max << 4) - 1) // (t_max << 4)
            if self.i_ua == i + 1:  # 1 uA of hysteresis: I does not flip between neighbours
                i += 1  # (Rp follows I, so the line's charge for I lies between the two)
            t = t_max
            if i <= self.i_max_ua:  # (above it the current ceiling below holds I at i_max)
                t = (qf + (i << 3)) // (i << 4)
                if t < t_min:
                    t = t_min
            st |= ST_T_MAX
        elif t < t_min:
            t = t_min
            i = _isqrt_round(_div_small(self._eh, self._el, t_min))
            st |= ST_T_MIN
        # current bounds: floor holds I and solves T; ceiling is safety (no mE)
        if i < self.i_min_ua:
            i = self.i_min_ua
            st |= ST_I_MIN
            t = _div2(self._eh, self._el, i * i, 1)
            if t > t_max:
                t = t_max
                st |= ST_T_MAX
            elif t < t_min:
                t = t_min
                st |= ST_T_MIN
        elif i > self.i_max_ua:
            i = self.i_max_ua
            st |= ST_I_MAX
        # charge ceiling (safety): shorten the pulse, then lower the current
        q_max = self.q_max_pc
        if i * t > q_max:
            st |= ST_Q_MAX
            t = q_max // i
            if t < t_min:
                t = t_min
                i = q_max // t_min
        elif st == ST_OK and self.mode == MODE_FAST:
            # the integer pulse nearest the charge: I = round(Q / T), so I*T is
            # within T/2 pC of Q (mE then within 1/(2T) of its value)
            i2 = (qf + (t << 3)) // (t << 4)
            if self.i_min_ua <= i2 <= self.i_max_ua and i2 * t <= q_max:
                i = i2
        self.i_ua = i
        self.t_us = t
        self.status = st
        return st
