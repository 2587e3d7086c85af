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
# a jump on the skin model raises the charge by at most 2**this paper steps
FAST_MODEL_RAISE_LOG2 = const(4)
# the skin model's accepted ranges (Controller.set_skin)
SKIN_RS_MAX_OHM = const(5000)
SKIN_BETA_MIN_Q16 = const(6554)  # 0.1
SKIN_BETA_MAX_Q16 = const(98303)  # < 1.5
SKIN_CP_MIN_PF = const(100)
SKIN_CP_MAX_PF = const(2000000)  # 2 uF


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


# ---- MODE_FAST's electrode model (optional: Controller.set_skin) ----
# Rp(I, T) = Rs + R(I) (1 - exp(-T / (R(I) Cp))), R(I) = S (I / 1 mA)**-beta: the
# electrode of docs/simulation.md. Logarithms are log2 in Q.16 ("l" names).
_LOG_TAB = (  # round(2**16 log2(1 + k/64)), k = 0..65
    0, 1466, 2909, 4331, 5732, 7112, 8473, 9814, 11136, 12440, 13727, 14996, 16248, 17484, 18704, 19909,
    21098, 22272, 23433, 24579, 25711, 26830, 27936, 29029, 30109, 31178, 32234, 33279, 34312, 35334, 36346,
    37346, 38336, 39316, 40286, 41246, 42196, 43137, 44068, 44990, 45904, 46809, 47705, 48593, 49472, 50344,
    51207, 52063, 52911, 53751, 54584, 55410, 56229, 57040, 57845, 58643, 59434, 60219, 60997, 61769, 62534,
    63294, 64047, 64794, 65536, 66272,
)
_EXP_TAB = (  # round(2**22 2**(k/64)), k = 0..65
    4194304, 4239977, 4286147, 4332820, 4380002, 4427697, 4475911, 4524651, 4573921, 4623728, 4674077,
    4724974, 4776426, 4828438, 4881016, 4934167, 4987896, 5042211, 5097117, 5152621, 5208729, 5265449,
    5322786, 5380747, 5439339, 5498570, 5558445, 5618973, 5680159, 5742012, 5804539, 5867746, 5931642,
    5996233, 6061528, 6127533, 6194258, 6261709, 6329894, 6398822, 6468501, 6538938, 6610143, 6682122,
    6754886, 6828442, 6902799, 6977965, 7053950, 7130763, 7208412, 7286906, 7366255, 7446469, 7527555,
    7609525, 7692387, 7776152, 7860829, 7946428, 8032959, 8120432, 8208857, 8298246, 8388608, 8479954,
)
_L_1E6 = const(1306235)  # log2(1e6): tau_us = R_ohm * Cp_pF / 1e6
_L_E = const(94548)  # log2(e)
_L_1MA = const(653118)  # log2(1000 uA): the model's reference current
_L_Z12 = const(234946)  # log2(12): beyond it exp(-T/tau) < 2**-17, taken as 0
_L_R_MAX = const(1310720)  # 20.0: R(I) above 2**20 ohm is far beyond RP_MAX_OHM
_NOROOT = const(-0x3FFFFFFF)
_L_LN2 = const(-34653)  # log2(ln 2)
_K_ANCHOR = const(0)  # _g kinds: log2 S that reads the stored pulse (p = log2 Cp)
_K_PEEL = const(1)  # contact scale that reads the stored pulse (p unused)
_K_LAW = const(2)  # the law on the mE curve, x = log2 Q
_K_CEIL = const(3)  # the line at T = t_max, x = log2 I
_K_TWO = const(4)  # log2 R(I) of the pulse before for which both stored pulses read right
_K_ANCHOR0 = const(5)  # log2 S that reads the pulse before (p = log2 Cp)


def _log2q(x):
    """log2(x) in Q.16 for an integer 1 <= x < 2**30 (error < 1 / 2**16: quadratic
    interpolation in a 64-cell table). x < 1 is read as 1 (no endless loop)."""
    if x < 1:
        x = 1
    n = 22
    while x >= 0x800000:
        x >>= 1
        n += 1
    while x < 0x400000:
        x <<= 1
        n -= 1
    k = (x >> 16) - 64
    a = _LOG_TAB[k]
    b = _LOG_TAB[k + 1]
    u = x & 0xFFFF
    v = u >> 8
    return (n << 16) + a + (((b - a) * u + 0x8000) >> 16) + ((v * (v - 256) * (_LOG_TAB[k + 2] - b - b + a) + 0x10000) >> 17)


def _exp2q(lx):
    """round(2**(lx / 2**16)) for lx < 29 * 2**16 (relative error < 1e-6 before the
    rounding: quadratic interpolation in a 64-cell table)."""
    n = lx >> 16
    f = lx & 0xFFFF
    k = f >> 10
    a = _EXP_TAB[k]
    b = _EXP_TAB[k + 1]
    u = f & 0x3FF
    v = u >> 2
    m = a + (((b - a) * u + 512) >> 10) + ((v * (v - 256) * (_EXP_TAB[k + 2] - b - b + a) + 0x10000) >> 17)  # Q.22
    if n >= 22:
        return m << (n - 22)
    if n < -2:
        return 0
    s = 22 - n
    return (m + (1 << (s - 1))) >> s


def _mul_q16(x, b):
    """x * b / 2**16 rounded towards zero, |x| < 2**21, |b| < 2**17 (split: < 2**30)."""
    a = -x if x < 0 else x
    c = -b if b < 0 else b
    y = (((a >> 10) * c) >> 6) + (((a & 0x3FF) * c) >> 16)
    return -y if (x < 0) != (b < 0) else y


def _half(f):
    """f / 2 keeping its sign (Illinois' down-weighting of a retained end)."""
    return f >> 1 if f > 1 or f < -1 else f


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
        # MODE_FAST's skin model (set_skin; 0 = none) and its state, logs in Q.16
        self.skin_rs_ohm = 0
        self.skin_beta_q16 = 0
        self.skin_cp_pf = 0
        self.model_jumps = 0  # telemetry/diagnostics: jumps solved on the skin model
        self._mon = 0  # 1: a skin model is set
        self._mlc0 = 0  # log2 Cp (pF) as set
        self._mlc = 0  # log2 Cp now (a two-pulse fit may move it)
        self._mls = 0  # log2 S (ohm at 1 mA), anchored on the last model jump
        self._mj = 0  # 1: the pulse just measured was a model jump
        self._mpred = 0  # the Rp the model predicted for it (ohm)
        self._lme = 0  # log2 mE (uA^2 us); log2 t_max is self._ltmax (set_limits)
        self._p0i = 0  # the pulse measured before the last one and its Rp (raw)
        self._p0t = 0
        self._p0rp = 0
        self._p1li = 0  # the pulse just measured (logs) and its Rp
        self._p1lt = 0
        self._p1rp = 0
        self._g0li = 0  # the pulse before it (logs), its Rp, and log2 S there
        self._g0lt = 0
        self._g0rp = 0
        self._g0ls = 0
        self._g2lc = 0  # log2 Cp of the last _K_TWO evaluation
        self._msw = 0  # _K_TWO: 1 = Cp from the pulse just measured, 0 = from the one before

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
        self._ltmax = _log2q(t_max_us)
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
        self._lme = (_log2q(i0_ua) << 1) + _log2q(t0_us)
        self._mj = 0
        self._p0rp = 0
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
            self._mj = 0
            self._p0rp = 0
        self.mode = mode

    def set_skin(self, rs_ohm, beta_q16, cp_pf):
        """MODE_FAST's electrode model (docs/controller.md): series resistance Rs (ohm),
        current exponent beta (Q.16) and capacitance Cp (pF) of the pair, as fitted to
        the calibration pulses (host/skin.py). All three 0: no model. ValueError
        (nothing changed) when out of range."""
        if rs_ohm == 0 and beta_q16 == 0 and cp_pf == 0:
            self._mon = 0
        else:
            _check("rs_ohm", rs_ohm, 0, SKIN_RS_MAX_OHM)
            _check("beta_q16", beta_q16, SKIN_BETA_MIN_Q16, SKIN_BETA_MAX_Q16)
            _check("cp_pf", cp_pf, SKIN_CP_MIN_PF, SKIN_CP_MAX_PF)
            self._mon = 1
            self._mlc0 = _log2q(cp_pf)
            self._mlc = self._mlc0
        self.skin_rs_ohm = rs_ohm
        self.skin_beta_q16 = beta_q16
        self.skin_cp_pf = cp_pf
        self._mj = 0

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
        self._mj = 0
        self._p0rp = 0
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
        rp_at = self._drift(q_k, rp_ohm)
        if rp_at != rp_ohm:
            qf = self._line(rp_at)
        p0i = self._p0i  # the pulse before (the skin model's two-pulse fit)
        p0t = self._p0t
        p0rp = self._p0rp
        self._p0i = i_k
        self._p0t = t_k
        self._p0rp = rp_ohm
        jumped = self._mj
        self._mj = 0
        # on the line within the pulse's resolution (1/2 uA and 1/2 us; at the ceiling,
        # where I and T are split for the charge, 1/2 us): the paper's step
        dq = qf - (q_k << 4)  # 1/16 pC
        if (dq if dq >= 0 else -dq) >= (i_k + (0 if ceiling else t_k)) << 3:
            if self._mon and q_k > 0:
                st = self._model_pulse(qf, q_k, rp_at, i_k, t_k, jumped, p0i, p0t, p0rp)
                if st >= 0:
                    return st
                self._measured(i_k, t_k, s_k)
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

    def _drift(self, q_k, rp_ohm):
        """MODE_FAST under a falling drift (sweat, gel soaking in): Rp's change since the
        last pulse less what our own step explains (with the least elasticity) is the
        skin moving; when it has fallen two pulses running, the law is applied to Rp
        one pulse ahead (the smaller of the two falls, at most Rp/16), which this
        returns (else rp_ohm). Only falls: a rising drift would raise the charge on a
        prediction."""
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
            return rp_ohm
        d = drift if drift > prev else prev  # the smaller fall
        if -d < rp_ohm >> 9:  # below 0.2 %: the quantisation of Rp and of the pulse, not drift
            return rp_ohm
        if -d > rp_ohm >> 4:
            d = -(rp_ohm >> 4)
        rp2 = rp_ohm + d
        if rp2 < RP_MIN_OHM:
            return rp_ohm
        return rp2

    # ---- MODE_FAST's skin model (docs/controller.md, "MODE_FAST with a skin model") ----

    def _rp_model(self, ls, lc, li, lt):
        """Rp (ohm, at most 2**21) of the model skin with log2 S = ls, log2 Cp = lc for a
        pulse with log2 I = li, log2 T = lt."""
        lr = ls - _mul_q16(li - _L_1MA, self.skin_beta_q16)  # log2 R(I)
        lz = lt - lr - lc + _L_1E6  # log2 (T / tau), tau = R Cp
        if lz < -0x10000:  # z < 1/2: R (1 - e^-z) = (T / Cp) (1 - e^-z) / z, by its series
            lrz = lt - lc + _L_1E6  # log2 (R z) = log2 (T / Cp), ohm
            if lrz > _L_R_MAX:
                return 0x200000
            z = _exp2q(lz + 0xE0000) if lz > -0x1E0000 else 0  # Q.14, < 2**13
            v = 16384 - z // 5
            v = 16384 - ((z * v) >> 14) // 4
            v = 16384 - ((z * v) >> 14) // 3
            v = 16384 - ((z * v) >> 14) // 2  # (1 - e^-z) / z in Q.14
            rz = _exp2q(lrz)  # < 2**20
            return self.skin_rs_ohm + (((rz >> 10) * v + (((rz & 0x3FF) * v) >> 10) + 8) >> 4)  # rounded
        if lr > _L_R_MAX:
            return 0x200000
        if lz > _L_Z12:  # charged: exp(-z) < 2**-17
            u = 0x8000
        else:
            zq = _exp2q(lz + 0x100000)  # z in Q.16, < 12 * 2**16
            lw = -((((zq >> 8) * _L_E) >> 8) + (((zq & 0xFF) * _L_E) >> 16))  # log2 e^-z
            u = 0x8000 - _exp2q(lw + 0xF0000)  # 1 - e^-z in Q.15
        r = _exp2q(lr)
        return self.skin_rs_ohm + (((r >> 10) * u + (((r & 0x3FF) * u) >> 10) + 16) >> 5)  # rounded

    def _g(self, kind, x, p):
        """The function of x whose sign change _root finds (kinds _K_*)."""
        if kind == _K_ANCHOR:  # x = log2 S, p = log2 Cp: misfit at the pulse just measured
            return self._rp_model(x, p, self._p1li, self._p1lt) - self._p1rp
        if kind == _K_ANCHOR0:  # the same at the pulse before it (_g0*)
            return self._rp_model(x, p, self._g0li, self._g0lt) - self._g0rp
        if kind == _K_PEEL:  # x = log2 contact from the skin before: S ~ a**(beta - 1), Cp ~ a
            ls = self._g0ls + _mul_q16(x, self.skin_beta_q16 - 0x10000)
            return self._rp_model(ls, self._mlc + x, self._p1li, self._p1lt) - self._p1rp
        if kind == _K_LAW:  # x = log2 Q on the mE curve: L(Rp(Q)) - Q, 1/16 pC
            r = self._rp_model(self._mls, self._mlc, self._lme - x, (x << 1) - self._lme)
            if r > RP_MAX_OHM:
                r = RP_MAX_OHM
            return self._line(r) - _exp2q(x + 0x40000)
        if kind == _K_CEIL:  # x = log2 I at T = t_max: L(Rp) - I t_max, 1/16 pC
            r = self._rp_model(self._mls, self._mlc, x, self._ltmax)
            if r > RP_MAX_OHM:
                r = RP_MAX_OHM
            return self._line(r) - _exp2q(x + self._ltmax + 0x40000)
        # _K_TWO: x = log2 R(I) at the less charged of the two pulses (_msw); its reading
        # gives Cp in closed form, Cp = T / (R z), z = -ln(1 - (Rp - Rs) / R); then the
        # misfit at the other pulse
        sw = self._msw  # (one name at a time: a 6-tuple would be allocated in MicroPython)
        cli = self._p1li if sw else self._g0li
        clt = self._p1lt if sw else self._g0lt
        crp = self._p1rp if sw else self._g0rp
        oli = self._g0li if sw else self._p1li
        olt = self._g0lt if sw else self._p1lt
        orp = self._g0rp if sw else self._p1rp
        r = _exp2q(x)
        y = x - _log2q(r - crp + self.skin_rs_ohm)  # log2 (R / (R - Rp + Rs)) = z / ln 2
        if y <= 0:
            return _NOROOT
        lc = clt - x + _L_1E6 - (_log2q(y) - 0x100000 + _L_LN2)
        ls = x + _mul_q16(cli - _L_1MA, self.skin_beta_q16)
        self._g2lc = lc
        return self._rp_model(ls, lc, oli, olt) - orp

    def _root(self, kind, a, b, p):
        """x in [a, b] where _g(kind, x, p) changes sign (Illinois' regula falsi), to
        1/2**16; _NOROOT if the ends have one sign or _g fails."""
        fa = self._g(kind, a, p)
        fb = self._g(kind, b, p)
        if fa == _NOROOT or fb == _NOROOT or (fa > 0) == (fb > 0):
            return _NOROOT if fa != 0 and fb != 0 else (a if fa == 0 else b)
        side = 0
        n = 0
        while b - a > 1 and n < 40:
            n += 1
            w = b - a
            num = fa if fa > 0 else -fa
            den = num + (fb if fb > 0 else -fb)
            while den >= 0x40000:
                den >>= 1
                num >>= 1
            if den >= 256 and w <= 0x40000:
                x = a + _muldiv(num, w, den, 0, _MQ_CAP)
            else:
                x = a + (w >> 1)
            if x <= a:
                x = a + 1
            elif x >= b:
                x = b - 1
            fx = self._g(kind, x, p)
            if fx == _NOROOT:
                return _NOROOT
            if fx == 0:
                return x
            if (fx > 0) == (fa > 0):
                a = x
                fa = fx
                if side < 0:
                    fb = _half(fb)
                side = -1
            else:
                b = x
                fb = fx
                if side > 0:
                    fa = _half(fa)
                side = 1
        if (fa if fa > 0 else -fa) <= (fb if fb > 0 else -fb):
            return a
        return b

    def _anchor(self, kind, li, rp, lc):
        """log2 S with which the model (log2 Cp = lc) reads rp on the pulse of log2 I = li
        (kind _K_ANCHOR: the pulse just measured, _K_ANCHOR0: the one before), or _NOROOT.
        R(I) >= Rp - Rs, so S is searched from there up to 16 times more."""
        d = rp - self.skin_rs_ohm
        if d < 16:
            return _NOROOT
        lo = _log2q(d) + _mul_q16(li - _L_1MA, self.skin_beta_q16)
        return self._root(kind, lo, lo + 0x40000, lc)

    def _model_q(self, lq_k):
        """The law's charge (1/16 pC) on the model skin: on the mE curve up to t_max
        (searched from Q_k/4 to 4 Q_k), else on the line at t_max; _NOROOT if none."""
        lq_max = _log2q(self.q_max_pc)
        hi = lq_k + 0x20000
        if hi > lq_max:
            hi = lq_max
        lq_t = (self._lme + self._ltmax) >> 1  # the mE curve's charge at t_max
        if hi >= lq_t:
            hi = lq_t
            if self._g(_K_LAW, hi, 0) > 0:  # more than the curve gives at t_max
                lo = _log2q(self.i_min_ua)
                hi = lq_max - self._ltmax
                x = _log2q(self.i_max_ua)
                if x < hi:
                    hi = x
                li = self._root(_K_CEIL, lo, hi, 0) if hi > lo else _NOROOT
                if li == _NOROOT:
                    return _NOROOT
                return _exp2q(li + self._ltmax + 0x40000)
        lq = self._root(_K_LAW, lq_k - 0x20000, hi, 0)
        if lq == _NOROOT:
            return _NOROOT
        return _exp2q(lq + 0x40000)

    def _model_pulse(self, qf, q_k, rp_ohm, i_k, t_k, jumped, p0i, p0t, p0rp):
        """MODE_FAST's jump with the skin model: the law solved on the model anchored
        to the pulse just measured (Rp = rp_ohm, or the drift's prediction). After a
        model jump that missed its prediction and moved I, Cp is refitted so that the
        model reads both the jump and the pulse before it (a change of contact moves
        Cp, one of hydration does not). On a fresh rise, the contact hypothesis is
        also solved and the smaller charge taken. Returns the status, or -1 when the
        model has no answer (the caller goes on without it)."""
        self._p1li = _log2q(i_k)
        self._p1lt = _log2q(t_k)
        self._p1rp = rp_ohm
        if p0rp > 0:
            self._g0li = _log2q(p0i)
            self._g0lt = _log2q(p0t)
            self._g0rp = p0rp
        if jumped and p0rp > 0:
            miss = rp_ohm - self._mpred
            dl = self._p1li - self._g0li
            if (miss if miss >= 0 else -miss) > rp_ohm >> 9 and (dl if dl >= 0 else -dl) > 0x800:
                # the less charged pulse (smaller T / tau on the model as it stands)
                # determines Cp, the other one (nearer Rs + R) S
                b = self.skin_beta_q16
                z0 = self._g0lt + _mul_q16(self._g0li - _L_1MA, b)  # log2 T/tau, less log2 (S Cp / 1e6)
                z1 = self._p1lt + _mul_q16(self._p1li - _L_1MA, b)
                self._msw = 1 if z0 > z1 else 0
                d = (rp_ohm if self._msw else p0rp) - self.skin_rs_ohm
                if d >= 16:
                    lo = _log2q(d + 2)  # R - (Rp - Rs) = 2 ohm: the pulse charged Cp fully
                    lr = self._root(_K_TWO, lo, lo + 0x40000, 0)
                    if lr != _NOROOT:
                        self._g(_K_TWO, lr, 0)  # (sets _g2lc for the root itself)
                        lc = self._g2lc
                        if self._mlc0 - 0x30000 <= lc <= self._mlc0 + 0x10000:  # Cp: 1/8 ... 2 x the fit's
                            self._mlc = lc
        ls = self._anchor(_K_ANCHOR, self._p1li, rp_ohm, self._mlc)
        if ls == _NOROOT:
            return -1
        self._mls = ls
        lq_k = _log2q(q_k)
        q16 = self._model_q(lq_k)
        if q16 == _NOROOT:
            return -1
        if q16 > q_k << 4 and not jumped and p0rp > 0:
            # a fresh rise: hydration (S alone) or contact (S and Cp)? The contact's
            # charge is the smaller one; take it, the next pulse tells them apart
            ls0 = self._anchor(_K_ANCHOR0, self._g0li, p0rp, self._mlc)
            if ls0 != _NOROOT:
                self._g0ls = ls0
                la = self._root(_K_PEEL, -0x30000, 0x10000, 0)
                if la != _NOROOT:
                    ls1 = self._mls
                    lc1 = self._mlc
                    self._mls = ls0 + _mul_q16(la, self.skin_beta_q16 - 0x10000)
                    self._mlc = lc1 + la
                    q2 = self._model_q(lq_k)
                    if q2 != _NOROOT and q2 < q16:
                        q16 = q2
                    else:
                        self._mls = ls1
                        self._mlc = lc1
        # the paper's direction only, and a rise of at most FAST_MODEL_RAISE paper steps
        base = q_k << 4
        step = qf - base
        if step == 0 or (q16 > base) != (step > 0):
            return -1
        if step > 0 and step < 0x4000000 >> FAST_MODEL_RAISE_LOG2 and q16 - base > step << FAST_MODEL_RAISE_LOG2:
            q16 = base + (step << FAST_MODEL_RAISE_LOG2)
        st = self._from_q(q16)
        self._mpred = self._rp_model(self._mls, self._mlc, _log2q(self.i_ua), _log2q(self.t_us))
        self._mj = 1
        if self.model_jumps < _SAT30:
            self.model_jumps += 1
        return st

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
