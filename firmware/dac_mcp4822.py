# The amplitude DAC: Microchip MCP4822 (dual 12-bit, SPI, internal 2.048 V
# reference), one output per stimulator channel: channel k is output A (k even)
# or B (k odd) of chip k // 2, each chip with its own chip-select pin. Why this
# part, the analog stage after it and the wiring: docs/hardware.md.
#
# The bus and the pins are injected (a machine.SPI and machine.Pin objects on the
# rp2, fakes in tests); nothing here imports machine. write() allocates nothing:
# one preallocated 2-byte buffer, small-int arithmetic, Pin and SPI method calls.
# Every value stays below 2**30 (the rp2's small-int range): the largest product
# is 4096 * full_ua with full_ua <= 100000.
try:
    from micropython import const
except ImportError:  # CPython (host tests and the board simulator's model)

    def const(x):
        return x


BITS = const(12)
CODES = const(4096)  # 2**BITS: the code that would give full scale (the largest is CODES - 1)
CODE_MAX = const(4095)
# MCP4822 write command (datasheet DS20002249, register 5-1): bit 15 selects the
# output (0 = A, 1 = B), bit 13 GA (1 = gain 1x: Vout = 2.048 V * code / 4096),
# bit 12 SHDN (1 = output active). The output follows on CS's rising edge (LDAC tied low).
_B = const(0x8000)
_GA_1X = const(0x2000)
_ACTIVE = const(0x1000)
FULL_UA_MAX = const(100000)  # checked at set-up: 4096 * full_ua stays a small int on the rp2
# set_gain(): the current at code 4096 of one output, scaled by its measured gain (the
# self-test against a scope, CMD_SET_VMON) within +-10 %: at most 1.1 * FULL_UA_MAX, so
# 4096 * full stays a small int; ppm taken to 10 ppm so full_ua * step < 2**30.
GAIN_PPM_MIN = const(900000)
GAIN_PPM_MAX = const(1100000)


def code_for(i_ua, full_ua):
    """DAC code for a current: the largest code whose current is <= i_ua (never more
    than asked), 0 for i_ua <= 0, CODE_MAX at or above full scale."""
    if i_ua <= 0:
        return 0
    if i_ua >= full_ua:
        return CODE_MAX
    code = i_ua * CODES // full_ua
    if code > CODE_MAX:
        code = CODE_MAX
    return code


def ua_for(code, full_ua):
    """The current a code delivers, in whole uA rounded up: code * full_ua / 4096. Up, so
    the current the firmware is told is never below the one the output drives at its
    full scale: the hard limits held on it (stim._dac_limits) hold the physical current
    (docs/safety.md: nearest let it pass a hard limit by up to 130 ppm)."""
    return (code * full_ua + (CODES - 1)) // CODES


def full_for(full_ua, ppm):
    """The full scale of an output whose gain is ppm / 1e6 (in the window), whole uA, rounded
    up, as the gain taken to 10 ppm (up): never below full_ua x ppm / 1e6, so a code's
    current as reported (ua_for) is never below what that gain drives. |d| <= 10000:
    full_ua * d < 2**30."""
    d = -((1000000 - ppm) // 10)
    return full_ua - ((-full_ua * d) // 100000)


def word(ch, code):
    """The 16-bit command word for output ch & 1 of its chip (gain 1x, active)."""
    w = _GA_1X | _ACTIVE | (code & CODE_MAX)
    if ch & 1:
        w |= _B
    return w


class MCP4822:
    """Amplitude outputs for n channels: spi is a configured bus (mode 0, MSB
    first, <= 20 MHz); cs is a sequence of output Pins, one per chip (channels 2j
    and 2j+1 on cs[j]), idle high; full_ua is the stimulator current at code 4096
    (2.048 V at the DAC output times the analog stage's gain)."""

    def __init__(self, spi, cs, n_channels, full_ua):
        if not 1 <= full_ua <= FULL_UA_MAX:
            raise ValueError("DAC full scale %d uA out of range [1, %d]" % (full_ua, FULL_UA_MAX))
        if len(cs) < (n_channels + 1) // 2:
            raise ValueError("%d channels need %d DAC chip-select pins, %d given"
                             % (n_channels, (n_channels + 1) // 2, len(cs)))
        self.spi = spi
        self.cs = list(cs)
        for p in self.cs:
            p(1)
        self.n = n_channels
        self.full_ua = full_ua
        self.full = [full_ua] * n_channels  # per output: full_ua x its gain (set_gain)
        self.buf = bytearray(2)
        self.codes = [0] * n_channels  # the code last written to each output

    def write(self, ch, code):
        """Write code (0..CODE_MAX) to channel ch's output; it follows at once.
        word() inlined, and the chip select called (Pin.__call__), not .value():
        ~35 us less per write on the chip (docs/performance.md)."""
        code &= 0xFFF
        w = 0x3000 | code  # _GA_1X | _ACTIVE
        if ch & 1:
            w |= 0x8000  # _B
        buf = self.buf
        buf[0] = w >> 8
        buf[1] = w & 0xFF
        cs = self.cs[ch >> 1]
        cs(0)
        self.spi.write(buf)
        cs(1)
        self.codes[ch] = code

    def set_gain(self, ch, ppm):
        """Output ch delivers ppm / 1e6 times its nominal current (0: nominal): its full
        scale follows, so set_ua() returns the current it delivers. ValueError out of
        range (nothing changes). Allocates nothing."""
        if ppm == 0:
            ppm = 1000000
        if not GAIN_PPM_MIN <= ppm <= GAIN_PPM_MAX:
            raise ValueError("DAC gain out of range")
        self.full[ch] = full_for(self.full_ua, ppm)

    def set_ua(self, ch, i_ua):
        """Set channel ch to the nearest current not above i_ua; return the current
        in uA the output stage will deliver (code * LSB, at most full scale).
        code_for(), ua_for() and write() inlined: each Python call costs 15-25 us
        on the chip, and this runs once per channel per frame. The channel's full
        scale includes its measured gain (set_gain)."""
        full = self.full[ch]
        if i_ua <= 0:
            code = 0
        elif i_ua >= full:
            code = 4095  # CODE_MAX
        else:
            code = i_ua * 4096 // full
        w = 0x3000 | code
        if ch & 1:
            w |= 0x8000
        buf = self.buf
        buf[0] = w >> 8
        buf[1] = w & 0xFF
        cs = self.cs[ch >> 1]
        cs(0)
        self.spi.write(buf)
        cs(1)
        self.codes[ch] = code
        return (code * full + 4095) // 4096  # (ua_for: rounded up)

    def zero_all(self):
        k = 0
        while k < self.n:
            self.write(k, 0)
            k += 1
