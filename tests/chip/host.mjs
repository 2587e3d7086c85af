// The chip tests' host: boots the real MicroPython firmware on the emulated
// RP2040 (rp2040js, through ../shared/emulator/rp2run.mjs used in place), and
// plays the world around the board:
//   - steps the PIO state machines on the emulated clock at their clock
//     dividers (rp2040js 1.4.1 runs PIO on setTimeout, 1000 steps a macrotask,
//     with no divider and no relation to emulated time), and records every
//     edge of the gate pins in emulated nanoseconds;
//   - feeds the ADC per sample with the electrode's monitor voltage while the
//     gate is high: V = I (Rs + Rp (1 - e^(-t/tau))), firmware/sim_electrode.py's
//     model, I from the PWM duty the board set, clamped at compliance;
//   - records watchdog feeds and turns a watchdog reset into a reply;
//   - is the USB host: CDC for the raw REPL, and the board's HID interface
//     (enumerated again when the board re-connects with it), whose 64-byte IN
//     reports it collects.
// Protocol: one JSON object a line on stdin, one JSON reply a line on stdout
// (tests/chip/chip.py is the Python side). Usage:
//   node host.mjs EMULATOR_DIR CACHE_DIR
import fs from 'node:fs';
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

class Chip {
  constructor(fsImage) {
    const b = new Board({
      uf2: path.join(emuDir, 'firmware.uf2'),
      bootrom: path.join(emuDir, 'bootrom-b1.bin'),
    });
    if (fsImage) b.mcu.flash.set(fs.readFileSync(fsImage), 0xa0000);
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

  /** Amplitude set by the PWM duty of channel k's amplitude pin (the RC filter's steady state). */
  amplitudeUa(k) {
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
      this.rise.set(k, [t, this.amplitudeUa(k)]);
      const l = this.loads[k];
      if (l && l.cycle) l.idx = ((l.idx ?? -1) + 1) % l.cycle.length; // a load that changes every pulse
    }
    else if (this.rise.has(k)) {
      const [t0, i] = this.rise.get(k);
      this.rise.delete(k);
      this.pulses.push({ ch: k, rise_ns: t0, fall_ns: t, i_ua: i });
    }
  }

  monitorCounts(adcInput, t) {
    const w = this.wiring;
    if (!w) return 0;
    const k = w.adc_inputs.indexOf(adcInput);
    if (k < 0 || !this.rise.has(k)) return 0;
    let load = this.loads[k];
    if (load && load.cycle) load = load.cycle[load.idx ?? 0];
    const [t0, i] = this.rise.get(k);
    let uv;
    if (!load || load.open) uv = w.compliance_mv * 1000; // no electrode: the stimulator sits at compliance
    else {
      const us = (t - t0) / 1000;
      const charge = load.tau_us > 0 ? 1 - Math.exp(-us / load.tau_us) : 1;
      uv = i * (load.rs_ohm + load.rp_ohm * charge);
      uv = Math.min(uv, w.compliance_mv * 1000);
    }
    return Math.max(0, Math.min(4095, Math.round(uv / w.uv_per_count)));
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
        gate: chip.wiring ? chip.wiring.gate_pins.map((p) => chip.mcu.gpio[p].value === GPIOPinState.High ? 1 : 0) : [] };
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
    default:
      throw new Error(`unknown op ${op}`);
  }
}

const rl = readline.createInterface({ input: process.stdin, terminal: false });
rl.on('line', (line) => {
  if (!line.trim()) return;
  let msg;
  try {
    msg = JSON.parse(line);
    out({ ok: true, ...handle(msg) });
  } catch (e) {
    if (e instanceof BoardReset) out({ ok: false, reset: e.reason, reset_ns: e.nanos, nanos: chip.clock.nanos,
      feeds: chip.feeds, rx: chip.b.rxText().slice(-2000) });
    else out({ ok: false, error: String(e.stack || e), rx: chip ? chip.b.rxText().slice(-2000) : '' });
  }
});
rl.on('close', () => process.exit(0));
