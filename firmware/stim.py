# steadytouch firmware core: the deadline-scheduled stimulation frame, the
# safety supervisor and the command handler. Hardware is injected (a Board with
# the interface documented in docs/hardware.md), so this module runs unchanged
# on the rp2 and in the MicroPython unix VM with the simulated board.
#
# The frame (Stimulator.frame) reads as the paper's Fig. 3 loop, channel by
# channel: pulse (the hard-limit check right before the gate opens), then
# measure -> supervise -> control -> output -> report, a short method each (the
# supervisor's rules open _control: a call fewer; Rp is computed in _measure).
# On the rp2 the PIO gate and the ADC -> DMA capture deliver a pulse by
# themselves: channel k's pulse runs while the CPU does channel k-1's work.
#
# The firmware part of the frame runs between heap_lock()/heap_unlock() (on the
# device too): it allocates nothing, and large function frames go on the C
# stack instead of the heap. The rp2 board's pulse, output and stop calls
# allocate nothing and run inside that section; the simulated board's calls
# (floats) run between sections. A board whose interrupts schedule Python
# callbacks that allocate (the rp2's USB stack) provides irq_off()/irq_on(state):
# a section then runs with interrupts held off, so no such callback can land
# inside it (the USB controller itself goes on: PIO, DMA and timers need no CPU).
import struct
from array import array

import sensation_core as sc
from decay import ltau_q16 as _ltau  # the monitor's decay after the fall: log2 tau (stim._measure)
from fixmath import word as _word  # a word of Channel.v as an attribute (fixmath.word)
import hid_protocol as hp

try:
    import micropython

    _lock = micropython.heap_lock
    _unlock = micropython.heap_unlock
    const = micropython.const
except ImportError:  # CPython: no heap lock

    def _lock():
        pass

    def _unlock():
        pass

    def const(x):
        return x


# 0.2.0: GET_INFO's hard fields are the limits in force (held); 0.3.0: GET_INFO page 1 (the board's own)
# 0.4.0: telemetry O_SENT_STATUS (the bounds of the pulse delivered: the controller is told them),
# FLAG_MODE_SET, O_LTAU (the monitor's decay after the fall: the capture runs 100 us past it)
# 0.4.1: GET_INFO's Calibration report carries the channel's skin model (bytes 52-61: `audit` replays it)
# 0.5.0: the controller reads that decay (ctl.ltau_q16 before each update: MODE_FAST's model anchors on it where
# SET_SKIN gave the monitor's tau gain, bytes 14-15; GET_INFO's Calibration report bytes 62-63 carry it)
FW_VERSION = (0, 5, 0)
_MAX_CMDS_PER_FRAME = const(4)
RATE_MIN_HZ = hp.RATE_MIN_HZ
RATE_MAX_HZ = hp.RATE_MAX_HZ
# Literals for the viper methods (const() folds only literals of this module; checked
# against the modules' constants below)
_C_T_FLOOR_US = const(20)
_C_FAULT_MASK = const(0x1E0)
_C_RP_MIN_OHM = const(500)
_C_RP_MAX_OHM = const(200000)
_C_STOP_LIMIT = const(6)
_C_STOP_OFF = const(3)
_C_STOP_RP_FAULT = const(4)
_C_VP_LIMIT_MV = const(1000000)
_C_RP_OVER = const(1073741823)
_C_K_MODE = const(0)  # (sensation_core._K_MODE: ctl.mode as a word; checked below)
_C_K_ME = const(32)
_C_K_MQT = const(33)
_C_K_I = const(22)  # the controller's next pulse as words of ctl._k (sensation_core._K_I, _K_T, _K_ST:
_C_K_T = const(23)  # ctl.i_ua, ctl.t_us, ctl.status are properties over them; checked below)
_C_K_ST = const(24)
_C_K_MQL = const(26)  # and its mQ on the pulse measured (+ _C_W_BIAS: signed)
_C_K_LT = const(34)  # the decay's log2 tau after the pulse measured (sensation_core._K_LT: ctl.ltau_q16; checked below)
_C_K_TMIN = const(3)  # its soft t_min, t_max (sensation_core._K_TMIN, _K_TMAX; checked below)
_C_K_TMAX = const(4)
_C_ST_I_BOUND = const(0x003)  # sc.ST_I_MIN | sc.ST_I_MAX
_C_ST_I_MAX = const(0x002)
_C_ST_T_MIN = const(0x004)
_C_ST_Q_MAX = const(0x010)
_C_W_BIAS = const(0x20000000)
_C_MODE_CE = const(2)  # sc.MODE_CONSTANT_ENERGY: its T grows with Rp0 (the calibration takes the smaller reading)
_C_MODE_AKHTAR = const(4)  # sc.MODE_AKHTAR and above (MODE_FAST): pulses on the mE curve (Eq. 4)
if (sc.VP_LIMIT_MV != _C_VP_LIMIT_MV or sc.RP_OVER != _C_RP_OVER or hp.T_FLOOR_US != _C_T_FLOOR_US
        or sc.ST_FAULT_MASK != _C_FAULT_MASK or sc.RP_MIN_OHM != _C_RP_MIN_OHM
        or sc.RP_MAX_OHM != _C_RP_MAX_OHM or hp.STOP_LIMIT != _C_STOP_LIMIT or hp.STOP_ELECTRODE_OFF != _C_STOP_OFF
        or hp.STOP_RP_FAULT != _C_STOP_RP_FAULT or sc.MODE_CONSTANT_ENERGY != _C_MODE_CE
        or sc.MODE_AKHTAR != _C_MODE_AKHTAR or sc.MODE_FAST != _C_MODE_AKHTAR + 1
        or sc.ST_I_MIN | sc.ST_I_MAX != _C_ST_I_BOUND or sc.ST_T_MIN != _C_ST_T_MIN or sc.ST_Q_MAX != _C_ST_Q_MAX
        or sc.ST_I_MAX != _C_ST_I_MAX):
    raise ImportError("stim: a literal of the viper frame differs from its module's constant")
# The telemetry layout (bytes 0..O_LTAU + 3; the rest stays 0) that the viper writer
# _encode_telemetry hard-codes, as a struct format (tests/test_frame_telemetry.py
# compares the two); its offsets, type and flag values are checked at import.
_TEL_FMT = "<BBBBiiHHiiiiiHHHHHBBHxxi"
if not (hp.O_TYPE == 0 and hp.O_CH == 1 and hp.O_MODE == 2 and hp.O_STOP == 3 and hp.O_SEQ == 4
        and hp.O_TIME == 8 and hp.O_I == 12 and hp.O_T == 14 and hp.O_VP == 16 and hp.O_RP == 20
        and hp.O_ME == 24 and hp.O_MQT == 28 and hp.O_MQL == 32 and hp.O_STATUS == 36 and hp.O_NEXT_I == 38
        and hp.O_NEXT_T == 40 and hp.O_OVERRUNS == 42 and hp.O_LOOP == 44 and hp.O_FLAGS == 46
        and hp.O_RATE == 47 and hp.O_SENT_STATUS == 48 and hp.O_LTAU == 52 and struct.calcsize(_TEL_FMT) == 56
        and hp.REP_TELEMETRY == 1
        and hp.FLAG_ARMED == 1 and hp.FLAG_HELD == 2 and hp.FLAG_KEEPALIVE == 4 and hp.FLAG_CALIBRATING == 8
        and hp.FLAG_MODE_SET == 16):
    raise ImportError("stim: telemetry layout changed; update _TEL_FMT")
_c = sc.Controller(1, 2, 3, 4, 6)  # the controller's words as _control and the report read them
_c.i_ua, _c.t_us, _c.status, _c.mq_last_fc_per_ohm = 11, 12, 13, -14
_c.me_ua2ms, _c.mq_target_fc_per_ohm, _c.ltau_q16 = 15, 16, 17
_c.set_mode(sc.MODE_FAST)
if [_c._k[j] for j in (_C_K_I, _C_K_T, _C_K_ST, _C_K_MQL, _C_K_ME, _C_K_MQT, _C_K_MODE, _C_K_TMIN, _C_K_TMAX,
                       _C_K_LT)] != [11, 12, 13, _C_W_BIAS - 14, 15, 16, sc.MODE_FAST, 3, 4, 17]:
    raise ImportError("stim: the controller's words moved; update _C_K_I, _C_K_T, _C_K_ST, _C_K_MQL, _C_K_ME, _C_K_MQT, "
                      "_C_K_MODE, _C_K_TMIN, _C_K_TMAX, _C_K_LT, _C_W_BIAS")
del _c
if bytes(array("i", [1]))[0] != 1:  # _encode_telemetry packs the fields into little-endian words (as ptr32 stores them)
    raise ImportError("stim: a little-endian machine is needed (the RP2040 and the unix VM's x86/ARM are)")


_EDGE_RISE_COUNTS = const(8)  # what the last sample may rise above its predecessor: noise (~3 sigma) ...
_EDGE_RISE_SHIFT = const(6)  # ... plus 1/64 of it (the steepest genuine rise in 2 us at T >= 100 us is ~1.5 %)


@micropython.viper
def _peak_counts(buf, lo: int, hi: int) -> int:
    """The end-of-pulse voltage (12-bit ADC counts) in buf[lo:hi], an array('H')
    window of consecutive samples 2 us apart that holds the gate's falling edge:
    the larger of
      - the largest min of two neighbouring samples (on a pulse: the sample
        2-4 us before the edge; one wild sample can never lift it above a
        genuine sample), and
      - the last sample before the largest drop (the edge: on a pulse, within
        its last 2 us), capped at its predecessor + 8 counts + 1/64.
    Spike guard: one wild sample, high or low, anywhere, can never make the
    result exceed the largest genuine sample by more than 8 counts + 1/64 of it
    (~0.3 V + 1.6 %): it cannot read Rp much high, and a high Rp is what raises
    the charge (mQ ~ Q / (Rp - x*)); the frame's rule that a raise needs two
    measurements in a row (the smaller) keeps one such pulse from raising it.
    hi - lo == 1: that sample. Returns that value (< 2**16) | e << 16, e the index of
    the first sample after the largest drop (the fall: the monitor's decay follows it;
    hi when hi - lo < 2). Viper: machine code on the rp2, nothing allocated; every
    value is < 4096 + 8 + 64, so 32-bit (ARM) and 64-bit (x64) words agree."""
    p = ptr16(buf)
    if hi - lo < 2:
        return (int(p[lo]) if hi > lo else 0) | (hi << 16)
    best = 0
    drop = -4096
    e = hi
    k = hi - 1
    while k > lo:  # from the end: on equal drops the latest wins
        x = int(p[k])
        y = int(p[k - 1])
        if (y if y < x else x) > best:
            best = y if y < x else x
        if y - x > drop:
            drop = y - x
            e = k
        k -= 1
    if e - 1 > lo:
        x = int(p[e - 1])
        y = int(p[e - 2])
        y += _EDGE_RISE_COUNTS + (y >> _EDGE_RISE_SHIFT)
        if x > y:
            x = y
        if x > best:
            best = x
    return best | (e << 16)


# A channel's numbers the frame reads and writes every pulse, as words of one int array
# (Channel.v): the frame's viper methods reach each with one load or store (ptr32) instead of
# an attribute lookup (~1.5 us each on the chip, ~55 a channel a frame). Everything
# else (commands, tests) reads and writes them as attributes (the properties below).
_I = const(0)  # pulse for this frame (0: none), uA
_T = const(1)  # its width, us
_DI = const(2)  # pulse delivered this frame (telemetry)
_DT = const(3)
_AI = const(4)  # the current the amplitude output was last set for (0: stopped)
_AD = const(5)  # what the board said that setting delivers (board.set_amplitude's answer)
_NS = const(6)  # monitor samples captured across this frame's pulse
_VP = const(7)
_VPR = const(8)  # Vp before the monitor correction (the electrode-off rule reads both)
_RP = const(9)
_ARMED = const(10)  # 0/1 (read as a bool)
_HELD = const(11)  # 0/1: a raise is held for a second measurement
_CALIB = const(12)  # 0/1: the next pulse is the calibration pulse
_CALP = const(13)  # 0/1: this frame's pulse is the calibration pulse (telemetry flag)
_STOP = const(14)
_PI = const(15)  # the held proposal
_PT = const(16)
_CH = const(17)
_HID = const(18)  # hard limits for the current the board reports it delivers (_vmon_apply)
_HQD = const(19)
_VK = const(20)  # the monitor correction as vmon_cal.terms() for _measure (0: none)
_VO = const(21)
_W = const(22)  # samples in the capture window (len(c.adc))
_UV = const(23)  # uV per ADC count (the Stimulator's uv_per_count)
_HI = const(24)  # the Stimulator's hard_i, hard_t, hard_q, vp_off_mv (fixed at set-up): _pulse's and
_HT = const(25)  # _control's checks read them as words (an attribute of the Stimulator is ~2 us each)
_HQ = const(26)
_OFF = const(27)
_OVL = const(28)  # 1: the board delivers pulses by itself (the Stimulator's _overlap, fixed at set-up)
_CR = const(29)  # the last calibration pulse's Rp, not yet confirmed (0: none)
_CN = const(30)  # calibration pulses since arming
_FI = const(31)  # the pulse sent before the last fall of more than 1/32 in charge (_control) ...
_FT = const(32)
_FN = const(33)  # ... and the pulses left in which no raise goes past it (0: none)
_CLO = const(34)  # the two readings that gave Rp0 (the smaller, the larger): SET_MODE takes Rp0
_CHI = const(35)  # again from them for its mode (hid_protocol.cal_rp0)
_MS = const(36)  # the mode changed while armed: 1 its first pulse, 2 ramping, 3 one proposal within the cap (_control)
_MN = const(37)  # ... and the pulses left before the ramp ends whatever the law asks (_C_MODE_RAMP_MAX)
# the controller's status bits (bounds) of each pulse the supervisor may send: the controller is told
# the status of the pulse measured with its I and T before each update (MODE_FAST's step and skin model
# take their path from it: the status of its own last proposal after a held pulse said "no bound"
# where the pulse measured was at i_max, second review of session 23: +37 %)
_SS = const(38)  # the pulse to send (_I, _T)
_DS = const(39)  # the pulse delivered this frame (_DI, _DT; telemetry's O_SENT_STATUS)
_PS = const(40)  # the held proposal (_PI, _PT)
_FS = const(41)  # the pulse before the last fall (_FI, _FT)
_MC = const(42)  # 1: SET_MODE changed the law (calibrate again) since the last report of a pulse (FLAG_MODE_SET:
# two in one frame, FAST -> X -> FAST, left the mode as `audit` saw it but not the controller)
_LT = const(43)  # log2 of the monitor's decay time constant after this frame's pulse, Q.16 (decay.ltau_q16; 0: none)
_DTU = const(44)  # us between two ADC samples (the board's dt_us, fixed at set-up)
_PX = const(45)  # samples at the window's end past what Vp reads (the capture's decay beyond _C_PEAK_POST_US)
_NV = const(46)
# Vp reads the capture's samples up to _C_PEAK_POST_US past the fall, at most _C_PEAK_SAMPLES of them (the
# window before session 24): the longer capture after it is the decay's (tau). A longer read would take the
# largest pair-min over more of the plateau, and its noise would lift Vp (and Rp, which raises the charge)
_C_PEAK_POST_US = const(20)
_C_PEAK_SAMPLES = const(32)
# after a fall of the charge by more than 1/2**this, no raise goes past the pulse sent before the
# fall for _C_FALL_HOLD pulses or until that pulse is sent again (the readings on it are then the
# two-in-a-row rule's to judge): one wild reading that made the fall cannot make the recovery
# overshoot the charge it had (review of session 22: +73 % in constant energy, +10 % in MODE_FAST
# with a skin model, from one reading; with 1/8 a reading x 1.1 made a fall of 9 % and a recovery
# 3 % past it; docs/safety.md)
_C_FALL_LOG2 = const(5)
_C_FALL_HOLD = const(16)
# after SET_MODE while armed the new law's raises are capped at 1/2**this more than the pulse sent,
# until two proposals in a row ask for no more (_control, _MS), or for at most _C_MODE_RAMP_MAX
# pulses: a law that swings above and below the cap on every pulse (Rp that flips: the chip
# harness's 20 <-> 40 kohm load in constant energy) would keep it forever, and its raises rest on
# readings of its own pulses by then; 128 pulses hold 64 raises of 1/4, 1.25**64 > 2**25 / 20: more
# than any ramp between two pulses within the limits (q_max <= 2**25 pC, T >= 20 us, I >= 1 uA)
_C_MODE_RAMP_LOG2 = const(2)
_C_MODE_RAMP_MAX = const(128)


def _vmon_product_max(uv):
    """The largest |(16 x - o) k| + 2**16 _measure can form for a read x <= 4095 counts,
    the offset term o of +-VMON_OFFSET_MV_MAX at uv uV a count and the gain term k of the
    lowest accepted gain (Stimulator._vmon_apply's terms). In a machine word on the chip:
    the board config is refused where it could reach 2**30 (review: uv <= 187 wrapped)."""
    k = (81920000 + hp.VMON_GAIN_PPM_MIN // 200) // (hp.VMON_GAIN_PPM_MIN // 100)
    o = (hp.VMON_OFFSET_MV_MAX * 32000 + uv) // (2 * uv) + 1  # +1: a negative offset rounds down
    return (4095 * 16 + o) * k + 65536


def _vmon_uv_min():
    uv = 1
    while _vmon_product_max(uv) >= 1 << 30:
        uv += 1
    return uv


def _flag(k):
    def get(self):
        return self.v[k] != 0

    def put(self, x):
        self.v[k] = 1 if x else 0

    return property(get, put)


class Channel:
    """State of one electrode channel: its controller and its supervisor. Every word of
    v is >= 0 in the frame except _VO (the monitor offset's term): viper's ptr32 reads
    a word sign-extended in 32-bit words (ARM) but zero-extended in 64-bit ones (the unix
    VM), so a negative word is read with its sign restored (_measure)."""

    i = _word(_I)
    t = _word(_T)
    di = _word(_DI)
    dt = _word(_DT)
    ai = _word(_AI)
    ad = _word(_AD)
    n_samples = _word(_NS)
    vp = _word(_VP)
    vp_raw = _word(_VPR)
    rp = _word(_RP)
    armed = _flag(_ARMED)
    held = _flag(_HELD)
    calibrating = _flag(_CALIB)
    cal_pulse = _flag(_CALP)
    stop = _word(_STOP)
    pi = _word(_PI)
    pt = _word(_PT)
    ch = _word(_CH)
    hard_i_d = _word(_HID)
    hard_q_d = _word(_HQD)
    vmon_k = _word(_VK)
    vmon_o = _word(_VO)
    sent_status = _word(_SS)  # the status bits of the pulse to send (_I, _T) ...
    delivered_status = _word(_DS)  # ... and of the pulse delivered this frame (_DI, _DT)
    mode_set = _flag(_MC)
    ltau = _word(_LT)

    def __init__(self, ch, lim):
        self.v = array("i", [0] * _NV)
        self.ch = ch
        self.ctl = sc.Controller(lim[0], lim[1], lim[2], lim[3], lim[4])
        self.stop = hp.STOP_IDLE
        self.have_cal = False
        self.i0 = 0
        self.t0 = 0
        self.x = 0
        self.y = 0
        self.adc = None  # the capture buffer (the board's, bound by the Stimulator)
        self.vmon_g = 0  # the monitor correction applied (gain ppm, offset mV; 0, 0: none; terms in vmon_k, vmon_o)
        self.vmon_off = 0
        self.vmon_dac = 0  # the amplitude DAC's gain applied (ppm; 0: nominal)
        self.vmon_stored = None  # (gain ppm, offset mV, DAC gain ppm) the board's flash holds for this channel


class Stimulator:
    """The on-device loop. `board` is the hardware, `clock` the tick source."""

    def __init__(self, board, clock, cfg, n_channels=None, rate_hz=None, keepalive_ms=None):
        """keepalive_ms: None -> hp.KEEPALIVE_DEFAULT_MS. 0 (off) is for scripted
        simulations whose host is the script itself; no command can set 0."""
        self.board = board
        self.clock = clock
        # the board's hard limits and electrode-off level: fixed for the Stimulator's life (the
        # frame's checks read their copies in every channel's words _HI, _HT, _HQ, _OFF, set below)
        self.hard_i = cfg.HARD_I_MAX_UA
        self.hard_t = cfg.HARD_T_MAX_US
        self.hard_q = cfg.HARD_Q_MAX_PC
        self.compliance_mv = cfg.COMPLIANCE_MV
        self.vp_off_mv = cfg.COMPLIANCE_MV * cfg.ELECTRODE_OFF_PERMILLE // 1000
        self.board_name = cfg.BOARD_NAME
        self.board_bytes = cfg.BOARD_NAME.encode()  # indexing bytes allocates nothing
        self.uv_per_count = cfg.VMON_UV_PER_COUNT
        if not 0 < cfg.VMON_UV_PER_COUNT < (1 << 30) // 4096:  # _measure's products stay < 2**30
            raise ValueError("board config: VMON_UV_PER_COUNT must be in [1, %d]" % ((1 << 30) // 4096 - 1))
        if _vmon_product_max(cfg.VMON_UV_PER_COUNT) >= 1 << 30:  # _measure's correction product
            raise ValueError("board config: VMON_UV_PER_COUNT must be >= %d (the monitor correction's "
                             "offset term at +-%d mV stays < 2**30)" % (_vmon_uv_min(), hp.VMON_OFFSET_MV_MAX))
        if not (cfg.HARD_I_MAX_UA <= sc.I_LIMIT_UA and cfg.HARD_T_MAX_US <= sc.T_LIMIT_US
                and cfg.HARD_Q_MAX_PC <= sc.Q_LIMIT_PC and cfg.COMPLIANCE_MV <= sc.VP_LIMIT_MV):
            raise ValueError("board config hard limits exceed the core's envelope (docs/controller.md)")
        if cfg.HARD_T_MAX_US < hp.T_FLOOR_US or cfg.HARD_I_MAX_UA < 1:
            raise ValueError("board config: HARD_T_MAX_US must be >= %d us (T_FLOOR_US)" % hp.T_FLOOR_US)
        n = n_channels or cfg.N_CHANNELS
        if not 1 <= n <= 4 or n > board.n_channels:
            raise ValueError("n_channels=%d out of range [1, %d]" % (n, min(4, board.n_channels)))
        self.n = n
        rate = rate_hz or cfg.RATE_HZ
        if not hp.RATE_MIN_HZ <= rate <= hp.RATE_MAX_HZ:
            raise ValueError("rate_hz=%d out of range [%d, %d]" % (rate, hp.RATE_MIN_HZ, hp.RATE_MAX_HZ))
        # the worst-case frame fits its period; with room for a skin model's work where that
        # leaves a pulse (SET_SKIN then needs no lower t_max first; SET_LIMITS can raise it)
        t_max = min(cfg.HARD_T_MAX_US, hp.t_max_fitting(rate, n, 1))
        if t_max < hp.T_FLOOR_US:
            t_max = min(cfg.HARD_T_MAX_US, hp.t_max_fitting(rate, n))
        if t_max < hp.T_FLOOR_US:
            raise ValueError("%d channels at %d Hz cannot fit a frame: at most %d Hz (hid_protocol.frame_fits)"
                             % (n, rate, hp.rate_max_fitting(n, hp.T_FLOOR_US)))
        t_min = max(hp.T_FLOOR_US, min(cfg.T_MIN_US, t_max))
        lim = [max(1, min(cfg.I_MIN_UA, cfg.HARD_I_MAX_UA)), cfg.HARD_I_MAX_UA, t_min, t_max, cfg.HARD_Q_MAX_PC]
        self.lim = lim  # soft limits: i_min, i_max, t_min, t_max, q_max
        # the soft i_min, i_max and q_max as last set (board_config at boot, then SET_LIMITS):
        # lim's are these, lowered to the hard limits in force (_fit_limits); GET_INFO page 1
        self.lim_set = [lim[0], lim[1], lim[4]]
        self.chans = [Channel(k, lim) for k in range(n)]
        for c in self.chans:
            c.adc = board.adc[c.ch]  # the board's capture buffer of this channel (fixed)
            c.v[_W] = len(c.adc)
            c.v[_UV] = self.uv_per_count
            c.v[_DTU] = board.dt_us
            c.v[_PX] = (cfg.ADC_POST_US - _C_PEAK_POST_US) // board.dt_us if cfg.ADC_POST_US > _C_PEAK_POST_US else 0
            c.v[_HI] = self.hard_i
            c.v[_HT] = self.hard_t
            c.v[_HQ] = self.hard_q
            c.v[_OFF] = self.vp_off_mv
        # the monitor correction the board read from its flash at boot (vmon_cal.boot_load)
        vm = getattr(board, "vmon_cal", None)
        self.vmon_state = getattr(board, "vmon_state", hp.VMON_NONE)
        self._dac_gain = hasattr(board, "set_dac_gain")  # the board takes a DAC gain (SET_VMON) ...
        # ... and its DAC path applies it (the ideal simulated board has no DAC: it keeps the
        # commanded current whatever is stored; GET_INFO's INFO_FLAG_DAC_GAIN tells the host)
        self._dac_applied = self._dac_gain and getattr(board, "dac_gain_applied", True)
        # a board whose current is exactly the commanded one (the ideal simulated board) needs
        # no margin for an unmeasured DAC gain (_dac_limits)
        self._dac_exact = getattr(board, "dac_exact", False)
        # what the board's flash holds for every channel the board has (a store rewrites the
        # whole file: the lines of channels this Stimulator does not drive are kept)
        self._vmon_file = list(vm) if vm else []
        while len(self._vmon_file) < self.n:
            self._vmon_file.append(None)
        for c in self.chans:
            self._dac_limits(c, 0)
            v = vm[c.ch] if vm and c.ch < len(vm) else None
            if v:
                c.vmon_stored = v
                self._vmon_apply(c, v[0], v[1], v[2] if len(v) > 2 else 0)
        self._fit_limits()
        self.mode = sc.MODE_AKHTAR
        self.rate_hz = 0
        self.period_us = 0
        self.set_rate(rate_hz or cfg.RATE_HZ)
        self.seq = 0
        self.frames = 0
        self.overruns = 0
        self.loop_us = 0
        self.frame_t = 0
        if keepalive_ms is None:
            keepalive_ms = hp.KEEPALIVE_DEFAULT_MS
        if keepalive_ms and not hp.KEEPALIVE_MIN_MS <= keepalive_ms <= hp.KEEPALIVE_MAX_MS:
            raise ValueError("keepalive_ms=%d out of range: 0 (off, simulation only) or [%d, %d]"
                             % (keepalive_ms, hp.KEEPALIVE_MIN_MS, hp.KEEPALIVE_MAX_MS))
        self.keepalive_ms = keepalive_ms
        self.last_host = clock.ticks_us()
        self._ticks_diff = clock.ticks_diff  # bound once (the frame's keep-alive check)
        self.tx = bytearray(hp.REPORT_LEN)  # replies to commands
        self.tel = [bytearray(hp.REPORT_LEN) for _ in range(n)]  # each channel's telemetry, sent after the pulses
        for c in self.chans:
            c.tel = self.tel[c.ch]
        self.rx = bytearray(hp.REPORT_LEN)
        self.acks = 0
        self.n_cmds = 0
        self.locked = 0
        self._irq_off = getattr(board, "irq_off", None)  # bound once here: calling it allocates nothing
        self._irq_on = getattr(board, "irq_on", None)
        self._irq = 0
        # A board that delivers pulses by itself has start() and wait(): the CPU goes
        # on while the gate is open, and its start, wait, set_amplitude and stop
        # allocate nothing (they run inside the frame's heap-locked section; the
        # rp2's are checked on the emulated chip). Otherwise (the simulated board)
        # fire() delivers the whole pulse before it returns, outside the section.
        self._overlap = hasattr(board, "start") and hasattr(board, "wait")
        for c in self.chans:
            c.v[_OVL] = 1 if self._overlap else 0  # (_pulse reads it as a word)
        self._start = board.start if self._overlap else None  # bound once: calls allocate nothing
        self._wait = board.wait if self._overlap else None
        # Bound once, here: on the chip a method looked up on an instance costs ~15 us more than
        # a call of a bound one (~11 us), and the frame makes ~8 such calls a channel
        # (docs/performance.md); calling a bound method allocates nothing.
        self._set_amplitude = board.set_amplitude
        self._send = board.send
        self._recv = board.recv
        self._f_pulse = self._pulse
        self._f_measure = self._measure
        self._f_control = self._control
        self._f_output = self._output
        self._f_telemetry = self._encode_telemetry
        self.started = False
        self.deadline = 0
        self.errors = 0
        self.last_error = None

    def set_rate(self, hz):
        self.rate_hz = hz
        self.period_us = 1000000 // hz

    # ------------------------------------------------------------------ loop
    def run(self, frames=-1):
        """Deadline-based frames at rate_hz; frames < 0 runs forever."""
        clk = self.clock
        if not self.started:  # later calls continue on the same grid of deadlines
            self.deadline = clk.ticks_us()
            self.started = True
        deadline = self.deadline
        while frames != 0:
            wait = clk.ticks_diff(deadline, clk.ticks_us())
            if wait > 0:
                clk.sleep_us(wait)
            start = clk.ticks_us()
            try:
                self.frame(deadline)
            except Exception as e:  # a firmware error: stop every channel, keep reporting
                if self.locked:
                    self._leave()
                if self.errors < 0x3FFFFFFF:
                    self.errors += 1
                self.last_error = e
                self.stop_all(hp.STOP_INTERNAL)
            end = clk.ticks_us()
            self.loop_us = clk.ticks_diff(end, start)
            deadline = clk.ticks_add(deadline, self.period_us)
            if clk.ticks_diff(end, deadline) >= 0:  # missed the next deadline
                if self.overruns < 0x3FFFFFFF:
                    self.overruns += 1
                while clk.ticks_diff(end, deadline) >= 0:  # skip, keep the phase
                    deadline = clk.ticks_add(deadline, self.period_us)
            self.deadline = deadline
            if frames > 0:
                frames -= 1

    @micropython.viper
    def frame(self, now):
        """One frame. Every channel in turn: its pulse (hard limits checked right
        before the gate opens), then measure -> supervise -> control -> output ->
        report (_measure, _control: the supervisor's rules first, _output,
        _encode_telemetry). On a board that delivers pulses by itself (the rp2: PIO
        gate, ADC -> DMA capture) channel k's pulse runs while the CPU does channel
        k-1's work. Then the reports go out and the host's commands are served.
        (Viper: the loop's counters and flags are machine words, not a runtime call
        an operation as in native code; every value a small int: ticks < 2**30 on the
        rp2, keepalive_ms * 1000 < 2**24.)"""
        board = self.board
        self.frame_t = int(now) & 0x3FFFFFFF
        board.feed_watchdog()
        irq_off = self._irq_off  # one heap-locked section for the pulses and their control (_enter, inlined)
        if irq_off:  # (None or a bound method: viper cannot compare with None)
            self._irq = irq_off()
        _lock()
        self.locked = 1
        ka = int(self.keepalive_ms)
        if ka and int(self._ticks_diff(now, self.last_host)) > ka * 1000:  # before any pulse: none fires
            self._check_keepalive()  # once the host is overdue
        chans = self.chans
        overlap = int(self._overlap)
        n = int(self.n)
        k = 0
        while k <= n:  # channel k's pulse, and meanwhile channel k - 1's work
            ns = 0
            if k < n:
                ns = int(self._f_pulse(k, chans[k]))  # on the rp2 the gate is open when this returns (self._pulse)
            if k > 0:  # channel k - 1's work after its pulse, in the order of the paper's Fig. 3 loop
                c = chans[k - 1]  # (inline here, not a method: a call is ~10 us on the chip)
                self._f_measure(c)  # self._measure
                self._f_control(c)  # self._control: the supervisor's rules, then the controller
                if overlap:
                    self._f_output(c)  # self._output: the amplitude settles during the rest of the frame
                else:  # (the simulated board allocates: outside the heap-locked section)
                    self._leave()
                    self._f_output(c)
                    self._enter()
                self._f_telemetry(c)  # self._encode_telemetry
            if overlap and ns:
                self._wait()  # until channel k's capture is complete
            k += 1
        self.locked = 0  # _leave, inlined
        _unlock()
        irq_on = self._irq_on
        if irq_on:
            irq_on(self._irq)
        tel = self.tel
        k = 0
        send = self._send  # board.send
        while k < n:
            send(tel[k])
            k += 1
        if self._recv(self.rx):  # a command waits (most frames: none); board.recv
            self._serve_commands(now)
        self.frames = (int(self.frames) + 1) & 0x3FFFFFFF  # counters stay small ints (no long int on the rp2)

    @micropython.viper
    def _pulse(self, k: int, c) -> int:
        """Channel k's pulse for this frame, after the last check right before the
        gate opens: the hard limits, independent of the controller. Returns the
        samples its capture will hold (c.n_samples; 0: no pulse). Viper, because
        speed forces it (here and in the channel's work below: the channel's numbers
        are words of c.v, ~1.5 us less each than an attribute on the chip): each
        product is formed only once its factors passed their bounds (hard limits
        within the core's envelope: < 2**30), so machine words agree with CPython's ints."""
        v = ptr32(c.v)
        v[_NS] = 0
        v[_CALP] = v[_CALIB]
        i = v[_I]
        t = v[_T]
        ad = v[_AD]  # the delivered current is the truth: Rp, mQ and telemetry use it
        v[_DI] = 0
        v[_DT] = 0
        v[_DS] = 0
        if v[_ARMED] == 0 or i <= 0:
            return 0
        if i > v[_HI] or t > v[_HT] or t < _C_T_FLOOR_US or i * t > v[_HQ]:
            self._latch(c, _C_STOP_LIMIT)
            return 0
        if v[_AI] != i or ad <= 0:  # the output was not set for this pulse (or sets no current): no pulse
            return 0
        if ad > v[_HID] or ad * t > v[_HQD]:  # a board that would deliver beyond the hard limits
            self._latch(c, _C_STOP_LIMIT)
            return 0
        v[_DI] = ad
        v[_DT] = t
        v[_DS] = v[_SS]
        if v[_OVL]:  # (self._overlap)
            v[_NS] = int(self._start(k, t))
        else:  # the simulated board allocates: its calls run outside the heap-locked section
            self._leave()
            v[_NS] = int(self.board.fire(k, t))
            self._enter()
        return v[_NS]

    @micropython.native
    def _serve_commands(self, now):
        """The host's commands, the first already in self.rx: it is served always,
        more while a command's time (hp.FRAME_CMD_US) remains before the next
        deadline; the rest wait."""
        board = self.board
        rx = self.rx
        clk = self.clock
        end = clk.ticks_add(now, self.period_us - hp.FRAME_CMD_US)
        m = 0
        while True:
            self._enter()
            self.handle(rx, now)
            self._leave()
            board.send(self.tx)
            m += 1
            if m >= _MAX_CMDS_PER_FRAME or clk.ticks_diff(end, clk.ticks_us()) <= 0 or not board.recv(rx):
                break
        self.sync_outputs()  # outputs follow the commands at once

    @micropython.native
    def _enter(self):
        """Start a firmware section: nothing in it may allocate (raises MemoryError)."""
        if self._irq_off is not None:
            self._irq = self._irq_off()
        _lock()
        self.locked = 1

    @micropython.native
    def _leave(self):
        self.locked = 0
        _unlock()
        if self._irq_on is not None:
            self._irq_on(self._irq)

    # -------------------------------------------------------------- safety
    def _latch(self, c, reason):
        v = c.v
        v[_ARMED] = 0
        v[_CALIB] = 0
        v[_HELD] = 0
        v[_STOP] = reason
        v[_I] = 0
        v[_T] = 0
        v[_AI] = 0  # the output must be set again before any pulse
        v[_AD] = 0

    @micropython.viper
    def _measure(self, c):
        """Vp: the end-of-pulse voltage in mV (_peak_counts over the window's samples up to
        _C_PEAK_POST_US past the fall, with its spike guard). Rp from Vp and the delivered current
        (0: no pulse). log2 tau of the decay after the fall (decay.ltau_q16; 0: none to read).
        Machine-word arithmetic, every value < 2**30 (uv_per_count is
        checked at set-up: 4096 x it < 2**30), so 32-bit (ARM) and 64-bit (x64) words agree
        with CPython's ints; nothing allocated."""
        v = ptr32(c.v)
        n = v[_NS]
        x = 0
        e = 0
        w = v[_W]
        if n > 0:
            if n > w:  # a board that reports more samples than its window: read the window only
                n = w
            hi = w - v[_PX]  # (_C_PEAK_POST_US past the fall)
            lo = hi - _C_PEAK_SAMPLES
            if lo < w - n:
                lo = w - n
            x = int(_peak_counts(c.adc, lo, hi))
            e = x >> 16  # the first sample after the fall (the largest drop Vp's samples hold) ...
            x &= 0xFFFF
            b = ptr16(c.adc)  # ... unless a larger one lies past them: a longer lead than the emulated chip's
            d = (int(b[e - 1]) - int(b[e])) if lo < e and e < hi else -4096  # (a real chip's flash-cache misses)
            k = hi  # moved the fall there, and tau reads the samples after it (review of session 24: tau
            while k < w:  # read from the plateau, 0.6-4.8x, past ~17 us more lead; Vp then reads low: safe)
                y = int(b[k - 1]) - int(b[k])
                if y > d:
                    d = y
                    e = k
                k += 1
        uv = v[_UV]
        vp = x * uv // 1000
        v[_VPR] = vp
        k = v[_VK]  # the monitor's gain and offset out of the read (vmon_cal.correct, inlined;
        if k:  # monotonic: a higher read stays higher)
            o = v[_VO]  # may be negative: a 64-bit VM's ptr32 reads the word zero-extended,
            if (o >> 31) & 1:  # so its sign is restored (m * m is 2**32 there, 0 in 32-bit words)
                m = 65536
                o -= m * m
            x = ((x * 16 - o) * k + 65536) >> 17
            if x < 0:
                x = 0
            elif x > 4095:
                x = 4095
            vp = x * uv // 1000
        else:
            o = 0
        v[_VP] = vp
        # tau = R_skin Cp: the decay after the fall (its straddling sample skipped), the monitor's
        # offset out (gain cancels in the ratio); told to the controller before its update (rule 7, docs/controller.md)
        v[_LT] = int(_ltau(c.adc, e + 1, w - e - 1, o, v[_DTU])) if n > 0 and e + 1 < w else 0
        di = v[_DI]
        if di <= 0:
            v[_RP] = 0
        elif vp > _C_VP_LIMIT_MV:  # sc.rp_from_vp, inline (a call is ~11 us on the chip): vp >= 0 and
            v[_RP] = _C_RP_OVER  # vp * 1000 < 2**30 (x * uv < 2**30, above); tests/test_frame_peak.py
        else:  # checks it against sc.rp_from_vp
            v[_RP] = (vp * 1000 + (di >> 1)) // di

    @micropython.viper
    def _control(self, c):
        """The supervisor, then the controller's next pulse. Supervisor: the electrode
        rules on this pulse's Rp (no pulse: nothing to act on; off or shorted latches
        the channel). Controller: one measurement may lower the charge, raising it
        takes two in a row (the smaller of the two proposals). The products are of
        currents and widths within the soft limits: < 2**30. (One method: a call is
        ~10 us on the chip.)"""
        v = ptr32(c.v)
        if v[_DI] == 0:
            v[_CR] = 0  # calibration pulses pair only in consecutive frames (as `audit` sees them)
            return
        rp = v[_RP]
        off = v[_OFF]  # (self.vp_off_mv)
        # off: the corrected or the raw reading at compliance (a wrong stored gain > 1 must not hide it)
        if v[_VP] >= off or v[_VPR] >= off or rp > _C_RP_MAX_OHM:
            self._latch(c, _C_STOP_OFF)
            c.ctl.stop(sc.ST_RP_HIGH)
            return
        if rp < _C_RP_MIN_OHM:
            self._latch(c, _C_STOP_RP_FAULT)
            c.ctl.stop(sc.ST_RP_LOW)
            return
        ctl = c.ctl
        k = ptr32(ctl._k)  # the controller's words (the same array before and after calibrate, update)
        if v[_CALIB]:  # calibration pulses (validated at CALIBRATE) until two in a row agree: Rp0
            rp0 = int(hp.cal_rp0(v[_CR], rp, k[_C_K_MODE] == _C_MODE_CE))  # (docs/safety.md: no single reading sets it)
            if rp0 == 0:
                v[_CR] = rp  # the calibration pulse again: I0, T0 (v[_I], v[_T] as set at ARM)
                k[_C_K_I] = v[_I]  # (ctl.i_ua, ctl.t_us: telemetry's next pulse)
                k[_C_K_T] = v[_T]
                n = v[_CN] + 1
                v[_CN] = n
                if n >= int(hp.CAL_TRIES):  # readings that never settle: no Rp0 to trust
                    self._latch(c, _C_STOP_RP_FAULT)
                    ctl.stop(sc.ST_UNCALIBRATED)
                return
            k[_C_K_LT] = v[_LT]  # (ctl.ltau_q16: the calibration pulse's tau, rule 7's check in calibrate)
            ctl.calibrate(c.i0, c.t0, rp0, c.x, c.y)
            v[_CALIB] = 0
            r1 = v[_CR]
            v[_CLO] = rp if rp < r1 else r1
            v[_CHI] = r1 + rp - v[_CLO]
            v[_CR] = 0
        else:
            k[_C_K_I] = v[_DI]  # ctl.delivered, inline (ctl.i_ua, ctl.t_us, ctl.status): a held proposal
            k[_C_K_T] = v[_DT]  # was not what was measured, nor were its bounds
            k[_C_K_ST] = v[_DS]
            k[_C_K_LT] = v[_LT]  # (ctl.ltau_q16: the decay read after it, MODE_FAST's model anchors on it)
            if int(ctl.update(rp)) & _C_FAULT_MASK:
                self._latch(c, _C_STOP_RP_FAULT)
                return
        ni = k[_C_K_I]  # (ctl.i_ua, ctl.t_us, ctl.status)
        nt = k[_C_K_T]
        ns = k[_C_K_ST]
        q = ni * nt
        qs = v[_I] * v[_T]  # the pulse just sent
        ms = v[_MS]
        if ms:
            n = v[_MN] - 1
            v[_MN] = n
            if n <= 0:
                ms = 0
                v[_MS] = 0
        if ms:  # a law the mode changed to: its readings were on the old law's pulses, of another shape
            cap = qs  # (Rp rises with the width and falls as the current rises), so its first pulse is
            if ms > 1:  # capped at the charge just sent, later raises at 1/4 more each, in the law's own
                cap += qs >> _C_MODE_RAMP_LOG2  # shape, until two proposals in a row ask for no more:
            fn = v[_FN]  # a fall's hold (below) waits while the ramp climbs back: it does not count
            if fn > 0:  # down, and the ramp stops at the charge before the fall, in the new law's
                fq = v[_FI] * v[_FT]  # shape (the old-shape pulse is never sent again); a pulse
                if qs >= fq - (fq >> _C_FALL_LOG2):  # within 1/32 of it sent: the hold is done
                    v[_FN] = 0  # (second review of session 23: the hold ran out mid-ramp and a
                else:  # raise from below passed the pulse before a reading x 0.5's fall: 1.05x)
                    v[_FN] = fn + 1
                    if cap > fq:
                        cap = fq
            if q > cap:  # each raise then rests on a reading of the shape before, not of the old law's
                li = ni  # (review of session 22: +9.5 % after a switch to constant energy from 1097 uA;
                lt = nt
                if k[_C_K_MODE] >= _C_MODE_AKHTAR:  # 1.9-2.4x after the gel). Akhtar and FAST: the law's
                    st = k[_C_K_ST]  # own pulse on the mE curve for that charge (Eq. 4 and its bounds; a
                    ctl._from_q(cap << 4)  # pulse off the curve misleads FAST's secant: 1.2-1.4x, review
                    ni = k[_C_K_I]  # of session 23), the proposal left as it was for telemetry and audit
                    nt = k[_C_K_T]
                    ns = k[_C_K_ST]  # (the capped pulse's bounds)
                    k[_C_K_I] = li
                    k[_C_K_T] = lt
                    k[_C_K_ST] = st
                    if ni * nt < cap - (cap >> 5):  # held below it by a bound (at i_max Eq. 4's T = Q^2 / mE
                        if ns & _C_ST_I_MAX and cap // ni >= k[_C_K_TMIN]:  # is Q / i_max short): the law at
                            nt = cap // ni  # i_max moves T only, so the cap's charge at i_max is its own shape
                            if nt > k[_C_K_TMAX]:  # (review of session 24: the law's current instead, 3571 uA
                                nt = k[_C_K_TMAX]  # after a reading x 3, read Rp high off the operating point
                        else:  # at 4000 uA, and the law then sent 1.062x)
                            ni = li  # else the law's current
                            ns = st
                if ni == li or ni * nt > cap:  # the law's current (I fixed), a shorter pulse; at its
                    nt = cap // ni  # t_min the current that charge allows (a pulse sent had
                    ns = (ns & _C_ST_I_BOUND) | _C_ST_Q_MAX  # I >= i_min and T >= t_min: cap // t_min
                    if nt < k[_C_K_TMIN]:  # >= i_min); its bounds: the charge limited (by the ramp), the
                        nt = k[_C_K_TMIN]  # law's current's bounds, or t_min (an off-curve pulse: MODE_FAST
                        ni = cap // nt  # takes the paper's step from it)
                        ns = _C_ST_T_MIN | _C_ST_Q_MAX
                q = ni * nt
                v[_MS] = 2
            elif ms == 3:  # the second in a row within the cap: the ramp ends (one wild reading asking
                v[_MS] = 0  # less must not end it: x 9 did, and the next raise was 5.4x the pulse before)
            else:
                v[_MS] = 3
        fn = v[_FN]
        if fn > 0:
            fn -= 1
            if v[_I] == v[_FI] and v[_T] == v[_FT]:  # back at the pulse before the fall: the readings on
                fn = 0  # it are the two-in-a-row rule's to judge
            v[_FN] = fn
        if q <= qs:
            v[_HELD] = 0
            if fn == 0 and q < qs - (qs >> _C_FALL_LOG2):  # a large fall: the pulse before it kept
                v[_FI] = v[_I]
                v[_FT] = v[_T]
                v[_FS] = v[_SS]
                v[_FN] = _C_FALL_HOLD
        elif v[_HELD]:
            if v[_PI] * v[_PT] < q:
                ni = v[_PI]
                nt = v[_PT]
                ns = v[_PS]
                q = ni * nt
            v[_HELD] = 0
            if fn > 0 and q > v[_FI] * v[_FT]:  # not past the pulse before a recent large fall
                ni = v[_FI]
                nt = v[_FT]
                ns = v[_FS]
        else:
            v[_HELD] = 1
            v[_PI] = ni
            v[_PT] = nt
            v[_PS] = ns
            return
        v[_I] = ni
        v[_T] = nt
        v[_SS] = ns

    def _check_keepalive(self):
        """The host is overdue (frame checked it): every armed channel is latched."""
        k = 0
        while k < self.n:
            c = self.chans[k]
            if c.armed:
                self._latch(c, hp.STOP_KEEPALIVE)
            k += 1

    @micropython.viper
    def _output(self, c):
        """Channel c's outputs follow its state: amplitude for the next pulse, or stopped."""
        v = ptr32(c.v)
        if v[_ARMED]:
            i = v[_I]
            v[_AD] = int(self._set_amplitude(v[_CH], i))  # the current the output stage will deliver
            v[_AI] = i
        else:
            v[_AI] = 0
            v[_AD] = 0
            self.board.stop(v[_CH])

    def sync_outputs(self):
        k = 0
        while k < self.n:
            self._output(self.chans[k])
            k += 1

    def stop_all(self, reason):
        """Latch every channel (outside the frame: e.g. on a firmware error)."""
        k = 0
        while k < self.n:
            self._latch(self.chans[k], reason)
            self.board.stop(k)
            k += 1

    # ------------------------------------------------------------ reports
    def _head(self, typ):
        b = self.tx
        hp.clear(b)
        b[hp.O_TYPE] = typ
        struct.pack_into("<ii", b, hp.O_SEQ, self.seq, self.frame_t)
        self.seq = (self.seq + 1) & 0x3FFFFFFF
        return b

    @micropython.viper
    def _encode_telemetry(self, c):
        """Channel c's telemetry into its own report buffer (sent after the pulses):
        bytes 0..55 of hid_protocol's layout, little-endian as its '<' formats (the
        offsets are checked at import); the rest stays 0. Viper, because speed forces
        it: the fields go straight into the buffer, ~0.1 ms a channel less on the chip
        than one struct.pack_into. Every i32 field is within +-2**30; a u16 field
        takes the low 16 bits as put_u16 does; the u8 fields are small. Nothing
        allocated (each value stored back is a small int)."""
        ctl = c.ctl
        cv = ptr32(c.v)
        p32 = ptr32(c.tel)  # the buffer is a heap block: 4-byte aligned; fields packed into words
        di = cv[_DI]  # (little-endian, as hid_protocol's '<': the lowest byte first)
        f = 0
        if cv[_ARMED]:
            f = 0x01  # FLAG_ARMED
        if cv[_HELD]:
            f |= 0x02  # FLAG_HELD
        if self.keepalive_ms:
            f |= 0x04  # FLAG_KEEPALIVE
        if cv[_CALP]:
            f |= 0x08  # FLAG_CALIBRATING
        if cv[_MC] and di:  # (kept until a pulse is reported: `audit` replays pulses only)
            f |= 0x10  # FLAG_MODE_SET
            cv[_MC] = 0
        seq = int(self.seq)
        k = ptr32(ctl._k)  # ctl.mode, .mq_last_fc_per_ohm (+ bias), .status, .i_ua, .t_us: its words
        # REP_TELEMETRY, O_CH, O_MODE, O_STOP
        p32[0] = 0x01 | (cv[_CH] << 8) | (k[_C_K_MODE] << 16) | (cv[_STOP] << 24)
        p32[1] = seq  # O_SEQ 4
        p32[2] = int(self.frame_t)  # O_TIME 8
        p32[3] = (di & 0xFFFF) | ((cv[_DT] & 0xFFFF) << 16)  # O_I 12, O_T 14
        p32[4] = cv[_VP]  # O_VP 16
        p32[5] = cv[_RP]  # O_RP 20
        p32[6] = k[_C_K_ME]  # O_ME 24 (ctl.me_ua2ms)
        p32[7] = k[_C_K_MQT]  # O_MQT 28 (ctl.mq_target_fc_per_ohm)
        p32[8] = (k[_C_K_MQL] - _C_W_BIAS) if di else 0  # O_MQL 32
        p32[9] = (k[_C_K_ST] & 0xFFFF) | ((k[_C_K_I] & 0xFFFF) << 16)  # O_STATUS 36, O_NEXT_I 38
        v = int(self.overruns)  # hp.sat16 (run() changes both between frames: the same in every
        v = 0 if v < 0 else (v if v < 0xFFFF else 0xFFFF)  # report of a frame)
        p32[10] = (k[_C_K_T] & 0xFFFF) | (v << 16)  # O_NEXT_T 40, O_OVERRUNS 42
        v = int(self.loop_us)  # the previous frame's
        v = 0 if v < 0 else (v if v < 0xFFFF else 0xFFFF)
        p32[11] = v | (f << 16) | (int(self.rate_hz) << 24)  # O_LOOP 44, O_FLAGS 46, O_RATE 47
        p32[12] = cv[_DS] & 0xFFFF  # O_SENT_STATUS 48 (bytes 50, 51 stay 0)
        p32[13] = cv[_LT]  # O_LTAU 52
        self.seq = (seq + 1) & 0x3FFFFFFF

    def _ack(self, r, result, detail):
        b = self._head(hp.REP_ACK)
        b[hp.O_CMD] = r[hp.O_OUT_CMD]
        b[hp.O_RESULT] = result
        b[hp.O_TAG] = r[hp.O_OUT_TAG]
        b[hp.O_DETAIL] = detail
        self.acks = (self.acks + 1) & 0x3FFFFFFF
        return result

    def _info(self, r):
        page = r[hp.O_ARG]  # 0: the limits in force; INFO_PAGE_OWN: the board's own (hid_protocol)
        if page > hp.INFO_PAGE_OWN:
            return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG)
        b = self._head(hp.REP_INFO)
        b[hp.O_CMD] = r[hp.O_OUT_CMD]
        b[hp.O_RESULT] = hp.RES_OK
        b[hp.O_TAG] = r[hp.O_OUT_TAG]
        b[hp.O_FW] = FW_VERSION[0]
        b[hp.O_FW + 1] = FW_VERSION[1]
        b[hp.O_FW + 2] = FW_VERSION[2]
        b[hp.O_FW + 3] = self.n
        # the hard current and charge limits in force: held below the board's nominal ones while
        # a channel has no DAC gain applied (INFO_FLAG_HELD), x gain / VMON_DAC_PPM_MAX where one is (held_limit)
        hp.put_u16(b, hp.O_HARD_T, self.hard_t)
        hp.put_i32(b, hp.O_COMPLIANCE, self.compliance_mv)
        lim = self.lim
        hp.put_u16(b, hp.O_LIM + 4, lim[2])
        hp.put_u16(b, hp.O_LIM + 6, lim[3])
        if page:  # the board's own: its nominal hard limits, the soft ones as last set
            b[hp.O_INFO_PAGE] = page
            hp.put_u16(b, hp.O_HARD_I, self.hard_i)
            hp.put_i32(b, hp.O_HARD_Q, self.hard_q)
            lim = self.lim_set
            hp.put_u16(b, hp.O_LIM, lim[0])
            hp.put_u16(b, hp.O_LIM + 2, lim[1])
            hp.put_i32(b, hp.O_LIM + 8, lim[2])
        else:
            hp.put_u16(b, hp.O_HARD_I, self.held_limit(0))
            hp.put_i32(b, hp.O_HARD_Q, self.held_limit(1))
            hp.put_u16(b, hp.O_LIM, lim[0])
            hp.put_u16(b, hp.O_LIM + 2, lim[1])
            hp.put_i32(b, hp.O_LIM + 8, lim[4])
        b[hp.O_INFO_MODE] = self.mode
        b[hp.O_INFO_RATE] = self.rate_hz
        hp.put_u16(b, hp.O_INFO_KEEPALIVE, self.keepalive_ms)
        name = self.board_bytes
        k = 0
        while k < len(name) and k < hp.BOARD_LEN:
            b[hp.O_BOARD + k] = name[k]
            k += 1
        b[hp.O_INFO_VMON] = self.vmon_state
        f = 0
        if self._dac_applied:  # a stored DAC gain scales this board's DAC (else: stored, not applied)
            f = hp.INFO_FLAG_DAC_GAIN
        if self.no_dac_gain():  # the hard fields above are held x VMON_DAC_PPM_MIN
            f |= hp.INFO_FLAG_HELD
        elif self.held_limit(0) < self.hard_i or self.held_limit(1) < self.hard_q:
            f |= hp.INFO_FLAG_DAC_LOW  # ... lowered x a DAC gain below VMON_DAC_PPM_MAX (/ the max) on a channel
        b[hp.O_INFO_FLAGS] = f
        self.acks = (self.acks + 1) & 0x3FFFFFFF
        return hp.RES_OK

    def _cal_info(self, r, c):
        b = self._head(hp.REP_CAL)
        b[hp.O_CMD] = r[hp.O_OUT_CMD]
        b[hp.O_RESULT] = hp.RES_OK
        b[hp.O_TAG] = r[hp.O_OUT_TAG]
        b[hp.O_CAL_CH] = c.ch
        f = 0
        if c.have_cal:
            f |= 1
        if c.armed:
            f |= 2
        if c.ctl.calibrated:
            f |= 4
        if c.vmon_k:
            f |= hp.CAL_FLAG_VMON
        if c.vmon_dac:
            f |= hp.CAL_FLAG_DAC
        b[hp.O_CAL_FLAGS] = f
        hp.put_i32(b, hp.O_CAL_VMON_GAIN, c.vmon_g)
        hp.put_i32(b, hp.O_CAL_VMON_OFF, c.vmon_off)
        hp.put_i32(b, hp.O_CAL_DAC_GAIN, c.vmon_dac)
        ctl = c.ctl  # the skin model as set (`record` writes it into the header: `audit` replays MODE_FAST with it)
        hp.put_u16(b, hp.O_CAL_SKIN_RS, ctl.skin_rs_ohm)
        hp.put_i32(b, hp.O_CAL_SKIN_BETA, ctl.skin_beta_q16)
        hp.put_i32(b, hp.O_CAL_SKIN_CP, ctl.skin_cp_pf)
        hp.put_u16(b, hp.O_CAL_SKIN_TAU, ctl.skin_tau_q16 + 0x8000)
        b[hp.O_CAL_VMON_STATE] = self.vmon_state
        hp.put_u16(b, hp.O_CAL_I0, c.i0)
        hp.put_u16(b, hp.O_CAL_T0, c.t0)
        hp.put_i32(b, hp.O_CAL_X, c.x)
        hp.put_i32(b, hp.O_CAL_Y, c.y)
        hp.put_i32(b, hp.O_CAL_RP0, c.ctl.rp0_ohm if c.ctl.calibrated else 0)
        b[hp.O_CAL_MODE] = c.ctl.mode
        self.acks = (self.acks + 1) & 0x3FFFFFFF
        return hp.RES_OK

    # ------------------------------------------------------------ commands
    def handle(self, r, now):
        """Validate and apply one OUT report; the reply is left in self.tx.

        A report that is malformed, unknown or out of range changes nothing.
        """
        self.n_cmds = (self.n_cmds + 1) & 0x3FFFFFFF
        if not hp.crc_ok(r):
            return self._ack(r, hp.RES_BAD_CRC, hp.O_CRC)
        cmd = r[hp.O_OUT_CMD]
        if r[hp.O_OUT_RESERVED]:
            return self._ack(r, hp.RES_BAD_FORMAT, hp.O_OUT_RESERVED)
        ch = r[hp.O_OUT_CH]
        if ch != hp.CH_ALL and ch >= self.n:
            return self._ack(r, hp.RES_BAD_CHANNEL, hp.O_OUT_CH)
        lo = ch
        hi = ch + 1
        if ch == hp.CH_ALL:
            lo = 0
            hi = self.n
        self.last_host = now
        if cmd == hp.CMD_KEEPALIVE:
            ms = hp.get_u16(r, hp.O_ARG)
            if not hp.KEEPALIVE_MIN_MS <= ms <= hp.KEEPALIVE_MAX_MS:  # 0 (off) is refused too
                return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG)
            self.keepalive_ms = ms
            return self._ack(r, hp.RES_OK, 0)
        if cmd == hp.CMD_GET_INFO:
            if ch == hp.CH_ALL:
                return self._info(r)
            return self._cal_info(r, self.chans[ch])
        if cmd == hp.CMD_DISARM:
            k = lo
            while k < hi:  # a channel already stopped keeps the reason (electrode off, keep-alive, ...)
                if self.chans[k].armed:
                    self._latch(self.chans[k], hp.STOP_DISARMED)
                k += 1
            return self._ack(r, hp.RES_OK, 0)
        if cmd == hp.CMD_ARM:
            k = lo
            while k < hi:
                if not self.chans[k].have_cal:
                    return self._ack(r, hp.RES_NOT_CALIBRATED, hp.O_OUT_CH)
                k += 1
            k = lo
            while k < hi:
                c = self.chans[k]
                if not c.armed:
                    c.ctl.set_mode(self.mode)
                    c.armed = True
                    c.calibrating = True
                    c.v[_CN] = 0  # (_CR: a reading of the frame before pairs, as `audit` pairs them)
                    c.v[_FN] = 0  # (no fall to hold a raise below yet)
                    c.v[_MS] = 0
                    c.v[_MC] = 0
                    c.held = False
                    c.stop = hp.STOP_NONE
                    c.i = c.i0
                    c.t = c.t0
                    c.sent_status = sc.ST_OK  # (the calibration pulse: the controller's I0, T0)
                k += 1
            return self._ack(r, hp.RES_OK, 0)
        if cmd == hp.CMD_SET_MODE:
            mode = r[hp.O_ARG]
            rate = r[hp.O_ARG + 1]
            if not sc.MODE_OPEN_LOOP <= mode <= sc.MODE_FAST:
                return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG)
            if rate and not (hp.RATE_MIN_HZ <= rate <= hp.RATE_MAX_HZ
                             and hp.frame_fits(rate, self.n, self.lim[3], self._has_model())):
                return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG + 1)  # or the frame would not fit
            self.mode = mode
            k = 0
            while k < self.n:
                c = self.chans[k]
                if c.armed and not c.calibrating and mode != c.ctl.mode:  # Rp0 again from the pair that
                    # gave it, the one whose law asks less in this mode (review of session 22: Rp0 taken for
                    # constant energy then used by Eq. 2 let one reading x 0.97 raise every pulse 8.9 %)
                    c.ctl.calibrate(c.i0, c.t0, hp.cal_rp0(c.v[_CLO], c.v[_CHI], mode == sc.MODE_CONSTANT_ENERGY),
                                    c.x, c.y)
                    c.v[_MS] = 1  # (the new law's first raise is capped: _control)
                    c.v[_MC] = 1  # (telemetry's FLAG_MODE_SET)
                    c.v[_MN] = _C_MODE_RAMP_MAX
                c.ctl.set_mode(mode)
                k += 1
            if rate:
                self.set_rate(rate)
            return self._ack(r, hp.RES_OK, 0)
        if cmd == hp.CMD_CALIBRATE:
            return self._calibrate(r, lo, hi)
        if cmd == hp.CMD_SET_LIMITS:
            return self._set_limits(r)
        if cmd == hp.CMD_SET_SKIN:
            return self._set_skin(r, lo, hi)
        if cmd == hp.CMD_SET_VMON:
            return self._set_vmon(r, ch)
        return self._ack(r, hp.RES_UNKNOWN_COMMAND, hp.O_OUT_CMD)

    def _has_model(self):
        """1 if some channel has a skin model (its frame work is longer: hid_protocol.frame_us)."""
        k = 0
        while k < self.n:
            ctl = self.chans[k].ctl
            if ctl.skin_rs_ohm or ctl.skin_beta_q16 or ctl.skin_cp_pf:
                return 1
            k += 1
        return 0

    def _set_skin(self, r, lo, hi):
        # MODE_FAST's skin model for channels lo..hi-1; only while they are disarmed;
        # all three 0 removes it. Checked before anything changes.
        rs = hp.get_u16(r, hp.O_ARG)
        beta = hp.get_i32(r, hp.O_ARG + 2)
        cp = hp.get_i32(r, hp.O_ARG + 6)
        tau = hp.get_u16(r, hp.O_ARG + 10) - 0x8000  # rule 7's tau gain (0 on the wire: sc.SKIN_TAU_OFF; every
        # other u16 is within +-sc.SKIN_TAU_MAX_Q16)
        k = lo
        while k < hi:
            if self.chans[k].armed:
                return self._ack(r, hp.RES_BAD_STATE, hp.O_OUT_CH)
            k += 1
        if rs or beta or cp:
            if rs > sc.SKIN_RS_MAX_OHM:
                return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG)
            if not sc.SKIN_BETA_MIN_Q16 <= beta <= sc.SKIN_BETA_MAX_Q16:
                return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG + 2)
            if not sc.SKIN_CP_MIN_PF <= cp <= sc.SKIN_CP_MAX_PF:
                return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG + 6)
            if not hp.frame_fits(self.rate_hz, self.n, self.lim[3], 1):  # the model's work must fit the frame
                return self._ack(r, hp.RES_NO_FRAME_TIME, 0)
        elif tau != sc.SKIN_TAU_OFF:  # a tau gain with no model: malformed
            return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG + 10)
        k = lo
        while k < hi:
            self.chans[k].ctl.set_skin(rs, beta, cp, tau)
            k += 1
        return self._ack(r, hp.RES_OK, 0)

    def _calibrate(self, r, lo, hi):
        i0 = hp.get_u16(r, hp.O_ARG)
        t0 = hp.get_u16(r, hp.O_ARG + 2)
        x = hp.get_i32(r, hp.O_ARG + 4)
        y = hp.get_i32(r, hp.O_ARG + 8)
        lim = self.lim
        k = lo
        while k < hi:
            if self.chans[k].armed:
                return self._ack(r, hp.RES_BAD_STATE, hp.O_OUT_CH)
            k += 1
        if not lim[0] <= i0 <= lim[1]:
            return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG)
        if not (lim[2] <= t0 <= lim[3] and t0 >= hp.T_FLOOR_US):
            return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG + 2)
        if i0 * t0 > lim[4]:
            return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG + 2)
        if not sc.X_STAR_MIN_OHM <= x <= 0:
            return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG + 4)
        if not 0 <= y < i0 * t0:
            return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG + 8)
        k = lo
        while k < hi:
            c = self.chans[k]
            c.i0 = i0
            c.t0 = t0
            c.x = x
            c.y = y
            c.have_cal = True
            k += 1
        return self._ack(r, hp.RES_OK, 0)

    def _set_limits(self, r):
        i_min = hp.get_u16(r, hp.O_ARG)
        i_max = hp.get_u16(r, hp.O_ARG + 2)
        t_min = hp.get_u16(r, hp.O_ARG + 4)
        t_max = hp.get_u16(r, hp.O_ARG + 6)
        q_max = hp.get_i32(r, hp.O_ARG + 8)
        k = 0
        while k < self.n:
            if self.chans[k].armed:
                return self._ack(r, hp.RES_BAD_STATE, 0)
            k += 1
        if not 1 <= i_max <= self.held_limit(0):  # the hard limit every channel may deliver (_dac_limits)
            return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG + 2)
        if not 1 <= i_min <= i_max:
            return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG)
        if not (1 <= t_max <= self.hard_t and hp.frame_fits(self.rate_hz, self.n, t_max, self._has_model())):
            return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG + 6)  # or the frame would not fit
        if not hp.T_FLOOR_US <= t_min <= t_max:
            return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG + 4)
        if not i_min * t_min <= q_max <= self.held_limit(1):
            return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG + 8)
        k = 0
        while k < self.n:  # a calibration outside the new limits must be sent again
            c = self.chans[k]
            if c.have_cal and not (i_min <= c.i0 <= i_max and t_min <= c.t0 <= t_max and c.i0 * c.t0 <= q_max):
                c.have_cal = False
            k += 1
        lim = self.lim
        lim[0] = i_min
        lim[1] = i_max
        lim[2] = t_min
        lim[3] = t_max
        lim[4] = q_max
        lim = self.lim_set
        lim[0] = i_min
        lim[1] = i_max
        lim[2] = q_max
        k = 0
        while k < self.n:  # validated above against the same rules: cannot raise
            self.chans[k].ctl.set_limits(i_min, i_max, t_min, t_max, q_max)
            k += 1
        return self._ack(r, hp.RES_OK, 0)

    # ------------------------------------------------- the monitor correction
    def _vmon_apply(self, c, gain_ppm, offset_mv, dac_ppm):
        """Channel c's monitor correction (0, 0: none) and DAC gain (0: nominal) from now on;
        the output is set again before the next pulse (its current changes with the DAC's
        full scale). Allocates nothing."""
        if dac_ppm != c.vmon_dac:  # the same code now delivers another current: calibrate again
            c.have_cal = False
        c.vmon_dac = dac_ppm
        self._dac_limits(c, dac_ppm)
        if self._dac_gain:
            self.board.set_dac_gain(c.ch, dac_ppm)
        c.ai = 0  # _pulse: no pulse until _output has set the amplitude with the new scale
        c.vmon_g = gain_ppm
        c.vmon_off = offset_mv
        if gain_ppm:
            g = gain_ppm // 100  # vmon_cal.terms(), inlined: a tuple would allocate
            c.vmon_k = (81920000 + g // 2) // g
            c.vmon_o = (offset_mv * 32000 + self.uv_per_count) // (2 * self.uv_per_count)
        else:
            c.vmon_k = 0
            c.vmon_o = 0

    def _dac_limits(self, c, dac_ppm):
        # the hard limits on the current (and charge) the board reports it delivers, for a
        # DAC gain of dac_ppm applied (0: none measured). The board reports code x LSB x the
        # stored gain, the physical current is code x LSB x the true gain, which is the host's
        # word and may be anywhere in the window (a scope reading typed low): the reported one
        # is held to the limits x stored gain / VMON_DAC_PPM_MAX, so the physical current stays
        # within the hard limits for any true gain up to the window's top whatever is stored
        # (the full limits only for a DAC whose stored gain is VMON_DAC_PPM_MAX); with no gain
        # applied (a fresh board, a file ignored at boot, a self-test without --scope) the
        # board reports the nominal current, so the limits are held to the limits x
        # VMON_DAC_PPM_MIN (docs/safety.md). Allocates nothing; products < 2**30.
        hi = self.hard_i
        hq = self.hard_q
        if not dac_ppm or not self._dac_applied:  # no gain applied: the board's error is not known ...
            f = 0 if self._dac_exact else hp.VMON_DAC_PPM_MIN // 100  # ... unless it has none (the full limits)
        else:  # per 10 000, rounded down: (dac_ppm // 100) * 10000 <= 103 500 000
            f = (dac_ppm // 100) * 10000 // (hp.VMON_DAC_PPM_MAX // 100)
        if 0 < f < 10000:
            hi = hi * f // 10000  # products < 2**30: hard_i <= 2**16, f <= 10000
            hq = (hq // 10000) * f + (hq % 10000) * f // 10000
        c.hard_i_d = hi
        c.hard_q_d = hq

    def held_limit(self, q):
        """The held hard limit on the current (q 0, uA) or the charge (q 1, pC): the lowest
        a channel may report delivering (_dac_limits: the hard limits x VMON_DAC_PPM_MIN while
        a channel has no DAC gain applied, x its gain / VMON_DAC_PPM_MAX while one is). The limit in force
        for every controller: SET_LIMITS refuses above it, _fit_limits lowers the soft limits
        to it, GET_INFO reports it. Allocates nothing."""
        k = 0
        m = 0
        while k < self.n:
            c = self.chans[k]
            x = c.hard_q_d if q else c.hard_i_d
            if k == 0 or x < m:
                m = x
            k += 1
        return m

    def takes_dac_gain(self):
        """The board's DAC path applies a stored DAC gain (GET_INFO's INFO_FLAG_DAC_GAIN): only
        then does `selftest --scope` lift a hold (to the hard limits x gain / VMON_DAC_PPM_MAX)."""
        return bool(self._dac_applied)

    def no_dac_gain(self):
        """True while some channel's limits are held for want of a DAC gain (_dac_limits: none
        applied, on a board whose current is not exactly the commanded one): GET_INFO's
        INFO_FLAG_HELD. `selftest --scope` storing every channel's gain lifts it (the limits are then
        the hard limits x the lowest gain / VMON_DAC_PPM_MAX: INFO_FLAG_DAC_LOW below the max)."""
        if self._dac_exact:
            return False
        if not self._dac_applied:
            return True
        k = 0
        while k < self.n:
            if not self.chans[k].vmon_dac:
                return True
            k += 1
        return False

    def _fit_limits(self):
        """The soft current and charge limits never above held_limit(): a controller then never
        proposes a pulse the hard-limit check before the gate (_pulse) would latch (it stays
        the last line). At boot and after every SET_VMON. Lowered only (a DAC gain stored later
        does not raise them: SET_LIMITS may, up to held_limit()); when lowered, every controller gets
        the limits again and a calibration outside them must be sent again (as after SET_LIMITS).
        Allocates nothing (SET_VMON applies under the heap lock); products < 2**30 (soft limits
        within the core's envelope)."""
        lim = self.lim
        hi = self.held_limit(0)
        hq = self.held_limit(1)
        if lim[1] <= hi and lim[4] <= hq:
            return
        if lim[1] > hi:
            lim[1] = hi
        if lim[0] > lim[1]:
            lim[0] = lim[1]
        if lim[4] > hq:
            lim[4] = hq
        if lim[4] < lim[0] * lim[2]:  # (q_max >= i_min t_min: the core's own rule)
            lim[0] = lim[4] // lim[2]
            if lim[0] < 1:  # (a board config whose hard charge is below t_min: refused by the core)
                lim[0] = 1
        k = 0
        while k < self.n:
            c = self.chans[k]
            if c.have_cal and not (lim[0] <= c.i0 <= lim[1] and c.i0 * c.t0 <= lim[4]):
                c.have_cal = False
            c.ctl.set_limits(lim[0], lim[1], lim[2], lim[3], lim[4])
            k += 1

    def _vmon_bad(self, r, o):
        # the OUT byte of the first refused word of one channel's correction at o (its
        # gain, offset, DAC gain words), or 0 if all are accepted
        g = hp.get_i32(r, o)
        off = hp.get_i32(r, o + 4)
        dac = hp.get_i32(r, o + 8)
        if g or off:
            if not hp.VMON_GAIN_PPM_MIN <= g <= hp.VMON_GAIN_PPM_MAX:
                return o
            if not hp.VMON_OFFSET_MV_MIN <= off <= hp.VMON_OFFSET_MV_MAX:
                return o + 4
        # a DAC gain out of its window, or on a board that cannot scale its DAC: refused
        if dac and (not self._dac_gain or not hp.VMON_DAC_PPM_MIN <= dac <= hp.VMON_DAC_PPM_MAX):
            return o + 8
        return 0

    def _set_vmon(self, r, ch):
        # CMD_SET_VMON (hid_protocol): one channel, or every channel (CH_ALL: channel k's
        # words at O_ARG + 4 + VMON_STRIDE k); every channel disarmed; everything checked
        # before anything changes; VMON_STORE writes the board's flash once, for every
        # channel addressed (outside the heap lock: the file allocates), and applies only
        # what was written: a refusal or a failed write changes no channel.
        k = 0
        while k < self.n:
            if self.chans[k].armed:
                return self._ack(r, hp.RES_BAD_STATE, hp.O_OUT_CH)
            k += 1
        op = r[hp.O_ARG]
        if op != hp.VMON_APPLY and op != hp.VMON_STORE:
            return self._ack(r, hp.RES_OUT_OF_RANGE, hp.O_ARG)
        if r[hp.O_ARG + 1] or r[hp.O_ARG + 2] or r[hp.O_ARG + 3]:
            return self._ack(r, hp.RES_BAD_FORMAT, hp.O_ARG + 1)
        lo = ch
        hi = ch + 1
        step = 0  # one channel: its words at O_ARG + 4
        o = hp.O_ARG + 4 + hp.VMON_STRIDE  # after them: reserved, 0
        if ch == hp.CH_ALL:
            lo = 0
            hi = self.n
            step = hp.VMON_STRIDE
            o = hp.O_ARG + 4 + step * self.n  # the words of channels this board lacks: 0
            while o < hp.O_ARG + 4 + step * 4:
                if r[o]:
                    return self._ack(r, hp.RES_BAD_CHANNEL, o)
                o += 1
        while o < hp.O_CRC:  # reserved up to the CRC: 0 (a one-channel command in CH_ALL's layout is refused)
            if r[o]:
                return self._ack(r, hp.RES_BAD_FORMAT, o)
            o += 1
        k = lo
        while k < hi:
            bad = self._vmon_bad(r, hp.O_ARG + 4 + step * (k - lo))
            if bad:
                return self._ack(r, hp.RES_OUT_OF_RANGE, bad)
            k += 1
        if op == hp.VMON_STORE:
            locked = self.locked
            if locked:  # everything from here allocates (a bound method, the list, the file)
                self._leave()
            ok = False
            try:
                store = getattr(self.board, "store_vmon", None)
                values = list(self._vmon_file)  # the others as the flash holds them (undriven channels too)
                for k in range(lo, hi):
                    o = hp.O_ARG + 4 + step * (k - lo)
                    g = hp.get_i32(r, o)
                    dac = hp.get_i32(r, o + 8)
                    values[k] = (g, hp.get_i32(r, o + 4), dac) if g or dac else None
                self.board.feed_watchdog()  # a flash write may erase a sector: the full watchdog time for it
                ok = store is not None and store(values)  # one file for every channel: all or nothing
                self.board.feed_watchdog()
            except Exception:  # noqa: BLE001 - e.g. MemoryError building the file: answered, nothing applied
                pass  # (ok stays False unless the file was written before the error: then it is applied)
            finally:
                if locked:
                    self._enter()
            if not ok:
                return self._ack(r, hp.RES_STORE_FAILED, 0)
            self._vmon_file = values  # (heap-locked again from here: no range(), no new objects)
            k = lo
            while k < hi:
                self.chans[k].vmon_stored = values[k]
                k += 1
            self.vmon_state = hp.VMON_STORED
        k = lo
        while k < hi:
            o = hp.O_ARG + 4 + step * (k - lo)
            self._vmon_apply(self.chans[k], hp.get_i32(r, o), hp.get_i32(r, o + 4), hp.get_i32(r, o + 8))
            k += 1
        self._fit_limits()
        return self._ack(r, hp.RES_OK, 0)
