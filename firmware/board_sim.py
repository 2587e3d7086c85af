# The simulated board: the same interface as board_rp2.Board, with simulated
# electrodes behind each channel, a virtual or real clock, and USB reports
# framed on stdio (or kept in memory for tests). It is the "hardware" of the
# MicroPython unix VM: the firmware's frame runs against it unchanged.
#
# By default its analog path has the real parts' errors (AnalogPath below; each
# one with its source in docs/simulation.md, "The realistic board"): a 12-bit
# amplitude DAC (quantization, settling, gain error), the RP2040 ADC's noise at
# 8.7 ENOB and its DNL spikes (erratum RP2040-E11), the voltage monitor's gain
# and offset error, and compliance clipping. AnalogPath(ideal=True) is the
# board as it was before: the commanded current exactly, a 12-bit ADC with
# 1.5 counts of noise and nothing else (for tests of the ideal math).
import random
import sys
from array import array

import dac_mcp4822
import sim_electrode

MAGIC0 = 0xA5  # stdio framing: MAGIC0 MAGIC1 then a 64-byte report
MAGIC1 = 0x5A
# ... MAGIC0 MAGIC_SIM then 64 bytes: on stdin, a message to the simulated world, not a
# report (a real board never sees one); its byte 0 says what. SIM_START: the scenario's
# clock starts now (SimBoard.hold: the host's session began; host/transport.py's begin()).
MAGIC_SIM = 0x5B
SIM_START = 1
ADC_MAX = 4095

# ---- the realistic board's analog errors (docs/simulation.md, "The realistic board") ----
DAC_CODES = 4096  # 12-bit amplitude DAC (the board's MCP4822), full scale = cfg.AMP_UA_AT_FULL
DAC_SETTLE_US = 4.5  # MCP4822 data sheet DS22249A: 4.5 us typ. to 1/2 LSB (docs/hardware.md [S1])
DAC_TAU_US = 4.5 / 9.01  # first-order: 0.5 LSB of 12 bits = e^-9.01 after DAC_SETTLE_US
DAC_GAIN = (0.9940, 1.0060, 0.9970, 1.0040)  # per channel: DAC + stimulator transconductance
ADC_NOISE_COUNTS = 2.84  # 8.7 ENOB (RP2040 datasheet): 2**(12 - 8.7) / sqrt(12) LSB rms
ADC_DNL_CODES = (512, 1536, 2560, 3584)  # erratum RP2040-E11
ADC_DNL_WIDTH = 9  # those codes are ~9 LSB wide (DNL ~ +8 LSB); their neighbours go missing
MON_GAIN = (1.0150, 0.9880, 1.0070, 0.9930)  # per channel: divider tolerance x ADC reference
MON_OFFSET_MV = (160, -110, 80, 220)  # per channel, electrode-referred: amplifier + ADC offset
IDEAL_NOISE_COUNTS = 1.5  # the ideal board's ADC noise (as before the realistic model)
# ---- the capture, as board_rp2 makes it on the chip (docs/simulation.md, "Voltage monitor and ADC") ----
# The ADC converts every cfg.ADC_SAMPLE_US from its start, a lead before the gate rises
# (on the emulated chip 13.1-14.4 us in the frame, varying with the code path; a real
# chip adds flash-cache misses), for (T + 12 + cfg.ADC_POST_US) // dt conversions (board_rp2.
# _CAPTURE_LEAD_US, _CAPTURE_POST_US); the board keeps the last cfg.ADC_WINDOW of them, in
# time order, at the end of adc[ch]. The simulated lead is drawn per pulse from
# CAPTURE_LEAD_US (a 2 us span: every phase of the conversions against the edge).
CAPTURE_LEAD_US = (13.0, 15.0)
CAPTURE_LEAD_COUNT_US = 12  # (board_rp2._CAPTURE_LEAD_US; the capture's end: + cfg.ADC_POST_US past the fall)
# The capture before session 24 ended 20 us past the fall and kept 32 samples: those samples draw their
# noise from the board's generator in the same order as then, the others (the longer capture's) from a
# second one, so every reading of a pulse is the same as before the capture grew (the studies' figures
# stay comparable; Vp reads the samples before the fall)
_OLD_POST_US = 20
_OLD_WINDOW = 32


class AnalogPath:
    """The DAC -> stimulator -> electrode -> monitor -> ADC errors of n channels.

    ideal=True: the commanded current exactly, no gain/offset error, no DNL,
    1.5 counts of ADC noise (bit for bit the board before this model)."""

    def __init__(self, cfg, n_channels, ideal=False, noise_counts=None):
        self.ideal = ideal
        self.fs_ua = cfg.AMP_UA_AT_FULL
        self.fs_cal = [cfg.AMP_UA_AT_FULL] * n_channels  # per channel: full scale x the stored DAC gain
        self.uv = cfg.VMON_UV_PER_COUNT
        if ideal:
            self.noise = IDEAL_NOISE_COUNTS if noise_counts is None else noise_counts
            self.dac_gain = [1.0] * n_channels
            self.mon_gain = [1.0] * n_channels
            self.mon_off_counts = [0.0] * n_channels
            self.dnl = None
        else:
            self.noise = ADC_NOISE_COUNTS if noise_counts is None else noise_counts
            self.dac_gain = [DAC_GAIN[k % 4] for k in range(n_channels)]
            self.mon_gain = [MON_GAIN[k % 4] for k in range(n_channels)]
            self.mon_off_counts = [MON_OFFSET_MV[k % 4] * 1000.0 / self.uv for k in range(n_channels)]
            dnl = array("H", range(ADC_MAX + 1))  # raw code -> the code the ADC reports
            h = ADC_DNL_WIDTH // 2
            for s in ADC_DNL_CODES:
                for c in range(s - h, s + h + 1):
                    dnl[c] = s
            self.dnl = dnl

    def code(self, i_ua, ch=None):
        """The DAC code for a commanded current: the largest not above it (never more
        current than commanded), clipped to the DAC's range. ch: with that channel's
        stored DAC gain (set_dac_gain), else nominal."""
        if i_ua <= 0:
            return 0
        c = i_ua * DAC_CODES // (self.fs_ua if ch is None else self.fs_cal[ch])
        return DAC_CODES - 1 if c >= DAC_CODES else c

    def delivered_ua(self, code, ch=None):
        """What the firmware is told: code x LSB (with channel ch's stored DAC gain), whole uA
        rounded up, as dac_mcp4822.ua_for."""
        return dac_mcp4822.ua_for(code, self.fs_ua if ch is None else self.fs_cal[ch])

    def physical_ua(self, ch, code):
        """The current the output stage really drives (float uA): code x LSB x gain error."""
        return code * self.fs_ua / DAC_CODES * self.dac_gain[ch]


class VirtualClock:
    """ticks_us and friends on a virtual time line that wraps at 2**bits.

    sleep_us() and pulses advance it instantly, so a scenario runs as fast as
    the VM can compute it; `start` lets tests begin just before a wrap.
    """

    def __init__(self, start=0, bits=30):
        self.mask = (1 << bits) - 1
        self.half = 1 << (bits - 1)
        self.t = start & self.mask

    def ticks_us(self):
        return self.t

    def ticks_add(self, a, b):
        return (a + b) & self.mask

    def ticks_diff(self, a, b):
        return ((a - b + self.half) & self.mask) - self.half

    def sleep_us(self, us):
        self.t = (self.t + us) & self.mask

    advance = sleep_us


class RealClock:
    """The VM's own tick source (real time), wrapped at 2**bits like the rp2's
    ticks_us (the unix port's own ticks wrap only at 2**62; the report's
    time_us field and the host count on 30 bits)."""

    def __init__(self, bits=30):
        import time

        self.mask = (1 << bits) - 1
        self.half = 1 << (bits - 1)
        self._ticks = time.ticks_us
        self.sleep_us = time.sleep_us

    def ticks_us(self):
        return self._ticks() & self.mask

    def ticks_add(self, a, b):
        return (a + b) & self.mask

    def ticks_diff(self, a, b):
        return ((a - b + self.half) & self.mask) - self.half

    def advance(self, us):
        pass  # real time passes by itself


class MemoryUSB:
    """Reports kept in memory: `sent` gets a copy of each IN report, `inbox` feeds OUT reports."""

    def __init__(self, keep=True):
        self.sent = []
        self.inbox = []
        self.keep = keep
        self.n_sent = 0

    def send(self, buf):
        self.n_sent += 1
        if self.keep:
            self.sent.append(bytes(buf))

    def recv(self, buf):
        if not self.inbox:
            return False
        r = self.inbox.pop(0)
        for k in range(64):
            buf[k] = r[k]
        return True


class StdioUSB:
    """IN reports to stdout and OUT reports from stdin, each behind 2 magic bytes."""

    def __init__(self):
        import select

        self.out = sys.stdout.buffer
        self.inp = sys.stdin.buffer
        self.poll = select.poll()
        self.poll.register(sys.stdin, select.POLLIN)
        self.hdr = bytes((MAGIC0, MAGIC1))
        self.pending = bytearray()
        self.eof = False
        self.n_sent = 0
        self.on_sim = None  # called with byte 0 of each message to the simulated world (SimBoard.sim)

    def send(self, buf):
        self.out.write(self.hdr)
        self.out.write(buf)
        self.n_sent += 1

    def flush(self):
        self.out.flush()

    def recv(self, buf):
        while not self.eof and self.poll.poll(0):
            chunk = self.inp.read(1) if len(self.pending) >= 66 else self.inp.read(66 - len(self.pending))
            if not chunk:
                self.eof = True
                break
            self.pending.extend(chunk)
            if len(self.pending) >= 66:
                break
        # resynchronise on the magic bytes (a report's, or a message's to the simulated world)
        while len(self.pending) >= 2 and not (self.pending[0] == MAGIC0 and self.pending[1] in (MAGIC1, MAGIC_SIM)):
            self.pending = self.pending[1:]
        if len(self.pending) < 66:
            return False
        if self.pending[1] == MAGIC_SIM:  # not for the firmware: the simulated world's, then the next report
            code = self.pending[2]
            self.pending = self.pending[66:]
            if self.on_sim is not None:
                self.on_sim(code)
            return self.recv(buf)
        for k in range(64):
            buf[k] = self.pending[2 + k]
        self.pending = self.pending[66:]
        return True


# the monitor correction (steadytouch selftest) is the device's own code: vmon_cal
import vmon_cal
from vmon_cal import CAL_GAIN_PPM, CAL_HEADER, CAL_OFFSET_MV  # noqa: F401 (names for the host and tests)
from vmon_cal import correct as correct_count  # noqa: F401
from vmon_cal import parse as parse_correction  # noqa: F401
from vmon_cal import terms as correction_terms  # noqa: F401


class SimBoard:
    """n simulated channels, each a stimulator + electrode (or a resistor) + voltage monitor.

    ideal: False (default) the realistic analog path (AnalogPath); True the ideal one.
    load_ohm: a resistor on every channel instead of the electrodes (self-test).
    correction: [(gain_ppm, offset_mv) or None per channel], the monitor correction
    handed to the firmware at boot (stim._measure applies it to each pulse's peak);
    flash_dir: the board's flash folder instead, as the rp2 board reads /vmon_cal.txt
    (a missing or corrupt file: uncorrected, vmon_state says which) and where
    store_vmon() writes it (CMD_SET_VMON ... VMON_STORE)."""

    def __init__(self, cfg, clock, scenario, n_channels=2, seed=1, usb=None, electrodes=None,
                 noise_counts=None, ideal=False, load_ohm=0, correction=None, flash_dir=None):
        self.cfg = cfg
        self.clock = clock
        self.scenario = scenario
        self.n_channels = n_channels
        self.usb = usb or MemoryUSB()
        if electrodes is None:
            if load_ohm:
                electrodes = [sim_electrode.Resistor(load_ohm) for _ in range(n_channels)]
            else:
                electrodes = [sim_electrode.Electrode() for _ in range(n_channels)]
        self.electrodes = electrodes
        self.analog = AnalogPath(cfg, n_channels, ideal, noise_counts)
        self.ideal = ideal
        self.dac_gain_applied = not ideal  # the ideal board has no DAC: a stored DAC gain changes nothing (GET_INFO)
        self.dac_exact = ideal  # ... its current is exactly the commanded one (no margin for a DAC error: stim)
        self.noise = self.analog.noise
        self.rng = random
        random.seed(seed)
        self.r2 = (seed * 2654435761 + 12345) & 0xFFFFFFFF or 1  # the second generator's state (xorshift32)
        self.dt_us = cfg.ADC_SAMPLE_US
        self.n_max = cfg.ADC_WINDOW
        self.post_us = cfg.ADC_POST_US
        self.adc = [array("H", bytes(2 * self.n_max)) for _ in range(n_channels)]
        self.lead_us = None  # the ADC's start before the gate's rise (us); None: drawn per pulse (CAPTURE_LEAD_US)
        self.last_rise = [0] * n_channels  # window index of the last pulse's first sample in the pulse (tests)
        self.last_edge = [0] * n_channels  # ... and of its first sample after the fall
        self.amp = [0] * n_channels  # the delivered current the firmware was told (uA)
        self.code = [0] * n_channels  # the DAC code
        self.i_from = [0.0] * n_channels  # physical current (uA) when the DAC was last written
        self.t_set = [clock.ticks_us()] * n_channels  # ... and when
        self.gate_high = [False] * n_channels
        self.pulses = [0] * n_channels
        self.stops = [0] * n_channels
        self.watchdog_feeds = 0
        self.t_s = 0.0  # scenario time
        self._last = clock.ticks_us()
        self.held = False  # True: the scenario waits at its time 0 until start_scenario() (main.py --hold)
        self.glitch = [0.0] * n_channels  # next pulse's measurement x this factor (0: none)
        self.spike = [0] * n_channels  # next pulse: one ADC sample at full scale
        self.compliance_mv = cfg.COMPLIANCE_MV
        self.last_rp_kohm = [0.0] * n_channels  # the true Rp of the last pulse (kohm)
        self.last_i_ua = [0.0] * n_channels  # the true (physical) current of the last pulse (uA)
        self.cal_path = None
        self.vmon_state = 0  # hp.VMON_NONE
        self.vmon_cal = [None] * n_channels
        if flash_dir:
            self.cal_path = flash_dir.rstrip("/") + "/" + vmon_cal.CAL_FILE
            self.vmon_cal, self.vmon_state = vmon_cal.boot_load(self.cal_path, n_channels)
        if correction:
            for k in range(n_channels):
                if k < len(correction) and correction[k]:
                    self.vmon_cal[k] = correction[k]

    # -------------------------------------------------- the scenario's clock
    def start_scenario(self):
        """The scenario's clock starts now (it was held at time 0); once held no more, nothing."""
        if self.held:
            self.held = False
            self._last = self.clock.ticks_us()

    def sim(self, code):
        """A message to the simulated world (StdioUSB.on_sim): SIM_START starts the scenario."""
        if code == SIM_START:
            self.start_scenario()

    def _advance_scenario(self):
        now = self.clock.ticks_us()
        dt = self.clock.ticks_diff(now, self._last)
        self._last = now
        if self.held:
            dt = 0  # the world stays at the scenario's time 0 (its state there, no time passes)
        elif dt <= 0:
            return
        dt_s = dt / 1e6
        self.t_s += dt_s
        contact, h_t, tau = self.scenario.at(self.t_s)
        for e in self.electrodes:
            e.contact = contact
            e.step_hydration(h_t, tau, dt_s)

    def _level_ua(self, ch, after_us):
        """The physical output current after_us after the last DAC write (first-order settling)."""
        target = self.analog.physical_ua(ch, self.code[ch])
        d = self.i_from[ch] - target
        if self.ideal or d == 0.0 or after_us * 1.0 > 40.0 * DAC_TAU_US:
            return target
        return target + d * 2.718281828459045 ** (-after_us / DAC_TAU_US)

    # ---------------------------------------------------------- the board API
    def set_amplitude(self, ch, i_ua):
        """Write the amplitude DAC; return the current (uA) the output stage will deliver:
        code x LSB (the ideal board: i_ua itself)."""
        now = self.clock.ticks_us()
        self.i_from[ch] = self._level_ua(ch, self.clock.ticks_diff(now, self.t_set[ch]))
        self.t_set[ch] = now
        if self.ideal:
            self.code[ch] = i_ua if i_ua > 0 else 0
            self.amp[ch] = self.code[ch]
            return self.amp[ch]
        self.code[ch] = self.analog.code(i_ua, ch)
        self.amp[ch] = self.analog.delivered_ua(self.code[ch], ch)
        return self.amp[ch]

    def set_dac_gain(self, ch, ppm):
        """The stored DAC gain of channel ch (ppm, 0: nominal), as dac_mcp4822.MCP4822.set_gain:
        its full scale follows, so set_amplitude reports the current delivered. The ideal
        board has no DAC: nothing changes."""
        if not self.ideal:
            self.analog.fs_cal[ch] = dac_mcp4822.full_for(self.analog.fs_ua, ppm or 1000000)

    def stop(self, ch):
        self.set_amplitude(ch, 0)
        self.gate_high[ch] = False
        self.stops[ch] += 1

    def feed_watchdog(self):  # once per frame: the scenario follows the clock even with no pulse
        self.watchdog_feeds += 1
        self._advance_scenario()

    def _noise2(self):
        """The sum of three uniforms less 1.5 (as the board's generator's noise) from the second generator
        (xorshift32): the samples the capture before session 24 did not hold."""
        x = self.r2
        z = 0.0
        for _ in range(3):
            x ^= (x << 13) & 0xFFFFFFFF
            x ^= x >> 17
            x ^= (x << 5) & 0xFFFFFFFF
            z += x / 4294967296.0
        self.r2 = x
        return z - 1.5

    def fire(self, ch, t_us):
        """Gate a pulse of t_us at the set amplitude and capture the monitor as the
        chip does: conversions every dt_us from lead_us before the rise to past the
        fall, the last n (<= ADC_WINDOW) kept at the end of adc[ch] in time order;
        returns n. After the fall no current flows: the skin's capacitance
        discharges through Rp_skin (the Rs drop is gone at once)."""
        self._advance_scenario()
        an = self.analog
        i_set = an.physical_ua(ch, self.code[ch]) if not self.ideal else self.amp[ch]
        buf = self.adc[ch]
        if i_set <= 0 or t_us <= 0:
            self.clock.advance(t_us)
            return 0
        dt = self.dt_us
        total = (t_us + CAPTURE_LEAD_COUNT_US + self.post_us) // dt
        w = self.n_max
        n = total if total < w else w
        self.pulses[ch] += 1
        e = self.electrodes[ch]
        uv = self.cfg.VMON_UV_PER_COUNT
        full = self.compliance_mv
        exp = 2.718281828459045
        if e.pulse(i_set):
            rs, rp, tau = e.rs, e.rp_skin, e.tau
            self.last_rp_kohm[ch] = rs + rp * (1.0 - exp ** (-t_us / tau))
            on = True
        else:
            rs, rp, tau = 0.0, 0.0, 1.0  # off: the stimulator hits compliance
            self.last_rp_kohm[ch] = float("inf")
            on = False
        g = self.glitch[ch] or 1.0
        self.glitch[ch] = 0.0
        rnd = self.rng.random
        sig2 = 2.0 * self.noise
        gain = an.mon_gain[ch] * g * 1000.0 / uv  # electrode mV -> ADC counts
        off = an.mon_off_counts[ch]
        dnl = an.dnl
        since = self.clock.ticks_diff(self.clock.ticks_us(), self.t_set[ch])
        i_end = i_set if self.ideal else self._level_ua(ch, since + t_us)
        v_cap_mv = i_end / 1000.0 * rp * (1.0 - exp ** (-t_us / tau)) * 1000.0 if on else 0.0  # Rp || C at the fall
        lead = self.lead_us
        if lead is None:
            lead = CAPTURE_LEAD_US[0] + (CAPTURE_LEAD_US[1] - CAPTURE_LEAD_US[0]) * rnd()
        t0 = (total - n) * dt - lead  # the first kept conversion, from the rise (us)
        edge = w
        rise = w
        old_end = (t_us + CAPTURE_LEAD_COUNT_US + _OLD_POST_US) // dt  # the old capture's samples (_OLD_POST_US):
        old_lo = old_end - (old_end if old_end < _OLD_WINDOW else _OLD_WINDOW) - (total - n)  # window indices
        old_end -= total - n
        for j in range(n):
            t = t0 + j * dt
            if t < 0.0:
                mv = 0.0  # before the rise
            elif t < t_us:
                if rise == w:
                    rise = w - n + j
                if not on:
                    mv = full
                else:
                    i_ma = (i_set if self.ideal else self._level_ua(ch, since + t)) / 1000.0
                    mv = i_ma * (rs + rp * (1.0 - exp ** (-t / tau))) * 1000.0
                    if mv > full:
                        mv = full  # compliance: the output cannot drive more voltage
            else:
                if edge == w:
                    edge = w - n + j
                mv = v_cap_mv * exp ** (-(t - t_us) / tau) if on else 0.0
                if mv > full:
                    mv = full
            z = (rnd() + rnd() + rnd() - 1.5) if old_lo <= j < old_end else self._noise2()
            if self.ideal:
                counts = mv * 1000.0 / uv * g + z * sig2
            else:
                counts = mv * gain + off + z * sig2
            c = int(counts + 0.5)
            c = 0 if c < 0 else (ADC_MAX if c > ADC_MAX else c)
            if dnl is not None:
                c = dnl[c]
            buf[w - n + j] = c
        self.last_rise[ch] = rise
        self.last_edge[ch] = edge
        v_end = i_end / 1000.0 * self.last_rp_kohm[ch] * 1000.0 if on else full
        self.last_i_ua[ch] = i_end if v_end <= full else full / self.last_rp_kohm[ch]
        if self.spike[ch]:
            k = edge - 1  # the last sample of the pulse: where a spike would count most
            if k >= w - n:
                buf[k] = ADC_MAX
            self.spike[ch] = 0
        self.clock.advance(t_us)
        return n

    def store_vmon(self, values):
        """Write the monitor correction to the board's flash folder (CMD_SET_VMON ...
        VMON_STORE); False without one (nothing written)."""
        return self.cal_path is not None and vmon_cal.store(self.cal_path, values)

    def send(self, buf):
        self.usb.send(buf)

    def recv(self, buf):
        return self.usb.recv(buf)
