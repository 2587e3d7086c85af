"""The voltage monitor's correction on the device (firmware/vmon_cal.py, stim._measure,
CMD_SET_VMON): applied to every pulse's peak inside the heap-locked frame, set and
stored by command (checked before anything changes), read back by GET_INFO, read
from the board's flash at boot (a missing or corrupt file: uncorrected, reported).
Runs the firmware in the MicroPython VM on the simulated board (the realistic one)."""

import sys

import pytest

import hid_protocol as hp
from conftest import FIRMWARE
from fw_harness import run_fw
from steadytouch.protocol import Ack, CalInfo, Commands, CommandError, Info, Telemetry

sys.path.insert(0, str(FIRMWARE))
import board_sim  # noqa: E402
import vmon_cal  # noqa: E402

G_PPM = [round(board_sim.MON_GAIN[k] * board_sim.DAC_GAIN[k] * 1e6) for k in (0, 1)]

# open-loop pulses of 3000 uA x 300 us on a 10 kohm load, noise off: Rp per channel
PULSES = """
def rps(s, frames=6):
    s.board.usb.sent.clear()
    b = bytearray(64)
    assert apply(s, hp.cmd_set_mode(b, sc.MODE_OPEN_LOOP)) == 0
    assert apply(s, hp.cmd_calibrate(b, hp.CH_ALL, 3000, 300, 0, 0)) == 0
    assert apply(s, hp.cmd_arm(b, hp.CH_ALL)) == 0
    s.run(frames)
    assert apply(s, hp.cmd_disarm(b, hp.CH_ALL)) == 0
    out = {}
    for r in s.board.usb.sent:
        if r[0] == hp.REP_TELEMETRY and hp.get_u16(r, hp.O_I):
            out[r[1]] = hp.get_i32(r, hp.O_RP)
    s.board.usb.sent.clear()
    return [out[0], out[1]]

def locked(s, rep):
    # as _serve_commands handles a command: inside the heap-locked section
    r = bytearray(rep)
    now = s.clock.ticks_us()
    s._enter()
    try:
        return s.handle(r, now)
    finally:
        s._leave()

def board(correction=None, flash_dir=None):
    clock = VirtualClock(0)
    usb = MemoryUSB(True)
    bd = SimBoard(cfg, clock, sim_electrode.scenario("steady"), 2, 1, usb, noise_counts=0.0, load_ohm=10000,
                  correction=correction, flash_dir=flash_dir)
    return stim.Stimulator(bd, clock, cfg, 2, 50, 0)
"""


def test_the_correction_takes_out_the_path_gain_and_offset_in_the_heap_locked_frame():
    corr = [(G_PPM[0], board_sim.MON_OFFSET_MV[0]), (G_PPM[1], board_sim.MON_OFFSET_MV[1])]
    _, res, _ = run_fw(PULSES + f"""
result(raw=rps(board()), corrected=rps(board({corr!r})))
""")
    raw, corrected = res[0]["raw"], res[0]["corrected"]
    # the DAC delivers code x LSB x its gain, the firmware divides by code x LSB: the load reads
    # R x g_dac x g_mon + offset / I uncorrected, R within a count (27 mV / 3 mA = 9 ohm) corrected
    for ch in (0, 1):
        want_raw = 10000 * G_PPM[ch] / 1e6 + board_sim.MON_OFFSET_MV[ch] * 1000 / 2999
        assert abs(raw[ch] - want_raw) < 30, (ch, raw, want_raw)
        assert abs(corrected[ch] - 10000) <= 20, (ch, corrected)
        assert abs(raw[ch] - 10000) > 80  # ch0 +2.5 %, ch1 -0.9 % uncorrected


def test_set_vmon_checks_everything_before_anything_changes_and_get_info_reads_it_back(tmp_path):
    ok = hp.cmd_set_vmon(bytearray(64), 0, hp.VMON_APPLY, 1012000, 150)
    cases = {
        # every channel in one command (CH_ALL): channel 1's words refused -> channel 0 untouched too
        "all_ch1_gain": (hp.cmd_set_vmon_all(bytearray(64), hp.VMON_APPLY, [(1012000, 150, 0), (1090001, 0, 0)]),
                         hp.RES_OUT_OF_RANGE, hp.O_ARG + 4 + hp.VMON_STRIDE),
        "all_ch1_dac": (hp.cmd_set_vmon_all(bytearray(64), hp.VMON_STORE, [(1012000, 150, 0), (0, 0, hp.VMON_DAC_PPM_MAX + 1)]),
                        hp.RES_OUT_OF_RANGE, hp.O_ARG + 12 + hp.VMON_STRIDE),
        "all_ch2_words": (hp.cmd_set_vmon_all(bytearray(64), hp.VMON_APPLY, [(1012000, 150, 0), (0, 0, 0),
                                                                            (0, 0, 1000000)]),
                          hp.RES_BAD_CHANNEL, hp.O_ARG + 12 + 2 * hp.VMON_STRIDE),
        "all_store_no_flash": (hp.cmd_set_vmon_all(bytearray(64), hp.VMON_STORE, [(1012000, 150, 0), (990000, -40, 0)]),
                               hp.RES_STORE_FAILED, 0),
        "ch5": (hp.cmd_set_vmon(bytearray(64), 5, hp.VMON_APPLY, 1012000, 150), hp.RES_BAD_CHANNEL, hp.O_OUT_CH),
        "op": (hp.cmd_set_vmon(bytearray(64), 0, 2, 1012000, 150), hp.RES_OUT_OF_RANGE, hp.O_ARG),
        "gain_lo": (hp.cmd_set_vmon(bytearray(64), 0, hp.VMON_APPLY, hp.VMON_GAIN_PPM_MIN - 1, 150), hp.RES_OUT_OF_RANGE, hp.O_ARG + 4),
        "gain_hi": (hp.cmd_set_vmon(bytearray(64), 0, hp.VMON_APPLY, hp.VMON_GAIN_PPM_MAX + 1, 0), hp.RES_OUT_OF_RANGE, hp.O_ARG + 4),
        "gain_0": (hp.cmd_set_vmon(bytearray(64), 0, hp.VMON_APPLY, 0, 150), hp.RES_OUT_OF_RANGE, hp.O_ARG + 4),
        "off_hi": (hp.cmd_set_vmon(bytearray(64), 0, hp.VMON_APPLY, 1012000, hp.VMON_OFFSET_MV_MAX + 1), hp.RES_OUT_OF_RANGE, hp.O_ARG + 8),
        "off_lo": (hp.cmd_set_vmon(bytearray(64), 0, hp.VMON_APPLY, 1012000, hp.VMON_OFFSET_MV_MIN - 1), hp.RES_OUT_OF_RANGE,
                   hp.O_ARG + 8),
        "huge": (hp.cmd_set_vmon(bytearray(64), 0, hp.VMON_APPLY, 1 << 29, 0), hp.RES_OUT_OF_RANGE, hp.O_ARG + 4),
        "store_no_flash": (hp.cmd_set_vmon(bytearray(64), 0, hp.VMON_STORE, 1012000, 150), hp.RES_STORE_FAILED, 0),
    }
    fmt = bytearray(ok)
    fmt[hp.O_ARG + 1] = 1
    hp.seal(fmt)
    cases["reserved"] = (fmt, hp.RES_BAD_FORMAT, hp.O_ARG + 1)
    crc = bytearray(ok)
    crc[hp.O_ARG + 4] ^= 1
    cases["crc"] = (crc, hp.RES_BAD_CRC, hp.O_CRC)
    body = PULSES + """
s = board()
b = bytearray(64)
before = rps(s)
out = {}
"""
    for name, (rep, _, _) in cases.items():
        body += f"out[{name!r}] = (locked(s, {bytes(rep)!r}), s.tx[hp.O_DETAIL])\n"
    body += f"""
armed = s.handle(bytearray(hp.cmd_calibrate(b, hp.CH_ALL, 3000, 300, 0, 0)), 0), s.handle(bytearray(hp.cmd_arm(b, 1)), 0)
out["armed"] = (apply(s, {bytes(ok)!r}), s.tx[hp.O_DETAIL])
apply(s, hp.cmd_disarm(b, hp.CH_ALL))
after_refusals = rps(s)
s.board.usb.sent.clear()
apply(s, hp.cmd_get_info(b, 0, 0)); s.board.send(s.tx)
out["ok"] = (apply(s, {bytes(ok)!r}), 0)
apply(s, hp.cmd_get_info(b, 0, 0)); s.board.send(s.tx)
apply(s, hp.cmd_get_info(b, 0, 1)); s.board.send(s.tx)
apply(s, hp.cmd_get_info(b, 0)); s.board.send(s.tx)
dump(s.board.usb)
applied = rps(s)
out["clear"] = (apply(s, hp.cmd_set_vmon(b, 0, hp.VMON_APPLY, 0, 0)), 0)
cleared = rps(s)
result(out=out, before=before, after_refusals=after_refusals, applied=applied, cleared=cleared)
"""
    reps, res, _ = run_fw(body)
    r = res[0]
    for name, (_, result, detail) in cases.items():
        assert r["out"][name] == [result, detail], name
    assert r["out"]["armed"] == [hp.RES_BAD_STATE, hp.O_OUT_CH]
    assert r["out"]["ok"] == [hp.RES_OK, 0] and r["out"]["clear"] == [hp.RES_OK, 0]
    assert r["after_refusals"] == r["before"]  # nothing a refusal could change did
    cal = [x for x in reps if isinstance(x, CalInfo)]
    info = [x for x in reps if isinstance(x, Info)]
    assert (cal[0].vmon_gain_ppm, cal[0].vmon_offset_mv, cal[0].flags & hp.CAL_FLAG_VMON) == (0, 0, 0)
    assert (cal[1].vmon_gain_ppm, cal[1].vmon_offset_mv, cal[1].flags & hp.CAL_FLAG_VMON) == (1012000, 150, 8)
    assert (cal[2].channel, cal[2].vmon_gain_ppm, cal[2].flags & hp.CAL_FLAG_VMON) == (1, 0, 0)
    assert info[0].vmon_state == hp.VMON_NONE and cal[1].vmon_state == hp.VMON_NONE  # applied, not stored
    # ch0 now divides by 1.012 after taking 150 mV out; ch1 untouched; cleared: as before
    assert abs(r["applied"][0] - (r["before"][0] - 150 * 1000 / 2999) / 1.012) <= 12
    assert r["applied"][1] == r["before"][1] and r["cleared"] == r["before"]


def test_stored_survives_a_reset_a_missing_or_corrupt_file_boots_uncorrected(tmp_path):
    flash = str(tmp_path)
    corr = (G_PPM[0], board_sim.MON_OFFSET_MV[0])
    body = PULSES + f"""
b = bytearray(64)
s = board(flash_dir={flash!r})
state0 = s.vmon_state
raw = rps(s)
r1 = locked(s, hp.cmd_set_vmon(b, 0, hp.VMON_STORE, {corr[0]}, {corr[1]}))
r2 = locked(s, hp.cmd_set_vmon(b, 1, hp.VMON_APPLY, 1010000, 0))  # RAM only: not in the file
state1 = s.vmon_state
s2 = board(flash_dir={flash!r})  # a reset: a new board reads its flash
result(state0=state0, state1=state1, r=[r1, r2], raw=raw, after_reset=rps(s2), state2=s2.vmon_state,
       text=open({flash!r} + "/vmon_cal.txt").read())
"""
    _, res, _ = run_fw(body)
    r = res[0]
    assert r["state0"] == hp.VMON_NONE and r["state1"] == hp.VMON_STORED and r["state2"] == hp.VMON_LOADED
    assert r["r"] == [hp.RES_OK, hp.RES_OK]
    assert vmon_cal.parse(r["text"], 2) == [corr + (0,), None]
    assert abs(r["after_reset"][0] - 10000) <= 20 and r["after_reset"][1] == r["raw"][1]
    assert not (tmp_path / "vmon_cal.txt.tmp").exists()
    for bad in ("garbage\n", vmon_cal.CAL_HEADER + "\n0 5000000 0\n", vmon_cal.CAL_HEADER + "\n0 1000000\n",
                "\xff\xfe\x00",
                # ambiguous (review): a channel twice, a negative channel
                vmon_cal.CAL_HEADER + "\n0 1000000 0\n0 1050000 0\n", vmon_cal.CAL_HEADER + "\n-1 1000000 0\n"):
        (tmp_path / "vmon_cal.txt").write_bytes(bad.encode("latin-1"))
        _, res, _ = run_fw(PULSES + f"""
s = board(flash_dir={flash!r})
result(state=s.vmon_state, rp=rps(s))
""")
        assert res[0]["state"] == hp.VMON_BAD and res[0]["rp"] == r["raw"], bad


def test_boot_load_and_store_on_cpython(tmp_path):
    p = str(tmp_path / "vmon_cal.txt")
    assert vmon_cal.boot_load(p, 2) == ([None, None], hp.VMON_NONE)
    assert vmon_cal.store(p, [None, (1010000, -40, 994000)])
    assert vmon_cal.boot_load(p, 2) == ([None, (1010000, -40, 994000)], hp.VMON_LOADED)
    (tmp_path / "old.txt").write_text(vmon_cal.CAL_HEADER + "\n1 1010000 -40\n")  # a file without the DAC column
    assert vmon_cal.boot_load(str(tmp_path / "old.txt"), 2) == ([None, (1010000, -40, 0)], hp.VMON_LOADED)
    assert vmon_cal.boot_load(p, 1) == ([None], hp.VMON_LOADED)  # a channel the board does not have: ignored
    assert not vmon_cal.store(str(tmp_path / "no" / "dir.txt"), [None])


def test_host_command_checks_the_same_ranges():
    c = Commands()
    assert c.set_vmon(1, 1012000, -150, store=True)[hp.O_ARG] == hp.VMON_STORE
    assert c.set_vmon(0, 0, 0)[hp.O_ARG] == hp.VMON_APPLY
    for args, words in (((hp.CH_ALL, 1012000, 0), "one channel"), ((0, 1200000, 0), "gain_ppm"),
                        ((0, 1000000, 3000), "offset_mv"), ((0, 0, 5), "gain_ppm")):
        with pytest.raises(CommandError, match=words):
            c.set_vmon(*args)
    assert isinstance(Ack, type) and isinstance(Telemetry, type)


def test_the_dac_gain_makes_the_reported_current_the_delivered_one():
    """With the DAC's gain stored the board scales its full scale: the current the firmware
    reports (and counts against the hard limits) is the physical one within a DAC step, and
    the monitor's own gain then makes Rp exact."""
    corr = [(round(board_sim.MON_GAIN[k] * 1e6), board_sim.MON_OFFSET_MV[k], round(board_sim.DAC_GAIN[k] * 1e6))
            for k in (0, 1)]
    _, res, _ = run_fw(PULSES + f"""
s = board({corr!r})
rp = rps(s)
b = s.board
out = []
for ch in (0, 1):
    got = b.set_amplitude(ch, 3000)
    out.append([got, b.analog.physical_ua(ch, b.code[ch])])
r = locked(s, hp.cmd_set_vmon(bytearray(64), 0, hp.VMON_APPLY, 0, 0, 0, 1100001))
result(rp=rp, out=out, r=[r, s.tx[hp.O_DETAIL]], dac=s.chans[0].vmon_dac)
""")
    r = res[0]
    for ch in (0, 1):
        got, phys = r["out"][ch]
        assert 0 <= got - phys < 1.0 + 10000 / 4096 * 0.001, (ch, got, phys)  # whole uA, rounded up: never below it
        assert abs(r["rp"][ch] - 10000) <= 20
    assert r["r"] == [hp.RES_OUT_OF_RANGE, hp.O_ARG + 12] and r["dac"] == corr[0][2]  # refused: unchanged


def test_dac_set_gain_scales_the_full_scale_within_small_ints():
    import dac_mcp4822 as dac

    class Bus:
        def write(self, b):
            pass

    d = dac.MCP4822(Bus(), [lambda v=None: None], 2, dac.FULL_UA_MAX)
    for ppm in (dac.GAIN_PPM_MIN, 999990, 1000000, 1000010, dac.GAIN_PPM_MAX):
        d.set_gain(1, ppm)
        assert 0 <= d.full[1] - dac.FULL_UA_MAX * ppm / 1e6 < 1  # rounded up (dac_mcp4822.full_for)
        assert abs(dac.FULL_UA_MAX * ((ppm - 1000000) // 10 + 1)) < 2**30
        assert 4096 * d.full[1] < 2**30
    d.set_gain(1, 0)
    assert d.full == [dac.FULL_UA_MAX] * 2
    with pytest.raises(ValueError):
        d.set_gain(0, 1100001)


def test_info_shows_the_stored_correction_and_a_corrupt_file(tmp_path):
    import os
    import subprocess
    from pathlib import Path

    exe = str(Path(sys.executable).parent / "steadytouch")
    env = dict(os.environ, STEADYTOUCH_SIM_FLASH=str(tmp_path))
    (tmp_path / "vmon_cal.txt").write_text(vmon_cal.CAL_HEADER + "\n1 1010000 -30 995000\n")
    p = subprocess.run([exe, "info", "--device", "sim://steady"], capture_output=True, text=True, env=env, timeout=60)
    assert p.returncode == 0, p.stderr
    assert "ch1: monitor gain 1.0100 offset -30 mV, DAC gain 0.9950" in p.stdout and "ch0: monitor" not in p.stdout
    assert "correction: stored correction loaded at boot" in p.stdout
    (tmp_path / "vmon_cal.txt").write_text(vmon_cal.CAL_HEADER + "\n1 1010000 -30 995\n")  # DAC gain out of range
    p = subprocess.run([exe, "info", "--device", "sim://steady"], capture_output=True, text=True, env=env, timeout=60)
    assert p.returncode == 0 and "monitor gain" not in p.stdout and "ignored (monitor uncorrected)" in p.stdout


# ---- the accepted windows (docs/hardware.md, "The accepted window"): at, just inside, just outside each limit
WINDOW_LIMITS = [  # (field, limit, the step inward)
    ("gain", hp.VMON_GAIN_PPM_MIN, 1), ("gain", hp.VMON_GAIN_PPM_MAX, -1),
    ("offset", hp.VMON_OFFSET_MV_MIN, 1), ("offset", hp.VMON_OFFSET_MV_MAX, -1),
    ("dac", hp.VMON_DAC_PPM_MIN, 1), ("dac", hp.VMON_DAC_PPM_MAX, -1),
]
FIELD_OFFSET = {"gain": hp.O_ARG + 4, "offset": hp.O_ARG + 8, "dac": hp.O_ARG + 12}


def _vmon_args(field, v):
    return {"gain": (v, 0, 0), "offset": (1000000, v, 0), "dac": (0, 0, v)}[field]


def _window_cases():
    for field, limit, inward in WINDOW_LIMITS:
        for where, v in (("at", limit), ("inside", limit + inward), ("outside", limit - inward)):
            yield field, where, v, where != "outside"


def test_the_window_on_the_device_at_just_inside_and_just_outside_each_limit():
    """CMD_SET_VMON (and the stored file's parser, the same vmon_cal.ok) accepts each limit
    and the value just inside it; just outside: RES_OUT_OF_RANGE naming the field, nothing changed."""
    cases = list(_window_cases())
    body = PULSES + f"""
s = board()
c = s.chans[0]
out = []
for field, where, g, off, dac in {[(f, w, *_vmon_args(f, v)) for f, w, v, _ in cases]!r}:
    locked(s, hp.cmd_set_vmon(bytearray(64), 0, hp.VMON_APPLY, 1001000, 7, 0, 0))  # a known state before each
    r = locked(s, hp.cmd_set_vmon(bytearray(64), 0, hp.VMON_APPLY, g, off, 0, dac))
    out.append([r, s.tx[hp.O_DETAIL], c.vmon_g, c.vmon_off, c.vmon_dac])
result(out=out)
"""
    _, res, _ = run_fw(body)
    for (field, where, v, ok), (r, detail, g, off, dac) in zip(cases, res[0]["out"]):
        want = _vmon_args(field, v)
        if ok:
            assert (r, g, off, dac) == (hp.RES_OK, *want), (field, where, v)
        else:
            assert (r, detail) == (hp.RES_OUT_OF_RANGE, FIELD_OFFSET[field]), (field, where, v)
            assert (g, off, dac) == (1001000, 7, 0), (field, where, v)  # nothing changed
        assert vmon_cal.ok(*want) is ok, (field, where, v)
        text = vmon_cal.CAL_HEADER + "\n0 %d %d %d\n" % want
        if ok:
            assert vmon_cal.parse(text, 1) == [want if want[0] or want[2] else None]
        else:
            with pytest.raises(ValueError, match="out of range"):
                vmon_cal.parse(text, 1)


@pytest.mark.parametrize("field, where, v, ok", list(_window_cases()))
def test_the_window_on_the_host_before_anything_is_sent(field, where, v, ok):
    """The host's builder (one channel and every channel) accepts what the device accepts and
    refuses the rest with one line naming the value and the accepted range."""
    args = _vmon_args(field, v)
    lo, hi = {"gain": (hp.VMON_GAIN_PPM_MIN, hp.VMON_GAIN_PPM_MAX), "offset": (hp.VMON_OFFSET_MV_MIN,
              hp.VMON_OFFSET_MV_MAX), "dac": (hp.VMON_DAC_PPM_MIN, hp.VMON_DAC_PPM_MAX)}[field]
    c = Commands()
    if ok:
        rep = c.set_vmon(0, args[0], args[1], dac_gain_ppm=args[2])
        assert (hp.get_i32(rep, hp.O_ARG + 4), hp.get_i32(rep, hp.O_ARG + 8), hp.get_i32(rep, hp.O_ARG + 12)) == args
        rep = c.set_vmon_all([(1000000, 0, 0), args], store=True)
        assert hp.get_i32(rep, FIELD_OFFSET[field] + hp.VMON_STRIDE) == v and rep[hp.O_OUT_CH] == hp.CH_ALL
    else:
        for build in (lambda: c.set_vmon(0, args[0], args[1], dac_gain_ppm=args[2]),
                      lambda: c.set_vmon_all([(1000000, 0, 0), args], store=True)):
            with pytest.raises(CommandError) as e:
                build()
            msg = str(e.value)
            assert f"={v} out of range" in msg and f"{lo}..{hi}" in msg and "\n" not in msg, msg


def test_get_info_says_whether_the_board_applies_a_stored_dac_gain(tmp_path):
    """O_INFO_FLAGS (INFO_FLAG_DAC_GAIN): the realistic board scales its DAC by a stored gain,
    the ideal one keeps the commanded current whatever is stored (both report the stored value)."""
    (tmp_path / "vmon_cal.txt").write_text(vmon_cal.CAL_HEADER + "\n1 0 0 1012300\n")
    flash = str(tmp_path)
    reps, res, _ = run_fw(f"""
out = []
for ideal in (False, True):
    bd = SimBoard(cfg, VirtualClock(0), sim_electrode.scenario("steady"), 2, 1, MemoryUSB(True), load_ohm=10000,
                  ideal=ideal, flash_dir={flash!r})
    s = stim.Stimulator(bd, VirtualClock(0), cfg, 2, 50, 0)
    apply(s, hp.cmd_get_info(bytearray(64), 0)); bd.send(s.tx)
    apply(s, hp.cmd_get_info(bytearray(64), 0, 1)); bd.send(s.tx)
    dump(bd.usb)
    out.append([s.tx[hp.O_INFO_FLAGS] if s.tx[0] == hp.REP_INFO else None, bd.set_amplitude(1, 3000)])
result(out=out)
""")
    info = [x for x in reps if isinstance(x, Info)]
    cal = [x for x in reps if isinstance(x, CalInfo)]
    # (the realistic board's ch0 has no DAC gain stored: its hard limits are held too, INFO_FLAG_HELD)
    assert [i.flags for i in info] == [hp.INFO_FLAG_DAC_GAIN | hp.INFO_FLAG_HELD, 0]
    assert [i.dac_gain_applied for i in info] == [True, False]
    assert [c.dac_gain_ppm for c in cal] == [1012300, 1012300]
    real, ideal = res[0]["out"]
    assert ideal[1] == 3000 and real[1] != 3000  # the ideal board: the commanded current, gain or not
    b = bytearray(64)
    b[0] = hp.REP_INFO
    b[hp.O_FW + 3] = 1
    for o, v in ((hp.O_HARD_I, 1000), (hp.O_HARD_T, 100), (hp.O_HARD_Q, 100000), (hp.O_LIM, 1), (hp.O_LIM + 2, 1000),
                 (hp.O_LIM + 4, 20), (hp.O_LIM + 6, 100), (hp.O_LIM + 8, 100000)):
        hp.put_i32(b, o, v) if o in (hp.O_HARD_Q, hp.O_LIM + 8) else hp.put_u16(b, o, v)
    from steadytouch.protocol import decode
    assert decode(bytes(b)).flags == 0  # firmware before the flag: 0, "not applied" (never claimed)
    # a bit this host does not know (a later firmware's new flag): ignored, never a refused session
    # (review of d560dd3, finding 7: every session broke); the known bit still reads as before
    for flags, applied in ((0x02, False), (0xFE, False), (0x03, True), (0xFF, True)):
        b[hp.O_INFO_FLAGS] = flags
        i = decode(bytes(b))
        assert i.dac_gain_applied is applied and i.flags == flags


def test_store_to_every_channel_is_all_or_nothing_on_the_device(tmp_path):
    """CMD_SET_VMON to CH_ALL with VMON_STORE: one file write for every channel. A refusal of
    the second channel's values, or a failed flash write, leaves the first channel's stored
    and applied correction, and the file, as they were."""
    flash = str(tmp_path)
    old = vmon_cal.CAL_HEADER + "\n0 1020000 100 0\n1 990000 -50 0\n"
    (tmp_path / "vmon_cal.txt").write_text(old)
    body = PULSES + f"""
s = board(flash_dir={flash!r})
def state():
    return [[c.vmon_g, c.vmon_off, c.vmon_dac, c.vmon_stored] for c in s.chans]
before = state()
r_bad = locked(s, hp.cmd_set_vmon_all(bytearray(64), hp.VMON_STORE, [(1050000, 200, 0), (1090001, 0, 0)]))
d_bad = s.tx[hp.O_DETAIL]
after_bad = state()
import os
os.mkdir({flash!r} + "/vmon_cal.txt.tmp")  # the flash write fails (the temporary file cannot be opened)
r_fail = locked(s, hp.cmd_set_vmon_all(bytearray(64), hp.VMON_STORE, [(1050000, 200, 0), (1060000, 0, 0)]))
after_fail = state()
text_fail = open({flash!r} + "/vmon_cal.txt").read()
os.rmdir({flash!r} + "/vmon_cal.txt.tmp")
r_ok = locked(s, hp.cmd_set_vmon_all(bytearray(64), hp.VMON_STORE, [(1050000, 200, 0), (1060000, -20, 0)]))
after_ok = state()
s2 = board(flash_dir={flash!r})  # a reset
r_apply = locked(s, hp.cmd_set_vmon_all(bytearray(64), hp.VMON_APPLY, [(0, 0, 0), (1001000, 3, 0)]))  # heap-locked
applied = state()
result(before=before, r=[r_bad, d_bad, r_fail, r_ok], after_bad=after_bad, after_fail=after_fail, after_ok=after_ok,
       text_fail=text_fail, r_apply=r_apply, applied=applied,
       reset=[[c.vmon_g, c.vmon_off] for c in s2.chans], state=s2.vmon_state)
"""
    _, res, _ = run_fw(body)
    r = res[0]
    assert r["r"] == [hp.RES_OUT_OF_RANGE, hp.O_ARG + 4 + hp.VMON_STRIDE, hp.RES_STORE_FAILED, hp.RES_OK]
    assert r["before"][0][:2] == [1020000, 100]
    assert r["after_bad"] == r["before"] and r["after_fail"] == r["before"]  # channel 0 untouched by either failure
    assert r["text_fail"] == old  # the file too
    assert r["after_ok"][0][:2] == [1050000, 200] and r["after_ok"][1][:2] == [1060000, -20]
    assert r["reset"] == [[1050000, 200], [1060000, -20]] and r["state"] == hp.VMON_LOADED
    # every channel in RAM, inside the heap-locked command section: applied, the flash's values kept
    assert r["r_apply"] == hp.RES_OK and [a[:3] for a in r["applied"]] == [[0, 0, 0], [1001000, 3, 0]]
    assert [a[3] for a in r["applied"]] == [[1050000, 200, 0], [1060000, -20, 0]]


def test_set_vmon_reserved_bytes_must_be_zero(tmp_path):
    """Review of d560dd3 (finding 4): bytes after the words a SET_VMON carries, up to the CRC, are
    reserved: a CH_ALL command's 56..61, a one-channel command's 20..61. Anything there is refused
    with RES_BAD_FORMAT naming the byte, nothing changes (a one-channel command in CH_ALL's layout
    applied channel 0 only and answered RES_OK)."""
    body = PULSES + f"""
s = board(flash_dir={str(tmp_path)!r})
def state():
    return [[c.vmon_g, c.vmon_off, c.vmon_dac] for c in s.chans]
before = state()
out = []
rep = hp.cmd_set_vmon_all(bytearray(64), hp.VMON_APPLY, [(1010000, 10, 0), (1020000, 20, 0)])
for o in (56, 61):
    r2 = bytearray(rep); r2[o] = 0x5a; hp.seal(r2)
    out.append([locked(s, r2), s.tx[hp.O_DETAIL]])
one = bytearray(rep); one[hp.O_OUT_CH] = 0; hp.seal(one)  # channel 1's words in a one-channel command
out.append([locked(s, one), s.tx[hp.O_DETAIL]])
for o in (20, 61):
    r2 = hp.cmd_set_vmon(bytearray(64), 1, hp.VMON_STORE, 1010000, 10); r2[o] = 1; hp.seal(r2)
    out.append([locked(s, r2), s.tx[hp.O_DETAIL]])
after = state()
ok = [locked(s, rep), locked(s, hp.cmd_set_vmon(bytearray(64), 1, hp.VMON_APPLY, 1030000, 5))]
result(out=out, same=before == after, ok=ok, state=state())
"""
    _, res, _ = run_fw(body)
    r = res[0]
    assert r["out"] == [[hp.RES_BAD_FORMAT, 56], [hp.RES_BAD_FORMAT, 61], [hp.RES_BAD_FORMAT, 20],
                        [hp.RES_BAD_FORMAT, 20], [hp.RES_BAD_FORMAT, 61]]
    assert r["same"] and not (tmp_path / "vmon_cal.txt").exists()
    assert r["ok"] == [hp.RES_OK, hp.RES_OK] and r["state"] == [[1010000, 10, 0], [1030000, 5, 0]]


def test_a_store_that_raises_anything_is_answered_store_failed_with_the_heap_unlocked(tmp_path):
    """Review of d560dd3 (finding 6): a store raising something other than OSError (MemoryError while
    building the file's text) escaped handle(): no answer, the heap left locked. Now it is answered
    RES_STORE_FAILED through the loop's command path, nothing applied, the heap unlocked."""
    body = PULSES + f"""
s = board(flash_dir={str(tmp_path)!r})
before = [[c.vmon_g, c.vmon_off, c.vmon_dac, c.vmon_stored] for c in s.chans]
def boom(values):
    raise MemoryError("simulated")
s.board.store_vmon = boom
s.board.usb.sent.clear()
s.rx[:] = hp.cmd_set_vmon_all(bytearray(64), hp.VMON_STORE, [(1010000, 10, 0), (1020000, 20, 0)], 7)
try:
    s._serve_commands(s.clock.ticks_us())
    raised = None
except Exception as e:
    import micropython
    while micropython.heap_unlock():
        pass
    raised = repr(e)
x = [1, 2, 3]  # allocates: the heap is unlocked
acks = [[r[hp.O_RESULT], r[hp.O_TAG]] for r in s.board.usb.sent if r[0] == hp.REP_ACK]
result(raised=raised, locked=s.locked, acks=acks,
       same=before == [[c.vmon_g, c.vmon_off, c.vmon_dac, c.vmon_stored] for c in s.chans], state=s.vmon_state)
"""
    _, res, _ = run_fw(body)
    r = res[0]
    assert r["raised"] is None and r["locked"] == 0
    assert r["acks"] == [[hp.RES_STORE_FAILED, 7]]
    assert r["same"] and r["state"] == hp.VMON_NONE


def test_a_store_keeps_the_lines_of_channels_the_stimulator_does_not_drive(tmp_path):
    """Review of d560dd3 (finding 8): a Stimulator driving 1 channel of a 2-channel board rewrote the
    file from its own channels only, dropping channel 1's line. The other lines are kept."""
    (tmp_path / "vmon_cal.txt").write_text(vmon_cal.CAL_HEADER + "\n0 1020000 100 0\n1 990000 -50 1006000\n")
    body = PULSES + f"""
clock = VirtualClock(0)
bd = SimBoard(cfg, clock, sim_electrode.scenario("steady"), 2, 1, MemoryUSB(True), noise_counts=0.0, load_ohm=10000,
              flash_dir={str(tmp_path)!r})
s = stim.Stimulator(bd, clock, cfg, 1, 50, 0)
r = [locked(s, hp.cmd_set_vmon(bytearray(64), 0, hp.VMON_STORE, 1011000, 150)),
     locked(s, hp.cmd_set_vmon_all(bytearray(64), hp.VMON_STORE, [(1012000, 151, 0)]))]
result(n=s.n, r=r)
"""
    _, res, _ = run_fw(body)
    assert res[0] == {"n": 1, "r": [hp.RES_OK, hp.RES_OK]}
    assert vmon_cal.parse((tmp_path / "vmon_cal.txt").read_text(), 2) == [(1012000, 151, 0), (990000, -50, 1006000)]


def _info(n_channels):
    from steadytouch.protocol import decode

    b = bytearray(64)
    b[0] = hp.REP_INFO
    b[hp.O_FW + 3] = n_channels
    for o, v in ((hp.O_HARD_I, 1000), (hp.O_HARD_T, 100), (hp.O_LIM, 1), (hp.O_LIM + 2, 1000),
                 (hp.O_LIM + 4, 20), (hp.O_LIM + 6, 100)):
        hp.put_u16(b, o, v)
    hp.put_i32(b, hp.O_HARD_Q, 100000)
    hp.put_i32(b, hp.O_LIM + 8, 100000)
    return decode(bytes(b))


def test_set_vmon_all_takes_exactly_the_devices_channel_count_once_known():
    """Review of d560dd3 (finding 3): fewer values than the device has channels were sent, the
    missing ones read by the device as 0 (uncorrected, DAC nominal) and stored. Once GET_INFO told
    the count (Commands.know), exactly that many are required; before, 1..4 (documented)."""
    c = Commands()
    assert c.set_vmon_all([(1011000, 150, 0)], store=True)  # the count not known yet: 1..4
    c.know(_info(2))
    for n in (1, 3, 4):
        with pytest.raises(CommandError, match="the device has 2, give exactly 2"):
            c.set_vmon_all([(1011000, 150, 0)] * n, store=True)
    rep = c.set_vmon_all([(1011000, 150, 0), (0, 0, 0)], store=True)
    assert hp.get_i32(rep, hp.O_ARG + 4) == 1011000


@pytest.mark.parametrize("values", [
    [(1000000, 0, 0, 1)], [(1000000,)], [5], [None], [{"g": 1}], [("1000000", 0, 0)], "abc", 7, None,
    {"g": 1}, [b"abc"], [(1000000, 0)], [], [(1000000, 0, 0)] * 5, [(float("nan"), 0, 0)]])
def test_set_vmon_all_refuses_any_other_shape_with_one_line(values):
    """Review of d560dd3 (finding 5): a 4-tuple, 1-tuple, scalar, None, dict, string or int raised
    TypeError tracebacks. Each is one CommandError line naming what is expected."""
    with pytest.raises(CommandError) as e:
        Commands().set_vmon_all(values, store=True)
    assert "\n" not in str(e.value) and ("monitor correction" in str(e.value) or "gain_ppm" in str(e.value))


def test_a_session_on_a_board_that_ignored_its_stored_correction_says_so_in_one_line(tmp_path):
    """Review of d560dd3 (finding 2a): a file stored under the old, wider windows (monitor gain 1.095)
    is ignored at boot (VMON_BAD) and only `info` told. Now calibrate/arm/record/monitor print one
    stderr line (what happened, what to do), and a Session logs it; a board with a valid file or none
    prints nothing."""
    import os
    import subprocess
    from pathlib import Path

    from steadytouch.device import vmon_warning
    from steadytouch.session import Session

    exe = str(Path(sys.executable).parent / "steadytouch")
    env = dict(os.environ, STEADYTOUCH_SIM_FLASH=str(tmp_path))
    args = [exe, "calibrate", "--device", "sim://steady", "--i0-ua", "3000", "--t0-us", "300", "--x-star-ohm",
            "-1670", "--y-star-pc", "0"]
    for text, warned in ((vmon_cal.CAL_HEADER + "\n0 1095000 0 0\n1 0 0 1006000\n", True),
                         (vmon_cal.CAL_HEADER + "\n0 1000000 1500 0\n", True),
                         (vmon_cal.CAL_HEADER + "\n0 1010000 0 0\n1 0 0 1006000\n", False), (None, False)):
        if text is None:
            (tmp_path / "vmon_cal.txt").unlink()
        else:
            (tmp_path / "vmon_cal.txt").write_text(text)
        p = subprocess.run(args, capture_output=True, text=True, env=env, timeout=60)
        assert p.returncode == 0, p.stderr
        lines = [ln for ln in p.stderr.splitlines() if "ignored its stored correction" in ln]
        assert len(lines) == (1 if warned else 0), (text, p.stderr)
        if warned:
            assert "run `steadytouch selftest` again" in lines[0] and "uncorrected" in lines[0]
    logged = []

    class Dev:
        def info(self):
            return _info_with(hp.VMON_BAD)

    Session(Dev(), None, log=logged.append)
    assert logged == [vmon_warning(hp.VMON_BAD)] and logged[0]
    assert [vmon_warning(v) for v in (hp.VMON_NONE, hp.VMON_LOADED, hp.VMON_STORED)] == [None] * 3


def _info_with(state):
    import dataclasses

    return dataclasses.replace(_info(2), vmon_state=state)


FOUR = (vmon_cal.CAL_HEADER + "\n0 1020000 100 0\n1 990000 -50 1006000\n2 1030000 -200 994000\n"
        "3 0 0 1012000\n")  # stored by a 4-channel build


def test_store_keeps_the_lines_of_channels_this_board_is_not_built_with_on_cpython(tmp_path):
    """Issue 13 (deliverable 4's loose ends): a correction measured on a 4-channel build was lost when a
    2-channel build stored its own (store rewrote the file from this board's channels only). The lines of
    channels past the board's are kept as they stand; a file the firmware ignores (corrupt, out of its
    windows) is replaced whole; no file: only this board's lines."""
    p = tmp_path / "vmon_cal.txt"
    p.write_text(FOUR)
    assert vmon_cal.store(str(p), [(1011000, 150, 0), None])  # ch1 cleared (uncorrected), ch2 and ch3 kept
    assert vmon_cal.parse(p.read_text(), 4) == [(1011000, 150, 0), None, (1030000, -200, 994000), (0, 0, 1012000)]
    assert vmon_cal.parse(p.read_text(), 2) == [(1011000, 150, 0), None]
    assert not (tmp_path / "vmon_cal.txt.tmp").exists()
    for bad in ("garbage\n", FOUR + "2 5000000 0 0\n", FOUR.replace("-200", "-5000"), "\xff\xfe"):
        p.write_bytes(bad.encode("latin-1"))
        assert vmon_cal.store(str(p), [(1011000, 150, 0), None])
        assert vmon_cal.parse(p.read_text(), 4) == [(1011000, 150, 0), None, None, None], bad
    p.unlink()
    assert vmon_cal.store(str(p), [None, (990000, -50, 1006000)])
    assert vmon_cal.parse(p.read_text(), 4) == [None, (990000, -50, 1006000), None, None]


def test_store_keeps_the_other_builds_lines_on_the_simulated_board_in_the_vm(tmp_path):
    """The same on the device: a 2-channel SimBoard in the MicroPython VM stores with SET_VMON to every
    channel (VMON_STORE, heap-locked section left for the write); the next boot of a 4-channel board
    loads all four."""
    (tmp_path / "vmon_cal.txt").write_text(FOUR)
    body = PULSES + f"""
s = board(flash_dir={str(tmp_path)!r})
r = locked(s, hp.cmd_set_vmon_all(bytearray(64), hp.VMON_STORE, [(1011000, 150, 0), (0, 0, 0)]))
bd4 = SimBoard(cfg, VirtualClock(0), sim_electrode.scenario("steady"), 4, 1, MemoryUSB(True), noise_counts=0.0,
               load_ohm=10000, flash_dir={str(tmp_path)!r})
result(r=r, state=s.vmon_state, four=[list(v) if v else None for v in bd4.vmon_cal], state4=bd4.vmon_state)
"""
    _, res, _ = run_fw(body)
    assert res[0] == {"r": hp.RES_OK, "state": hp.VMON_STORED, "state4": hp.VMON_LOADED,
                      "four": [[1011000, 150, 0], None, [1030000, -200, 994000], [0, 0, 1012000]]}


RP2_STORE = """
import sys, time, types
sys.path[:0] = [{tests!r}, {firmware!r}, {shared!r}]
import fake_rp2
fake_rp2.install().asm_pio_encode = lambda text, side: 0
machine = types.ModuleType("machine")
machine.disable_irq = lambda: 0
machine.enable_irq = lambda state: None
sys.modules["machine"] = machine
mp = types.ModuleType("micropython")
mp.const = lambda x: x
mp.viper = mp.native = lambda f: f
sys.modules["micropython"] = mp
sys.modules["uctypes"] = types.ModuleType("uctypes")
for name in ("ticks_us", "ticks_ms", "ticks_diff", "ticks_add", "sleep_us", "sleep_ms"):
    setattr(time, name, lambda *a: 0)
import board_rp2
path = sys.argv[1]
ok = board_rp2.Board.store_vmon(None, [(1011000, 150, 0), None], path)  # (store_vmon uses nothing of self)
print(repr([ok, board_rp2.load_vmon(4, path)]))
"""


def test_store_keeps_the_other_builds_lines_on_the_rp2_boards_path(tmp_path):
    """board_rp2's own store and boot load (the rp2 board's code, imported on CPython with the tests'
    fake rp2 and stand-ins for machine, micropython and uctypes)."""
    import subprocess

    from conftest import ROOT, SHARED

    (tmp_path / "vmon_cal.txt").write_text(FOUR)
    script = RP2_STORE.format(tests=str(ROOT / "tests"), firmware=str(FIRMWARE), shared=str(SHARED))
    p = subprocess.run([sys.executable, "-c", script, str(tmp_path / "vmon_cal.txt")], capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    ok, (values, state) = eval(p.stdout.strip().splitlines()[-1])
    assert ok is True and state == hp.VMON_LOADED
    assert values == [(1011000, 150, 0), None, (1030000, -200, 994000), (0, 0, 1012000)]


def test_a_file_past_the_size_cap_is_ignored_at_boot_and_replaced_by_a_store_in_a_small_heap(tmp_path):
    """Review rev-lims F2: store read the old file whole to keep other builds' lines, so a big file (a
    recording copied over it by mistake) ran a 146 KB chip out of memory and every store failed. Now boot,
    kept and flash's read stop at CAL_MAX_BYTES: a longer file is one boot ignores, and a store replaces
    it. Run in the MicroPython VM with a 100 KB heap (MemoryError before)."""
    import subprocess

    from conftest import SHARED, tool

    cap = vmon_cal.CAL_MAX_BYTES
    ok = FOUR.encode()
    at_cap = ok + b"#" * (cap - len(ok) - 1) + b"\n"
    cases = {"at cap": at_cap, "one past": at_cap + b"\n", "128 KB": (b"not a correction: a recording\n" * 4500),
             "128 KB valid start": ok + b"# note\n" * 19000}
    for k, data in enumerate(cases.values()):
        (tmp_path / f"{k}.txt").write_bytes(data)
    script = f"""
import vmon_cal
for k in range({len(cases)}):
    p = {str(tmp_path)!r} + "/%d.txt" % k
    st = vmon_cal.boot_load(p, 2)[1]
    kept = vmon_cal.kept(p, 2)
    ok = vmon_cal.store(p, [(1010000, 0, 1000000), None])
    print(repr((st, kept, ok, vmon_cal.boot_load(p, 4))))
"""
    env = dict(__import__("os").environ, MICROPYPATH=f"{SHARED}:{FIRMWARE}")
    p = subprocess.run([tool("micropython"), "-X", "heapsize=100K", "-c", script], capture_output=True, text=True,
                       timeout=60, env=env)
    assert p.returncode == 0, p.stdout + p.stderr
    rows = dict(zip(cases, [eval(ln) for ln in p.stdout.splitlines()]))
    four = [(1020000, 100, 0), (990000, -50, 1006000), (1030000, -200, 994000), (0, 0, 1012000)]
    assert rows["at cap"][:3] == (hp.VMON_LOADED, [(2,) + four[2], (3,) + four[3]], True)
    assert rows["at cap"][3] == ([(1010000, 0, 1000000), None] + four[2:], hp.VMON_LOADED)
    for name in ("one past", "128 KB", "128 KB valid start"):
        assert rows[name] == (hp.VMON_BAD, [], True, ([(1010000, 0, 1000000), None, None, None], hp.VMON_LOADED)), \
            name
    assert "longer than 4096 bytes" in str(pytest.raises(ValueError, vmon_cal.entries, at_cap + b"\n").value)


def test_kept_counts_a_memory_error_as_a_file_boot_would_ignore(tmp_path, monkeypatch):
    """A MemoryError reading or checking the old file: nothing kept, the store goes on (was: the store failed)."""
    p = tmp_path / "vmon_cal.txt"
    p.write_text(FOUR)

    def no_memory(text):
        raise MemoryError("memory allocation failed")

    monkeypatch.setattr(vmon_cal, "entries", no_memory)
    assert vmon_cal.kept(str(p), 2) == []
    assert vmon_cal.store(str(p), [(1011000, 150, 0), None])
    monkeypatch.undo()
    assert vmon_cal.parse(p.read_bytes(), 4) == [(1011000, 150, 0), None, None, None]
