# The simulated board: the same interface as board_rp2.Board, with simulated
# electrodes behind each channel, a virtual or real clock, and USB reports
# framed on stdio (or kept in memory for tests). It is the "hardware" of the
# MicroPython unix VM: the firmware's frame runs against it unchanged.
import random
import sys
from array import array

import sim_electrode

MAGIC0 = 0xA5  # stdio framing: MAGIC0 MAGIC1 then a 64-byte report
MAGIC1 = 0x5A
ADC_MAX = 4095


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
        # resynchronise on the magic bytes
        while len(self.pending) >= 2 and not (self.pending[0] == MAGIC0 and self.pending[1] == MAGIC1):
            self.pending = self.pending[1:]
        if len(self.pending) < 66:
            return False
        for k in range(64):
            buf[k] = self.pending[2 + k]
        self.pending = self.pending[66:]
        return True


class SimBoard:
    """n simulated channels, each a stimulator + electrode + voltage monitor."""

    def __init__(self, cfg, clock, scenario, n_channels=2, seed=1, usb=None, electrodes=None,
                 noise_counts=1.5):
        self.cfg = cfg
        self.clock = clock
        self.scenario = scenario
        self.n_channels = n_channels
        self.usb = usb or MemoryUSB()
        self.electrodes = electrodes or [sim_electrode.Electrode() for _ in range(n_channels)]
        self.noise = noise_counts
        self.rng = random
        random.seed(seed)
        self.dt_us = cfg.ADC_SAMPLE_US
        self.n_max = cfg.HARD_T_MAX_US // cfg.ADC_SAMPLE_US + 2
        self.adc = [array("H", bytes(2 * self.n_max)) for _ in range(n_channels)]
        self.amp = [0] * n_channels
        self.gate_high = [False] * n_channels
        self.pulses = [0] * n_channels
        self.stops = [0] * n_channels
        self.watchdog_feeds = 0
        self.t_s = 0.0  # scenario time
        self._last = clock.ticks_us()
        self.glitch = [0.0] * n_channels  # next pulse's measurement x this factor (0: none)
        self.spike = [0] * n_channels  # next pulse: one ADC sample at full scale
        self.compliance_mv = cfg.COMPLIANCE_MV
        self.last_rp_kohm = [0.0] * n_channels

    # -------------------------------------------------- the scenario's clock
    def _advance_scenario(self):
        now = self.clock.ticks_us()
        dt = self.clock.ticks_diff(now, self._last)
        self._last = now
        if dt <= 0:
            return
        dt_s = dt / 1e6
        self.t_s += dt_s
        contact, h_t, tau = self.scenario.at(self.t_s)
        for e in self.electrodes:
            e.contact = contact
            e.step_hydration(h_t, tau, dt_s)

    # ---------------------------------------------------------- the board API
    def set_amplitude(self, ch, i_ua):
        """Ideal output stage: delivers exactly i_ua (the board contract: returns the delivered uA)."""
        self.amp[ch] = i_ua
        return i_ua

    def stop(self, ch):
        self.amp[ch] = 0
        self.gate_high[ch] = False
        self.stops[ch] += 1

    def feed_watchdog(self):  # once per frame: the scenario follows the clock even with no pulse
        self.watchdog_feeds += 1
        self._advance_scenario()

    def fire(self, ch, t_us):
        """Gate a pulse of t_us at the set amplitude; fill adc[ch]; return the sample count."""
        self._advance_scenario()
        i_ua = self.amp[ch]
        n = t_us // self.dt_us
        if n > self.n_max:
            n = self.n_max
        buf = self.adc[ch]
        if i_ua <= 0 or n <= 0:
            self.clock.advance(t_us)
            return 0
        self.pulses[ch] += 1
        e = self.electrodes[ch]
        uv = self.cfg.VMON_UV_PER_COUNT
        full = self.compliance_mv
        if e.pulse(i_ua):
            i_ma = i_ua / 1000.0
            rs, rp, tau = e.rs, e.rp_skin, e.tau
            self.last_rp_kohm[ch] = rs + rp * (1.0 - 2.718281828459045 ** (-t_us / tau))
            decay = 2.718281828459045 ** (-self.dt_us / tau)
        else:
            i_ma, rs, rp, decay = 0.0, 0.0, 0.0, 0.0  # off: the stimulator hits compliance
            self.last_rp_kohm[ch] = float("inf")
        g = self.glitch[ch] or 1.0
        self.glitch[ch] = 0.0
        rnd = self.rng.random
        sig2 = 2.0 * self.noise
        left = 1.0  # e^(-t/tau) at t = (k+1) dt
        for k in range(n):
            left *= decay
            mv = full if i_ma == 0.0 else i_ma * (rs + rp * (1.0 - left)) * 1000.0
            if mv > full:
                mv = full
            counts = mv * 1000.0 / uv * g + (rnd() + rnd() + rnd() - 1.5) * sig2
            c = int(counts + 0.5)
            buf[k] = 0 if c < 0 else (ADC_MAX if c > ADC_MAX else c)
        if self.spike[ch]:
            buf[n // 2] = ADC_MAX
            self.spike[ch] = 0
        self.clock.advance(t_us)
        return n

    def send(self, buf):
        self.usb.send(buf)

    def recv(self, buf):
        return self.usb.recv(buf)
