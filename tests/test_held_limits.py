"""The held limits (issue 13, docs/safety.md "no DAC gain known"): while a channel of a board whose
current is not exactly the commanded one has no DAC gain applied, the hard current and charge limits
in force are the board's x VMON_DAC_PPM_MIN (0.965: 9650 uA of 10000). The soft limits never go above
them (at boot and after every SET_VMON), SET_LIMITS refuses above them, GET_INFO reports them
(O_HARD_I / O_HARD_Q, INFO_FLAG_HELD), and the host refuses ahead with the reason. Each test fails on
the firmware before this (soft i_max 10000 on such a board: a pulse above 9650 latched STOP_LIMIT at the
gate, with no warning and no reason given to the host)."""

import subprocess
import sys
from pathlib import Path

import hid_protocol as hp
import sensation_core as sc
from steadytouch.protocol import Info, Telemetry, decode

from conftest import ROOT
from fw_harness import run_fw

EXE = str(Path(sys.executable).parent / "steadytouch")
HARD_I, HARD_Q = 10000, 10_000_000  # board_config's nominal hard limits (checked below against the device)
HELD_I, HELD_Q = HARD_I * hp.VMON_DAC_PPM_MIN // 1000000, HARD_Q * hp.VMON_DAC_PPM_MIN // 1000000


def dac_held(x, gain_ppm):
    """The hard limit x (uA or pC) held for a stored DAC gain (stim._dac_limits): x gain / VMON_DAC_PPM_MAX, rounded
    down per 10 000, so the physical current stays within x for any true gain in the window (review of session 22:
    the full limits at a gain >= 1 let 10 058 uA through on a DAC whose true gain is 1.006)."""
    f = (gain_ppm // 100) * 10000 // (hp.VMON_DAC_PPM_MAX // 100)
    h = x * f // 10000
    assert x * gain_ppm / hp.VMON_DAC_PPM_MAX - x / 5000 <= h <= x * gain_ppm / hp.VMON_DAC_PPM_MAX
    return h


LOW_I, LOW_Q = dac_held(HARD_I, 1000000), dac_held(HARD_Q, 1000000)  # a DAC gain of 1.000 stored: 9661 uA, 9.661 uC

SETUP = """
def board(ideal=False, flash=None, n=2):
    clock = VirtualClock(0)
    bd = SimBoard(cfg, clock, sim_electrode.scenario("steady"), n, 1, MemoryUSB(True), ideal=ideal,
                  flash_dir=flash, load_ohm=1000)
    return stim.Stimulator(bd, clock, cfg, n, 50, 0), bd, clock

def framed(s, rep):
    # one report handled inside a real frame (heap-locked, as on the device); its answer
    usb = s.board.usb
    usb.sent.clear()
    usb.inbox.append(bytes(rep))
    s.run(1)
    ans = [r for r in usb.sent if r[0] != hp.REP_TELEMETRY]
    usb.sent.clear()
    assert len(ans) == 1 and s.errors == 0, (len(ans), s.errors, s.last_error)
    return bytes(ans[0]).hex()

def limits(s):
    # the soft limits, every controller's, every channel's calibration flag and held hard limits
    return [list(s.lim), [[c.ctl.i_min_ua, c.ctl.i_max_ua, c.ctl.t_min_us, c.ctl.t_max_us, c.ctl.q_max_pc]
                          for c in s.chans], [c.have_cal for c in s.chans], [[c.hard_i_d, c.hard_q_d] for c in s.chans]]
"""


def _info(hexrep) -> Info:
    i = decode(bytes.fromhex(hexrep))
    assert isinstance(i, Info)
    return i


def _ack(hexrep):
    a = decode(bytes.fromhex(hexrep))
    return a.command, a.result, a.detail


def test_boot_without_a_dac_gain_holds_the_soft_limits_and_get_info_reports_the_held_limits(tmp_path):
    """Boot: a fresh realistic board, one whose file has a DAC gain on one channel only, and the ideal board
    (its current exactly the commanded one) and a realistic one whose file has a gain on every channel (not held:
    lowered to the hard limits x the lowest gain / VMON_DAC_PPM_MAX, INFO_FLAG_DAC_LOW)."""
    one, every = tmp_path / "one", tmp_path / "every"
    one.mkdir()
    every.mkdir()
    (one / "vmon_cal.txt").write_text("steadytouch monitor correction v1\n0 0 0 1000000\n")
    (every / "vmon_cal.txt").write_text("steadytouch monitor correction v1\n0 0 0 1000000\n1 0 0 1006000\n")
    _, res, _ = run_fw(SETUP + f"""
out = {{}}
for name, ideal, flash in (("fresh", False, None), ("one gain", False, {str(one)!r}), ("ideal", True, None),
                           ("every gain", False, {str(every)!r})):
    s, bd, clock = board(ideal, flash)
    out[name] = [limits(s), framed(s, hp.cmd_get_info(bytearray(64), 5)), s.hard_i, s.hard_q, s.vmon_state]
result(**out)
""")
    r = res[0]
    for name in ("fresh", "one gain", "ideal", "every gain"):
        assert r[name][2:4] == [HARD_I, HARD_Q], name  # the board's nominal limits (board_config)
    for name, held, want_i, want_q in (("fresh", True, HELD_I, HELD_Q), ("one gain", True, HELD_I, HELD_Q),
                                       ("ideal", False, HARD_I, HARD_Q), ("every gain", False, LOW_I, LOW_Q)):
        (lim, ctl, _cal, hard_d), info_hex, _, _, _ = r[name]
        i = _info(info_hex)
        assert (i.hard_i_max_ua, i.hard_q_max_pc, i.held) == (want_i, want_q, held), name
        assert i.dac_low == (name == "every gain"), name  # lowered x the gain / 1.035, said so
        assert i.hard_t_max_us == 8000  # the width limit is not held
        assert (lim[1], lim[4]) == (want_i, want_q) == (i.i_max_ua, i.q_max_pc), (name, lim)  # boot soft = held
        assert all(c[1] == want_i and c[4] == want_q for c in ctl), (name, ctl)  # every controller has them
        assert min(h[0] for h in hard_d) == want_i
    assert r["every gain"][0][3] == [[LOW_I, LOW_Q], [dac_held(HARD_I, 1006000), dac_held(HARD_Q, 1006000)]]
    assert _info(r["ideal"][1]).dac_gain_applied is False and _info(r["fresh"][1]).dac_gain_applied is True
    assert r["one gain"][4] == r["every gain"][4] == hp.VMON_LOADED


def test_set_limits_above_the_held_limit_is_refused_and_changes_nothing():
    _, res, _ = run_fw(SETUP + """
s, bd, clock = board()
b = bytearray(64)
pre = [framed(s, hp.cmd_set_mode(b, sc.MODE_OPEN_LOOP)), framed(s, hp.cmd_calibrate(b, hp.CH_ALL, 3000, 1000, -1670, 0))]
before = limits(s)
held_i, held_q = s.lim[1], s.lim[4]
refused = [framed(s, hp.cmd_set_limits(b, 100, held_i + 1, 50, 4000, held_q)),
           framed(s, hp.cmd_set_limits(b, 100, s.hard_i, 50, 4000, held_q)),
           framed(s, hp.cmd_set_limits(b, 100, held_i, 50, 4000, held_q + 1)),
           framed(s, hp.cmd_set_limits(b, 100, held_i, 50, 4000, s.hard_q)),
           framed(s, hp.cmd_calibrate(b, hp.CH_ALL, held_i + 1, 100, -1670, 0))]
after = limits(s)
ok = framed(s, hp.cmd_set_limits(b, 100, held_i, 50, 4000, held_q))  # at the held limits: accepted
result(pre=pre, before=before, after=after, refused=refused, ok=ok, at=limits(s), held=[held_i, held_q])
""")
    r = res[0]
    assert r["held"] == [HELD_I, HELD_Q]
    assert [_ack(a)[1] for a in r["pre"]] == [hp.RES_OK, hp.RES_OK]
    assert [_ack(a) for a in r["refused"]] == [
        (hp.CMD_SET_LIMITS, hp.RES_OUT_OF_RANGE, hp.O_ARG + 2), (hp.CMD_SET_LIMITS, hp.RES_OUT_OF_RANGE, hp.O_ARG + 2),
        (hp.CMD_SET_LIMITS, hp.RES_OUT_OF_RANGE, hp.O_ARG + 8), (hp.CMD_SET_LIMITS, hp.RES_OUT_OF_RANGE, hp.O_ARG + 8),
        (hp.CMD_CALIBRATE, hp.RES_OUT_OF_RANGE, hp.O_ARG)]
    assert r["after"] == r["before"]  # nothing changed: soft limits, controllers, calibrations
    assert r["before"][2] == [True, True]
    assert _ack(r["ok"]) == (hp.CMD_SET_LIMITS, hp.RES_OK, 0)
    assert r["at"][0] == [100, HELD_I, 50, 4000, HELD_Q] and r["at"][2] == [True, True]


def test_a_stored_dac_gain_lets_set_limits_reach_the_limit_it_holds_and_a_removed_one_lowers_them(tmp_path):
    """A DAC gain stored on every channel (VMON_STORE, heap-locked) lifts the hold: GET_INFO reports the hard limits
    x that gain / VMON_DAC_PPM_MAX (1.000 stored: 9661 uA; the full limits only at 1.035, review of session 22), the
    soft ones stay where they were until SET_LIMITS raises them (up to that limit, accepted; one above it refused),
    a pulse there is delivered, its physical current within the hard limit; the next boot starts there. A gain removed
    again (VMON_APPLY, heap-locked) lowers the soft limits at once, every controller's with them, and drops
    only the calibrations above them."""
    d = str(tmp_path)
    _, res, _ = run_fw(SETUP + f"""
s, bd, clock = board(flash={d!r}, n=3)
b = bytearray(64)
r = {{}}
r["store"] = framed(s, hp.cmd_set_vmon_all(b, hp.VMON_STORE, [(0, 0, 1000000)] * 3))
r["stored"] = limits(s)
r["info"] = framed(s, hp.cmd_get_info(b))
r["above"] = [framed(s, hp.cmd_set_limits(b, 100, s.hard_i, 50, 4000, s.held_limit(1))),
              framed(s, hp.cmd_set_limits(b, 100, s.held_limit(0), 50, 4000, s.held_limit(1) + 1))]
r["acks"] = [framed(s, hp.cmd_set_limits(b, 100, s.held_limit(0), 50, 4000, s.held_limit(1))),
             framed(s, hp.cmd_set_mode(b, sc.MODE_OPEN_LOOP)),
             framed(s, hp.cmd_calibrate(b, 0, s.held_limit(0), 1000, -1670, 0)),
             framed(s, hp.cmd_calibrate(b, 1, 3000, 1000, -1670, 0)),
             framed(s, hp.cmd_calibrate(b, 2, 3000, 1000, -1670, 0)),
             framed(s, hp.cmd_arm(b, hp.CH_ALL))]
s.run(4)
r["pulses"] = [[c.stop, c.di, bd.last_i_ua[c.ch]] for c in s.chans]
r["acks"].append(framed(s, hp.cmd_disarm(b, hp.CH_ALL)))
r["raised"] = limits(s)
r["removed"] = framed(s, hp.cmd_set_vmon(b, 2, hp.VMON_APPLY, 0, 0))
r["lowered"] = limits(s)
r["info2"] = framed(s, hp.cmd_get_info(b))
r["arm"] = [framed(s, hp.cmd_arm(b, 0)), framed(s, hp.cmd_arm(b, 1)), framed(s, hp.cmd_arm(b, 2))]
s2, bd2, _ = board(flash={d!r}, n=3)  # the next boot, from the stored file
r["boot"] = limits(s2)
result(**r)
""")
    r = res[0]
    assert _ack(r["store"]) == (hp.CMD_SET_VMON, hp.RES_OK, 0)
    assert r["stored"][0][1] == HELD_I and r["stored"][0][4] == HELD_Q  # not raised by the store itself
    assert [h for h in r["stored"][3]] == [[LOW_I, LOW_Q]] * 3  # the hold is lifted on every channel: x 1 / 1.035
    i = _info(r["info"])
    assert (i.hard_i_max_ua, i.hard_q_max_pc, i.held, i.dac_low, i.i_max_ua) == (LOW_I, LOW_Q, False, True, HELD_I)
    assert [_ack(a) for a in r["above"]] == [(hp.CMD_SET_LIMITS, hp.RES_OUT_OF_RANGE, hp.O_ARG + 2),
                                             (hp.CMD_SET_LIMITS, hp.RES_OUT_OF_RANGE, hp.O_ARG + 8)]
    assert [_ack(a)[1] for a in r["acks"]] == [hp.RES_OK] * 7
    assert r["raised"][0] == [100, LOW_I, 50, 4000, LOW_Q]
    for stop, di, phys in r["pulses"]:
        assert stop == hp.STOP_NONE and 0 < di <= LOW_I and phys <= HARD_I, r["pulses"]
    assert LOW_I - 5 <= r["pulses"][0][1]  # ch0 at the limit in force (the DAC rounds down)
    # ch2's gain removed: the soft limits follow its held limit down, ch0's calibration at 10000 uA is dropped,
    # ch1's at 3000 uA kept (ch2's is dropped by its gain change itself: the same code is another current)
    assert _ack(r["removed"]) == (hp.CMD_SET_VMON, hp.RES_OK, 0)
    lim, ctl, cal, hard_d = r["lowered"]
    assert lim == [100, HELD_I, 50, 4000, HELD_Q] and all(c == lim for c in ctl)
    assert hard_d == [[LOW_I, LOW_Q], [LOW_I, LOW_Q], [HELD_I, HELD_Q]]
    assert cal == [False, True, False]
    i = _info(r["info2"])
    assert (i.hard_i_max_ua, i.hard_q_max_pc, i.held, i.i_max_ua, i.q_max_pc) == (HELD_I, HELD_Q, True, HELD_I, HELD_Q)
    assert [_ack(a)[1] for a in r["arm"]] == [hp.RES_NOT_CALIBRATED, hp.RES_OK, hp.RES_NOT_CALIBRATED]
    assert r["boot"][0][1] == LOW_I and r["boot"][0][4] == LOW_Q  # boots with every gain applied: x 1 / 1.035


def run_cli(*args, env=None):
    return subprocess.run([EXE, *args], capture_output=True, text=True, timeout=240, cwd=ROOT, env=env)


def test_a_closed_loop_on_the_realistic_sim_that_wants_more_is_clamped_not_latched(tmp_path):
    """`steadytouch sim` on the realistic board (no DAC gain): the gel step drops Rp and the Akhtar law asks
    for more than the held 9650 uA; the core clamps it there (bound) and the channel keeps stimulating (was:
    latched STOP_LIMIT at the gate at the first such pulse). The recording's header carries the limits the
    device ran with, so `audit` replays it bit-exact."""
    p = run_cli("sim", "gel-step", "--mode", "akhtar", "--i0-ua", "8000", "--t0-us", "300", "--x-star-ohm", "-1670",
                "--y-star-pc", "0", "--no-plot", "--out", str(tmp_path))
    assert p.returncode == 0, p.stderr
    from steadytouch.record import read_recording

    meta, rows = read_recording(tmp_path / "gel-step-akhtar.csv")
    assert int(meta["i_max_ua"]) == HELD_I and int(meta["q_max_pc"]) == HELD_Q
    pulses = [r for r in rows if r["i_ua"]]
    assert len(pulses) >= 250 and all(r["stop"] == hp.STOP_NONE for r in rows)
    bound = [r for r in pulses if r["status"] & sc.ST_BOUND_MASK]
    assert bound and max(r["next_i_ua"] for r in pulses) == HELD_I  # the law wanted more: clamped at the held limit
    assert HELD_I - 3 <= max(r["i_ua"] for r in pulses) <= HELD_I  # delivered there (the DAC rounds down)
    a = run_cli("audit", str(tmp_path / "gel-step-akhtar.csv"))
    assert a.returncode == 0 and "bit-exact" in a.stdout, a.stdout + a.stderr


def test_the_host_refuses_above_the_held_limit_ahead_with_the_reason(tmp_path):
    url = "sim://steady?channels=2"
    p = run_cli("info", "--device", url)
    assert p.returncode == 0, p.stderr
    assert f"hard limits: I <= {HELD_I} uA, T <= 8000 us, Q <= {HELD_Q} pC" in p.stdout and "(held)" in p.stdout
    assert "no DAC gain was measured" in p.stdout and "selftest --load-ohm OHMS --scope" in p.stdout
    for args, words in (
            (["limits", "--i-min-ua", "500", "--i-max-ua", "9800", "--t-min-us", "100", "--t-max-us", "4000",
              "--q-max-pc", "5000000"], f"i_max_ua=9800 out of range: the device accepts 1..{HELD_I} uA"),
            (["limits", "--i-min-ua", "500", "--i-max-ua", "5000", "--t-min-us", "100", "--t-max-us", "4000",
              "--q-max-pc", str(HARD_Q)], f"q_max_pc={HARD_Q} out of range: the device accepts up to {HELD_Q} pC"),
            (["calibrate", "--i0-ua", "9800", "--t0-us", "100", "--x-star-ohm", "-1670", "--y-star-pc", "0"],
             f"i0_ua=9800 out of range: the device's soft limits are 500..{HELD_I} uA"),
            (["calibrate", "--interactive", "--participant", "sim", "--strong-ua", "9800"],
             f"--strong-ua 9800 out of range: the device accepts at most {HELD_I} uA at 200 us")):
        p = run_cli(*args, "--device", url)
        err = p.stderr.strip().splitlines()
        assert p.returncode == 2 and len(err) == 1 and words in err[0], (args, p.stderr)
        assert "no DAC gain was measured" in err[0] and "steadytouch selftest" in err[0] and "--scope" in err[0]
        assert "Traceback" not in p.stderr
    # `steadytouch sim` on the realistic board: checked against the simulated board's soft limits first
    p = run_cli("sim", "steady", "--i0-ua", "9800", "--t0-us", "100", "--x-star-ohm", "-1670", "--y-star-pc", "0",
                "--no-plot", "--out", str(tmp_path))
    err = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(err) == 1, p.stderr
    assert err[0].startswith(f"steadytouch: --i0-ua=9800 out of range: the device's soft limits are 500..{HELD_I} uA")
    assert "no DAC gain was measured" in err[0] and "--scope" in err[0] and not list(tmp_path.iterdir())
    # the ideal board (its current exactly the commanded one) is not held: 9800 is accepted there
    p = run_cli("limits", "--i-min-ua", "500", "--i-max-ua", "9800", "--t-min-us", "100", "--t-max-us", "4000",
                "--q-max-pc", "5000000", "--device", url + "&board=ideal")
    assert p.returncode == 0 and "limits: ok" in p.stdout, p.stderr


def test_the_host_forgets_the_hard_limits_after_a_set_vmon():
    """Device.limits reads GET_INFO when it does not know the hard limits in force, and again after a SET_VMON
    (which may lift or bring back the hold): a gain applied on every channel of the realistic sim:// lets
    SET_LIMITS reach the limit that gain holds (the hard limits x gain / 1.035) from the host, not above it."""
    from steadytouch.device import Device
    from steadytouch.protocol import CommandError
    from steadytouch.transport import open_transport

    import pytest

    with open_transport("sim://steady?channels=2") as t:
        d = Device(t)
        with pytest.raises(CommandError, match=f"i_max_ua={HARD_I} out of range: the device accepts 1..{HELD_I} uA"):
            d.limits(500, HARD_I, 100, 4000, 5_000_000)
        d.set_vmon_all([(0, 0, 1000000), (0, 0, 1000000)])
        assert d.cmds.hard is None
        assert d.limits(500, LOW_I, 100, 4000, LOW_Q).ok
        with pytest.raises(CommandError, match=f"i_max_ua={LOW_I + 1} out of range: the device accepts 1..{LOW_I} uA"):
            d.limits(500, LOW_I + 1, 100, 4000, LOW_Q)
        i = d.info()
        assert (i.hard_i_max_ua, i.held, i.dac_low, i.i_max_ua, i.q_max_pc) == (LOW_I, False, True, LOW_I, LOW_Q)


def test_a_refusal_names_the_value_and_the_range_and_the_hold_only_when_it_is_the_cause(tmp_path):
    """`steadytouch sim` and the firmware's own --auto: 300 uA is below i_min (500): the hold is not the cause and
    is not named (was: "(held: ...)" on every refusal, with "command 0x12 with result 4 (detail byte 4)" and a
    doubled "steadytouch: steadytouch firmware:" prefix); 9800 uA is above the held 9650 and within the board's
    10000: the hold is named; 20000 is above the board's own: not the hold."""
    for i0, t0, words, held in ((300, 1000, "--i0-ua=300 out of range: the device's soft limits are 500..9650 uA", False),
                                (5000, 2000, "--i0-ua*--t0-us=10000000 pC out of range: the device's charge limit is "
                                             "9650000 pC", True)):
        p = run_cli("sim", "steady", "--i0-ua", str(i0), "--t0-us", str(t0), "--no-plot", "--out", str(tmp_path))
        err = p.stderr.strip().splitlines()
        assert p.returncode == 2 and len(err) == 1 and err[0].startswith(f"steadytouch: {words}"), p.stderr
        assert ("no DAC gain was measured" in err[0]) == held and "steadytouch firmware" not in err[0], err
        assert not list(tmp_path.iterdir())
    import os

    from steadytouch.simrun import FIRMWARE, SHARED, micropython_exe

    env = dict(os.environ, MICROPYPATH=os.pathsep.join([str(SHARED), str(FIRMWARE)]))
    for i0, words, held in ((300, "I0 300 uA out of range: the device accepts 500..9650 uA", False),
                            (9800, "I0 9800 uA out of range: the device accepts 500..9650 uA", True),
                            (20000, "I0 20000 uA out of range: the device accepts 500..9650 uA", False)):
        p = subprocess.run([micropython_exe(), str(FIRMWARE / "main.py"), "--scenario", "steady", "--frames", "5",
                            "--auto", f"{i0},300,-1670,0", "--flash-dir", str(tmp_path)], capture_output=True,
                           text=True, errors="replace", timeout=60, env=env)
        err = p.stderr.strip().splitlines()
        assert p.returncode == 2 and err == [err[0]] and err[0].startswith(f"steadytouch firmware: --auto: {words}"), err
        assert ("held at 9650 uA, 9650000 pC: no DAC gain was measured" in err[0]) == held, err
        assert "0x12" not in err[0]


def test_a_dac_gain_lowers_the_limits_only_where_it_is_applied_and_the_host_says_why(tmp_path):
    """A stored DAC gain of 0.98 on ch0: the ideal board (its current exactly the commanded one; the gain is
    stored, not applied) keeps the full limits (was: 9800 uA / 9.8 uC, against the docs and `info`'s "stored,
    not applied"); the realistic board applies it, its hard limits are x 0.98 / 1.035 (the lowest gain over the
    window's top: 9468 uA), and `info` and the `limits` refusal say that reason (GET_INFO's INFO_FLAG_DAC_LOW),
    not the hold."""
    import os

    (tmp_path / "vmon_cal.txt").write_text("steadytouch monitor correction v1\n0 0 0 980000\n1 0 0 1000000\n")
    env = dict(os.environ, STEADYTOUCH_SIM_FLASH=str(tmp_path))
    url = "sim://steady?channels=2"
    p = run_cli("info", "--device", url + "&board=ideal", env=env)
    assert p.returncode == 0 and f"hard limits: I <= {HARD_I} uA, T <= 8000 us, Q <= {HARD_Q} pC" in p.stdout, p.stdout
    assert f"soft limits: I 500-{HARD_I} uA" in p.stdout and "(held)" not in p.stdout and "lowered" not in p.stdout
    assert "DAC gain 0.9800 stored, not applied" in p.stdout
    p = run_cli("limits", "--i-min-ua", "500", "--i-max-ua", str(HARD_I), "--t-min-us", "100", "--t-max-us", "4000",
                "--q-max-pc", str(HARD_Q), "--device", url + "&board=ideal", env=env)
    assert p.returncode == 0 and "limits: ok" in p.stdout, p.stderr
    lo_i, lo_q = dac_held(HARD_I, 980000), dac_held(HARD_Q, 980000)
    assert (lo_i, lo_q) == (9468, 9468000)
    p = run_cli("info", "--device", url, env=env)
    assert p.returncode == 0 and f"hard limits: I <= {lo_i} uA, T <= 8000 us, Q <= {lo_q} pC" in p.stdout, p.stdout
    assert "(lowered)" in p.stdout and ("lowered: the board's own limits x the lowest DAC gain measured / 1.035 (ch0 "
                                        "0.9800, ch1 1.0000)") in p.stdout and "held" not in p.stdout, p.stdout
    p = run_cli("limits", "--i-min-ua", "500", "--i-max-ua", str(lo_i + 1), "--t-min-us", "100", "--t-max-us", "4000",
                "--q-max-pc", "5000000", "--device", url, env=env)
    err = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(err) == 1, p.stderr
    assert (f"i_max_ua={lo_i + 1} out of range: the device accepts 1..{lo_i} uA: its hard limits are the board's own x "
            "the lowest DAC gain measured / 1.035") in err[0] and "no DAC gain" not in err[0], err


def test_a_limits_refused_by_the_host_sends_nothing_and_changes_nothing():
    """On one open transport (every sim:// CLI call boots a new VM, so a check across two calls says nothing):
    SET_LIMITS above the held limit is refused by the host, no report is written, and the device's soft limits
    are as they were."""
    import pytest
    from steadytouch.device import Device
    from steadytouch.protocol import CommandError
    from steadytouch.transport import open_transport

    with open_transport("sim://steady?channels=2") as t:
        d = Device(t)
        before = d.info()
        sent = []
        write = t.write
        t.write = lambda rep: (sent.append(bytes(rep)), write(rep))[1]
        for v in ((500, 9800, 100, 4000, 5_000_000), (500, 5000, 100, 4000, HELD_Q + 1)):
            with pytest.raises(CommandError, match="no DAC gain was measured"):
                d.limits(*v)
        assert sent == []
        after = d.info()
        assert [r[0] for r in sent] == [hp.CMD_GET_INFO]
    soft = lambda i: (i.i_min_ua, i.i_max_ua, i.t_min_us, i.t_max_us, i.q_max_pc)  # noqa: E731
    assert soft(after) == soft(before) == (500, HELD_I, before.t_min_us, before.t_max_us, HELD_Q)


def test_the_firmware_version_tells_a_board_that_reports_the_held_limits_from_an_older_one():
    """GET_INFO's hard fields and SET_LIMITS's rule changed in 0.2.0 (page 1 came in 0.3.0); the host tells an older
    board (nominal hard fields, no flag) from it and `info` says to update it."""
    import dataclasses

    from steadytouch.device import Device
    from steadytouch.transport import open_transport

    with open_transport("sim://steady?channels=1") as t:
        i = Device(t).info()
    assert i.firmware == "0.5.0" and i.reports_held_limits and i.held
    old = dataclasses.replace(i, firmware="0.1.0", flags=i.flags & ~hp.INFO_FLAG_HELD)
    assert not old.reports_held_limits and not dataclasses.replace(i, firmware="0.1.9").reports_held_limits
    assert dataclasses.replace(i, firmware="1.0.0").reports_held_limits


def test_the_advice_to_measure_the_dac_gain_only_for_a_board_that_takes_one():
    """Held on a board whose DAC path applies no DAC gain (GET_INFO without INFO_FLAG_DAC_GAIN): `selftest --scope`
    would not lift it, so the reason says the hold stays instead of advising it."""
    import dataclasses

    from steadytouch.device import Device
    from steadytouch.protocol import Commands, CommandError
    from steadytouch.transport import open_transport

    import pytest

    with open_transport("sim://steady?channels=1") as t:
        i = Device(t).info()
    assert i.held and i.dac_gain_applied and "--scope" in i.lowered_reason()
    no_dac = dataclasses.replace(i, flags=i.flags & ~hp.INFO_FLAG_DAC_GAIN)
    assert no_dac.held and "--scope" not in no_dac.lowered_reason() and "the hold stays" in no_dac.lowered_reason()
    c = Commands()
    c.know(no_dac)
    with pytest.raises(CommandError) as e:
        c.set_limits(500, HELD_I + 1, 100, 4000, 5_000_000)
    assert "the hold stays" in str(e.value) and "selftest" not in str(e.value)


def test_get_info_page_1_reports_the_boards_own_limits_beside_the_held_ones(tmp_path):
    """Issue 13 (deliverable 4's loose ends): GET_INFO carried only the held hard limits, so no host could show
    the board's own. Page 1 (O_ARG = INFO_PAGE_OWN, answered inside the heap-locked frame) carries the nominal
    hard limits and the soft limits as last set; page 0 is unchanged; a page > 1 is refused and changes nothing.
    A SET_VMON that lowers the soft limits in force leaves the ones set as they were."""
    _, res, _ = run_fw(SETUP + """
s, bd, clock = board()
b = bytearray(64)
r = {}
r["p0"] = framed(s, hp.cmd_get_info(b, 1))
r["p1"] = framed(s, hp.cmd_get_info(b, 2, hp.CH_ALL, hp.INFO_PAGE_OWN))
before = limits(s)
r["p2"] = framed(s, hp.cmd_get_info(b, 3, hp.CH_ALL, 2))
r["same"] = limits(s) == before
r["set"] = framed(s, hp.cmd_set_limits(b, 400, 9000, 50, 4000, 9000000))
r["p1_set"] = framed(s, hp.cmd_get_info(b, 4, hp.CH_ALL, hp.INFO_PAGE_OWN))
r["gain"] = framed(s, hp.cmd_set_vmon_all(b, hp.VMON_APPLY, [(0, 0, 1000000), (0, 0, 1000000)]))
r["above"] = framed(s, hp.cmd_set_limits(b, 400, 10000, 50, 4000, 10000000))  # above the gain's limit: refused
r["full"] = framed(s, hp.cmd_set_limits(b, 400, s.held_limit(0), 50, 4000, s.held_limit(1)))
r["drop"] = framed(s, hp.cmd_set_vmon(b, 1, hp.VMON_APPLY, 0, 0))  # ch1's gain removed: held, lowered
r["p0_low"] = framed(s, hp.cmd_get_info(b, 5))
r["p1_low"] = framed(s, hp.cmd_get_info(b, 6, hp.CH_ALL, hp.INFO_PAGE_OWN))
result(**r)
""")
    r = res[0]
    p0, p1 = _info(r["p0"]), _info(r["p1"])
    assert (p0.page, p0.hard_i_max_ua, p0.hard_q_max_pc, p0.i_max_ua, p0.q_max_pc) == (0, HELD_I, HELD_Q, HELD_I, HELD_Q)
    assert (p1.page, p1.hard_i_max_ua, p1.hard_q_max_pc, p1.i_max_ua, p1.q_max_pc) == (1, HARD_I, HARD_Q, HARD_I, HARD_Q)
    assert p1.nominal == (HARD_I, HARD_Q) and p0.nominal is None  # (page 0 alone: not known)
    assert (p1.hard_t_max_us, p1.t_min_us, p1.t_max_us, p1.flags, p1.board) == (
        p0.hard_t_max_us, p0.t_min_us, p0.t_max_us, p0.flags, p0.board)
    assert _ack(r["p2"]) == (hp.CMD_GET_INFO, hp.RES_OUT_OF_RANGE, hp.O_ARG) and r["same"]
    assert _ack(r["set"])[1] == hp.RES_OK
    p1 = _info(r["p1_set"])
    assert (p1.i_min_ua, p1.i_max_ua, p1.q_max_pc, p1.hard_i_max_ua) == (400, 9000, 9_000_000, HARD_I)
    assert [_ack(r[k])[1] for k in ("gain", "above", "full", "drop")] == [hp.RES_OK, hp.RES_OUT_OF_RANGE] + [hp.RES_OK] * 2
    low, own = _info(r["p0_low"]), _info(r["p1_low"])
    assert (low.held, low.i_max_ua, low.q_max_pc) == (True, HELD_I, HELD_Q)  # lowered in force ...
    assert (own.i_min_ua, own.i_max_ua, own.q_max_pc) == (400, LOW_I, LOW_Q)  # ... as set: kept


class _OldFirmware:
    """A transport whose device ignores GET_INFO's page byte, as firmware before page 1 does (it answers page 0)."""

    SENT_PAGE = 0  # what page 1 reaches the device as

    def __init__(self, t):
        self.t = t

    def write(self, rep):
        rep = bytearray(rep)
        if rep[0] == hp.CMD_GET_INFO and rep[hp.O_ARG]:
            rep[hp.O_ARG] = self.SENT_PAGE
            hp.seal(rep)
        self.t.write(bytes(rep))

    def __getattr__(self, name):
        return getattr(self.t, name)


def test_the_host_names_the_boards_own_limit_beside_the_held_one_and_copes_with_older_firmware(tmp_path):
    """`info`, and the one-line refusals of `limits` and `calibrate`, name the board's own hard limits (GET_INFO
    page 1) beside the held ones; `info` shows the soft limits as set where the firmware lowered them. A firmware
    that answers page 0 to page 1 (before it) is told apart: no nominal, one line saying `flash` updates it."""
    from steadytouch.device import Device
    from steadytouch.protocol import CommandError
    from steadytouch.transport import open_transport

    import pytest

    url = "sim://steady?channels=2"
    p = run_cli("info", "--device", url)
    assert p.returncode == 0, p.stderr
    assert f"held: its hard limits are held 3.5 % below the board's own (I {HARD_I} uA, Q {HARD_Q} pC) because no " \
           "DAC gain was measured" in p.stdout, p.stdout
    assert (f"soft limits: I 500-{HELD_I} uA, T 100-8000 us, Q <= {HELD_Q} pC (set: I 500-{HARD_I} uA, Q <= {HARD_Q} pC; "
            "lowered to the hard limits in force") in p.stdout, p.stdout
    for args, words in (
            (["limits", "--i-min-ua", "500", "--i-max-ua", "9800", "--t-min-us", "100", "--t-max-us", "4000",
              "--q-max-pc", "5000000"], f"i_max_ua=9800 out of range: the device accepts 1..{HELD_I} uA"),
            (["calibrate", "--i0-ua", "9800", "--t0-us", "100", "--x-star-ohm", "-1670", "--y-star-pc", "0"],
             f"i0_ua=9800 out of range: the device's soft limits are 500..{HELD_I} uA")):
        p = run_cli(*args, "--device", url)
        err = p.stderr.strip().splitlines()
        assert p.returncode == 2 and len(err) == 1 and words in err[0], (args, p.stderr)
        assert f"held 3.5 % below the board's own (I {HARD_I} uA, Q {HARD_Q} pC)" in err[0], err
    with open_transport(url) as t:
        d = Device(t)
        assert d.info().nominal == (HARD_I, HARD_Q) and d.own_limits().i_max_ua == HARD_I
        old = Device(_OldFirmware(t))
        i = old.info()
        assert i.held and i.nominal is None and old.own_limits() is None
        assert "below the board's own because no DAC gain was measured" in i.lowered_reason()
        with pytest.raises(CommandError, match=r"the board's own because no DAC gain"):
            old.limits(500, 9800, 100, 4000, 5_000_000)
        with pytest.raises(CommandError, match="page"):
            d.cmds.get_info(0, page=1)
    bad = bytearray(64)
    bad[0] = hp.REP_INFO
    from steadytouch.protocol import ProtocolError
    with pytest.raises(ProtocolError, match="page=2"):
        good = bytes.fromhex(run_fw(SETUP + "s, bd, clock = board()\nresult(x=framed(s, hp.cmd_get_info(bytearray(64))))"
                                    )[1][0]["x"])
        decode(good[:hp.O_INFO_PAGE] + b"\x02" + good[hp.O_INFO_PAGE + 1:])


class _RefusingPage(_OldFirmware):
    """A transport whose device refuses GET_INFO page 1 with an error code (the firmware's answer to a page it
    lacks: RES_OUT_OF_RANGE, nothing changed): page 1 sent as page 2."""

    SENT_PAGE = 2


def test_own_limits_is_none_when_a_board_refuses_page_1_and_info_says_which_firmware_has_it(monkeypatch, capsys):
    """Review rev-lims F7: Device.own_limits raised when a board refused page 1 (info, selftest's restore and every
    refusal's Device.info stopped there); now None, as for a board that answers page 0. FW_VERSION 0.3.0 and later mark
    the firmware with page 1, and info's advice names it."""
    from steadytouch import cli
    from steadytouch.device import Device
    from steadytouch.protocol import FW_OWN_LIMITS
    from steadytouch.transport import open_transport

    import contextlib

    url = "sim://steady?channels=2"
    with open_transport(url) as t:
        d = Device(_RefusingPage(t))
        assert d.own_limits() is None
        i = d.info()
        assert i.held and i.nominal is None and i.firmware == "0.5.0" and FW_OWN_LIMITS == (0, 3, 0)

    @contextlib.contextmanager
    def refusing(u):
        with open_transport(u) as t:
            yield _RefusingPage(t)

    monkeypatch.setattr(cli, "open_transport", refusing)
    assert cli.main(["info", "--device", url]) == 0
    out = capsys.readouterr().out
    assert "firmware 0.5.0 does not report the board's own limits beside the lowered ones (GET_INFO page 1, " \
           "firmware 0.3.0 on): `steadytouch flash` updates it" in out, out
