# The voltage monitor's correction that `steadytouch selftest` finds on a dummy
# load and stores in the board's flash as vmon_cal.txt (docs/simulation.md,
# "Dummy load and the self-test"): measured mV = gain x true mV + offset, per
# channel. Read once at boot (load); applying it is integer-only with every
# intermediate < 2**30 (correct), and monotonic, so correcting the peak of a
# pulse equals correcting every sample before the peak search.
# Both boards read it at boot (board_rp2.load_vmon, board_sim.SimBoard: boot_load,
# which never raises: a missing file or a corrupt one leaves the monitors
# uncorrected and says which in its state, reported by GET_INFO) and write it
# when the host sends CMD_SET_VMON ... VMON_STORE (store: a temporary file
# renamed over the old one, so a reset mid-write keeps the old file or the new
# one, never half of one; the lines of channels this build lacks, stored by a
# build with more channels, are kept). stim._measure applies it to each pulse's
# peak count.
import hid_protocol as hp

CAL_HEADER = "steadytouch monitor correction v1"
CAL_FILE = "vmon_cal.txt"
CAL_GAIN_PPM = (hp.VMON_GAIN_PPM_MIN, hp.VMON_GAIN_PPM_MAX)  # accepted monitor gain (measured/true) in ppm
CAL_OFFSET_MV = (hp.VMON_OFFSET_MV_MIN, hp.VMON_OFFSET_MV_MAX)  # accepted monitor offset (electrode-referred mV)
CAL_DAC_PPM = (hp.VMON_DAC_PPM_MIN, hp.VMON_DAC_PPM_MAX)  # accepted DAC gain (delivered/nominal) in ppm
# (the windows: what a healthy board can need, docs/hardware.md "The accepted window")
ADC_MAX = 4095


CAL_CHANNELS = (hp.O_CRC - hp.O_ARG - 4) // hp.VMON_STRIDE  # 4: the most SET_VMON CH_ALL carries, so a line's
# channel is 0..3; a board builds 1..4 (board_config.N_CHANNELS)
CAL_MAX_BYTES = 4096  # a longer file is one the firmware ignores, read no further: a full 4-channel file is
# ~300 bytes (header, comment, 4 lines), so 4 KB leaves room for notes while reading and checking it stays a few
# KB of heap and a few ms on the chip, inside a store answered from the loop (a 64 KB file read whole ran the
# chip out of memory; 130 lines, the watchdog out of time: review rev-lims F2). boot_load, kept and
# steadytouch flash's read all stop at it.
_DIGITS = 9  # a number of at most 9 digits: < 2**30, a small int on the chip


def _fields(ln):
    """A line's fields: split on ASCII space and tab only (str.split() and MicroPython's split() differ
    on the others: form feed, NBSP, U+3000 ...)."""
    out = []
    for w in ln.replace(b"\t", b" ").split(b" "):
        if w:
            out.append(w)
    return out


def _num(w):
    """A field as an int: ASCII digits (at most 9) with an optional sign, else ValueError (int() takes
    other digits, underscores and spaces, and differently on CPython and MicroPython)."""
    k = 1 if w[0] == 43 or w[0] == 45 else 0  # "+", "-"
    if not 0 < len(w) - k <= _DIGITS:
        raise ValueError
    v = 0
    for c in w[k:]:
        if not 48 <= c <= 57:
            raise ValueError
        v = v * 10 + c - 48
    return -v if w[0] == 45 else v


def entries(text):
    """Every line of the file (bytes, or str taken as UTF-8) as (ch, gain_ppm, offset_mv, dac_gain_ppm),
    in file order, each checked (format, windows, channel 0..3 once). The text: a header line, then one
    line `CH GAIN_PPM OFFSET_MV [DAC_GAIN_PPM]` per channel (GAIN_PPM 0 with OFFSET_MV 0: the monitor
    uncorrected; DAC_GAIN_PPM 0 or absent: the DAC nominal); a line of spaces and tabs, or one starting
    with #, is skipped. Strict, so CPython (steadytouch flash's verdict) and MicroPython (the board's
    boot) read any file alike: ASCII only; a line ends at \n, \r\n or \r; fields are apart by spaces or
    tabs; numbers are ASCII digits with an optional sign. ValueError names the line."""
    if isinstance(text, str):
        text = text.encode()
    if len(text) > CAL_MAX_BYTES:
        raise ValueError("correction file: longer than %d bytes" % CAL_MAX_BYTES)
    if text and max(text) > 127:
        raise ValueError("correction file: not ASCII text")
    text = text.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    # one line at a time (a list of every line of 4 KB of blank lines ran the chip out of memory at boot)
    e = text.find(b"\n")
    e = len(text) if e < 0 else e
    if text[:e].strip(b" \t") != CAL_HEADER.encode():
        raise ValueError("correction file: the first line must be %r" % CAL_HEADER)
    out = []
    seen = []
    k = 0
    while e < len(text):
        b = e + 1
        e = text.find(b"\n", b)
        e = len(text) if e < 0 else e
        k += 1
        parts = _fields(text[b:e])
        if not parts or parts[0][0] == 35:  # "#"
            continue
        try:
            if not 3 <= len(parts) <= 4:
                raise ValueError
            ch, g, off = _num(parts[0]), _num(parts[1]), _num(parts[2])
            dac = _num(parts[3]) if len(parts) == 4 else 0
        except ValueError:
            raise ValueError("correction file line %d: expected CH GAIN_PPM OFFSET_MV [DAC_GAIN_PPM] (ASCII digits)"
                             % (k + 1))
        if not ok(g, off, dac):
            raise ValueError("correction file line %d: gain %d ppm, offset %d mV or DAC gain %d ppm out of range "
                             "[%d, %d] / [%d, %d] / [%d, %d] (or 0)" % (k + 1, g, off, dac, CAL_GAIN_PPM[0],
                                                                        CAL_GAIN_PPM[1], CAL_OFFSET_MV[0],
                                                                        CAL_OFFSET_MV[1], CAL_DAC_PPM[0],
                                                                        CAL_DAC_PPM[1]))
        if not 0 <= ch < CAL_CHANNELS or ch in seen:  # two values for one channel: which one?
            raise ValueError("correction file line %d: channel %d %s" % (
                k + 1, ch, "given twice" if ch in seen else "out of range 0..%d" % (CAL_CHANNELS - 1)))
        seen.append(ch)
        out.append((ch, g, off, dac))
    return out


def parse(text, n_channels):
    """The file's text (entries()) for a board of n_channels: [(gain_ppm, offset_mv,
    dac_gain_ppm) or None per channel]; ValueError names the line. A line of a channel
    this board is not built with is checked like the others and kept in the file (store),
    unused."""
    out = [None] * n_channels
    for ch, g, off, dac in entries(text):
        if ch < n_channels and (g or dac):
            out[ch] = (g, off, dac)
    return out


def ok(gain_ppm, offset_mv, dac_gain_ppm):
    """What CMD_SET_VMON and the file accept: the monitor's gain and offset in range, or both 0
    (uncorrected); the DAC's gain in range or 0 (nominal)."""
    if gain_ppm or offset_mv:
        if not (CAL_GAIN_PPM[0] <= gain_ppm <= CAL_GAIN_PPM[1] and CAL_OFFSET_MV[0] <= offset_mv <= CAL_OFFSET_MV[1]):
            return False
    return dac_gain_ppm == 0 or CAL_DAC_PPM[0] <= dac_gain_ppm <= CAL_DAC_PPM[1]


def read(path):
    """The file's first CAL_MAX_BYTES + 1 bytes (entries() refuses a longer file; never more is read);
    OSError when there is none or it cannot be read."""
    with open(path, "rb") as f:
        return f.read(CAL_MAX_BYTES + 1)


def load(path, n_channels):
    """parse() of the file at path; None when there is none (the monitor is used uncorrected)."""
    try:
        text = read(path)
    except OSError:
        return None
    return parse(text, n_channels)


def boot_load(path, n_channels):
    """(values, state) for a board's boot: values as parse() (None per channel when
    nothing usable is stored); state hp.VMON_NONE (no file), VMON_LOADED or VMON_BAD
    (unreadable or out of range: ignored). Never raises."""
    try:
        f = open(path, "rb")
    except OSError:
        return [None] * n_channels, hp.VMON_NONE
    try:
        with f:
            return parse(f.read(CAL_MAX_BYTES + 1), n_channels), hp.VMON_LOADED
    except Exception:  # ValueError (not ASCII, out of range ...), OSError, MemoryError: never a crash at boot
        return [None] * n_channels, hp.VMON_BAD


def text(values, others=()):
    """The file's text for values [(gain_ppm, offset_mv, dac_gain_ppm) or None per channel],
    then the lines `others` [(ch, gain_ppm, offset_mv, dac_gain_ppm)] of channels past them."""
    out = CAL_HEADER + ("\n# CH GAIN_PPM OFFSET_MV DAC_GAIN_PPM: measured mV = gain x true mV + offset; "
                        "delivered uA = DAC gain x nominal uA (steadytouch selftest)\n")
    for ch in range(len(values)):
        v = values[ch]
        if v:
            out += "%d %d %d %d\n" % (ch, v[0], v[1], v[2] if len(v) > 2 else 0)
    for e in others:
        out += "%d %d %d %d\n" % e
    return out


def kept(path, n_channels):
    """The lines of the file at path for channels >= n_channels (stored by a build with more
    channels), as entries(): a store keeps them. None of them when there is no file or it is
    one the firmware ignores at boot (unreadable, out of range, longer than CAL_MAX_BYTES, or
    one that runs out of memory: it is replaced whole and the store goes on)."""
    try:
        return [e for e in entries(read(path)) if e[0] >= n_channels]
    except (OSError, ValueError, MemoryError):  # no file, or one boot_load calls VMON_BAD
        return []


def store(path, values):
    """Write the file for values (one entry per channel of this board) and the lines the
    file holds for channels past them (kept): a temporary file renamed over the old one,
    so a reset mid-write leaves the old file or the new one. True if written."""
    import os

    others = kept(path, len(values))
    tmp = path + ".tmp"
    try:
        with open(tmp, "w") as f:
            f.write(text(values, others))
        os.rename(tmp, path)
    except OSError:
        return False
    return True


def terms(gain_ppm, offset_mv, uv_per_count):
    """(k_q13, off_q4) for correct(): 1/gain in Q13 (gain taken to 100 ppm), the offset in
    1/16 ADC counts. Every intermediate < 2**30 within CAL_GAIN_PPM / CAL_OFFSET_MV."""
    g = gain_ppm // 100
    return (8192 * 10000 + g // 2) // g, (offset_mv * 32000 + uv_per_count) // (2 * uv_per_count)


def correct(c, k_q13, off_q4):
    """One ADC count with the monitor's offset and gain taken out, clipped to 0..4095."""
    v = ((c * 16 - off_q4) * k_q13 + 65536) >> 17
    return 0 if v < 0 else (ADC_MAX if v > ADC_MAX else v)
