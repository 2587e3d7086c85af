// The emulated Pico's host (the chip tests and the emu:// transport): boots the
// real MicroPython firmware on the emulated RP2040 (rp2040js, through
// ../shared/emulator/rp2run.mjs used in place), and plays the world around the board:
//   - steps the PIO state machines on the emulated clock at their clock
//     dividers (rp2040js 1.4.1 runs PIO on setTimeout, 1000 steps a macrotask,
//     with no divider and no relation to emulated time), and records every
//     edge of the gate pins in emulated nanoseconds;
//   - is the amplitude DAC (MCP4822s on the SPI bus, one chip select each): takes
//     every 16-bit word clocked in while a chip select is low, latches it at the
//     select's rising edge (LDAC tied low), records it with its time, and keeps
//     the SPI busy for the word's bits at the bus clock (so a write costs its
//     real bus time in emulated us);
//   - feeds the ADC per sample with the electrode's monitor voltage while the
//     gate is high: V = I (Rs + Rp (1 - e^(-t/tau))), firmware/sim_electrode.py's
//     model, I from the DAC code the board set, clamped at compliance; after the
//     fall the skin's capacitance discharging through Rp: V(fall) e^(-t/tau) (no
//     current: the Rs drop is gone), what the firmware reads tau from;
//   - records watchdog feeds and turns a watchdog reset into a reply;
//   - is the USB host: CDC for the raw REPL, and the board's HID interface
//     (enumerated again when the board re-connects with it), whose 64-byte IN
//     reports it collects.
// Protocol: one JSON object a line on stdin, one JSON reply a line on stdout
// (host/emu/__init__.py is the Python side). The op `stream` switches to the
// streaming mode of the emu:// transport (see streamMode below): from then on every
// stdin line is one HID OUT report in hex and every stdout line one IN report in
// hex, the board runs paced by the wall clock, and stdin EOF ends the process.
// The op `serve` (see serveMode below) instead boots the board from its flash as at
// power-up and serves it on two TCP ports on 127.0.0.1, as a Pico on a USB cable is
// two devices: its USB serial (CDC bytes, for mpremote and `steadytouch flash --port
// socket://127.0.0.1:PORT`) and its HID interface (64-byte reports as hex lines, for
// the emu+tcp:// transport); a hard reset reboots the chip with its flash kept.
// Usage:
//   node host.mjs EMULATOR_DIR CACHE_DIR
import fs from 'node:fs';
import net from 'node:net';
import path from 'node:path';
import readline from 'node:readline';
import { register } from 'node:module';
import { pathToFileURL } from 'node:url';

const [emuDir, cacheDir] = process.argv.slice(2);
register('./resolve-hook.mjs', import.meta.url, {
  data: { parentURL: pathToFileURL(path.join(path.resolve(cacheDir), 'package.json')).href },
});
const { Board, BoardReset, CYCLE_NS } = await import(pathToFileURL(path.join(emuDir, 'rp2run.mjs')).href);
const { GPIOPinState } = await import('rp2040js');
const { UsbHost } = await import('./usbhost.mjs');

const WATCHDOG_LOAD = 0x40058004;

// ------------------------------------------------------------------ the electrode of a scenario
// A line-by-line port of firmware/sim_electrode.py's Electrode and Scenario (the
// simulator's model; parameters and keyframes come from the Python side, so the
// numbers have one source): Rs + (Rp_skin || Cp), Rp_skin from the current density
// and hydration, contact and hydration following the scenario's keyframes.
class Electrode {
  constructor(p) {
    this.area0 = p.area0;
    this.rs = p.rs; // kohm
    this.rho_ref = p.rho_ref;
    this.j_ref = p.j_ref;
    this.beta = p.beta;
    this.c = p.c; // nF/cm^2
    this.alpha = p.alpha;
    this.contact = 1.0;
    this.h = 1.0;
    this.rho = 0.0;
    this.rp_skin = 0.0; // kohm
    this.tau = 0.0; // us
  }

  stepHydration(hTarget, tauS, dtS) {
    if (tauS <= 0) this.h = hTarget;
    else this.h += (hTarget - this.h) * (1.0 - Math.exp(-dtS / tauS));
  }

  /** Set rp_skin and tau for a pulse of iUa; false if the electrode is off. */
  pulse(iUa) {
    const a = this.area0 * this.contact;
    if (a <= 1e-6 || iUa <= 0) return false;
    const j = iUa / 1000.0 / a;
    const rhoEq = this.h * this.rho_ref * (j / this.j_ref) ** -this.beta;
    if (this.rho <= 0.0) this.rho = rhoEq;
    else this.rho += this.alpha * (rhoEq - this.rho);
    this.rp_skin = this.rho / a;
    this.tau = this.rp_skin * this.c * a;
    return true;
  }
}

class Scenario {
  constructor({ keys, interp_h }) {
    this.keys = keys; // [t_s, contact, h_target, tau_s]
    this.interpH = interp_h;
    this.k = 0;
  }

  /** [contact, h_target, tau_s] at t_s (calls must not go back in time). */
  at(tS) {
    const keys = this.keys;
    let k = this.k;
    while (k + 1 < keys.length && keys[k + 1][0] <= tS) k++;
    this.k = k;
    const a = keys[k];
    if (k + 1 < keys.length) {
      const b = keys[k + 1];
      const f = (tS - a[0]) / (b[0] - a[0]);
      return [a[1] + (b[1] - a[1]) * f, this.interpH ? a[2] + (b[2] - a[2]) * f : a[2], a[3]];
    }
    return [a[1], a[2], a[3]];
  }
}

/** mulberry32: a small seeded generator for the monitor's noise (reproducible runs). */
function rng(seed) {
  let a = seed >>> 0;
  return () => {
    a = (a + 0x6d2b79f5) >>> 0;
    let t = a;
    t = Math.imul(t ^ (t >>> 15), t | 1);
    t ^= t + Math.imul(t ^ (t >>> 7), t | 61);
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
}

class Chip {
  /** fsImage: a littlefs image for flash offset 0xa0000; flash: the whole flash of a chip
   *  that reset (serving: a hard reset keeps the flash, as on a real Pico). */
  constructor(fsImage, flash = null) {
    const b = new Board({
      uf2: path.join(emuDir, 'firmware.uf2'),
      bootrom: path.join(emuDir, 'bootrom-b1.bin'),
    });
    if (flash) b.mcu.flash.set(flash);
    else if (fsImage) b.mcu.flash.set(fs.readFileSync(fsImage), 0xa0000);
    this.b = b;
    this.mcu = b.mcu;
    this.clock = b.clock;
    this.edges = [];
    this.pulses = [];
    this.feeds = [];
    this.samples = []; // ADC conversions started: [input, ns, counts]
    this.nowNs = null; // time of the PIO step being executed (edge timestamps)
    this.wiring = null;
    this.loads = [];
    this.rise = new Map(); // gate pin -> [rise ns, i_ua]
    this.fall = new Map(); // gate pin -> [rise ns, fall ns, i_ua, load] of its last pulse (the decay after it)
    this.world = null; // a scenario's electrodes (setScenario), else the fixed loads
    this.dacCodes = []; // the code each DAC output holds (channel k: chip k >> 1, output k & 1)
    this.dacWrites = []; // [ns, channel, word] of every word latched
    this.installPio();
    this.installWatchdogLog();
    this.usb = new UsbHost(b);
  }

  // ---------------------------------------------------------------- PIO on the emulated clock
  installPio() {
    const { mcu, clock } = this;
    this.sms = [];
    for (const pio of mcu.pio) {
      pio.run = () => {}; // stepped below instead
      for (const m of pio.machines) this.sms.push({ pio, m, next: -1 });
      const write = pio.writeUint32.bind(pio);
      pio.writeUint32 = (offset, value) => {
        this.stepPio(clock.nanos);
        write(offset, value);
        this.pioNext = 0; // enables, FIFO words, restarts: find the next step again
        // an instruction the CPU executes directly (SMx_INSTR) changes pins at once
        this.nowNs = clock.nanos;
        pio.checkChangedPins();
        this.nowNs = null;
      };
    }
    this.pioNext = 0; // earliest step of a running state machine (ns); Infinity: all idle
    const tick = clock.tick.bind(clock);
    clock.tick = (ns) => {
      tick(ns);
      if (clock.nanos >= this.pioNext) this.stepPio(clock.nanos);
    };
  }

  periodNs(m) {
    const div = (m.clockDivInt === 0 ? 65536 : m.clockDivInt) + m.clockDivFrac / 256;
    return div * CYCLE_NS;
  }

  /** Run every enabled state machine up to time t, one instruction per divided clock. */
  stepPio(t) {
    const sms = this.sms;
    for (;;) {
      let best = null;
      for (const s of sms) {
        if (!s.m.enabled) {
          s.next = -1;
          continue;
        }
        if (s.next < 0) s.next = t; // just enabled: first instruction now
        const m = s.m;
        if (m.waiting && m.waitType === 3 /* txFIFO */ && m.txFIFO.empty && !m.execValid) {
          // blocked on pull with nothing to pull: skip whole cycles, keep the phase
          const p = this.periodNs(m);
          if (s.next <= t) s.next += Math.ceil((t - s.next + 1) / p) * p;
          continue;
        }
        if (s.next <= t && (!best || s.next < best.next)) best = s;
      }
      if (!best) break;
      this.nowNs = best.next;
      best.m.step();
      best.pio.checkChangedPins();
      this.nowNs = null;
      best.next += this.periodNs(best.m);
    }
    let next = Infinity;
    for (const s of sms) {
      const m = s.m;
      if (m.enabled && !(m.waiting && m.waitType === 3 && m.txFIFO.empty && !m.execValid) && s.next < next) next = s.next;
    }
    this.pioNext = next;
  }

  // ---------------------------------------------------------------- world: gate, amplitude, monitor
  setWiring(w) {
    this.wiring = w;
    if (w.dac) this.installDac(w.dac);
    for (let k = 0; k < w.gate_pins.length; k++) {
      const pin = w.gate_pins[k];
      this.mcu.gpio[pin].addListener((v) => this.onGate(k, pin, v === GPIOPinState.High));
    }
    this.mcu.adc.onADCRead = (channel) => {
      const adc = this.mcu.adc;
      this.stepPio(this.clock.nanos);
      const v = this.monitorCounts(channel, this.clock.nanos);
      adc.channelValues[channel] = v;
      this.samples.push([channel, this.clock.nanos, v]);
      adc.currentChannel = channel;
      adc.sampleAlarm.schedule(adc.sampleTime * 1000);
    };
  }

  /** MCP4822s on SPI d.spi_id, chip j selected by d.cs_pins[j] (datasheet DS20002249: a 16-bit word,
   * bit 15 output B, bit 13 gain 1x, bit 12 active, bits 11..0 the code, latched at CS's rising edge). */
  installDac(d) {
    const spi = this.mcu.spi[d.spi_id];
    this.dacCodes = new Array(2 * d.cs_pins.length).fill(0);
    let bytes = null; // bytes clocked in while a chip select is low
    let sel = -1;
    const done = this.clock.createAlarm(() => spi.completeTransmit(0));
    spi.onTransmit = (v) => {
      if (bytes) bytes.push(v & 0xff);
      const hz = spi.clockFrequency || 1e6;
      done.schedule(Math.round((spi.dataBits * 1e9) / hz)); // the frame's bits on the wire
    };
    d.cs_pins.forEach((pin, j) => this.mcu.gpio[pin].addListener((v) => {
      if (v === GPIOPinState.Low) {
        bytes = [];
        sel = j;
      } else if (v === GPIOPinState.High && sel === j && bytes) {
        if (bytes.length >= 2) { // the last 16 bits clocked in count
          const word = (bytes[bytes.length - 2] << 8) | bytes[bytes.length - 1];
          const ch = 2 * j + (word >> 15);
          this.dacCodes[ch] = word & 0x1000 ? word & 0xfff : 0; // SHDN low: output off
          this.dacWrites.push([this.clock.nanos, ch, word]);
        }
        bytes = null;
        sel = -1;
      }
    }));
  }

  /** Amplitude of channel k: its DAC code (gain 1x) or, without a DAC, the PWM duty of its amplitude pin
   * (the RC filter's steady state). */
  amplitudeUa(k) {
    const a = this.world && this.world.analog; // the realistic board: the DAC + stimulator gain of channel k
    if (this.wiring.dac) return (this.wiring.amp_full_ua * (this.dacCodes[k] ?? 0)) / 4096 * (a ? a.dac_gain[k] : 1);
    const pin = this.wiring.pwm_pins[k];
    const ch = this.mcu.pwm.channels[(pin >> 1) & 7];
    if (!(ch.csr & 1)) return 0;
    const cc = pin & 1 ? ch.cc >>> 16 : ch.cc & 0xffff;
    const top = ch.top + 1;
    return (this.wiring.amp_full_ua * Math.min(cc, top)) / top;
  }

  onGate(k, pin, high) {
    const t = this.nowNs ?? this.clock.nanos;
    this.edges.push([pin, high ? 1 : 0, t]);
    if (high) {
      this.fall.delete(k);
      this.rise.set(k, [t, this.amplitudeUa(k)]);
      if (this.world) this.electrodePulse(k, t, this.rise.get(k)[1]);
      const l = this.loads[k];
      // a load that changes every pulse; `lead`: its first load for that many pulses first (the
      // firmware's calibration takes two pulses that agree)
      if (l && l.cycle) {
        if ((l.lead ?? 0) > 0) { l.lead -= 1; l.idx = 0; }
        else l.idx = ((l.idx ?? -1) + 1) % l.cycle.length;
      }
    }
    else if (this.rise.has(k)) {
      const [t0, i] = this.rise.get(k);
      this.rise.delete(k);
      let load = this.loads[k];
      if (load && load.cycle) load = load.cycle[load.idx ?? 0];
      this.fall.set(k, [t0, t, i, load]);
      this.pulses.push({ ch: k, rise_ns: t0, fall_ns: t, i_ua: i });
    }
  }

  monitorCounts(adcInput, t) {
    const w = this.wiring;
    if (!w) return 0;
    const k = w.adc_inputs.indexOf(adcInput);
    if (k < 0) return 0;
    let uv;
    if (!this.rise.has(k)) { // after a pulse: Cp's charge at the fall decays through Rp (none before any pulse)
      const f = this.fall.get(k);
      if (!f) return 0;
      const [t0, tf, i, load] = f;
      uv = 0;
      if (load && !load.open && load.tau_us > 0) {
        const v = i * load.rp_ohm * (1 - Math.exp(-(tf - t0) / 1000 / load.tau_us));
        uv = Math.min(v, w.compliance_mv * 1000) * Math.exp(-(t - tf) / 1000 / load.tau_us);
      }
    }
    else {
      let load = this.loads[k];
      if (load && load.cycle) load = load.cycle[load.idx ?? 0];
      const [t0, i] = this.rise.get(k);
      if (!load || load.open) uv = w.compliance_mv * 1000; // no electrode: the stimulator sits at compliance
      else {
        const us = (t - t0) / 1000;
        const charge = load.tau_us > 0 ? 1 - Math.exp(-us / load.tau_us) : 1;
        uv = i * (load.rs_ohm + load.rp_ohm * charge);
        uv = Math.min(uv, w.compliance_mv * 1000);
      }
    }
    const a = this.world && this.world.analog; // the realistic board (board_sim.AnalogPath's errors)
    let counts = uv / w.uv_per_count;
    if (a) counts = counts * a.mon_gain[k] + a.mon_off_counts[k];
    if (this.world && this.world.noise) {
      const r = this.world.random;
      counts += (r() + r() + r() - 1.5) * 2 * this.world.noise; // board_sim's noise, seeded
    }
    let c = Math.max(0, Math.min(4095, Math.round(counts)));
    if (a) { // erratum RP2040-E11: a code within dnl_width/2 of 512, 1536, 2560, 3584 reads as that code
      const h = Math.floor(a.dnl_width / 2);
      for (const s of a.dnl_codes) if (Math.abs(c - s) <= h) c = s;
    }
    return c;
  }

  /** Electrodes that follow a scenario (emu://): spec = {keys, interp_h, electrode, noise_counts, seed}. */
  setScenario(spec) {
    const n = this.wiring.gate_pins.length;
    this.world = {
      scenario: new Scenario(spec),
      electrodes: Array.from({ length: n }, () => new Electrode(spec.electrode)),
      t0: this.clock.nanos, // scenario time 0: now
      last: this.clock.nanos,
      noise: spec.noise_counts,
      random: rng(spec.seed),
      load_ohm: spec.load_ohm || 0,
      analog: spec.analog || null, // {dac_gain, mon_gain, mon_off_counts, dnl_codes, dnl_width} or null (ideal)
    };
  }

  /** The scenario at emulated time t (ns): contact and hydration of every electrode. */
  advanceScenario(t) {
    const w = this.world;
    const dtS = (t - w.last) / 1e9;
    if (dtS <= 0) return;
    w.last = t;
    const [contact, hT, tauS] = w.scenario.at((t - w.t0) / 1e9);
    for (const e of w.electrodes) {
      e.contact = contact;
      e.stepHydration(hT, tauS, dtS);
    }
  }

  /** A pulse starts on channel k: the electrode's Rp and tau for it become the channel's load. */
  electrodePulse(k, t, iUa) {
    if (this.world.load_ohm) { // a resistor in place of the electrodes (emu://...?load=OHM, the self-test)
      this.loads[k] = { rs_ohm: this.world.load_ohm, rp_ohm: 0, tau_us: 0 };
      return;
    }
    this.advanceScenario(t);
    const e = this.world.electrodes[k];
    if (e.pulse(iUa)) this.loads[k] = { rs_ohm: e.rs * 1000, rp_ohm: e.rp_skin * 1000, tau_us: e.tau };
    else this.loads[k] = { open: true }; // off (or no current): the stimulator runs into compliance
  }

  installWatchdogLog() {
    const write = this.mcu.writeUint32.bind(this.mcu);
    this.mcu.writeUint32 = (addr, value) => {
      if (addr >>> 0 === WATCHDOG_LOAD) this.feeds.push(this.clock.nanos);
      write(addr, value);
    };
  }
}

// -------------------------------------------------------------------- protocol
let chip = null;
const out = (o) => process.stdout.write(JSON.stringify(o) + '\n');

function handle(msg) {
  const op = msg.op;
  if (op === 'serve') {
    serveMode(msg); // replies once both ports listen
    return null;
  }
  if (op === 'boot') {
    chip = new Chip(msg.fs_image || null);
    const banner = chip.b.boot();
    chip.b.enterRaw();
    return { banner: banner.trim().split(/\r?\n/).pop(), nanos: chip.clock.nanos };
  }
  if (!chip) throw new Error('boot first');
  const b = chip.b;
  switch (op) {
    case 'exec': {
      const t0 = chip.clock.nanos;
      const w0 = Date.now();
      const { out: o, err } = b.exec(msg.code, (msg.timeout_ms ?? 600000) * 1e6);
      return { out: o.replace(/\r\n/g, '\n'), err: err.replace(/\r\n/g, '\n'), t0, t1: chip.clock.nanos,
        wall_ms: Date.now() - w0 };
    }
    case 'put':
      b.put(Buffer.from(msg.data, 'base64'), msg.path);
      return { nanos: chip.clock.nanos };
    case 'save_fs':
      fs.writeFileSync(msg.file, b.fsBytes());
      return {};
    case 'wiring':
      chip.setWiring(msg.wiring);
      return {};
    case 'load':
      chip.loads[msg.ch] = msg.load;
      return {};
    case 'take': {
      // edges, pulses and watchdog feeds recorded so far (and forget them)
      const r = { edges: chip.edges, pulses: chip.pulses, feeds: chip.feeds, samples: chip.samples, nanos: chip.clock.nanos,
        gate: chip.wiring ? chip.wiring.gate_pins.map((p) => chip.mcu.gpio[p].value === GPIOPinState.High ? 1 : 0) : [],
        dac_writes: chip.dacWrites, dac_codes: chip.dacCodes };
      chip.dacWrites = [];
      chip.edges = [];
      chip.pulses = [];
      chip.feeds = [];
      chip.samples = [];
      return r;
    }
    case 'run':
      b.run(msg.ms * 1e6);
      return { nanos: chip.clock.nanos };
    case 'debug': {
      if (msg.ms) b.run(msg.ms * 1e6);
      const c = b.cdc;
      return { rx: b.rxText(), pending: b.pending.length, held: b.heldRead, fifo: c.txFIFO.itemCount,
        cdc: { initialized: c.initialized, in: c.inEndpoint, out: c.outEndpoint }, outReads: b.outReads,
        pc: b.core.PC.toString(16), waiting: b.core.waiting, cycles: b.core.cycles, ipsr: b.core.IPSR };
    }
    case 'hid':
      return chip.usb.take(msg);
    case 'stream':
      // the electrodes follow the scenario; `code` (e.g. `import main`) is started in
      // the raw REPL and not waited for; then streamMode() takes over stdin and stdout
      if (msg.scenario) chip.setScenario(msg.scenario);
      b.write(Buffer.from(msg.code, 'utf8'));
      b.write('\x04');
      b.expect('OK', 5e9);
      streaming = true;
      return { nanos: chip.clock.nanos };
    default:
      throw new Error(`unknown op ${op}`);
  }
}

// -------------------------------------------------------------------- streaming (emu://)
// The board runs continuously, paced by the wall clock in slices of at most SLICE_MS
// of wall time, between which stdin is serviced (the way ../shared/emulator/rp2tcp.mjs
// paces its board). Emulated time never runs ahead of wall time: a busy board falls
// behind (~0.4x) and the lag is forgotten beyond MAX_LAG_NS, so an idle board (WFI,
// skipped by the emulator) cannot fast-forward to catch up. That is what keeps the
// device's keep-alive safe: it counts emulated time, the host's keep-alive is sent on
// wall time, so the device sees the host at least as often as the host writes.
const SLICE_MS = 20;
const MAX_LAG_NS = 100e6;
let streaming = false;
let stopped = false;
const say = (s) => process.stderr.write(`[emu] ${s}\n`);

/** Run the board to emulated time untilNs or for budgetMs of wall time, whichever first. */
function advance(b, untilNs, budgetMs) {
  const { core, clock } = b;
  const fifo = b.cdc.txFIFO;
  const w0 = performance.now();
  while (clock.nanos < untilNs && !b.resetReason && performance.now() - w0 < budgetMs) {
    while (b.pending.length && !fifo.full) fifo.push(b.pending.shift());
    if (b.heldRead && !fifo.empty) {
      const { endpoint, size } = b.heldRead;
      b.heldRead = null;
      b.deliverRead(endpoint, size);
    }
    for (let i = 0; i < 4000 && clock.nanos < untilNs && !b.resetReason; i++) {
      if (core.waiting) {
        const n = clock.nanosToNextAlarm;
        clock.tick(Math.min(n > 0 ? n : 1000, untilNs - clock.nanos)); // idle jumps stop at the target
      } else {
        clock.tick(core.executeInstruction() * CYCLE_NS);
      }
    }
  }
}

function streamMode() {
  const b = chip.b;
  let target = b.nanos; // emulated ns the board may reach
  let lastWall = performance.now();
  let boardLine = ''; // what the board printed on its serial port, line by line to stderr
  let lastBoardLine = '';
  chip.usb.onReport = (hex) => process.stdout.write(hex + '\n');
  for (const [, hex] of chip.usb.reports) process.stdout.write(hex + '\n');
  chip.usb.reports = [];
  const end = (code, why) => {
    if (stopped) return;
    stopped = true;
    say(why);
    process.exit(code);
  };
  const serial = () => {
    if (!b.rx.length) return false;
    const text = Buffer.from(b.rx).toString('latin1');
    b.rx = [];
    for (const ch of text) {
      if (ch === '\x04') return true; // the raw REPL's end of output: the firmware's loop returned
      if (ch === '\n') {
        const line = boardLine.replace(/\r$/, '');
        if (line.trim()) {
          process.stderr.write(`[board] ${line}\n`);
          lastBoardLine = line.trim();
        }
        boardLine = '';
      } else boardLine += ch;
    }
    return false;
  };
  const step = () => {
    if (stopped) return;
    const now = performance.now();
    target += (now - lastWall) * 1e6;
    lastWall = now;
    if (target - b.nanos > MAX_LAG_NS) target = b.nanos + MAX_LAG_NS;
    try {
      advance(b, target, SLICE_MS);
    } catch (e) {
      return end(3, `emulator error: ${e.stack || e}`);
    }
    chip.usb.pump();
    if (b.resetReason) {
      serial();
      return end(3, `the board reset (${b.resetReason}) at ${(b.resetNanos / 1e9).toFixed(3)} s emulated` +
        (lastBoardLine ? `; it printed: ${lastBoardLine}` : ''));
    }
    if (serial()) {
      if (boardLine.trim()) lastBoardLine = boardLine.trim();
      return end(4, `the firmware's loop ended at ${(b.nanos / 1e9).toFixed(3)} s emulated` +
        (lastBoardLine ? `: ${lastBoardLine}` : ''));
    }
    if (b.nanos < target) setImmediate(step);
    else setTimeout(step, 1);
  };
  say(`streaming: the firmware's loop runs, paced by the wall clock (${(b.nanos / 1e9).toFixed(3)} s emulated)`);
  step();
}

function onReportLine(line) {
  const hex = line.trim();
  if (!hex) return;
  if (!/^[0-9a-fA-F]{128}$/.test(hex)) {
    say(`not a 64-byte report in hex, ignored: ${hex.slice(0, 40)}`);
    return;
  }
  chip.usb.outQueue.push(Uint8Array.from(Buffer.from(hex, 'hex')));
  chip.usb.pump();
}

// -------------------------------------------------------------------- serving (flash end to end)
// The board boots from its flash as at power-up (main.py runs) and runs paced by the wall
// clock like streamMode, while two TCP servers on 127.0.0.1 play its USB cable:
//   - the serial port: the CDC byte stream both ways (pyserial's socket:// URL), as
//     ../shared/emulator/rp2tcp.mjs serves it;
//   - the HID interface: on connect one line, `HID VVVV:PPPP` (the device descriptor's
//     ids) when the board's HID interface is enumerated, else `NOHID why` and the
//     connection closes (a host that finds no such device); then each line the client
//     sends is one OUT report in hex, each IN report the board sends one line back.
// One client per port at a time (a new one replaces the old). A hard reset (machine.reset(),
// a watchdog timeout) or a USB re-connect drops the clients, as unplugging a cable would,
// and a hard reset reboots a fresh chip with the whole flash kept. Progress goes to stderr
// (`hard reset, REASON`, `emulated host: enumerating again`, HID client report counts).
const PENDING_HIGH = 64 * 1024; // pause the serial client while this many bytes wait for the board
let serving = false;
let atExit = null;
const hex4 = (v) => v.toString(16).padStart(4, '0');

function serveMode(msg) {
  serving = true;
  let c = new Chip(msg.fs_image || null);
  let serial = null; // the serial client's socket
  let hid = null; // the HID client: {sock, in, out, buf}
  const w0 = Date.now();
  const log = (s) => process.stderr.write(`[emu] ${s} (${((Date.now() - w0) / 1000).toFixed(1)} s wall, ` +
    `${(c.b.nanos / 1e9).toFixed(2)} s emulated)\n`);
  const dropHid = (why) => {
    if (!hid) return;
    log(`HID client disconnected (${why}) after ${hid.out} OUT and ${hid.in} IN reports`);
    const s = hid.sock;
    hid = null;
    s.destroy();
  };
  const attach = (chip) => {
    const b = chip.b;
    b.cdc.onSerialData = (buf) => {
      if (serial) serial.write(Buffer.from(buf));
    };
    const connected = b.cdc.onDeviceConnected;
    b.cdc.onDeviceConnected = () => {
      connected();
      log('USB CDC enumerated by the emulated host');
    };
    chip.usb.onLog = (s) => {
      if (s.startsWith('emulated host')) dropHid('the board re-connected USB');
      log(s);
    };
    chip.usb.onReport = (hex) => {
      if (!hid) return; // nobody reads the interface: the report is gone, as on a real host
      hid.in++;
      hid.sock.write(hex + '\n');
    };
  };
  attach(c);
  const hidReady = () => {
    const u = c.usb;
    if (!u.hid || !c.b.cdc.initialized) return 'the board has no HID interface (yet)';
    if (!u.ids && c.b.nanos < u.hidAt + 100e6) return 'the board is still enumerating';
    return null;
  };

  const serialServer = net.createServer((sock) => {
    if (serial) {
      log('new serial client replaces the old one');
      serial.destroy();
    }
    serial = sock;
    sock.setNoDelay(true);
    log('serial client connected');
    sock.on('data', (d) => {
      if (sock !== serial) return;
      c.b.write(d);
      if (c.b.pending.length > PENDING_HIGH) sock.pause();
    });
    sock.on('error', () => {});
    sock.on('close', () => {
      if (sock === serial) {
        serial = null;
        log('serial client disconnected');
      }
    });
  });

  const hidServer = net.createServer((sock) => {
    sock.setNoDelay(true);
    sock.on('error', () => {});
    const why = hidReady();
    if (why) {
      sock.end(`NOHID ${why}\n`);
      return;
    }
    if (hid) dropHid('a new HID client replaces it');
    const me = { sock, in: 0, out: 0, buf: '' };
    hid = me;
    c.usb.outQueue = [];
    const ids = c.usb.ids ? `${hex4(c.usb.ids.vid)}:${hex4(c.usb.ids.pid)}` : '????:????';
    sock.write(`HID ${ids}\n`);
    log(`HID client connected (device ${ids})`);
    sock.on('data', (d) => {
      if (hid !== me) return;
      me.buf += d.toString('latin1');
      for (let k = me.buf.indexOf('\n'); k >= 0; k = me.buf.indexOf('\n')) {
        const line = me.buf.slice(0, k).trim();
        me.buf = me.buf.slice(k + 1);
        if (!line) continue;
        if (!/^[0-9a-fA-F]{128}$/.test(line)) {
          log(`HID client sent a line that is not a 64-byte report in hex, ignored: ${line.slice(0, 40)}`);
          continue;
        }
        me.out++;
        c.usb.outQueue.push(Uint8Array.from(Buffer.from(line, 'hex')));
        c.usb.pump();
      }
    });
    sock.on('close', () => {
      if (hid === me) {
        hid = null;
        log(`HID client disconnected after ${me.out} OUT and ${me.in} IN reports`);
      }
    });
  });

  atExit = () => {
    if (msg.save_fs) fs.writeFileSync(msg.save_fs, c.b.fsBytes());
  };
  const finish = (code) => {
    if (stopped) return;
    stopped = true;
    atExit();
    process.exit(code);
  };
  if (msg.seconds) setTimeout(() => {
    log(`served ${msg.seconds} s: exit`);
    finish(0);
  }, msg.seconds * 1000).unref();

  let target = 0;
  let lastWall = performance.now();
  const step = () => {
    if (stopped) return;
    const now = performance.now();
    target += (now - lastWall) * 1e6;
    lastWall = now;
    if (target - c.b.nanos > MAX_LAG_NS) target = c.b.nanos + MAX_LAG_NS;
    try {
      advance(c.b, target, SLICE_MS);
    } catch (e) {
      log(`emulator error: ${e.stack || e}`);
      return finish(3);
    }
    const u = c.usb;
    u.pump();
    if (u.hid && u.ids === null && !u.ep0 && c.b.cdc.initialized && c.b.nanos > u.hidAt + 5e6) {
      u.ids = false; // asked
      u.askIds((ids) => {
        u.ids = ids;
        log(`device descriptor: ${hex4(ids.vid)}:${hex4(ids.pid)}`);
      });
    }
    if (c.b.resetReason) {
      const why = c.b.resetReason.replace('forced reset', 'forced');
      log(`hard reset, ${why}: rebooting the emulated chip, flash kept`);
      const flash = c.b.mcu.flash.slice();
      c = new Chip(null, flash);
      attach(c);
      target = 0;
      if (serial) {
        serial.destroy();
        serial = null;
        log('serial client disconnected (the board left the USB bus)');
      }
      dropHid('the board reset');
    }
    if (serial && serial.isPaused() && c.b.pending.length < PENDING_HIGH / 4) serial.resume();
    if (c.b.nanos < target) setImmediate(step);
    else setTimeout(step, 1);
  };

  let listening = 0;
  const ready = () => {
    if (++listening < 2) return;
    out({ ok: true, cdc_port: serialServer.address().port, hid_port: hidServer.address().port });
    log(`serving: booting MicroPython from flash${msg.fs_image ? ` with filesystem ${msg.fs_image}` : ''}`);
    step();
  };
  serialServer.listen(msg.cdc_port || 0, '127.0.0.1', ready);
  hidServer.listen(msg.hid_port || 0, '127.0.0.1', ready);
}

const rl = readline.createInterface({ input: process.stdin, terminal: false });
rl.on('line', (line) => {
  if (streaming) return onReportLine(line);
  if (serving) return; // stdin only tells when the host is gone (EOF)
  if (!line.trim()) return;
  let msg;
  try {
    msg = JSON.parse(line);
    const r = handle(msg);
    if (r) out({ ok: true, ...r });
    if (streaming) streamMode();
  } catch (e) {
    if (e instanceof BoardReset) out({ ok: false, reset: e.reason, reset_ns: e.nanos, nanos: chip.clock.nanos,
      feeds: chip.feeds, rx: chip.b.rxText().slice(-2000) });
    else out({ ok: false, error: String(e.stack || e), rx: chip ? chip.b.rxText().slice(-2000) : '' });
  }
});
rl.on('close', () => {
  stopped = true;
  if (atExit) atExit();
  process.exit(0); // the host is gone (stdin EOF): stop the board with it
});
