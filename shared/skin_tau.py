"""skin_tau: the skin model anchored on the monitor's decay after the fall (MODE_FAST's jump, rule 7
of docs/controller.md, when the controller is told the decay's tau: Controller.ltau_q16).

With tau = R(I) Cp read after a pulse (decay.ltau_q16) and that pulse's Rp, the model's S and Cp
follow in closed form: Rp = Rs + R(I) (1 - exp(-T / tau)), so R(I) = (Rp - Rs) / z,
z = 1 - exp(-T / tau); log2 S = log2 R(I) + beta (log2 I - log2 1 mA), log2 Cp = log2 tau +
log2 1e6 - log2 R(I). A module of its own (skin_model imports it): in skin_model this one viper
function lengthened the chip's boot (session 24: tests/chip/test_chip_vmon.py's 1.5 s of emulated time
ended before its second store's ack; 2.5 s passed). Integer, allocation-free.
"""

try:
    import micropython
    from micropython import const
except ImportError:  # CPython: the decorator does nothing, ptr32 indexes the array itself

    class micropython:  # noqa: N801 (stands in for the module's decorator)
        @staticmethod
        def viper(f):
            return f

    def const(x):
        return x

    def ptr32(a):
        return a


from fixmath import exp2q, log2q, mul_q16

# skin_model's words and constants (a const() is folded only inside its own module, and an underscored
# one is no attribute of it in MicroPython: tests/test_skin_tau.py checks that the values agree)
_V_RS = const(0)
_V_BETA = const(1)
_V_LS = const(2)
_V_LC = const(3)
_V_BIAS = const(0x10000000)
_L_1E6 = const(1306235)
_L_E = const(94548)
_L_1MA = const(653118)
_L_Z12 = const(234946)
_L_R_MAX = const(1310720)
_LC_MIN = const(238804)  # log2q(SKIN_CP_MIN_PF) - 3 octaves: 1/8 x the least Cp set_skin accepts
_LC_MAX = const(1437307)  # log2q(SKIN_CP_MAX_PF) + 1 octave: 2 x the largest


@micropython.viper
def anchor_tau(m, rp_ohm: int, ltau: int, i_ua: int, t_us: int) -> int:
    """Anchor the skin model m (skin_model.SkinModel, its Rs and beta set) on a pulse of i_ua x t_us
    that read Rp = rp_ohm with log2 tau (us) = ltau in Q.16 (decay.ltau_q16). Sets m.ls, m.lc and
    returns 1; 0 (nothing set) when tau is unread (ltau <= 0), Rp - Rs < 16 ohm, T / tau below 2**-16,
    R(I) above 2**20 ohm or Cp outside 1/8 x SKIN_CP_MIN_PF ... 2 x SKIN_CP_MAX_PF. z in Q.20 from
    fixmath.exp2q, or for T / tau < 1/8 log2 z = log2 x + log2(1 - x/2 + x**2/6 - x**3/24) (2e-6),
    which keeps z's relative precision where z is small (docs/fixed-point.md)."""
    if ltau <= 0 or i_ua < 1 or t_us < 1:
        return 0
    v = ptr32(m.v)
    n = rp_ohm - v[_V_RS]
    if n < 16:
        return 0
    lx = int(log2q(t_us)) - ltau  # log2 (T / tau), Q.16
    if lx < -0x100000:  # T / tau < 2**-16
        return 0
    if lx >= _L_Z12:  # exp(-T / tau) < 2**-17: z = 1
        lz = 0
    else:
        xq = int(exp2q(lx + 0x100000))  # T / tau in Q.16 (< 12 * 2**16)
        if xq < 0x2000:  # x < 1/8: the series, from lx
            xx = xq * xq
            lz = lx + int(log2q(0x10000 - (xq >> 1) + xx // 393216 - ((xx >> 16) * xq) // 1572864)) - 0x100000
        else:
            zq = 0x100000 - int(exp2q(0x140000 - int(mul_q16(xq, _L_E))))  # (1 - exp(-x)) in Q.20, >= 4080
            lz = int(log2q(zq)) - 0x140000
    lr = int(log2q(n)) - lz  # log2 R(I)
    if lr > _L_R_MAX:
        return 0
    lc = ltau + _L_1E6 - lr
    if lc < _LC_MIN or lc > _LC_MAX:
        return 0
    v[_V_LS] = lr + int(mul_q16(int(log2q(i_ua)) - _L_1MA, v[_V_BETA])) + _V_BIAS
    v[_V_LC] = lc + _V_BIAS
    return 1
