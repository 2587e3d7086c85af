"""The amplitude DAC driver (firmware/dac_mcp4822.py) off the chip, and the
delivered current as the truth in the firmware (stim.py) and the host's audit.

- The driver's code math against the MCP4822's transfer function, exhaustively
  over the current range; its words against the datasheet's register layout;
  the bytes and chip-select order it drives on an injected bus; no allocation in
  the MicroPython VM under the heap lock.
- In the VM, a board whose output stage quantizes like the DAC: the firmware
  fires what the board said it would deliver, computes Rp from it, reports it in
  telemetry, and `audit` replays the recording with no mismatch (and does find
  mismatches if the recording carried the commanded current instead).
- The firmware's last check: a board that did not set the output for this pulse
  gets no pulse; one that would deliver beyond the hard limits is latched.
(The chip side: tests/chip/test_chip_dac.py.)"""

from __future__ import annotations

import importlib.util
import math
import subprocess
import textwrap

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hid_protocol as hp
import sensation_core as sc
from steadytouch.audit import audit
from steadytouch.protocol import Telemetry

from conftest import FIRMWARE
from fw_harness import run_fw

_spec = importlib.util.spec_from_file_location("dac_mcp4822", FIRMWARE / "dac_mcp4822.py")
dac = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(dac)

FULL = 10000  # board_config.AMP_UA_AT_FULL
LSB = FULL / 4096


class Bus:
    """An injected SPI bus and chip-select pins that log what the driver does."""

    def __init__(self):
        self.log = []

    def write(self, buf):
        self.log.append(("spi", bytes(buf)))

    def pin(self, name):
        bus = self

        class Pin:
            def __call__(self, v):
                bus.log.append((name, v))

        return Pin()


def make(n=4, full=FULL):
    bus = Bus()
    d = dac.MCP4822(bus, [bus.pin("cs0"), bus.pin("cs1")], n, full)
    bus.log.clear()
    return d, bus


def test_code_math_is_the_transfer_function_never_above_the_command():
    assert FULL / 4096 <= 2.5  # the resolution: <= 2.5 uA a step at 10 mA full scale
    last = 0
    for i in range(-3, FULL + 50):
        code = dac.code_for(i, FULL)
        assert 0 <= code <= 4095 and code >= last  # monotonic, in range
        last = code
        exact = code * FULL / 4096  # MCP4822, gain 1x: Vout = 2.048 V * code / 4096
        assert exact <= max(i, 0)  # never more than asked
        if 0 < i < FULL:
            assert i - exact < LSB  # short of it by under one step
        assert dac.ua_for(code, FULL) == math.ceil(exact) <= max(i, 0)  # rounded up: never below it
    assert dac.code_for(FULL, FULL) == dac.code_for(10**6, FULL) == 4095
    assert dac.ua_for(4095, FULL) == 9998
    # the largest intermediate stays a small int on the rp2 (31-bit)
    assert 4096 * dac.FULL_UA_MAX < 2**30 and 4095 * dac.FULL_UA_MAX + 4095 < 2**30


@settings(max_examples=400, deadline=None)
@given(full=st.integers(1, dac.FULL_UA_MAX), ppm=st.integers(dac.GAIN_PPM_MIN, dac.GAIN_PPM_MAX),
       code=st.integers(0, 4095))
def test_the_reported_current_is_never_below_what_the_stored_gain_drives(full, ppm, code):
    """The firmware is told ua_for(code, full_for(full, ppm)); the output drives code x full x g / 4096
    for its true gain g. Both rounded up, so what it is told is never below what a gain of ppm
    drives: the hard limits held on the reported current (stim._dac_limits, x stored gain / 1.035)
    then hold the physical one for any true gain up to 1.035. (Rounded to the nearest uA, a
    2097 uA full scale with 1.035 stored and true delivered 2097.27 uA against a 2097 uA hard limit.)"""
    f = dac.full_for(full, ppm)
    assert f * 10**6 >= full * ppm and f - full * ppm / 1e6 < 1 + full * 1e-5
    got = dac.ua_for(code, f)
    assert got * 4096 * 10**6 >= code * full * ppm  # exact integers: never below
    assert got - code * f / 4096 < 1
    assert abs(full * ((ppm - 1000000) // 10 + 1)) < 2**30 and 4095 * f + 4095 < 2**30  # small ints on the rp2


def test_words_follow_the_datasheet_register():
    # MCP4822 register 5-1: bit 15 A/B, bit 14 don't care, bit 13 /GA (1 = 1x), bit 12 /SHDN (1 = active)
    assert dac.word(0, 0) == 0b0011_0000_0000_0000
    assert dac.word(1, 0x123) == 0b1011_0001_0010_0011
    assert dac.word(2, 4095) == 0x3FFF and dac.word(3, 4095) == 0xBFFF


def test_set_ua_drives_the_bus_and_returns_the_delivered_current():
    d, bus = make()
    for ch, i in [(0, 1000), (1, 2500), (2, 9999), (3, 20000), (1, -4), (0, 1)]:
        bus.log.clear()
        got = d.set_ua(ch, i)
        code = dac.code_for(i, FULL)
        w = dac.word(ch, code)
        assert bus.log == [(f"cs{ch >> 1}", 0), ("spi", bytes([w >> 8, w & 0xFF])), (f"cs{ch >> 1}", 1)]
        assert got == dac.ua_for(code, FULL) and d.codes[ch] == code
    bus.log.clear()
    d.zero_all()
    assert [e for e in bus.log if e[0] == "spi"] == [("spi", bytes([dac.word(k, 0) >> 8, 0])) for k in range(4)]
    assert d.codes == [0, 0, 0, 0]


def test_set_up_refuses_what_it_cannot_drive():
    bus = Bus()
    with pytest.raises(ValueError, match="full scale"):
        dac.MCP4822(bus, [bus.pin("cs0")], 2, dac.FULL_UA_MAX + 1)
    with pytest.raises(ValueError, match="3 channels need 2 DAC chip-select pins, 1 given"):
        dac.MCP4822(bus, [bus.pin("cs0")], 3, FULL)


def test_the_driver_allocates_nothing_in_the_micropython_vm(micropython):
    code = textwrap.dedent("""
        import micropython, dac_mcp4822 as dac
        class Spi:
            def write(self, buf):
                pass
        class Pin:
            def __call__(self, v):
                pass
        d = dac.MCP4822(Spi(), [Pin(), Pin()], 4, 10000)
        def run():
            micropython.heap_lock()
            try:
                s = 0
                for i in range(-2, 10050, 7):
                    s += d.set_ua(i & 3, i)
                    d.write(i & 3, 0)
                ok = 1
            except MemoryError:
                ok = 0
            micropython.heap_unlock()
            return ok, s
        ok, s = run()
        print(ok, s)
    """)
    p = subprocess.run([micropython, "-c", code], capture_output=True, text=True, timeout=60,
                       env={"MICROPYPATH": str(FIRMWARE)})
    assert p.returncode == 0, p.stderr
    ok, s = p.stdout.split()
    assert ok == "1"
    assert int(s) == sum(dac.ua_for(dac.code_for(i, FULL), FULL) for i in range(-2, 10050, 7))


# ---------------------------------------------------------------- the delivered current in the firmware
QBOARD = """
import dac_mcp4822 as dac
class QBoard(SimBoard):
    # an output stage that quantizes as the DAC does (the realistic model is board_sim's own, wt-sim)
    def set_amplitude(self, ch, i_ua):
        d = dac.ua_for(dac.code_for(i_ua, cfg.AMP_UA_AT_FULL), cfg.AMP_UA_AT_FULL)
        self.amp[ch] = d
        return d
clock = VirtualClock(0)
usb = MemoryUSB(True)
board = QBoard(cfg, clock, sim_electrode.scenario("{scenario}"), 2, 3, usb, ideal=True)
s = stim.Stimulator(board, clock, cfg, 2, 50, 0)
start(s, i0={i0}, t0={t0}, mode={mode})
cmd = []
for f in range({frames}):
    cmd.append([c.i for c in s.chans])
    s.run(1)
dump(usb)
result(cmd=cmd, lim=s.lim)
"""


def quant(i):
    return dac.ua_for(dac.code_for(i, FULL), FULL)


def tel_rows(reports):
    return [t for t in reports if isinstance(t, Telemetry)]


@pytest.mark.parametrize("mode", [sc.MODE_AKHTAR, sc.MODE_FAST])
def test_the_firmware_uses_and_reports_the_delivered_current_and_audit_replays_it(mode):
    i0, t0 = 1003, 997
    reports, results, _ = run_fw(QBOARD.format(scenario="peel", i0=i0, t0=t0, mode=mode, frames=150))
    tel = tel_rows(reports)
    cmd = results[0]["cmd"]
    assert len(tel) == 2 * len(cmd)
    fired = 0
    for f, pair in enumerate(zip(tel[0::2], tel[1::2])):
        for t in pair:
            if not t.i_ua:
                continue
            fired += 1
            asked = cmd[f][t.channel]
            assert t.i_ua == quant(asked) and asked - LSB < t.i_ua <= asked  # delivered, not commanded
            assert t.rp_ohm == sc.rp_from_vp(t.vp_mv, t.i_ua)  # Rp = Vp / I_delivered
    assert fired >= 2 * 140
    assert sum(t.i_ua != cmd[k // 2][t.channel] for k, t in enumerate(tel) if t.i_ua) > 100  # it mattered
    lim = dict(zip(("i_min_ua", "i_max_ua", "t_min_us", "t_max_us", "q_max_pc"), results[0]["lim"]))
    meta = {**{k: str(v) for k, v in lim.items()}, "i0_ua": str(i0), "t0_us": str(t0), "x_star_ohm": "-1670",
            "y_star_pc": "186000"}
    rows = [{"seq": t.seq, "channel": t.channel, "i_ua": t.i_ua, "t_us": t.t_us, "rp_ohm": t.rp_ohm,
             "mode": t.mode, "flags": t.flags, "stop": t.stop, "next_i_ua": t.next_i_ua, "next_t_us": t.next_t_us}
            for t in tel]
    res = audit(meta, rows)
    assert res.checked >= 2 * 140 and res.mismatches == []
    # the audit can see it: what the firmware would have recorded with the commanded current as the
    # truth (Rp = Vp / I_commanded) does not replay into the device's choices
    cmd_rows = []
    for k, r in enumerate(rows):
        i = cmd[k // 2][r["channel"]] if r["i_ua"] else 0
        cmd_rows.append(dict(r, i_ua=i, rp_ohm=sc.rp_from_vp(tel[k].vp_mv, i) if i else 0))
    assert audit(meta, cmd_rows).mismatches


SUPERVISOR = """
class Liar(SimBoard):
    said = None
    def set_amplitude(self, ch, i_ua):
        self.amp[ch] = i_ua
        return i_ua if self.said is None else self.said
clock = VirtualClock(0)
usb = MemoryUSB(True)
board = Liar(cfg, clock, sim_electrode.scenario("steady"), 1, 1, usb, ideal=True)
s = stim.Stimulator(board, clock, cfg, 1, 50, 0)
start(s)
s.run(3)
n0 = board.pulses[0]
c = s.chans[0]
# the output is not set for the pulse the channel holds (a change without set_amplitude): no pulse
c.i = c.i + 7
s.frame(clock.ticks_us())
skipped = (board.pulses[0] == n0, c.di, c.armed)
s.run(2)
again = board.pulses[0] > n0 and c.armed
# a board that says it would deliver beyond the hard limit: latched, no pulse
board.said = cfg.HARD_I_MAX_UA + 1
s.run(1)
n1 = board.pulses[0]
s.run(1)
result(skipped=skipped, again=again, stop=c.stop, armed=c.armed, more=board.pulses[0] - n1)
"""


def test_the_last_check_fires_only_what_the_output_was_set_for_within_the_hard_limits():
    _, results, _ = run_fw(SUPERVISOR)
    r = results[0]
    assert r["skipped"] == [True, 0, True]
    assert r["again"] is True
    assert r["stop"] == hp.STOP_LIMIT and r["armed"] is False and r["more"] == 0
