"""USB HID on the emulated chip: the real Board brings up usb_hid64 on
micropython-lib's usb-device-hid (board-lib, as mip installs it), the emulated host
(host/emu/usbhost.mjs) enumerates the board again, finds the HID interface with
its 64-byte interrupt IN and OUT endpoints, reads the report descriptor, drives a
run with commands sent as OUT reports, and the host's protocol decoder
(host/protocol.py) reads the telemetry of that run from the IN reports."""

import math

import hid_protocol as hp
import sensation_core as sc
from steadytouch.protocol import Ack, Commands, Telemetry, decode

from .harness import make_board

LOOP = """
s = stim.Stimulator(b, board_rp2.Clock(), cfg, {n}, 50)
s.run({frames})
print(([(c.ch, c.di, c.dt, c.rp) for c in s.chans], b.usb.dropped))
"""


def test_the_host_enumerates_the_hid_interface_and_reads_its_descriptor(chip, cfg):
    make_board(chip, cfg, usb=True)
    h = chip.hid(report_descriptor=len(hp.REPORT_DESCRIPTOR), device_descriptor=True)
    dev = bytes.fromhex(h["device_descriptor"])
    assert dev[1] == 1 and int.from_bytes(dev[8:10], "little") == hp.VID and int.from_bytes(dev[10:12], "little") == hp.PID
    assert h["enumerations"] == 2  # CDC at boot, then CDC + HID after usb.device init
    assert h["hid"]["in_size"] == hp.REPORT_LEN and h["hid"]["out_size"] == hp.REPORT_LEN
    assert h["hid"]["in"] == h["hid"]["out"] > 0 and h["hid"]["interval"] == 1
    assert bytes.fromhex(h["report_descriptor"]) == bytes(hp.REPORT_DESCRIPTOR)
    assert chip.eval("1 + 1") == 2  # the REPL (CDC) still works beside it


def test_a_run_driven_over_hid_out_and_read_by_the_host_decoder(chip, cfg):
    make_board(chip, cfg, usb=True)
    chip.load(0, rp_ohm=10000)
    chip.load(1, rs_ohm=470, rp_ohm=4700)
    chip.hid()
    cmd = Commands()
    sent = [cmd.set_mode(sc.MODE_AKHTAR), cmd.calibrate(1000, 1000, -1670, 186000), cmd.arm()]
    chip.hid(send=sent)
    frames = 12
    rows = chip.eval_out(LOOP.format(n=2, frames=frames))
    reps = [decode(bytes.fromhex(x)) for _t, x in chip.hid()["reports"]]
    acks = [r for r in reps if isinstance(r, Ack)]
    tel = [r for r in reps if isinstance(r, Telemetry)]
    assert [(a.command, a.result, a.tag) for a in acks] == [(r[hp.O_OUT_CMD], hp.RES_OK, r[hp.O_OUT_TAG]) for r in sent]
    assert len(tel) == 2 * frames and [t.seq for t in tel] == sorted(t.seq for t in tel)
    pulses = chip.take()["pulses"]
    last = {t.channel: t for t in tel}
    fired = [t for t in tel if t.i_ua]
    assert len(fired) == len(pulses) >= 2 * (frames - 2)  # commands land in the first frames
    for t, p in zip(fired, pulses):
        assert (t.channel, t.t_us * 1000) == (p["ch"], p["fall_ns"] - p["rise_ns"])  # the width the gate had
        assert t.i_ua == math.ceil(p["i_ua"])  # (rounded up) the telemetry carries the current the DAC set (delivered)
        assert t.stop == hp.STOP_NONE and t.flags & hp.FLAG_ARMED
    # the decoder's Rp is the firmware's: the last frame's channel state read over the REPL
    chans, dropped = rows
    assert dropped == 0
    assert [(c, last[c].i_ua, last[c].t_us, last[c].rp_ohm) for c in (0, 1)] == [tuple(c) for c in chans]
    assert abs(last[0].rp_ohm - 10000) < 150 and abs(last[1].rp_ohm - 5170) < 100
