// The emulated USB host of the chip tests, on top of rp2run.mjs's CDC host (the raw
// REPL). rp2040js's USBCDC enumerates once and knows only a CDC data interface; this
// adds what the board's HID interface (board_rp2 + usb_hid64 + usb-device-hid) needs:
//   - re-enumeration when the board re-connects (pull-up off, then on), which
//     usb.device's init() does to add the HID interface: bus reset, address,
//     configuration descriptor, set configuration, as on a real host;
//   - the configuration descriptor parsed for the HID interface (class 3) and its
//     interrupt IN and OUT endpoints;
//   - GET_DESCRIPTOR(Report) on the control pipe;
//   - every IN report the board sends on the HID IN endpoint, timestamped in
//     emulated ns (rp2040js delivers IN buffers to the host 10 us after the board
//     arms them, so an interrupt IN endpoint is read as fast as the board writes);
//   - OUT reports queued by the test, handed over when the board arms its OUT buffer.
const SIE_CTRL_PULLUP_EN = 1 << 16;
const DESC_INTERFACE = 4;
const DESC_ENDPOINT = 5;
const HID_CLASS = 3;

export function parseHid(desc) {
  let itf = null;
  for (let i = 0; i + 1 < desc.length && desc[i] >= 2; i += desc[i]) {
    const len = desc[i];
    const type = desc[i + 1];
    if (type === DESC_INTERFACE && len === 9) {
      if (itf) break;
      if (desc[i + 5] === HID_CLASS) itf = { number: desc[i + 2], n_eps: desc[i + 4], in: -1, out: -1, in_size: 0,
        out_size: 0, interval: 0 };
    } else if (itf && type === DESC_ENDPOINT && len === 7 && (desc[i + 3] & 3) === 3) {
      const addr = desc[i + 2];
      const size = desc[i + 4] | (desc[i + 5] << 8);
      if (addr & 0x80) Object.assign(itf, { in: addr & 0xf, in_size: size, interval: desc[i + 6] });
      else Object.assign(itf, { out: addr & 0xf, out_size: size });
    }
  }
  return itf;
}

export class UsbHost {
  constructor(board) {
    this.b = board;
    const usb = board.mcu.usbCtrl;
    const cdc = board.cdc;
    const clock = board.clock;
    this.usb = usb;
    this.reports = []; // [ns, hex] IN reports from the HID interface
    this.hid = null;
    this.config = null;
    this.enumerations = 0;
    this.outQueue = [];
    this.heldOut = null;
    this.ep0 = null; // pending control-IN request: collects EP0 data
    this.sent = 0;
    this.onReport = null; // streaming: called with each IN report (hex) instead of collecting it
    this.ids = null; // {vid, pid} of the device descriptor once asked for (askIds)
    this.hidAt = 0; // emulated ns the HID interface was last enumerated
    this.onLog = null; // serving: told of re-enumerations and of the HID interface appearing

    const cdcWrite = usb.onEndpointWrite;
    usb.onEndpointWrite = (ep, buf) => {
      if (this.hid && ep === this.hid.in && ep !== 0) {
        const hex = Buffer.from(buf).toString('hex');
        if (this.onReport) this.onReport(hex);
        else this.reports.push([clock.nanos, hex]);
        return;
      }
      if (ep === 0 && this.ep0) {
        this.ep0.data.push(...buf);
        const r = this.ep0;
        if (r.done && r.data.length >= r.length) {
          this.ep0 = null;
          r.done(r.data.slice(0, r.length));
        }
        return;
      }
      const complete = () => cdc.descriptorsSize !== null && cdc.descriptors.length === cdc.descriptorsSize;
      const before = complete();
      cdcWrite(ep, buf);
      if (!before && complete()) {
        this.config = [...cdc.descriptors];
        this.hid = parseHid(this.config);
        this.enumerations++;
        this.hidAt = clock.nanos;
        this.ids = null;
        if (this.onLog && this.hid) this.onLog(`HID interface ${this.hid.number} enumerated (IN ep ${this.hid.in}, ` +
          `OUT ep ${this.hid.out}, ${this.hid.in_size} bytes)`);
      }
    };

    const prevRead = usb.onEndpointRead;
    usb.onEndpointRead = (ep, size) => {
      if (this.hid && ep === this.hid.out && ep !== 0) {
        this.heldOut = { ep, size };
        this.pump();
        return;
      }
      prevRead(ep, size);
    };

    // usb.device's init() drops the pull-up and raises it again with the new configuration
    const sieWrite = usb.handleSieCtrlWrite.bind(usb);
    let pullup = false;
    usb.handleSieCtrlWrite = (value) => {
      sieWrite(value);
      const up = !!(value & SIE_CTRL_PULLUP_EN);
      if (up === pullup) return;
      pullup = up;
      if (process.env.CHIP_USB_DEBUG) console.error(`[usb] pull-up ${up} at ${clock.nanos} cdc.initialized=${cdc.initialized}`);
      if (up && cdc.initialized) {
        Object.assign(cdc, { initialized: false, descriptorsSize: null, descriptors: [], inEndpoint: -1,
          outEndpoint: -1 });
        board.heldRead = null;
        this.hid = null;
        this.ids = null;
        this.ep0 = null;
        this.heldOut = null;
        usb.resetDevice();
        if (this.onLog) this.onLog('emulated host: enumerating again');
      }
    };
  }

  pump() {
    if (this.heldOut && this.outQueue.length) {
      const { ep } = this.heldOut;
      this.heldOut = null;
      this.usb.endpointReadDone(ep, this.outQueue.shift());
      this.sent++;
    }
  }

  /** The device descriptor's idVendor and idProduct, asked for without running the board
   *  (serving): done({vid, pid}) once the board answered on the control pipe. */
  askIds(done) {
    this.ep0 = { data: [], length: 18, done: (d) => done({ vid: d[8] | (d[9] << 8), pid: d[10] | (d[11] << 8) }) };
    this.usb.sendSetupPacket(new Uint8Array([0x80, 6, 0, 1, 0, 0, 18, 0]));
  }

  /** A standard GET_DESCRIPTOR on the control pipe (to the device, or to interface `itf`); its bytes. */
  getDescriptor(type, length, { itf = null, index = 0 } = {}) {
    const w = itf === null ? 0 : itf;
    const setup = new Uint8Array([itf === null ? 0x80 : 0x81, 6, index, type, w & 0xff, w >> 8, length & 0xff,
      length >> 8]);
    this.ep0 = { data: [] };
    this.usb.sendSetupPacket(setup);
    const ok = this.b.runUntil(() => this.ep0.data.length >= length, 1e9);
    const data = this.ep0.data;
    this.ep0 = null;
    if (!ok) throw new Error(`GET_DESCRIPTOR(0x${type.toString(16)}) on interface ${itf}: no answer`);
    return data;
  }

  take(msg) {
    if (msg.send) for (const hex of msg.send) this.outQueue.push(Uint8Array.from(Buffer.from(hex, 'hex')));
    this.pump();
    let reportDescriptor = null;
    if (msg.report_descriptor && this.hid) reportDescriptor = Buffer.from(this.getDescriptor(0x22,
      msg.report_descriptor, { itf: this.hid.number })).toString('hex');
    const device = msg.device_descriptor ? Buffer.from(this.getDescriptor(1, 18)).toString('hex') : null;
    const r = { reports: this.reports, hid: this.hid, enumerations: this.enumerations, sent: this.sent,
      queued: this.outQueue.length, config: this.config ? Buffer.from(this.config).toString('hex') : null,
      report_descriptor: reportDescriptor, device_descriptor: device, nanos: this.b.clock.nanos };
    this.reports = [];
    return r;
  }
}
