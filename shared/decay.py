"""decay: the monitor's decay after the gate falls, as log2 of its time constant.

When the stimulator's output stops, the skin's capacitance Cp discharges through its
resistance R_skin: the monitor falls by I·Rs at once, then as exp(-t / tau) with
tau = R_skin·Cp. With tau and the pulse's Rp the per-pulse skin model is fixed
(docs/performance.md, "The monitor's decay after the fall"); this module reads tau
from the ADC samples captured after the fall. Integer only, every intermediate below
2**30, no allocation: it runs in the firmware's frame and, unchanged, on the host.

Estimator: two adjacent windows of m samples each (m = n // 2), offset taken out,
summed: Sa, Sb. For a pure exponential Sa / Sb = exp(m·dt / tau), so
log2 tau = log2(m·dt) - log2(ln 2) - log2(log2 Sa - log2 Sb), in Q.16 with
fixmath.log2q (error < 2**-16 a call). Format: docs/fixed-point.md.
"""

try:
    import micropython
    from micropython import const
except ImportError:  # CPython: the decorator does nothing, ptr16 indexes the array itself

    class micropython:  # noqa: N801 (stands in for the module's decorator)
        @staticmethod
        def viper(f):
            return f

    def const(x):
        return x

    def ptr16(a):
        return a


from fixmath import log2q

_L_LN2_NEG = const(34653)  # -log2(ln 2) in Q.16
_Q16_16 = const(0x100000)  # 16 in Q.16: log2q(d) reads d (Q.16) as an integer
N_MIN = const(4)  # samples needed (two windows of 2)
N_MAX = const(1024)  # a window sum stays below 2**30: 512 samples x 4095 x 16 < 2**25
DT_MAX_US = const(1000)
LTAU_END = const(0x140000)  # 20 in Q.16: a tau of 2**20 us (1 s) or more is no decay the capture can read
# a decay to read: the first window's mean at least MIN_LEVEL_COUNTS above the offset, and the two windows'
# means at least MIN_DROP_COUNTS apart. On a flat record (a resistor: nothing after the fall) the means of
# two windows of m = 24 samples differ by 0.82 counts rms at the realistic board's 2.84 counts of noise
# (8.7 ENOB): 4 counts is 4.9 of that (review of session 24: without it a 10 kohm resistor read a tau
# on 94 of 200 pulses, 132-7273 us, where skin reads ~480)
MIN_LEVEL_COUNTS = const(16)
MIN_DROP_COUNTS = const(4)


@micropython.viper
def ltau_q16(buf, lo: int, n: int, off_x16: int, dt_us: int) -> int:
    """log2(tau in us) in Q.16 from the n samples buf[lo:lo + n] (ADC counts, an array of
    unsigned 16-bit, the first after the fall's straddling sample), sampled every dt_us,
    with the monitor's offset off_x16 (counts x 16) taken out. 0 when tau cannot be read:
    n or dt_us out of range (N_MIN..N_MAX, 1..DT_MAX_US), the second window's sum not
    above 0, or no decay to read: the first window's mean less than MIN_LEVEL_COUNTS above
    the offset, or the two windows' means less than MIN_DROP_COUNTS apart (noise on a flat
    record, a resistor's). A tau of 1 us or less also reads 0 (log2 1 = 0):
    the capture cannot resolve it (2 us a sample); so does one of LTAU_END or more (a decay
    too flat to read: the windows' sums differ by their rounding)."""
    if n < N_MIN or n > N_MAX or dt_us < 1 or dt_us > DT_MAX_US:
        return 0
    b = ptr16(buf)
    m = n >> 1
    sa = 0
    sb = 0
    k = 0
    while k < m:
        sa += int(b[lo + k]) * 16 - off_x16
        sb += int(b[lo + m + k]) * 16 - off_x16
        k += 1
    if sb <= 0 or sa < m * (MIN_LEVEL_COUNTS * 16) or sa - sb < m * (MIN_DROP_COUNTS * 16):
        return 0
    d = int(log2q(sa)) - int(log2q(sb))  # log2(Sa / Sb) in Q.16, >= 0 (log2q is monotonic)
    if d <= 0:  # Sa, Sb too close for log2q to part them: no decay to read
        return 0
    lt = int(log2q(m * dt_us)) + _Q16_16 - int(log2q(d)) + _L_LN2_NEG
    return lt if 0 < lt < LTAU_END else 0
