# The rp2 (Raspberry Pi Pico) board: PIO-gated pulses, amplitude by an SPI DAC
# (dac_mcp4822.py, written after each pulse for the next one), free-running
# ADC -> FIFO -> rp2.DMA capture of the voltage monitor, the hardware watchdog
# and the USB HID interface. Pins and scales: board_config.py and
# docs/hardware.md. This layer needs the real chip; everything above it runs in
# the MicroPython unix VM against board_sim.SimBoard, which has the same
# interface. Registers: RP2040 datasheet, sections 4.9 (ADC) and 2.5 (DMA).
import time
from array import array

import machine
import micropython
import rp2
import uctypes
from micropython import const

import dac_mcp4822
import hid_protocol as hp
import pio_gate
import vmon_cal

_ADC_CS = const(0x4004C000)
_ADC_FCS = const(0x4004C008)
_ADC_FIFO = const(0x4004C00C)
_ADC_DIV = const(0x4004C010)
_CS_EN = const(0x1)
_CS_START_MANY = const(0x8)
_FCS_EN = const(0x1)
_FCS_DREQ_EN = const(0x8)
_FCS_THRESH_1 = const(0x1000000)
_FCS_ERR_FLAGS = const(0xC00)  # UNDER | OVER, write 1 to clear
_DREQ_ADC = const(36)
_DMA_CHAN_ABORT = const(0x50000444)
_ADC_CLK_HZ = const(48000000)
# The capture (issue 13): the ADC converts every ADC_SAMPLE_US = 2 us (its full rate), so
# the last conversion before the gate's falling edge starts within the last 2 us of the
# pulse whatever T and whatever the phase of the conversions against the gate (no CPU
# timing is involved). The DMA writes into a ring of ADC_WINDOW samples, so each channel
# keeps only the capture's last 256 us, in time order, ending _CAPTURE_POST_US after
# the falling edge: the edge, the end of the pulse and the monitor's decay after it (the
# skin's tau, stim._measure) are always in it.
# _CAPTURE_LEAD_US: from the ADC's start to the gate's rise on the emulated chip (start()'s
# timed wait of _LEAD_WAIT_US between the two stores plus the gate program's set-up:
# 12.9-14.2 us; tests/chip/test_chip_adc.py asserts 12-16). The capture runs to _CAPTURE_POST_US past the
# edge there (~50 samples after it, ~78 before it in the window). Vp reads the samples up
# to 20 us past the edge (stim._C_PEAK_POST_US: the window before session 24); a real chip's
# flash cache misses only lengthen the lead, which moves the edge later: ~17 us more takes it
# out of Vp's samples, which then read low (a lower charge, never a higher one), and the
# frame seeks the fall past them for tau (fewer samples of the decay: up to ~90 us more
# leaves it in the window; tests/test_frame_tau.py).
_CAPTURE_LEAD_US = const(12)
_CAPTURE_POST_US = const(100)  # board_config.ADC_POST_US (checked in Board()): the monitor's decay after the fall
_T_FLOOR_US = const(20)  # hp.T_FLOOR_US (checked below): a literal, so the viper start() folds it
_SAMPLE_US = const(2)  # board_config.ADC_SAMPLE_US (checked in Board()): start() divides by it as a shift
# start()'s wait between the ADC's first conversion and the gate's word, in us of the
# TIMER (RP2040 datasheet 4.6: TIMERAWL; 8-9 us, the timer's phase): with the gate
# program's own ~5.5 us set-up this keeps the capture's lead on the gate at 12-16 us
# (tests/chip/test_chip_adc.py), as the Python between the two stores did before start()
# was viper. Timed, not counted: a real chip's flash cache misses cannot shorten it.
_LEAD_WAIT_US = const(9)
_TIMERAWL = const(0x40054028)
_PIO0_TXF0 = const(0x50200010)  # PIO0's TX FIFO of state machine 0; sm k at + 4k (StateMachine(k), k < 4)
_DMA_BASE = const(0x50000000)  # DMA channel c's READ_ADDR, WRITE_ADDR, TRANS_COUNT, CTRL_TRIG at + 0x40c
_DMA_BUSY = const(0x1000000)  # CTRL.BUSY
_SPI0_BASE = const(0x4003C000)  # SPI1 at + 0x4000; SSPDR at word 2, SSPSR at word 3
_SIO_BASE = const(0xD0000000)
# Board.p: the numbers start(), wait() and set_amplitude() read, one int array (ptr32 in viper)
_P_DMA = const(0)  # the DMA channel's register base
_P_CTRL = const(1)  # its CTRL_TRIG word for a capture
_P_WORD = const(2)  # what the gate's word is short of t_us (pio_gate.GATE_OVERHEAD_US)
_P_HARD_T = const(3)
_P_ADDR = const(4)  # + ch: channel ch's capture window address
_P_SEL = const(8)  # + ch: its CS.AINSEL << 12
_P_SPI = const(12)  # the DAC's SPI register base
_P_FULL = const(13)  # + ch: the DAC output's current at code 4096 (with its gain)
_P_CS = const(17)  # + ch: 1 << its chip-select pin
_P_ADC = const(21)  # the peripherals' addresses (as words here: an address >= 2**30 written as a
_P_TMR = const(22)  # const() is a long int the viper code would convert at every use, ~1.2 us each)
_P_TXF = const(23)
_P_SIO = const(24)  # SIO base: GPIO_OUT_SET at word 5, GPIO_OUT_CLR at word 6
_P_NMAX = const(25)  # the capture window (samples, a power of 2)
_P_LEN = const(26)
if hp.T_FLOOR_US != _T_FLOOR_US:
    raise ImportError("board_rp2: _T_FLOOR_US differs from hid_protocol.T_FLOOR_US")
# Instructions executed directly by stop(), encoded once at import (nothing per call)
_PULL_NOBLOCK = rp2.asm_pio_encode("pull(noblock)", 0)
_SET_PINS_0 = rp2.asm_pio_encode("set(pins, 0)", 0)
_WDT_CTRL = const(0x40058000)  # RP2040 datasheet 4.7.7: CTRL.ENABLE (bit 30) pauses the count when clear
_WDT_ENABLE = const(0x40000000)
_disable_irq = machine.disable_irq  # one global load in irq_off()


VMON_PATH = "/" + vmon_cal.CAL_FILE  # the monitor correction in the board's flash (steadytouch selftest)


def load_vmon(n, path=VMON_PATH):
    """The monitor correction stored in the flash, read once at boot: ([(gain_ppm,
    offset_mv, dac_gain_ppm) or None per channel], hp.VMON_NONE / LOADED / BAD). A missing or
    corrupt file leaves every monitor uncorrected; it never stops the boot."""
    return vmon_cal.boot_load(path, n)


def watchdog_pause():
    """Pause the hardware watchdog (pico-sdk's watchdog_disable()). MicroPython's
    WDT cannot be stopped, and a soft reset keeps it running: without this the
    chip resets 500 ms after the loop stops, even with the REPL in use.
    machine.WDT() enables it again (the next boot of the loop)."""
    machine.mem32[_WDT_CTRL] = machine.mem32[_WDT_CTRL] & ~_WDT_ENABLE


def watchdog_running():
    return bool(machine.mem32[_WDT_CTRL] & _WDT_ENABLE)


def dac(cfg, n):
    """The amplitude DAC of board_config: SPI bus and chip selects (idle high)."""
    spi = machine.SPI(cfg.DAC_SPI_ID, baudrate=cfg.DAC_SPI_HZ, polarity=0, phase=0, bits=8, firstbit=machine.SPI.MSB,
                      sck=machine.Pin(cfg.DAC_SCK_PIN), mosi=machine.Pin(cfg.DAC_MOSI_PIN),
                      miso=machine.Pin(cfg.DAC_MISO_PIN))
    cs = [machine.Pin(p, machine.Pin.OUT, value=1) for p in cfg.DAC_CS_PINS]
    return dac_mcp4822.MCP4822(spi, cs, n, cfg.AMP_UA_AT_FULL)


def outputs_off(cfg):
    """Every stimulator output off, whatever state a failed set-up left: the PIO
    state machines stopped, each gate pin taken back as a plain GPIO output
    driven low, every DAC output written to code 0 (if the bus can be set up),
    then the DAC's clock and data pins plain GPIO low and its chip selects high
    (deselected: nothing can be clocked in)."""
    for k in range(len(cfg.GATE_PINS)):
        try:
            rp2.StateMachine(k).active(0)
        except Exception:  # never configured: nothing runs on it
            pass
    for pin in cfg.GATE_PINS:
        machine.Pin(pin, machine.Pin.OUT, value=0)
    try:
        dac(cfg, 2 * len(cfg.DAC_CS_PINS)).zero_all()
    except Exception:  # the gates are low: no pulse can be delivered whatever the DAC holds
        pass
    for pin in (cfg.DAC_SCK_PIN, cfg.DAC_MOSI_PIN):
        machine.Pin(pin, machine.Pin.OUT, value=0)
    for pin in cfg.DAC_CS_PINS:
        machine.Pin(pin, machine.Pin.OUT, value=1)


class Clock:
    ticks_us = staticmethod(time.ticks_us)
    ticks_add = staticmethod(time.ticks_add)
    ticks_diff = staticmethod(time.ticks_diff)
    sleep_us = staticmethod(time.sleep_us)

    def advance(self, us):
        pass


class Board:
    def __init__(self, cfg):
        self.cfg = cfg
        n = cfg.N_CHANNELS
        self.n_channels = n
        self.dt_us = cfg.ADC_SAMPLE_US
        self.n_max = cfg.ADC_WINDOW
        self.adc, self.adc_addr = self._windows(n, cfg.ADC_WINDOW)
        self.gates = [machine.Pin(cfg.GATE_PINS[k], machine.Pin.OUT, value=0) for k in range(n)]
        self.sms = []
        for k in range(n):
            sm = rp2.StateMachine(k, pio_gate.gate, freq=pio_gate.FREQ_HZ, set_base=self.gates[k])
            sm.active(1)
            self.sms.append(sm)
        if cfg.ADC_SAMPLE_US != _SAMPLE_US or n > 4 or cfg.ADC_POST_US != _CAPTURE_POST_US:
            raise ValueError("board_rp2: ADC_SAMPLE_US must be %d us, ADC_POST_US %d us, N_CHANNELS at most 4"
                             % (_SAMPLE_US, _CAPTURE_POST_US))
        p = self.p = array("i", [0] * _P_LEN)  # start(), wait(), set_amplitude() (viper) read these
        self.dac = dac(cfg, n)
        self.codes = self.dac.codes = array("i", self.dac.codes)  # the driver's record of the codes written,
        # as an int array: set_amplitude() (viper) keeps it too
        p[_P_SPI] = _SPI0_BASE + 0x4000 * cfg.DAC_SPI_ID
        for k in range(n):
            p[_P_CS + k] = 1 << cfg.DAC_CS_PINS[k >> 1]
            p[_P_FULL + k] = self.dac.full[k]
        self.dac.zero_all()
        self.irq_on = machine.enable_irq  # the same: one Python call a frame's section less (method below)
        self.ainsel = [cfg.ADC_INPUTS[k] << 12 for k in range(n)]
        for k in range(n):
            p[_P_SEL + k] = self.ainsel[k]
            p[_P_ADDR + k] = self.adc_addr[k]
        for k in range(n):
            machine.ADC(26 + cfg.ADC_INPUTS[k])  # configures the pad as an analog input
        machine.mem32[_ADC_DIV] = (_ADC_CLK_HZ // 1000000 * cfg.ADC_SAMPLE_US - 1) << 8
        self.dma = rp2.DMA()
        ring = 2 * cfg.ADC_WINDOW  # bytes; the write address wraps inside the window (ring_sel: write)
        self.dma_ctrl = self.dma.pack_ctrl(size=1, inc_read=False, inc_write=True, treq_sel=_DREQ_ADC,
                                           ring_size=len(bin(ring)) - 3, ring_sel=True)
        # start() programs the channel by its registers (RP2040 datasheet 2.5.7: READ_ADDR,
        # WRITE_ADDR, TRANS_COUNT, CTRL_TRIG at word 0..3), 3 stores instead of a
        # keyword call: the read address (the ADC FIFO) never changes, the buffers
        # never move (MicroPython's heap does not compact).
        self.dma.config(read=_ADC_FIFO, write=self.adc_addr[0], count=1, ctrl=self.dma.pack_ctrl(
            enable=False, size=1, inc_read=False, inc_write=True, treq_sel=_DREQ_ADC))
        self.dma_regs = self.dma.registers
        self.overhead = pio_gate.GATE_OVERHEAD_US
        self.hard_t = cfg.HARD_T_MAX_US
        p[_P_DMA] = _DMA_BASE + 0x40 * self.dma.channel
        p[_P_ADC] = _ADC_CS
        p[_P_TMR] = _TIMERAWL
        p[_P_TXF] = _PIO0_TXF0
        p[_P_SIO] = _SIO_BASE - (1 << 32)  # the same 32 bits as a signed word
        p[_P_NMAX] = self.n_max
        p[_P_CTRL] = self.dma_ctrl
        p[_P_WORD] = self.overhead
        p[_P_HARD_T] = self.hard_t
        self.capturing = -1  # the channel whose pulse start() began and wait() has not ended
        self.vmon_cal, self.vmon_state = load_vmon(n)  # stim.Stimulator applies it (stim._measure)
        self.refused = 0  # pulses fire() refused (T outside [T_FLOOR_US, HARD_T_MAX_US])
        self.usb = self._usb()
        # last, once everything above worked: a failed set-up must not turn into a reset loop
        self.wdt = machine.WDT(timeout=cfg.WATCHDOG_MS)
        # the frame's calls go to the parts' own methods (one Python call less each, as
        # set_amplitude above); the methods below document the contract
        self.feed_watchdog = self.wdt.feed
        if self.usb is not None:
            self.send = self.usb.send
            self.recv = self.usb.recv

    def _usb(self):
        try:
            import usb.device
        except ImportError:
            raise ImportError("usb-device is not installed on the board: run `steadytouch flash`")
        import usb_hid64  # checks the usb-device-hid version

        hid = usb_hid64.Hid64()
        # builtin_driver=True keeps the REPL's USB serial port beside the HID interface
        usb.device.get().init(hid, manufacturer_str="steadytouch", product_str="steadytouch stimulator",
                              id_vendor=hp.VID, id_product=hp.PID, builtin_driver=True)
        return hid

    @staticmethod
    def _windows(n, w):
        """n capture windows of w samples (2w bytes, a power of 2), each aligned to its own
        size as the DMA's write ring needs (RP2040 datasheet 2.5.1.2): views into arrays of 2w
        samples (the heap aligns blocks to 8 or 16 bytes only). Returns (views, addresses)."""
        size = 2 * w
        if size & (size - 1) or size < 16:
            raise ValueError("board_config.ADC_WINDOW must be a power of 2 >= 8")
        views, addrs = [], []
        for _ in range(n):
            a = array("H", bytes(2 * size))
            base = uctypes.addressof(a)
            off = (-base) % size  # bytes to the next aligned address, < size
            views.append(memoryview(a)[off // 2:off // 2 + w])
            addrs.append(base + off)
        return views, addrs

    # ------------------------------------------------------------ board API
    def irq_off(self):
        """Interrupts off for one heap-locked section of the frame (stim._enter).
        The USB stack's interrupt schedules Python callbacks (usb-device) that
        allocate; one that ran inside a heap-locked section failed with
        MemoryError and the HID interface never opened (seen on the emulated
        chip). With interrupts off nothing new is scheduled, and the loop below
        is a jump: the VM runs what was already pending there, before the lock."""
        state = _disable_irq()
        k = 0
        while k < 1:
            k += 1
        return state

    def irq_on(self, state):
        machine.enable_irq(state)

    @micropython.viper
    def set_amplitude(self, ch: int, i_ua: int) -> int:
        """Write channel ch's DAC for the next pulse; return the current in uA the
        output stage will deliver (code * LSB, never above i_ua nor full scale;
        i_ua is a machine word: an int past 32 bits is cut, never to above full scale).
        The MCP4822 settles in ~4.5 us; the frame writes it right after a pulse,
        milliseconds before the next gate opens. Allocates nothing.
        The code and word are dac_mcp4822.MCP4822.set_ua's (tests/chip/test_chip_dac.py
        reads the words the DAC receives); viper, because speed forces it: the two bytes
        go through the SPI's data register and the chip select through the SIO, ~45 us
        less a write on the chip than the driver's spi.write and Pin calls."""
        p = ptr32(self.p)
        full = p[_P_FULL + ch]
        if i_ua <= 0:
            code = 0
        elif i_ua >= full:
            code = 4095  # dac_mcp4822.CODE_MAX
        else:
            code = i_ua * 4096 // full  # < 4096 * 110000 < 2**31
        w = 0x3000 | code  # gain 1x, active
        if ch & 1:
            w |= 0x8000  # output B
        spi = ptr32(p[_P_SPI])
        cs = p[_P_CS + ch]
        sio = ptr32(p[_P_SIO])
        sio[6] = cs  # GPIO_OUT_CLR: chip select low
        spi[2] = w >> 8  # SSPDR: the FIFO is empty (every write waits for the bus and drains it)
        spi[2] = w & 0xFF
        while spi[3] & 0x10:  # SSPSR.BSY: the 16 bits on the wire
            pass
        while spi[3] & 0x4:  # SSPSR.RNE: drain what came back
            x = spi[2]
        sio[5] = cs  # GPIO_OUT_SET: chip select high: the DAC latches the word
        ptr32(self.codes)[ch] = code  # the driver's record (dac.codes, an int array)
        return (code * full + 4095) >> 12  # rounded up (dac_mcp4822.ua_for)

    def stop(self, ch):
        """Gate low, no pulse pending, amplitude 0: whatever the state machine was
        doing (waiting, mid-pulse, a word still in its FIFO). Allocates nothing."""
        sm = self.sms[ch]
        sm.active(0)
        if self.capturing == ch:
            self._abort_capture()
        sm.exec(_PULL_NOBLOCK)  # drain the 4-word TX FIFO: a queued word must not fire later
        sm.exec(_PULL_NOBLOCK)
        sm.exec(_PULL_NOBLOCK)
        sm.exec(_PULL_NOBLOCK)
        sm.restart()  # back to the program's first instruction (pull), shift counters cleared
        sm.exec(_SET_PINS_0)  # stopping mid-pulse would otherwise leave the gate high
        sm.active(1)
        self.set_amplitude(ch, 0)

    def stop_all(self):
        for k in range(self.n_channels):
            self.stop(k)

    def feed_watchdog(self):
        self.wdt.feed()

    @micropython.viper
    def start(self, ch: int, t_us: int) -> int:
        """Start one pulse of t_us at the set amplitude and the capture of the
        monitor across it; returns at once with the number of samples the capture
        will hold: the last n of adc[ch], in time order, the falling edge among
        them (the capture's last 256 us, see _CAPTURE_LEAD_US). The PIO gate
        times the pulse and the DMA fills adc[ch] while the CPU goes on; wait() ends the capture. One capture at a time (one ADC):
        a capture still running is waited for first. Allocates nothing.

        The board's own last check: t_us outside [T_FLOOR_US, HARD_T_MAX_US] is
        refused (no pulse, 0 samples, counted in `refused`); the PIO program
        bounds the gate at HARD_T_MAX_US whatever word reaches it. ch and t_us are
        machine words (viper): an int past 32 bits is cut before the check, so the
        check is on the cut value; stim passes words it checked against the hard limits.
        Viper, because speed forces it: the ADC, DMA (RP2040 datasheet 2.5.7: READ_ADDR,
        WRITE_ADDR, TRANS_COUNT, CTRL_TRIG) and PIO FIFO stores are machine code, ~80 us
        less a pulse on the chip than from Python. The read address (the ADC FIFO) never
        changes and the buffers never move (MicroPython's heap does not compact)."""
        if int(self.capturing) >= 0:
            self.wait()
        p = ptr32(self.p)
        if t_us < _T_FLOOR_US or t_us > p[_P_HARD_T]:
            self.refused = int(self.refused) + 1
            return 0
        w = p[_P_NMAX]  # a power of 2 (_windows)
        total = (t_us + _CAPTURE_LEAD_US + _CAPTURE_POST_US) >> 1  # conversions (_SAMPLE_US), to past the fall
        first = (0 - total) & (w - 1)  # the ring's first slot: the capture's last sample lands in the window's last
        sel = p[_P_SEL + ch]
        adc = ptr32(p[_P_ADC])  # _adc_arm, inlined: CS, RESULT, FCS, FIFO at words 0..3
        adc[0] = _CS_EN | sel
        adc[2] = _FCS_EN | _FCS_DREQ_EN | _FCS_THRESH_1 | _FCS_ERR_FLAGS
        while adc[2] & 0xF0000:  # FCS.LEVEL: drain the FIFO
            x = adc[3]
        dma = ptr32(p[_P_DMA])
        dma[1] = p[_P_ADDR + ch] + 2 * first
        dma[2] = total
        dma[3] = p[_P_CTRL]  # CTRL_TRIG: starts the channel, paced by the ADC's DREQ
        self.capturing = ch
        tmr = ptr32(p[_P_TMR])
        t0 = tmr[0]
        adc[0] = _CS_EN | sel | _CS_START_MANY  # the conversions start; the gate rises ~_CAPTURE_LEAD_US later
        while tmr[0] - t0 < _LEAD_WAIT_US:
            pass
        ptr32(p[_P_TXF])[ch] = t_us - p[_P_WORD]  # the gate's word (its FIFO is empty between pulses)
        return total if total < w else w  # what the window keeps

    @micropython.viper
    def wait(self):
        """Until the capture start() began is complete (the pulse is over: the
        capture runs past its falling edge); the ADC stops. Allocates nothing."""
        ch = int(self.capturing)
        if ch < 0:
            return
        p = ptr32(self.p)
        dma = ptr32(p[_P_DMA])
        while dma[3] & _DMA_BUSY:
            pass
        ptr32(p[_P_ADC])[0] = _CS_EN | p[_P_SEL + ch]
        self.capturing = -1

    def _abort_capture(self):
        """The ADC stopped and the DMA channel aborted (RP2040 datasheet 2.5.5.3:
        CHAN_ABORT), e.g. when the channel being captured is stopped mid-pulse.
        Waits for the channel's BUSY flag to clear (rp2040js does not model the
        CHAN_ABORT read-back), at most a bounded number of polls: a stop never hangs;
        the next start() programs the channel afresh anyway."""
        machine.mem32[_ADC_CS] = _CS_EN | self.ainsel[self.capturing]
        machine.mem32[_DMA_CHAN_ABORT] = 1 << self.dma.channel
        k = 0
        while self.dma.active() and k < 100:
            k += 1
        self.capturing = -1

    def fire(self, ch, t_us):
        """One whole pulse (start() then wait()); returns the sample count."""
        n = self.start(ch, t_us)
        self.wait()
        return n

    def set_dac_gain(self, ch, ppm):
        """Channel ch's DAC delivers ppm / 1e6 x nominal (0: nominal; the self-test's
        correction): set_amplitude() then returns the current delivered. Allocates nothing."""
        self.dac.set_gain(ch, ppm)
        self.p[_P_FULL + ch] = self.dac.full[ch]

    def store_vmon(self, values, path=VMON_PATH):
        """Write the monitor correction to the flash (CMD_SET_VMON ... VMON_STORE),
        read at the next boot. Allocates: the Stimulator calls it outside its
        heap-locked section, only while every channel is disarmed (the flash write
        stalls the loop). True if written."""
        return vmon_cal.store(path, values)

    def send(self, buf):
        if self.usb is not None:
            self.usb.send(buf)

    def recv(self, buf):
        return self.usb is not None and self.usb.recv(buf)
