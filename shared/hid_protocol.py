"""steadytouch USB HID protocol: 64-byte IN and OUT reports (docs/protocol.md).

Shared by the firmware (MicroPython) and the host (CPython). Encoders write
into a caller's preallocated bytearray and decoders read fields one at a time,
so the firmware's frame allocates nothing; every value on the wire stays below
2**30 in magnitude (a 32-bit MicroPython never makes a long int from it).
"""

try:
    from micropython import const
except ImportError:  # CPython

    def const(x):
        return x


PROTOCOL_VERSION = const(1)
REPORT_LEN = const(64)
VID = const(0x1209)  # pid.codes; 0x0001 is its "test PID": for private use only
PID = const(0x0001)

# Vendor-defined page 0xFF00, one 64-byte IN and one 64-byte OUT report, no report IDs.
REPORT_DESCRIPTOR = bytes(
    (
        0x06, 0x00, 0xFF,  # Usage Page (Vendor 0xFF00)
        0x09, 0x01,  # Usage (1)
        0xA1, 0x01,  # Collection (Application)
        0x15, 0x00,  # Logical Minimum (0)
        0x26, 0xFF, 0x00,  # Logical Maximum (255)
        0x75, 0x08,  # Report Size (8)
        0x95, 0x40,  # Report Count (64)
        0x09, 0x02,  # Usage (2)
        0x81, 0x02,  # Input (Data, Var, Abs)
        0x09, 0x03,  # Usage (3)
        0x91, 0x02,  # Output (Data, Var, Abs)
        0xC0,  # End Collection
    )
)

# ---- IN report types (byte 0) ----
REP_TELEMETRY = const(0x01)
REP_ACK = const(0x02)
REP_INFO = const(0x03)
REP_CAL = const(0x04)  # GET_INFO addressed to one channel: its calibration

# ---- OUT commands (byte 0) ----
CMD_ARM = const(0x10)
CMD_DISARM = const(0x11)
CMD_CALIBRATE = const(0x12)
CMD_SET_LIMITS = const(0x13)
CMD_SET_MODE = const(0x14)
CMD_KEEPALIVE = const(0x15)
CMD_GET_INFO = const(0x16)
CMD_SET_SKIN = const(0x17)  # MODE_FAST's skin model (Controller.set_skin)
CMD_SET_VMON = const(0x18)  # one channel's voltage-monitor correction (steadytouch selftest), below
CH_ALL = const(0xFF)

# ---- what the device accepts (the host's command builders check the same) ----
# Shortest pulse any command may set (soft t_min, t0): the PIO gate needs
# T > its 2-cycle overhead, and the 10 us ADC must catch >= 2 samples inside
# the pulse for the median-of-3 peak. Enforced at SET_LIMITS/CALIBRATE and
# again at the board layer (docs/safety.md).
T_FLOOR_US = const(20)
# Keep-alive: on whenever a channel is armed; a command can change the timeout
# within these bounds but never turn it off (0 is refused).
KEEPALIVE_MIN_MS = const(50)
KEEPALIVE_MAX_MS = const(10000)
KEEPALIVE_DEFAULT_MS = const(1000)
RATE_MIN_HZ = const(10)
RATE_MAX_HZ = const(100)
# The frame's worst case must fit its period: rate x frame_us(n, t_max) <= 1 s.
# On the rp2 channel k's work runs while channel k+1's pulse is delivered, so a
# frame is: n pulses of up to t_max, each started FRAME_GAP_US after the one
# before; a pulse shorter than the previous channel's work (FRAME_WORK_US at
# most) stretches to it; then the last channel's work and the frame's own
# work (FRAME_TAIL_US). Host commands come after that: the first waiting one is
# always served, another only while FRAME_CMD_US remain before the next
# deadline (a frame with a command can overrun by one command, counted).
# Figures: the worst measured on the emulated RP2040 in MODE_FAST, with a
# margin; with a skin model on any channel (SET_SKIN) a channel's work and the
# tail are longer (the model's root searches, bounded by FAST_MODEL_WORK_MAX):
# FRAME_WORK_MODEL_US, FRAME_TAIL_MODEL_US (docs/performance.md, "The frame on
# the emulated RP2040"). A SET_MODE rate or SET_LIMITS t_max that breaks the
# rule is refused (RES_OUT_OF_RANGE), a SET_SKIN whose model's work would not
# fit with RES_NO_FRAME_TIME; at boot the default soft t_max is lowered to the
# largest that fits (no model then).
FRAME_GAP_US = const(300)
FRAME_WORK_US = const(1800)
FRAME_TAIL_US = const(2200)
FRAME_WORK_MODEL_US = const(3000)
FRAME_TAIL_MODEL_US = const(3000)
FRAME_CMD_US = const(1500)


def frame_us(n_channels, t_max_us, model=0):
    """The longest frame of n_channels pulses of at most t_max_us (us); model:
    a skin model is set on some channel."""
    work = FRAME_WORK_MODEL_US if model else FRAME_WORK_US
    w = t_max_us if t_max_us > work else work
    tail = FRAME_TAIL_MODEL_US if model else FRAME_TAIL_US
    return n_channels * FRAME_GAP_US + t_max_us + (n_channels - 1) * w + tail


def frame_fits(rate_hz, n_channels, t_max_us, model=0):
    """True if the longest frame of n_channels pulses of t_max_us fits the period at rate_hz."""
    return rate_hz * frame_us(n_channels, t_max_us, model) <= 1000000


def t_max_fitting(rate_hz, n_channels, model=0):
    """Longest t_max (us) that frame_fits() accepts at rate_hz with n_channels;
    below T_FLOOR_US (possibly negative) if no pulse fits."""
    work = FRAME_WORK_MODEL_US if model else FRAME_WORK_US
    room = 1000000 // rate_hz - n_channels * FRAME_GAP_US - (FRAME_TAIL_MODEL_US if model else FRAME_TAIL_US)
    t = room // n_channels
    if n_channels > 1 and t < work:  # every pulse stretched to the work it hides
        t = room - (n_channels - 1) * work
    return t


def rate_max_fitting(n_channels, t_max_us, model=0):
    """Highest rate (Hz) that frame_fits() accepts for n_channels pulses of t_max_us."""
    return 1000000 // frame_us(n_channels, t_max_us, model)


# ---- result codes (ACK byte 2) ----
RES_OK = const(0)
RES_BAD_CRC = const(1)
RES_UNKNOWN_COMMAND = const(2)
RES_BAD_CHANNEL = const(3)
RES_OUT_OF_RANGE = const(4)
RES_BAD_STATE = const(5)  # e.g. calibrate or set limits while armed
RES_NOT_CALIBRATED = const(6)  # arm before calibrate
RES_BAD_FORMAT = const(7)  # reserved bytes not zero
RES_NO_FRAME_TIME = const(8)  # SET_SKIN: the model's work would not fit the frame (rate, t_max)
RES_STORE_FAILED = const(9)  # SET_VMON: the board could not write its flash (nothing changed)

# ---- the voltage monitor's correction (CMD_SET_VMON; firmware/vmon_cal.py) ----
# measured mV = gain x true mV + offset; the firmware divides it out of every
# pulse's peak. OUT: ch = one channel; O_ARG u8 op: VMON_APPLY (in RAM until the
# next reset: the self-test measures the raw monitor with 0, 0) or VMON_STORE
# (written to the board's flash first, then applied; read at every boot);
# O_ARG + 4 i32 gain in ppm, O_ARG + 8 i32 offset in mV; gain 0 and offset 0 =
# uncorrected; O_ARG + 12 i32 the amplitude DAC's gain in ppm (delivered /
# nominal current, found against a scope; 0 = nominal): the board scales the
# DAC's full scale by it, so the current it reports, the Rp and the hard limits
# count the current delivered. ch = CH_ALL: every channel in one command, channel
# k's three words at O_ARG + 4 + VMON_STRIDE * k (channel 0's where a one-channel
# command has them; the words of channels the board lacks must be 0; the bytes after
# the words, up to the CRC, are reserved: 0, else RES_BAD_FORMAT with the byte): all
# checked before anything changes, VMON_STORE writes the one file once (all or nothing).
# Refused while any channel is armed (a flash write stalls the loop for tens of
# ms) with RES_BAD_STATE, outside the ranges with RES_OUT_OF_RANGE (detail: the
# field), a failed flash write with RES_STORE_FAILED: nothing changes.
# The windows are what a healthy board can need (docs/hardware.md, "The accepted
# window"): the monitor's gain (the whole path's when no scope separated the
# DAC's) 0.91-1.09, its offset +-1.2 V at the electrodes, the DAC's gain 0.965-1.035.
VMON_APPLY = const(0)
VMON_STORE = const(1)
VMON_STRIDE = const(12)
VMON_GAIN_PPM_MIN = const(910000)
VMON_GAIN_PPM_MAX = const(1090000)
VMON_OFFSET_MV_MIN = const(-1200)
VMON_OFFSET_MV_MAX = const(1200)
VMON_DAC_PPM_MIN = const(965000)
VMON_DAC_PPM_MAX = const(1035000)
# what the board's flash held at boot (REP_INFO O_INFO_VMON, REP_CAL O_CAL_VMON_STATE)
VMON_NONE = const(0)  # no correction file: every monitor uncorrected
VMON_LOADED = const(1)  # the file was read and applied
VMON_BAD = const(2)  # a file that cannot be read or is out of range: ignored, every monitor uncorrected
VMON_STORED = const(3)  # SET_VMON ... VMON_STORE wrote the file since boot

# ---- stop reasons (telemetry byte 3; 0 = stimulating) ----
STOP_NONE = const(0)
STOP_IDLE = const(1)  # never armed since boot
STOP_DISARMED = const(2)  # by command
STOP_ELECTRODE_OFF = const(3)  # Vp near compliance or Rp above range: latched
STOP_RP_FAULT = const(4)  # controller fault (Rp below range, ...): latched
STOP_KEEPALIVE = const(5)  # host silent longer than the keep-alive timeout: latched
STOP_LIMIT = const(6)  # a pulse would exceed a hard limit: latched
STOP_INTERNAL = const(7)  # firmware error in the frame: latched

# ---- telemetry flags (byte 46) ----
FLAG_ARMED = const(0x01)
FLAG_HELD = const(0x02)  # a charge increase waits for a confirming measurement
FLAG_KEEPALIVE = const(0x04)
FLAG_CALIBRATING = const(0x08)  # this pulse is a calibration pulse (at I0, T0: Rp0 once two agree, cal_rp0)
FLAG_MODE_SET = const(0x10)  # SET_MODE changed this armed channel's law (Rp0 again) since its last pulse's report

# ---- the calibration pulses after ARM: Rp0 (the device's stim._control, the host's audit) ----
CAL_AGREE_LOG2 = const(5)  # two readings in a row within 1/32 of the larger agree
CAL_TRIES = const(16)  # calibration pulses that never agree: the channel is latched STOP_RP_FAULT


def cal_rp0(r1_ohm, rp_ohm, smaller=False):
    """Rp0 from a calibration pulse's reading rp_ohm and the one before it (r1_ohm; 0: none), when
    the two agree within 1/2**CAL_AGREE_LOG2 of the larger, else 0 (the calibration pulse is sent
    again): the one whose law asks less charge, so that no single reading raises it: the larger
    (Eq. 2's mQ target and the pulse-width-linear slope fall with Rp0), or with `smaller` the
    smaller (MODE_CONSTANT_ENERGY: T = T0 Rp0 / Rp)."""
    top = rp_ohm if rp_ohm > r1_ohm else r1_ohm
    low = r1_ohm + rp_ohm - top
    if r1_ohm <= 0 or top - low > top >> CAL_AGREE_LOG2:
        return 0
    return low if smaller else top

# ---- byte offsets ----
# common to all IN reports
O_TYPE = const(0)
O_SEQ = const(4)  # u32, wraps at 2**30
O_TIME = const(8)  # u32, device ticks_us at frame start, wraps at 2**30
# telemetry
O_CH = const(1)
O_MODE = const(2)
O_STOP = const(3)
O_I = const(12)  # u16 uA delivered in this frame (0: no pulse)
O_T = const(14)  # u16 us
O_VP = const(16)  # u32 mV peak measured on it
O_RP = const(20)  # i32 ohm
O_ME = const(24)  # u32 uA^2*ms
O_MQT = const(28)  # i32 fC/ohm target
O_MQL = const(32)  # i32 fC/ohm of this pulse
O_STATUS = const(36)  # u16 controller status bits
O_NEXT_I = const(38)  # u16 controller output for the next pulse
O_NEXT_T = const(40)  # u16
O_OVERRUNS = const(42)  # u16 saturating
O_LOOP = const(44)  # u16 us, saturating
O_FLAGS = const(46)
O_RATE = const(47)
O_SENT_STATUS = const(48)  # u16 the status bits (bounds) of the pulse delivered in this frame (0: none)
O_LTAU = const(52)  # u32 log2 of the monitor's decay time constant (us) after that pulse, Q.16 (0: none)
# ack / info
O_CMD = const(1)
O_RESULT = const(2)
O_TAG = const(3)
O_DETAIL = const(12)  # ack: offset of the offending OUT byte (0 = none)
O_FW = const(12)  # info: major, minor, patch, n_channels
O_HARD_I = const(16)
O_HARD_T = const(18)
O_HARD_Q = const(20)
O_COMPLIANCE = const(24)
O_LIM = const(28)  # i_min u16, i_max u16, t_min u16, t_max u16, q_max u32
O_INFO_MODE = const(40)
O_INFO_RATE = const(41)
O_INFO_KEEPALIVE = const(42)
O_BOARD = const(44)  # 16 bytes ASCII, NUL padded
BOARD_LEN = const(16)
O_INFO_VMON = const(60)  # u8 VMON_NONE / LOADED / BAD / STORED
O_INFO_FLAGS = const(61)  # u8 board flags (0 from firmware before it): INFO_FLAG_*
INFO_FLAG_DAC_GAIN = const(0x01)  # the board's DAC path applies a stored DAC gain (else stored, not applied)
# O_HARD_I / O_HARD_Q are the limits in force: held to the board's nominal ones x VMON_DAC_PPM_MIN
# while a channel has no DAC gain applied (this flag; a self-test with --scope lifts it), x the DAC
# gain / VMON_DAC_PPM_MAX where one is applied (the physical current then stays within the nominal
# ones whatever the true gain in the window). SET_LIMITS accepts up to them (docs/protocol.md).
INFO_FLAG_HELD = const(0x02)
# O_HARD_I / O_HARD_Q lowered below the board's nominal ones x a DAC gain below VMON_DAC_PPM_MAX
# applied on a channel / VMON_DAC_PPM_MAX (not held: every channel has its gain; REP_CAL's
# O_CAL_DAC_GAIN says which)
INFO_FLAG_DAC_LOW = const(0x04)
# (other bits: for later firmware; a host ignores bits it does not know)
# GET_INFO (CH_ALL) with O_ARG = INFO_PAGE_OWN asks for the board's own limits: the same
# REP_INFO layout with O_INFO_PAGE = 1, O_HARD_I / O_HARD_Q the board's nominal hard limits
# (board_config, never held) and O_LIM the soft limits as last set (at boot: board_config's;
# then SET_LIMITS), before the firmware lowered them to the hard limits in force. Firmware
# before it answers page 0 (O_INFO_PAGE 0) whatever O_ARG holds; a page > 1 is refused
# (RES_OUT_OF_RANGE, O_ARG).
O_INFO_PAGE = const(62)  # u8 (IN reports carry no CRC): 0 the limits in force, 1 the board's own
INFO_PAGE_OWN = const(1)
# calibration report (REP_CAL)
O_CAL_CH = const(12)
O_CAL_FLAGS = const(13)  # 0x01 calibration received, 0x02 armed, 0x04 Rp0 measured, 0x08 monitor corrected,
# 0x10 DAC gain corrected
O_CAL_I0 = const(14)
O_CAL_T0 = const(16)
O_CAL_X = const(20)
O_CAL_Y = const(24)
O_CAL_RP0 = const(28)
O_CAL_MODE = const(32)
O_CAL_VMON_GAIN = const(36)  # i32 ppm applied to this channel's monitor (0: uncorrected)
O_CAL_VMON_OFF = const(40)  # i32 mV
O_CAL_VMON_STATE = const(44)  # u8, as O_INFO_VMON
O_CAL_DAC_GAIN = const(48)  # i32 ppm applied to this channel's amplitude DAC (0: nominal)
O_CAL_SKIN_RS = const(52)  # MODE_FAST's skin model as set (SET_SKIN; all 0: none), firmware 0.4.1 on: u16 Rs (ohm),
O_CAL_SKIN_BETA = const(54)  # u32 beta (Q.16),
O_CAL_SKIN_CP = const(58)  # u32 Cp (pF)
O_CAL_SKIN_TAU = const(62)  # u16 rule 7's tau gain as set (SET_SKIN byte 14: log2, Q.16, + 0x8000; 0: tau not used),
# firmware 0.5.0 on (IN reports carry no CRC)
CAL_FLAG_VMON = const(0x08)
CAL_FLAG_DAC = const(0x10)
# OUT
O_OUT_CMD = const(0)
O_OUT_TAG = const(1)
O_OUT_CH = const(2)
O_OUT_RESERVED = const(3)  # must be 0
O_ARG = const(4)
O_CRC = const(62)
CRC_LEN = const(62)

I32_BAD = const(-0x3FFFFFFF)  # get_i32 of a value outside +-2**29


def _crc_table():
    """CRC-16/CCITT-FALSE of each byte value, built once at import: crc16 then
    does one table look-up a byte instead of eight shift/xor steps (about
    6x faster on the RP2040, the same CRC bit for bit)."""
    t = []
    for v in range(256):
        crc = v << 8
        for _ in range(8):
            if crc & 0x8000:
                crc = ((crc << 1) ^ 0x1021) & 0xFFFF
            else:
                crc = (crc << 1) & 0xFFFF
        t.append(crc)
    return tuple(t)


_CRC_TABLE = _crc_table()


def crc16(buf, n):
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) of buf[0:n]. Allocates nothing."""
    crc = 0xFFFF
    t = _CRC_TABLE
    k = 0
    while k < n:
        crc = ((crc << 8) & 0xFF00) ^ t[(crc >> 8) ^ buf[k]]
        k += 1
    return crc


def put_u16(b, o, v):
    b[o] = v & 0xFF
    b[o + 1] = (v >> 8) & 0xFF


def put_i32(b, o, v):
    """Little-endian 32-bit; v must be within +-2**30 (u32 fields use it too)."""
    b[o] = v & 0xFF
    b[o + 1] = (v >> 8) & 0xFF
    b[o + 2] = (v >> 16) & 0xFF
    b[o + 3] = (v >> 24) & 0xFF


def get_u16(b, o):
    return b[o] | (b[o + 1] << 8)


def get_i32(b, o):
    """Signed 32-bit, or I32_BAD if outside -2**29 .. 2**29-1 (never a long int)."""
    top = b[o + 3]
    if top >= 0xE0:
        top -= 0x100
    elif top >= 0x20:
        return I32_BAD
    return (top << 24) | (b[o + 2] << 16) | (b[o + 1] << 8) | b[o]


_ZEROS = bytes(REPORT_LEN)


def clear(b):
    # one slice copy: allocation-free under heap_lock (MicroPython >= 1.23 keeps
    # the slice off the heap when subscripting a built-in), ~10x the byte loop
    b[0:REPORT_LEN] = _ZEROS


def sat16(v):
    return 0xFFFF if v > 0xFFFF else (0 if v < 0 else v)


def seal(b):
    """Write the CRC of an OUT report into its last two bytes."""
    put_u16(b, O_CRC, crc16(b, CRC_LEN))


def crc_ok(b):
    return get_u16(b, O_CRC) == crc16(b, CRC_LEN)


# ---- OUT report builders (host, and the firmware's --auto start) ----
def _cmd(b, cmd, ch, tag):
    clear(b)
    b[O_OUT_CMD] = cmd
    b[O_OUT_TAG] = tag & 0xFF
    b[O_OUT_CH] = ch & 0xFF
    return b


def cmd_arm(b, ch, tag=0):
    seal(_cmd(b, CMD_ARM, ch, tag))
    return b


def cmd_disarm(b, ch, tag=0):
    seal(_cmd(b, CMD_DISARM, ch, tag))
    return b


def cmd_calibrate(b, ch, i0_ua, t0_us, x_star_ohm, y_star_pc, tag=0):
    _cmd(b, CMD_CALIBRATE, ch, tag)
    put_u16(b, O_ARG, i0_ua)
    put_u16(b, O_ARG + 2, t0_us)
    put_i32(b, O_ARG + 4, x_star_ohm)
    put_i32(b, O_ARG + 8, y_star_pc)
    seal(b)
    return b


def cmd_set_limits(b, i_min_ua, i_max_ua, t_min_us, t_max_us, q_max_pc, tag=0):
    _cmd(b, CMD_SET_LIMITS, CH_ALL, tag)
    put_u16(b, O_ARG, i_min_ua)
    put_u16(b, O_ARG + 2, i_max_ua)
    put_u16(b, O_ARG + 4, t_min_us)
    put_u16(b, O_ARG + 6, t_max_us)
    put_i32(b, O_ARG + 8, q_max_pc)
    seal(b)
    return b


def cmd_set_mode(b, mode, rate_hz=0, tag=0):
    _cmd(b, CMD_SET_MODE, CH_ALL, tag)
    b[O_ARG] = mode
    b[O_ARG + 1] = rate_hz
    seal(b)
    return b


def cmd_set_skin(b, ch, rs_ohm, beta_q16, cp_pf, tag=0, tau_q16=-0x8000):
    """tau_q16: the monitor's tau gain (log2, Q.16) measured with the model, -0x8000 (sc.SKIN_TAU_OFF): none."""
    _cmd(b, CMD_SET_SKIN, ch, tag)
    put_u16(b, O_ARG, rs_ohm)
    put_i32(b, O_ARG + 2, beta_q16)
    put_i32(b, O_ARG + 6, cp_pf)
    put_u16(b, O_ARG + 10, tau_q16 + 0x8000)
    seal(b)
    return b


def cmd_set_vmon(b, ch, op, gain_ppm, offset_mv, tag=0, dac_gain_ppm=0):
    _cmd(b, CMD_SET_VMON, ch, tag)
    b[O_ARG] = op
    put_i32(b, O_ARG + 4, gain_ppm)
    put_i32(b, O_ARG + 8, offset_mv)
    put_i32(b, O_ARG + 12, dac_gain_ppm)
    seal(b)
    return b


def cmd_set_vmon_all(b, op, values, tag=0):
    """CMD_SET_VMON to every channel at once: values = [(gain_ppm, offset_mv, dac_gain_ppm)
    per channel] (at most 4)."""
    _cmd(b, CMD_SET_VMON, CH_ALL, tag)
    b[O_ARG] = op
    k = 0
    while k < len(values):
        o = O_ARG + 4 + VMON_STRIDE * k
        put_i32(b, o, values[k][0])
        put_i32(b, o + 4, values[k][1])
        put_i32(b, o + 8, values[k][2])
        k += 1
    seal(b)
    return b


def cmd_keepalive(b, timeout_ms=0, tag=0):
    _cmd(b, CMD_KEEPALIVE, CH_ALL, tag)
    put_u16(b, O_ARG, timeout_ms)
    seal(b)
    return b


def cmd_get_info(b, tag=0, ch=CH_ALL, page=0):
    _cmd(b, CMD_GET_INFO, ch, tag)
    b[O_ARG] = page
    seal(b)
    return b
