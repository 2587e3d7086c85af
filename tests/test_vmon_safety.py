"""A stored correction that is wrong but inside its accepted window must not make the
device less safe (found by review, reproduced in the MicroPython VM on the realistic
simulated board):
- a monitor gain stored too high must not hide an electrode that came off (the raw
  reading at compliance latches too);
- a DAC gain stored too low must not let the physical charge past the hard limits (the
  reported current is held to the limits x that gain / VMON_DAC_PPM_MAX, the window's top);
- a changed DAC gain changes the current a code delivers: the channel must be calibrated
  again before it can be armed."""

import hid_protocol as hp
from fw_harness import run_fw
from steadytouch.protocol import decode

SETUP = """
import board_config as cfg
from board_sim import SimBoard, VirtualClock, MemoryUSB

def make(scen, rate=50):
    clock = VirtualClock(0)
    board = SimBoard(cfg, clock, sim_electrode.scenario(scen), 1, 1, MemoryUSB(True), ideal=False)
    return stim.Stimulator(board, clock, cfg, 1, rate, 0), board, clock

def cmd(s, clock, rep):
    s.handle(bytearray(rep), clock.ticks_us())
    s.sync_outputs()
    return s.tx[hp.O_RESULT]

def force_nominal_soft_limits(s):
    # behind the firmware's back: the soft current and charge limits at the board's nominal hard ones, past
    # what _fit_limits holds them to (no command can do this). The check right before the gate opens is
    # the last line; these tests show it still holds when the soft layer above it has failed.
    s.lim[1] = s.hard_i
    s.lim[4] = s.hard_q
    for c in s.chans:
        c.ctl.set_limits(s.lim[0], s.lim[1], s.lim[2], s.lim[3], s.lim[4])
"""


def test_a_monitor_gain_stored_too_high_does_not_hide_an_electrode_off():
    _, res, _ = run_fw(SETUP + """
out = []
for g in (0, 1015000, hp.VMON_GAIN_PPM_MAX):
    s, board, clock = make("off")
    b = bytearray(64)
    r = [cmd(s, clock, hp.cmd_set_vmon(b, 0, hp.VMON_APPLY, g, 160 if g else 0)),
         cmd(s, clock, hp.cmd_set_mode(b, sc.MODE_AKHTAR)),
         cmd(s, clock, hp.cmd_calibrate(b, hp.CH_ALL, 3000, 1000, -1670, 186000)),
         cmd(s, clock, hp.cmd_arm(b, hp.CH_ALL))]
    s.run(300)
    c = s.chans[0]
    out.append([g, r, c.armed, c.stop, c.i * c.t])
result(out=out)
""")
    for g, acks, armed, stop, q in res[0]["out"]:
        assert acks == [hp.RES_OK] * 4, (g, acks)
        assert not armed and stop == hp.STOP_ELECTRODE_OFF, (g, armed, stop, q)  # was: 1.1 stayed armed at 10 uC


def test_a_dac_gain_stored_too_low_keeps_the_physical_charge_within_the_hard_limits():
    _, res, _ = run_fw(SETUP + """
out = []
for dac in (0, hp.VMON_DAC_PPM_MIN, hp.VMON_DAC_PPM_MAX, 1000000):
    s, board, clock = make("steady", 20)
    b = bytearray(64)
    r = [cmd(s, clock, hp.cmd_set_vmon(b, 0, hp.VMON_APPLY, 0, 0, dac_gain_ppm=dac))]
    force_nominal_soft_limits(s)  # (else a gain below 1.035 would hold them: the pulse below is refused ahead)
    r += [cmd(s, clock, hp.cmd_set_mode(b, sc.MODE_OPEN_LOOP)),
          cmd(s, clock, hp.cmd_calibrate(b, hp.CH_ALL, 1250, 8000, -1670, 0)),  # at the nominal hard charge
          cmd(s, clock, hp.cmd_arm(b, hp.CH_ALL))]
    s.run(5)
    c = s.chans[0]
    out.append([dac, r, c.stop, c.di * c.dt, board.last_i_ua[0] * c.dt if c.dt else 0.0, s.hard_q])
result(out=out)
""")
    for dac, acks, stop, q_reported, q_physical, hard_q in res[0]["out"]:
        assert acks == [hp.RES_OK] * 4, (dac, acks)
        assert q_reported <= hard_q and q_physical <= hard_q, (dac, stop, q_reported, q_physical)  # was 11.03 uC
    top = res[0]["out"][2]  # a DAC measured at the window's top (1.035) still pulses at the nominal hard charge
    assert top[0] == hp.VMON_DAC_PPM_MAX and top[2] == hp.STOP_NONE and top[3] > 0, top
    measured = res[0]["out"][3]  # one measured nominal (1.0) is held x 1 / 1.035: the gate latches, nothing delivered
    assert measured[0] == 1000000 and measured[2] == hp.STOP_LIMIT and measured[3] == 0, measured


def test_a_changed_dac_gain_needs_a_new_calibration_before_arming():
    _, res, _ = run_fw(SETUP + """
s, board, clock = make("steady")
b = bytearray(64)
r = [cmd(s, clock, hp.cmd_set_mode(b, sc.MODE_OPEN_LOOP)),
     cmd(s, clock, hp.cmd_calibrate(b, hp.CH_ALL, 3000, 300, -1670, 0)),
     cmd(s, clock, hp.cmd_arm(b, hp.CH_ALL))]
s.run(3)
r.append(cmd(s, clock, hp.cmd_disarm(b, hp.CH_ALL)))
r.append(cmd(s, clock, hp.cmd_set_vmon(b, 0, hp.VMON_APPLY, 0, 0, dac_gain_ppm=hp.VMON_DAC_PPM_MIN)))
r.append(cmd(s, clock, hp.cmd_arm(b, hp.CH_ALL)))  # refused: the calibrated I0 is another current now
armed_after = s.chans[0].armed
r.append(cmd(s, clock, hp.cmd_calibrate(b, hp.CH_ALL, 3000, 300, -1670, 0)))
r.append(cmd(s, clock, hp.cmd_arm(b, hp.CH_ALL)))
same = cmd(s, clock, hp.cmd_disarm(b, hp.CH_ALL))
r2 = cmd(s, clock, hp.cmd_set_vmon(b, 0, hp.VMON_APPLY, 1010000, 0, dac_gain_ppm=hp.VMON_DAC_PPM_MIN))
result(r=r, armed_after=armed_after, same=same, r2=r2, have_cal=s.chans[0].have_cal)
""")
    r = res[0]
    assert r["r"][:5] == [hp.RES_OK] * 5, r
    assert r["r"][5] != hp.RES_OK and not r["armed_after"], r
    assert r["r"][6:] == [hp.RES_OK, hp.RES_OK], r
    assert r["r2"] == hp.RES_OK and r["have_cal"]  # the monitor alone changed: the calibration stands


def test_a_board_config_whose_monitor_correction_could_pass_2_30_is_refused():
    """_measure forms (16 x - o) k in a machine word on the chip; at a small enough
    VMON_UV_PER_COUNT the offset term o makes it wrap there (review: uv <= 187 read 0 V as
    full scale). The set-up refuses such a config, naming the least it accepts; at that
    least, the real terms the board computes for the extreme gain and offsets stay < 2**30."""
    _, res, _ = run_fw(SETUP + """
class Cfg:
    pass

def with_uv(uv):
    c = Cfg()
    for k in dir(cfg):
        if not k.startswith('_'):
            setattr(c, k, getattr(cfg, k))
    c.VMON_UV_PER_COUNT = uv
    return c

least = stim._vmon_uv_min()
errs = []
for uv in (100, 187, least - 1):
    try:
        stim.Stimulator(SimBoard(cfg, VirtualClock(0), sim_electrode.scenario('steady'), 1, 1, MemoryUSB(True)), VirtualClock(0), with_uv(uv), 1, 50, 0)
        errs.append(None)
    except ValueError as e:
        errs.append(str(e))
s = stim.Stimulator(SimBoard(cfg, VirtualClock(0), sim_electrode.scenario('steady'), 1, 1, MemoryUSB(True)), VirtualClock(0), with_uv(least), 1, 50, 0)
c = s.chans[0]
worst = 0
for g in (hp.VMON_GAIN_PPM_MIN, hp.VMON_GAIN_PPM_MAX):
    for off in (hp.VMON_OFFSET_MV_MIN, hp.VMON_OFFSET_MV_MAX):
        s._vmon_apply(c, g, off, 0)
        for x in (0, 4095):
            worst = max(worst, abs((16 * x - c.vmon_o) * c.vmon_k) + 65536)
result(least=least, errs=errs, worst=worst, bound=stim._vmon_product_max(least))
""")
    r = res[0]
    assert 300 <= r["least"] <= 420  # about 358 with the accepted windows (0.91, +-1.2 V; 611 at 0.9, +-2 V)
    assert all(e and "VMON_UV_PER_COUNT must be >= %d" % r["least"] in e for e in r["errs"])
    assert r["worst"] <= r["bound"] < 2 ** 30


def test_a_board_reporting_more_samples_than_its_window_is_read_within_the_window():
    """_measure trusts the board's sample count only up to the capture window (review: a
    count past it read the heap below the buffer as ADC counts)."""
    _, res, _ = run_fw(SETUP + """
s, board, clock = make('steady')
c = s.chans[0]
w = len(c.adc)  # the capture window
for k in range(w):
    c.adc[k] = 1000
c.n_samples = w
s._measure(c)
at_w = c.vp_raw
c.n_samples = 4 * w
s._measure(c)
result(at_w=at_w, past=c.vp_raw)
""")
    r = res[0]
    assert r["at_w"] == r["past"] == 1000 * 27000 // 1000


def test_no_dac_gain_applied_holds_the_hard_limits_to_the_dac_windows_low_edge(tmp_path):
    """Review of d560dd3 (finding 2c): a correction file stored under the old, wider windows is
    ignored at boot (VMON_BAD); every DAC then runs uncorrected and a realistic board's ch1 (DAC gain
    1.006) delivered 10058 uA at its hard limit of 10000. With no DAC gain applied (a fresh board, a
    file ignored, a self-test without --scope) the reported current and charge are held to the hard
    limits x VMON_DAC_PPM_MIN: a DAC whose gain is anywhere in its window stays within them. The soft
    limits follow (stim._fit_limits): a CALIBRATE or SET_LIMITS above the held limits is refused ahead,
    GET_INFO reports them (INFO_FLAG_HELD); the gate's own check, the last line, still latches a pulse
    above them when the soft layer is bypassed. The ideal board (its current exactly the commanded one)
    keeps the full limits."""
    d = str(tmp_path)
    (tmp_path / "vmon_cal.txt").write_text("steadytouch monitor correction v1\n0 0 0 1050000\n1 0 0 1006000\n")
    _, res, _ = run_fw(SETUP + f"""
out = {{}}
for name, flash, ideal in (("fresh", None, False), ("bad file", {d!r}, False), ("ideal", None, True)):
    clock = VirtualClock(0)
    bd = SimBoard(cfg, clock, sim_electrode.scenario("steady"), 2, 1, MemoryUSB(True), noise_counts=0.0,
                  load_ohm=1000, flash_dir=flash, ideal=ideal)
    s = stim.Stimulator(bd, clock, cfg, 2, 20, 0)
    rows = []
    for c in s.chans:
        bd.analog.dac_gain[c.ch] = 1.0 if ideal else hp.VMON_DAC_PPM_MAX / 1e6  # the worst a healthy DAC can be
        rep = bd.set_amplitude(c.ch, c.hard_i_d)  # the most the hard limit lets the board report
        rows.append([c.hard_i_d, c.hard_q_d, rep, bd.analog.physical_ua(c.ch, bd.code[c.ch])])
    b = bytearray(64)
    r = [cmd(s, clock, hp.cmd_set_mode(b, sc.MODE_OPEN_LOOP)),
         cmd(s, clock, hp.cmd_calibrate(b, hp.CH_ALL, s.hard_i, 1000, -1670, 0)),  # above the soft limit: refused
         cmd(s, clock, hp.cmd_set_limits(b, 1, s.hard_i, 100, 1000, s.hard_q)),  # refused above the held limits
         cmd(s, clock, hp.cmd_calibrate(b, hp.CH_ALL, s.lim[1], 1000, -1670, 0)),  # at the held soft limit
         cmd(s, clock, hp.cmd_arm(b, hp.CH_ALL))]
    s.run(4)
    pulses = [[c.stop, c.di, bd.last_i_ua[c.ch]] for c in s.chans]
    s.handle(bytearray(hp.cmd_get_info(b, 7)), clock.ticks_us())
    info = bytes(s.tx).hex()
    lim = list(s.lim)
    # the gate's check stays the last line: the soft limits forced to the nominal ones behind the firmware's
    # back, a pulse at the hard limit's current is stopped, never delivered
    r.append(cmd(s, clock, hp.cmd_disarm(b, hp.CH_ALL)))
    force_nominal_soft_limits(s)
    r += [cmd(s, clock, hp.cmd_calibrate(b, hp.CH_ALL, s.hard_i, 1000, -1670, 0)), cmd(s, clock, hp.cmd_arm(b, hp.CH_ALL))]
    s.run(4)
    gate = [[c.stop, c.di, bd.last_i_ua[c.ch]] for c in s.chans]
    out[name] = [s.vmon_state, rows, r, pulses, s.hard_i, s.hard_q, lim, info, gate]
result(**out)
""")
    r = res[0]
    assert r["bad file"][0] == hp.VMON_BAD and r["fresh"][0] == hp.VMON_NONE
    for name in ("fresh", "bad file"):
        state, rows, acks, pulses, hard_i, hard_q, lim, info, gate = r[name]
        # the soft limits are held to what the board may deliver, so a pulse above them is refused
        # ahead (CALIBRATE, SET_LIMITS: out of range, nothing changed), never latched at the gate
        assert acks == [hp.RES_OK, hp.RES_OUT_OF_RANGE, hp.RES_OUT_OF_RANGE, hp.RES_OK, hp.RES_OK] + [hp.RES_OK] * 3, (
            name, acks)
        for hid, hqd, rep, phys in rows:
            assert hid == hard_i * hp.VMON_DAC_PPM_MIN // 1000000 and hqd == hard_q * hp.VMON_DAC_PPM_MIN // 1000000
            assert rep <= hid and phys <= hard_i, (name, rows)  # was 10350 uA at a gain of 1.035
        assert lim[1] == rows[0][0] and lim[4] == min(row[1] for row in rows), (name, lim)
        for stop, di, phys in pulses:  # at the held limit: delivered, within the hard limit
            assert stop == hp.STOP_NONE and 0 < di <= lim[1] and phys <= hard_i, (name, pulses)
        i = decode(bytes.fromhex(info))  # GET_INFO: the held limits, and why
        assert (i.hard_i_max_ua, i.hard_q_max_pc, i.held) == (rows[0][0], rows[0][1], True), name
        for stop, di, phys in gate:  # a pulse at the hard limit's current is stopped, never delivered
            assert stop == hp.STOP_LIMIT and di == 0 and phys <= hard_i, (name, gate)
    state, rows, acks, pulses, hard_i, hard_q, lim, info, gate = r["ideal"]
    assert acks == [hp.RES_OK] * 8 and lim[1] == hard_i, (acks, lim)
    assert [row[0] for row in rows] == [hard_i, hard_i] and all(p[0] == hp.STOP_NONE and p[1] > 0 for p in pulses)
    assert all(g[0] == hp.STOP_NONE and g[1] > 0 for g in gate)  # nothing is held on the ideal board
    i = decode(bytes.fromhex(info))
    assert (i.hard_i_max_ua, i.hard_q_max_pc, i.held) == (hard_i, hard_q, False)


def test_a_dac_gain_stored_below_the_true_one_keeps_the_physical_current_within_the_hard_limits():
    """Review of session 22: the board reports code x LSB x the *stored* DAC gain, the physical current
    is code x LSB x the *true* one, and the stored gain is the host's word (a scope plateau typed low).
    The reported current was held to the hard limits x the stored gain only below 1: 1.000 stored on the
    realistic board's ch1 (true 1.006, board_sim.DAC_GAIN) gave back the full limits and a pulse there
    delivered 10 058 uA against the 10 000 uA hard limit (10.06 uC against 10). Now held to the hard limits
    x stored gain / VMON_DAC_PPM_MAX (stim._dac_limits): for every stored gain in the window, on both
    channels, with SET_LIMITS raised to the limits in force, a run at the highest current and one at the
    highest charge never deliver a physical current or charge above the hard limits."""
    _, res, _ = run_fw(SETUP + """
out = []
for dac in (hp.VMON_DAC_PPM_MIN, 1000000, 1006000, hp.VMON_DAC_PPM_MAX):
    for i_of, t_of in (("i", 1000), ("q", hp.T_FLOOR_US), ("q", 0)):
        clock = VirtualClock(0)
        bd = SimBoard(cfg, clock, sim_electrode.scenario("steady"), 2, 1, MemoryUSB(True), noise_counts=0.0,
                      load_ohm=1000)
        s = stim.Stimulator(bd, clock, cfg, 2, 20, 0)
        b = bytearray(64)
        r = [cmd(s, clock, hp.cmd_set_vmon_all(b, hp.VMON_APPLY, [(0, 0, dac), (0, 0, dac)]))]
        hi = s.held_limit(0)  # the limits in force (GET_INFO's hard fields)
        hq = s.held_limit(1)
        r.append(cmd(s, clock, hp.cmd_set_limits(b, 1, hi, hp.T_FLOOR_US, s.hard_t, hq)))
        if t_of == 0:  # the highest charge at the longest pulse
            t = s.hard_t
            i = hq // t
        elif i_of == "i":  # the highest current
            i, t = hi, t_of
        else:  # the highest charge at the highest current
            i = hi
            t = hq // hi
        r += [cmd(s, clock, hp.cmd_set_mode(b, sc.MODE_OPEN_LOOP)),
              cmd(s, clock, hp.cmd_calibrate(b, hp.CH_ALL, i, t, -1670, 0)),
              cmd(s, clock, hp.cmd_arm(b, hp.CH_ALL))]
        peak = [[0, 0.0, 0.0, 0], [0, 0.0, 0.0, 0]]
        for k in range(6):
            s.run(1)
            for c in s.chans:
                p = peak[c.ch]
                p[0] = c.stop
                if c.dt and bd.last_i_ua[c.ch] > p[1]:
                    p[1] = bd.last_i_ua[c.ch]
                    p[2] = bd.last_i_ua[c.ch] * c.dt
                    p[3] = c.di
                ph = bd.analog.physical_ua(c.ch, bd.code[c.ch])
                if ph > p[1]:
                    p[1] = ph
                    p[2] = ph * c.dt
        out.append([dac, i, t, hi, hq, r, peak, s.hard_i, s.hard_q])
result(out=out)
""")
    over = [(dac, ch, i, t, round(phys_i, 1), round(phys_q)) for dac, i, t, hi, hq, acks, peak, hard_i, hard_q
            in res[0]["out"] for ch, (stop, phys_i, phys_q, di) in enumerate(peak) if phys_i > hard_i or phys_q > hard_q]
    assert not over, over  # was: at 1.000 and 1.006 stored, ch1 delivered 10 058 uA, 10.06 uC
    for dac, i, t, hi, hq, acks, peak, hard_i, hard_q in res[0]["out"]:
        assert acks == [hp.RES_OK] * 5, (dac, i, t, acks)
        for ch, (stop, phys_i, phys_q, di) in enumerate(peak):
            assert stop == hp.STOP_NONE and di > 0, (dac, ch, i, t, peak)  # delivered, not latched
        # the limits in force: the hard limits x stored gain / VMON_DAC_PPM_MAX (the full ones only at 1.035)
        assert hi <= hard_i * dac / hp.VMON_DAC_PPM_MAX and hq <= hard_q * dac / hp.VMON_DAC_PPM_MAX, (dac, hi, hq)
        assert hi >= hard_i * dac / hp.VMON_DAC_PPM_MAX - 2 and hq >= hard_q * dac / hp.VMON_DAC_PPM_MAX - 2000, (dac,)
    assert [o[3] for o in res[0]["out"] if o[0] == hp.VMON_DAC_PPM_MAX] == [res[0]["out"][0][7]] * 3  # full at 1.035


def test_the_held_limits_times_the_window_top_never_pass_the_hard_limits():
    """stim._dac_limits holds the reported current and charge to the hard limits x stored gain /
    VMON_DAC_PPM_MAX: for every stored gain of the window (10 ppm apart) and hard limits of any size,
    the held limit x 1.035 never passes the hard limit x the stored gain (exact integers), so with the
    reported current never below what the stored gain drives (tests/test_dac.py) the physical current
    stays within the hard limit for any true gain up to 1.035."""
    _, res, _ = run_fw(SETUP + """
s, board, clock = make("steady")
c = s.chans[0]
s._dac_applied = True
bad = []
n = 0
for hi, hq in ((10000, 10000000), (2097, 2097000), (99999, 99999999), (1, 1)):
    s.hard_i = hi
    s.hard_q = hq
    ppm = hp.VMON_DAC_PPM_MIN
    while ppm <= hp.VMON_DAC_PPM_MAX:
        s._dac_limits(c, ppm)
        n += 1
        if c.hard_i_d * hp.VMON_DAC_PPM_MAX > hi * ppm or c.hard_q_d * hp.VMON_DAC_PPM_MAX > hq * ppm:
            bad.append((hi, ppm, c.hard_i_d, c.hard_q_d))
        if c.hard_i_d < hi * ppm // hp.VMON_DAC_PPM_MAX - hi // 5000 - 1:  # and not far below it (<= 200 ppm)
            bad.append(("low", hi, ppm, c.hard_i_d))
        ppm += 10
result(bad=bad[:5], n=n)
""")
    assert res[0]["n"] == 4 * 7001 and res[0]["bad"] == [], res[0]
