"""The amplitude DAC (MCP4822 on SPI, firmware/dac_mcp4822.py) on the emulated chip,
driven by the real board_rp2.Board and stim.Stimulator: the Node host takes the
16-bit words clocked in while a chip select is low and latches them at its rising
edge (host/emu/host.mjs), so the test sees the bytes the DAC would receive. For
every pulse of a run the channel's DAC holds the code of the current the frame
commanded (never more, less by under one LSB), written after the channel's
previous pulse and settled before its gate opens; the current the firmware uses
and reports is that code times the LSB."""

import importlib.util
import math

import pytest

import sensation_core as sc

from .harness import FIRMWARE

_spec = importlib.util.spec_from_file_location("dac_mcp4822", FIRMWARE / "dac_mcp4822.py")
dac = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(dac)  # the driver's own code math (plain Python), as the board runs it

US = 1000  # ns
SETTLE_US = 10  # MCP4822: 4.5 us typical to within 1/2 LSB (datasheet); 0.1 % is reached well before

RUN = """
s = stim.Stimulator(b, board_rp2.Clock(), cfg, {n}, 50)
for rep in (hp.cmd_set_mode(bytearray(64), {mode}), hp.cmd_calibrate(bytearray(64), hp.CH_ALL, {i0}, {t0}, -1670, 186000),
            hp.cmd_arm(bytearray(64), hp.CH_ALL)):
    assert s.handle(rep, time.ticks_us()) == hp.RES_OK
s.sync_outputs()
rows = []
for f in range({frames}):
    cmd = [(c.i, c.t) for c in s.chans]  # what this frame's pulses were commanded at
    s.run(1)
    for c in s.chans:
        rows.append((c.ch, cmd[c.ch][0], cmd[c.ch][1], c.di, c.dt, c.rp, c.stop))
print(rows)
"""


def lsb_ua(cfg):
    return cfg.AMP_UA_AT_FULL / dac.CODES


def check_word(word, ch, code):
    assert word == dac.word(ch, code)
    assert word >> 15 == ch & 1 and word & 0x2000 and word & 0x1000  # output A/B, gain 1x, active
    assert word & 0xFFF == code


def test_every_pulse_of_a_run_has_its_code_written_and_settled_before_the_gate_opens(on_board, cfg):
    # Rp changes every pulse on both channels after the two calibration pulses, so the controller
    # moves the current every frame
    on_board.host.call("load", ch=0, load={"cycle": [{"rs_ohm": 0, "rp_ohm": r, "tau_us": 0}
                                                 for r in (10000, 14000, 8000, 12000, 9000)], "lead": 2})
    on_board.host.call("load", ch=1, load={"cycle": [{"rs_ohm": 470, "rp_ohm": r, "tau_us": 0}
                                                 for r in (4700, 6100, 3900)], "lead": 2})
    frames = 12
    rows = on_board.eval_out(RUN.format(n=2, mode=sc.MODE_AKHTAR, i0=1000, t0=1000, frames=frames))
    r = on_board.take()
    pulses, writes = r["pulses"], r["dac_writes"]
    fired = [row for row in rows if row[3]]
    assert len(fired) == len(pulses) == 2 * frames
    assert len({row[1] for row in fired if row[0] == 0}) >= 3  # the current did move
    last_fall = {0: 0, 1: 0}
    for (ch, i_cmd, t_cmd, di, dt, rp, stop), p in zip(fired, pulses):
        assert p["ch"] == ch and stop == 0 and (p["fall_ns"] - p["rise_ns"]) == t_cmd * US == dt * US
        before = [w for w in writes if w[1] == ch and w[0] < p["rise_ns"]]
        assert before, "no DAC write before the pulse"
        t_w, _, word = before[-1]
        code = dac.code_for(i_cmd, cfg.AMP_UA_AT_FULL)
        check_word(word, ch, code)
        # written after the channel's previous pulse, settled before this gate opens
        assert last_fall[ch] <= t_w <= p["rise_ns"] - SETTLE_US * US
        last_fall[ch] = p["fall_ns"]
        # what the stimulator drives is code x LSB: never above the command, short of it by under one LSB
        assert p["i_ua"] == code * lsb_ua(cfg) and i_cmd - lsb_ua(cfg) < p["i_ua"] <= i_cmd
        # and that delivered current is what the firmware uses (Rp) and reports, to the nearest uA
        assert di == dac.ua_for(code, cfg.AMP_UA_AT_FULL) == math.ceil(p["i_ua"])  # rounded up


def test_stop_writes_code_0_and_a_latched_channel_is_left_at_0(on_board, cfg):
    on_board.load(0, rp_ohm=10000)
    on_board.host.call("load", ch=1, load={"open": True})  # electrode off: the first pulse latches channel 1
    rows = on_board.eval_out(RUN.format(n=2, mode=sc.MODE_AKHTAR, i0=2000, t0=500, frames=3))
    r = on_board.take()
    assert [row[6] for row in rows if row[0] == 1][0] != 0 and r["dac_codes"][0] == dac.code_for(2000, 10000)
    after = [w for w in r["dac_writes"] if w[1] == 1 and w[0] > r["pulses"][1]["fall_ns"]]
    assert after and all(w[2] & 0xFFF == 0 for w in after)  # stopped: code 0 ever since
    on_board.exec("b.stop_all()")
    r = on_board.take()
    assert r["dac_codes"][:2] == [0, 0]
    assert sorted((w[1], w[2]) for w in r["dac_writes"]) == [(0, dac.word(0, 0)), (1, dac.word(1, 0))]


def test_set_amplitude_clips_and_returns_the_delivered_current(on_board, cfg):
    asks = [-5, 0, 1, 2, 3, 1000, 2500, 9997, 9998, 10000, 20000]
    got = on_board.eval(f"[b.set_amplitude(0, i) for i in {asks}]")
    r = on_board.take()
    codes = [w[2] & 0xFFF for w in r["dac_writes"]]
    assert codes == [dac.code_for(i, cfg.AMP_UA_AT_FULL) for i in asks]
    assert codes[-1] == dac.CODE_MAX and codes[:3] == [0, 0, 0]
    assert got == [dac.ua_for(c, cfg.AMP_UA_AT_FULL) for c in codes]
    assert got[-1] == 9998 and all(g <= max(i, 0) for g, i in zip(got, asks))


def test_the_dac_write_allocates_nothing_and_its_cost_in_emulated_us(on_board, cfg):
    """set_amplitude (code, SPI write of 2 bytes at DAC_SPI_HZ, chip select) under the heap lock;
    its cost in emulated us (deterministic; a lower bound for a real Pico): docs/performance.md."""
    out = on_board.exec("""
def dac_cost(n):
    micropython.heap_lock()
    try:
        t0 = time.ticks_us()
        for k in range(n):
            b.set_amplitude(k & 1, 1000 + k)
        t1 = time.ticks_us()
        for k in range(n):
            pass
        t2 = time.ticks_us()
        ok = 1
    except MemoryError:
        ok = 0
    micropython.heap_unlock()
    return ok, time.ticks_diff(t1, t0) - time.ticks_diff(t2, t1)
ok, us = dac_cost(200)
print(ok, us / 200)""")
    ok, us = out.split()
    r = on_board.take()
    assert ok == "1" and len(r["dac_writes"]) == 200
    us = float(us)
    print(f"set_amplitude on the emulated chip: {us:.1f} us a write (SPI at {cfg.DAC_SPI_HZ / 1e6:g} MHz)")
    assert 2 < us < 45  # the 16 bits on the wire (1.6 us), the call and ~15 us of viper (31 us): docs/performance.md
