"""fixmath: the core's integer arithmetic, every intermediate below 2**30.

Runs unchanged on CPython and MicroPython (RP2040: ints of 31 bits; anything at or
above 2**30 would become a heap-allocated long int). Formats and error bounds:
docs/fixed-point.md. Logarithms are log2 in Q.16, as the skin model uses them.
"""

from array import array

try:
    import micropython
    from micropython import const
except ImportError:  # CPython: the decorator does nothing, ptr32 indexes the array itself

    class micropython:  # noqa: N801 (stands in for the module's decorator)
        @staticmethod
        def viper(f):
            return f

        native = viper

    def const(x):
        return x

    def ptr32(a):
        return a


_M11 = const(0x7FF)
_M15 = const(0x7FFF)
_SAT15 = const(0x8000)  # "at least 2**15": what div2 returns when saturated
_SAT30 = const(0x3FFFFFFF)


@micropython.viper
def muldiv(a: int, b: int, c: int, fbits: int, cap: int) -> int:
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


@micropython.native
def rp_from_vp(vp_mv, i_ua):
    """Peak resistance in ohm from peak voltage (mV) and current (uA), rounded (sensation_core's API).
    Returns RP_INVALID (-1) for i_ua <= 0 or vp_mv < 0 (update() faults on it) and RP_OVER
    (2**30 - 1) for vp_mv > VP_LIMIT_MV (10**6; update() reads it as electrode off)."""
    if i_ua <= 0 or vp_mv < 0:
        return -1
    if vp_mv > 1000000:
        return 0x3FFFFFFF
    return (vp_mv * 1000 + (i_ua >> 1)) // i_ua


@micropython.viper
def div2(hi: int, lo: int, dv: int, rnd: int) -> int:
    """(hi * 2**15 + lo) / dv, floored (rnd=0) or rounded half up (rnd=1).

    Needs 0 <= lo < 2**15, 1 <= dv <= 2**29. Returns _SAT15 when the quotient
    is >= 2**15. Long division over lo's bits, as many a step as keep the partial
    remainder's shift below 2**30 (r < dv): one step of 15 bits for dv <= 2**15,
    then 8 + 7, 5 + 5 + 5, 3 bits a step; above 2**27 one bit a step (restoring,
    2r+1 < 2**30). (The chip has no divide instruction: a division costs ~0.4 us.)"""
    if hi >= dv:
        return _SAT15
    r = hi
    q = 0
    if dv <= 0x8000000:
        s = 3
        if dv <= 0x8000:
            s = 15
        elif dv <= 0x400000:
            s = 8
        elif dv <= 0x2000000:
            s = 5
        n = 15  # bits of lo still to bring down
        while n > 0:
            t = s if s < n else n
            n -= t
            r = (r << t) + ((lo >> n) & ((1 << t) - 1))
            d = r // dv
            q = (q << t) + d
            r = r - d * dv
    else:
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


@micropython.viper
def div_small(hi: int, lo: int, dv: int) -> int:
    """floor((hi * 2**15 + lo) / dv) for 1 <= dv < 2**15; 2**30 - 1 if >= 2**30."""
    q = hi // dv
    if q >= _SAT15:
        return _SAT30
    r = hi - q * dv
    return (q << 15) + ((r << 15) + lo) // dv


@micropython.viper
def isqrt_round(n: int) -> int:
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


@micropython.viper
def frac12(x: int, den: int) -> int:
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


_LOG_TAB = array("i", (  # round(2**16 log2(1 + k/64)), k = 0..65
    0, 1466, 2909, 4331, 5732, 7112, 8473, 9814, 11136, 12440, 13727, 14996, 16248, 17484, 18704, 19909,
    21098, 22272, 23433, 24579, 25711, 26830, 27936, 29029, 30109, 31178, 32234, 33279, 34312, 35334, 36346,
    37346, 38336, 39316, 40286, 41246, 42196, 43137, 44068, 44990, 45904, 46809, 47705, 48593, 49472, 50344,
    51207, 52063, 52911, 53751, 54584, 55410, 56229, 57040, 57845, 58643, 59434, 60219, 60997, 61769, 62534,
    63294, 64047, 64794, 65536, 66272,
))
_EXP_TAB = array("i", (  # round(2**22 2**(k/64)), k = 0..65
    4194304, 4239977, 4286147, 4332820, 4380002, 4427697, 4475911, 4524651, 4573921, 4623728, 4674077,
    4724974, 4776426, 4828438, 4881016, 4934167, 4987896, 5042211, 5097117, 5152621, 5208729, 5265449,
    5322786, 5380747, 5439339, 5498570, 5558445, 5618973, 5680159, 5742012, 5804539, 5867746, 5931642,
    5996233, 6061528, 6127533, 6194258, 6261709, 6329894, 6398822, 6468501, 6538938, 6610143, 6682122,
    6754886, 6828442, 6902799, 6977965, 7053950, 7130763, 7208412, 7286906, 7366255, 7446469, 7527555,
    7609525, 7692387, 7776152, 7860829, 7946428, 8032959, 8120432, 8208857, 8298246, 8388608, 8479954,
))


@micropython.viper
def log2q(x: int) -> int:
    """log2(x) in Q.16 for an integer 1 <= x < 2**30 (error < 1 / 2**16: quadratic
    interpolation in a 64-cell table). x < 1 is read as 1 (no endless loop)."""
    if x < 1:
        x = 1
    n = 22
    if x >= 0x800000:  # to [2**22, 2**23): a binary search (a shift loop is ~0.6 us a bit on the chip)
        if x >= 0x4000000:
            x >>= 4
            n += 4
        if x >= 0x1000000:
            x >>= 2
            n += 2
        if x >= 0x800000:
            x >>= 1
            n += 1
    else:
        if x < 0x80:
            x <<= 16
            n -= 16
        if x < 0x8000:
            x <<= 8
            n -= 8
        if x < 0x80000:
            x <<= 4
            n -= 4
        if x < 0x200000:
            x <<= 2
            n -= 2
        if x < 0x400000:
            x <<= 1
            n -= 1
    t = ptr32(_LOG_TAB)
    k = (x >> 16) - 64
    a = int(t[k])
    b = int(t[k + 1])
    u = x & 0xFFFF
    v = u >> 8
    return (n << 16) + a + (((b - a) * u + 0x8000) >> 16) + ((v * (v - 256) * (int(t[k + 2]) - b - b + a) + 0x10000) >> 17)


@micropython.viper
def exp2q(lx: int) -> int:
    """round(2**(lx / 2**16)) for lx < 29 * 2**16 (relative error < 1e-6 before the
    rounding: quadratic interpolation in a 64-cell table)."""
    n = lx >> 16
    f = lx & 0xFFFF
    t = ptr32(_EXP_TAB)
    k = f >> 10
    a = int(t[k])
    b = int(t[k + 1])
    u = f & 0x3FF
    v = u >> 2
    m = a + (((b - a) * u + 512) >> 10) + ((v * (v - 256) * (int(t[k + 2]) - b - b + a) + 0x10000) >> 17)  # Q.22
    if n >= 22:
        return m << (n - 22)
    if n < -2:
        return 0
    s = 22 - n
    return (m + (1 << (s - 1))) >> s


@micropython.viper
def mul_q16(x: int, b: int) -> int:
    """x * b / 2**16 rounded towards zero, |x| < 2**21, |b| < 2**17 (split: < 2**30)."""
    a = 0 - x if x < 0 else x
    c = 0 - b if b < 0 else b
    y = (((a >> 10) * c) >> 6) + (((a & 0x3FF) * c) >> 16)
    if x < 0:
        return y if b < 0 else 0 - y
    return 0 - y if b < 0 else y


def word(j, bias=0):
    """A property for word j of self.v, an int array the viper code reads by ptr32 (kept
    + bias where the value can be negative: a 64-bit viper reads a word unsigned), so that
    commands and tests keep attribute names (sensation_core's Pulse view, SkinModel,
    stim.Channel). The array stores a machine word: a value whose stored word would be past
    +-2**30 is refused with ValueError on both VMs (MicroPython would cut it, CPython raise
    OverflowError), so an attribute reads back what was set or nothing changes."""

    def get(self):
        return self.v[j] - bias

    def put(self, x):
        if not -0x3FFFFFFF <= x + bias <= 0x3FFFFFFF:
            raise ValueError("%d out of range [%d, %d]" % (x, -0x3FFFFFFF - bias, 0x3FFFFFFF - bias))
        self.v[j] = x + bias

    return property(get, put)
