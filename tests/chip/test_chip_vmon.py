"""The monitor correction on the emulated chip, through the firmware's real entry point
(`import main`: main_rp2, board_rp2.Board, USB HID): CMD_SET_VMON ... VMON_STORE
writes /vmon_cal.txt to the board's flash from inside the running loop; after a
reset (a new boot from that flash) board_rp2.load_vmon reads it and the telemetry's
Rp is corrected; a corrupt file boots uncorrected, reported by GET_INFO, never a crash."""

import pytest

import hid_protocol as hp
import sensation_core as sc
from steadytouch.protocol import Ack, CalInfo, Commands, Info, Telemetry, decode

from .harness import ChipError

G_PPM, OFF_MV = 1050000, 200
DAC_PPM = 1020000  # ch1: its DAC delivers 1.02 x nominal (what a scope would have shown)  # what the correction says the monitor does: reads 1.05 x true + 200 mV
I_UA, T_US, R_OHM = 3000, 300, 10000


def _run(chip, cfg, sent, ms=1200):
    chip.wiring(cfg, cfg.N_CHANNELS)
    for ch in range(cfg.N_CHANNELS):
        chip.load(ch, rp_ohm=R_OHM)  # a resistor in place of the electrodes
    chip.hid(send=sent)
    with pytest.raises(ChipError, match="timeout"):  # the loop never returns to the REPL
        chip.exec("import main", timeout_ms=ms)
    return [decode(bytes.fromhex(x)) for _t, x in chip.hid()["reports"]]


def _pulses(cmd):
    return [cmd.set_mode(sc.MODE_OPEN_LOOP), cmd.calibrate(I_UA, T_US, 0, 0), cmd.arm()]


def _rp(reps, ch):
    rps = [t.rp_ohm for t in reps if isinstance(t, Telemetry) and t.channel == ch and t.i_ua]
    assert len(rps) >= 10
    return sorted(rps)[len(rps) // 2]


def test_stored_on_the_chip_survives_a_reset_and_corrects_rp(chip_host, cfg, tmp_path):
    cmd = Commands()
    chip = chip_host.boot(chip_host.image)
    # one channel, then every channel in one command (the self-test's all-or-nothing store): the same end state
    sent = [cmd.get_info(), cmd.set_vmon(0, G_PPM, OFF_MV, store=True),
            cmd.set_vmon_all([(G_PPM, OFF_MV, 0), (0, 0, DAC_PPM)], store=True), cmd.get_info(0), cmd.get_info(1),
            cmd.get_info()]
    reps = _run(chip, cfg, sent, ms=800)
    acks = [r for r in reps if isinstance(r, Ack)]
    assert [(a.command, a.result) for a in acks] == [(hp.CMD_SET_VMON, hp.RES_OK)] * 2
    info = [r for r in reps if isinstance(r, Info)]
    cal = [r for r in reps if isinstance(r, CalInfo)]
    assert info[0].vmon_state == hp.VMON_NONE and info[1].vmon_state == hp.VMON_STORED
    assert info[0].dac_gain_applied  # the rp2 board's MCP4822 driver scales its full scale by a stored DAC gain
    assert (cal[0].vmon_gain_ppm, cal[0].vmon_offset_mv, cal[0].flags & hp.CAL_FLAG_VMON) == (G_PPM, OFF_MV, 8)
    assert (cal[1].vmon_gain_ppm, cal[1].flags & hp.CAL_FLAG_VMON) == (0, 0)
    assert (cal[1].dac_gain_ppm, cal[1].flags & hp.CAL_FLAG_DAC, cal[0].dac_gain_ppm) == (DAC_PPM, hp.CAL_FLAG_DAC, 0)
    fs = tmp_path / "fs.bin"
    chip.save_fs(fs)

    # a reset: the board boots from the flash it wrote
    chip = chip_host.boot(fs)
    assert "steadytouch monitor correction v1\n" in chip.exec("print(open('/vmon_cal.txt').read())")
    # every channel in one command, channel 1's gain outside the window: refused whole, channel 0 as stored
    refused = bytes(hp.cmd_set_vmon_all(bytearray(64), hp.VMON_STORE, [(1010000, 0, 0), (hp.VMON_GAIN_PPM_MAX + 1, 0, 0)],
                                        tag=77))
    reps = _run(chip, cfg, [cmd.get_info(), refused, cmd.get_info(0)] + _pulses(cmd))
    info = [r for r in reps if isinstance(r, Info)]
    cal = [r for r in reps if isinstance(r, CalInfo)]
    acks = [r for r in reps if isinstance(r, Ack) and r.command == hp.CMD_SET_VMON]
    assert [(a.result, a.detail) for a in acks] == [(hp.RES_OUT_OF_RANGE, hp.O_ARG + 4 + hp.VMON_STRIDE)]
    assert info[0].vmon_state == hp.VMON_LOADED and (cal[0].vmon_gain_ppm, cal[0].vmon_offset_mv) == (G_PPM, OFF_MV)
    # the emulated monitor is exact (10 kohm reads 10 kohm within its noise): the correction
    # takes 200 mV out and divides by 1.05, as the firmware must
    want = (R_OHM * I_UA / 1000 - OFF_MV) / (G_PPM / 1e6) * 1000 / I_UA
    assert abs(_rp(reps, 0) - want) <= 25, (_rp(reps, 0), want)
    # ch1's DAC told it delivers 1.02 x nominal: the code for 3000 uA is 3000 x 4096 / 10200 and the
    # current reported (and counted against the hard limits) is that code's delivered current
    full1 = -(-cfg.AMP_UA_AT_FULL * DAC_PPM // 1000000)  # rounded up, as dac_mcp4822.full_for (ppm on its 10 ppm grid)
    code1 = I_UA * 4096 // full1
    assert chip.take()["dac_codes"][1] == code1
    i1 = {t.i_ua for t in reps if isinstance(t, Telemetry) and t.channel == 1 and t.i_ua}
    assert i1 == {(code1 * full1 + 4095) // 4096}  # rounded up (dac_mcp4822.ua_for)
    # the emulated stage is nominal (it delivers code x 10000 / 4096): Rp reads low by the told gain
    assert abs(_rp(reps, 1) - R_OHM * code1 * cfg.AMP_UA_AT_FULL / 4096 / min(i1)) <= 25
    assert all(t.stop == hp.STOP_NONE for t in reps if isinstance(t, Telemetry) and t.i_ua)


@pytest.mark.parametrize("content", [b"garbage\xff\xfe", b"steadytouch monitor correction v1\n0 2000000 0\n"])
def test_a_corrupt_file_boots_uncorrected_and_says_so(chip_host, cfg, content):
    cmd = Commands()
    chip = chip_host.boot(chip_host.image)
    chip.put(content, "/vmon_cal.txt")
    reps = _run(chip, cfg, [cmd.get_info(), cmd.get_info(0)] + _pulses(cmd))
    info = [r for r in reps if isinstance(r, Info)]
    cal = [r for r in reps if isinstance(r, CalInfo)]
    assert info[0].vmon_state == hp.VMON_BAD and cal[0].vmon_state == hp.VMON_BAD
    assert (cal[0].vmon_gain_ppm, cal[0].flags & hp.CAL_FLAG_VMON) == (0, 0)
    assert abs(_rp(reps, 0) - R_OHM) <= 25 and abs(_rp(reps, 1) - R_OHM) <= 25


def test_on_the_chip_reserved_bytes_are_refused_and_no_dac_gain_holds_the_hard_limit_low(chip_host, cfg):
    """Review of d560dd3 (findings 4, 2c) on the rp2 board, through main and USB HID: a CH_ALL SET_VMON
    with a byte set in the reserved 56..61 is refused (RES_BAD_FORMAT, the byte) and changes nothing.
    With a channel that has no DAC gain applied (a fresh board; here ch0) the hard current and charge
    limits in force are held to x 0.965 (the DAC's own gain error could push a pulse past them): GET_INFO
    reports them with INFO_FLAG_HELD, the boot soft limits are lowered to them, and a CALIBRATE or
    SET_LIMITS above them is refused ahead (RES_OUT_OF_RANGE, the byte; was: accepted, then latched
    STOP_LIMIT at the gate with no pulse and no reason given). Once every channel has a DAC gain (1.0)
    GET_INFO reports the hard limits x that gain / 1.035 (9661 uA: the physical current then stays within
    the hard limits whatever the DAC's true gain in its window; review of session 22: was the full limits),
    with INFO_FLAG_DAC_LOW, the soft ones stay where they were until SET_LIMITS raises them (up to there; above
    it refused), and both channels pulse there. Removing a gain again (under the heap lock) lowers the
    soft limits at once and drops the calibration above them."""
    cmd = Commands()
    chip = chip_host.boot(chip_host.image)
    junk = bytearray(hp.cmd_set_vmon_all(bytearray(64), hp.VMON_APPLY, [(1010000, 10, 0), (0, 0, 1000000)], tag=91))
    junk[56] = 0x5A
    hp.seal(junk)
    hard_i, hard_q = cfg.HARD_I_MAX_UA, cfg.HARD_Q_MAX_PC
    held_i, held_q = hard_i * hp.VMON_DAC_PPM_MIN // 1000000, hard_q * hp.VMON_DAC_PPM_MIN // 1000000
    f = (1000000 // 100) * 10000 // (hp.VMON_DAC_PPM_MAX // 100)  # a DAC gain of 1.000 stored (stim._dac_limits)
    low_i, low_q = hard_i * f // 10000, hard_q * f // 10000
    assert hard_i / 1.035 - 2 <= low_i <= hard_i / 1.035 and hard_q / 1.035 - 2000 <= low_q <= hard_q / 1.035
    assert low_i > held_i and low_q > held_q
    t_us = 100
    sent = [cmd.get_info(), bytes(junk), cmd.get_info(0), cmd.get_info(1),
            cmd.set_mode(sc.MODE_OPEN_LOOP),
            cmd.calibrate(hard_i, t_us, 0, 0),  # refused ahead: above the held soft limit
            cmd.set_limits(1, hard_i, t_us, 1000, hard_q),  # refused ahead: above the held hard limit
            cmd.set_vmon(1, 0, 0, dac_gain_ppm=1000000), cmd.get_info(),  # ch0 still has none: still held
            cmd.set_vmon_all([(0, 0, 1000000), (0, 0, 1000000)]), cmd.get_info(),  # every channel: x 1 / 1.035
            cmd.set_limits(1, hard_i, t_us, 1000, low_q),  # refused: above the limit the gain holds
            cmd.set_limits(1, low_i, t_us, 1000, low_q), cmd.calibrate(low_i, t_us, 0, 0), cmd.arm()]
    chip.wiring(cfg, cfg.N_CHANNELS)
    for ch in range(cfg.N_CHANNELS):
        chip.load(ch, rp_ohm=1000)  # 10 V at the hard limit: well within compliance
    chip.hid(send=sent)
    with pytest.raises(ChipError, match="timeout"):
        chip.exec("import main", timeout_ms=800)
    reps = [decode(bytes.fromhex(x)) for _t, x in chip.hid()["reports"]]
    acks = [(a.command, a.result, a.detail) for a in reps if isinstance(a, Ack)]
    assert acks == [(hp.CMD_SET_VMON, hp.RES_BAD_FORMAT, 56), (hp.CMD_SET_MODE, hp.RES_OK, 0),
                    (hp.CMD_CALIBRATE, hp.RES_OUT_OF_RANGE, hp.O_ARG),
                    (hp.CMD_SET_LIMITS, hp.RES_OUT_OF_RANGE, hp.O_ARG + 2),
                    (hp.CMD_SET_VMON, hp.RES_OK, 0), (hp.CMD_SET_VMON, hp.RES_OK, 0),
                    (hp.CMD_SET_LIMITS, hp.RES_OUT_OF_RANGE, hp.O_ARG + 2),
                    (hp.CMD_SET_LIMITS, hp.RES_OK, 0), (hp.CMD_CALIBRATE, hp.RES_OK, 0), (hp.CMD_ARM, hp.RES_OK, 0)]
    cal = [r for r in reps if isinstance(r, CalInfo)]
    assert [(c.vmon_gain_ppm, c.dac_gain_ppm) for c in cal] == [(0, 0), (0, 0)]  # the refused command changed nothing
    info = [r for r in reps if isinstance(r, Info)]
    soft = [(i.i_max_ua, i.q_max_pc) for i in info]
    assert [(i.hard_i_max_ua, i.hard_q_max_pc, i.held, i.dac_low) for i in info] == [
        (held_i, held_q, True, False), (held_i, held_q, True, False), (low_i, low_q, False, True)]
    assert soft == [(held_i, held_q)] * 3  # lowered at boot; a gain stored later does not raise them by itself
    tel = {ch: [t for t in reps if isinstance(t, Telemetry) and t.channel == ch] for ch in (0, 1)}
    for ch in (0, 1):
        assert not any(t.stop == hp.STOP_LIMIT for t in tel[ch])
        pulsed = [t for t in tel[ch] if t.i_ua]
        assert len(pulsed) >= 3 and all(t.stop == hp.STOP_NONE and low_i - 5 <= t.i_ua <= low_i for t in pulsed)

    # ch0's gain removed (SET_VMON under the heap lock): the soft limits follow it down at once, the
    # calibration above them must be sent again (ARM refused), GET_INFO says held again
    chip.hid(send=[cmd.disarm(), cmd.set_vmon(0, 0, 0), cmd.get_info(), cmd.arm()])
    chip.run(200)
    reps = [decode(bytes.fromhex(x)) for _t, x in chip.hid()["reports"]]
    acks = [(a.command, a.result) for a in reps if isinstance(a, Ack)]
    assert acks == [(hp.CMD_DISARM, hp.RES_OK), (hp.CMD_SET_VMON, hp.RES_OK), (hp.CMD_ARM, hp.RES_NOT_CALIBRATED)]
    info = [r for r in reps if isinstance(r, Info)]
    assert [(i.hard_i_max_ua, i.hard_q_max_pc, i.held, i.i_max_ua, i.q_max_pc) for i in info] == [
        (held_i, held_q, True, held_i, held_q)]
    disarmed = next(a.seq for a in reps if isinstance(a, Ack) and a.command == hp.CMD_DISARM)
    after = [t for t in reps if isinstance(t, Telemetry) and t.seq > disarmed]
    assert after and not any(t.i_ua for t in after) and {t.stop for t in after} == {hp.STOP_DISARMED}


def test_on_the_chip_the_gate_still_latches_a_pulse_above_the_held_limit(on_board, cfg):
    """The check right before the gate opens stays the last line: with the soft limits forced past the
    held ones (what _fit_limits prevents; here set behind its back), a pulse at the hard current limit on
    a channel with no DAC gain applied is latched STOP_LIMIT and never fired."""
    for ch in range(cfg.N_CHANNELS):
        on_board.load(ch, rp_ohm=1000)
    out = on_board.exec("""
s = stim.Stimulator(b, board_rp2.Clock(), cfg, 2, 50)
lim = s.lim
held = [lim[1], lim[4]]
lim[1] = s.hard_i
lim[4] = s.hard_q
for c in s.chans:
    c.ctl.set_limits(lim[0], lim[1], lim[2], lim[3], lim[4])
for rep in (hp.cmd_set_mode(bytearray(64), 0), hp.cmd_calibrate(bytearray(64), hp.CH_ALL, s.hard_i, 100, 0, 0),
            hp.cmd_arm(bytearray(64), hp.CH_ALL)):
    assert s.handle(rep, time.ticks_us()) == hp.RES_OK
s.sync_outputs()
s.run(3)
print([held, [c.stop for c in s.chans], [c.armed for c in s.chans], [c.hard_i_d for c in s.chans]])""")
    r = on_board.take()
    held_i = cfg.HARD_I_MAX_UA * hp.VMON_DAC_PPM_MIN // 1000000
    assert eval(out.strip().splitlines()[-1]) == [[held_i, cfg.HARD_Q_MAX_PC * hp.VMON_DAC_PPM_MIN // 1000000], [hp.STOP_LIMIT] * 2,
                         [False, False], [held_i, held_i]]
    assert r["pulses"] == [] and r["gate"] == [0, 0]


@pytest.mark.parametrize("name", ["130 channel lines", "4 KB of blank lines"])
def test_a_store_over_the_longest_file_boot_reads_finishes_within_the_watchdog(chip_host, cfg, tmp_path, name):
    """Review rev-lims F2: 130 channel lines (2.8 KB, loaded at boot then) made a HID store read, keep and write
    them all: the watchdog (500 ms) reset the board mid-store, every store after likewise. Now channels are 0..3
    and the file at most 4 KB: the 130-line file is one boot ignores (replaced whole), and the longest file boot
    loads (4 096 bytes, mostly blank lines: the most lines to split) is read, kept and replaced in time."""
    cmd = Commands()
    chip = chip_host.boot(chip_host.image)
    head = "steadytouch monitor correction v1\n"
    if name == "130 channel lines":
        data = (head + "".join("%d 1000000 0 1000000\n" % k for k in range(130))).encode()
        boot = hp.VMON_BAD
    else:
        data = (head + "2 1000000 0 1000000\n").encode()
        data += b"\n" * (4096 - len(data))
        boot = hp.VMON_LOADED
    chip.put(data, "/vmon_cal.txt")
    sent = [cmd.get_info(), cmd.set_vmon_all([(1010000, 0, 1000000), (1010000, 0, 1000000)], store=True),
            cmd.get_info(), cmd.set_vmon_all([(1010000, 0, 1000000), (1010000, 0, 1000000)], store=True),
            cmd.get_info()]
    reps = _run(chip, cfg, sent, ms=2000)
    acks = [(r.command, r.result) for r in reps if isinstance(r, Ack)]
    info = [r.vmon_state for r in reps if isinstance(r, Info)]
    assert acks == [(hp.CMD_SET_VMON, hp.RES_OK)] * 2, acks
    assert info == [boot, hp.VMON_STORED, hp.VMON_STORED], info
    fs = tmp_path / "fs.bin"
    chip.save_fs(fs)
    chip = chip_host.boot(fs)  # a reset: what the store left in the flash
    text = chip.exec("print(open('/vmon_cal.txt').read())")
    kept = "2 1000000 0 1000000" in text
    assert kept == (boot == hp.VMON_LOADED) and "0 1010000 0 1000000" in text and len(text) < 400, text
